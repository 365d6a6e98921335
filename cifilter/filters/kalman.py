"""filterpy filter classes that can fuse their estimate with other estimates.

``cifilter.KalmanFilter`` is ``filterpy.kalman.KalmanFilter`` with one more method,
:meth:`FusionMixin.fuse`; constructors, ``predict`` and ``update`` are filterpy's own.

Supported: filterpy 1.4.5 and 2.x. The classes inherit everything from the installed
filterpy, so what filterpy 2.0 changed (``KalmanFilter.M`` of shape (dim_x, dim_z),
``UnscentedKalmanFilter(..., state_add=)``, ``Saver.to_array(flatten=)``, ``stats.NEES``)
is there exactly when it is in filterpy; ``fuse`` uses only what both versions share
(``x``, ``P``, ``x_post``, ``P_post``; for ``horizon=`` ``F``, ``Q``, ``H``, ``R``; for
``lag=`` ``F`` and ``Q``; the UKF's ``residual_x`` and, from filterpy 2.0 on, its
``state_add``).
Until ``fuse`` is called a filter gives bit for bit the results of filterpy's class.
(filterpy 1.4.5's ``KalmanFilter.mahalanobis``, and so its ``repr`` and ``Saver``, raise
``TypeError`` with recent numpy, seen with 2.4.6, for filterpy's own class alike.)
"""

import math
import warnings
from collections.abc import Sequence
from typing import Any, Callable, Optional, Union

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter as _FilterpyEKF
from filterpy.kalman import KalmanFilter as _FilterpyKF
from filterpy.kalman import UnscentedKalmanFilter as _FilterpyUKF

from .._numerics.alignment import StepMotion
from .._numerics.validation import check_int
from ..registry import fuse_estimates, split_estimate
from ..result import FusionResult

__all__ = ["ExtendedKalmanFilter", "FusionMixin", "KalmanFilter", "UnscentedKalmanFilter"]


def _is_estimate_pair(item):
    """An (x, P) pair: a 2-sequence of a vector and a matrix (not of two estimates)."""
    if not (isinstance(item, (tuple, list)) and len(item) == 2):
        return False
    if any(hasattr(part, "P") for part in item):
        return False
    try:
        return np.ndim(item[0]) >= 1 and np.ndim(item[1]) >= 2
    except ValueError:  # a ragged pair of pairs
        return False


def _as_estimate_list(other):
    """``other`` as a list of estimates: a filter, an (x, P) pair or a sequence of them."""
    if hasattr(other, "x") and hasattr(other, "P"):
        return [other]
    if _is_estimate_pair(other):
        return [other]
    if isinstance(other, (tuple, list)) and len(other) > 0 and all(
        (hasattr(o, "x") and hasattr(o, "P")) or _is_estimate_pair(o) for o in other
    ):
        return list(other)
    if isinstance(other, (tuple, list)) and len(other) == 2 and not any(
        hasattr(o, "P") or _is_estimate_pair(o) for o in other
    ):
        return [other]  # an (x, P) pair of the wrong shapes: the validation names them
    raise TypeError(
        "other must be a filter (an object with .x and .P), an (x, P) pair, or a non-empty "
        f"list of them; got {type(other).__name__}"
    )


def _is_plain_pair(item):
    """``item`` is a tuple of two float arrays, a vector (or column) and a matrix: an (x, P)
    pair for :func:`_as_estimate_list`, which it answers sooner."""
    if type(item) is not tuple or len(item) != 2:
        return False
    x, P = item
    return (type(x) is np.ndarray and type(P) is np.ndarray and P.ndim == 2
            and 1 <= x.ndim <= 2)


_LABELS = ("this filter", "other")


def _labels(count, other_is_list):
    """Names of the estimates in messages: this filter, then other or other[i]."""
    if not other_is_list:
        return ("this filter", "other")
    return ("this filter",) + tuple(f"other[{i}]" for i in range(count - 1))


def _single_estimates(estimates, labels):
    """(x, P) pairs of single estimates, with any x holding n numbers as a vector.

    A filter's ``x`` may have any shape holding its n numbers (filterpy's (n, 1), the
    UKF's (n,), or (1, n)); (n,) and (n, 1) pass unchanged, other shapes become (n,).
    Batches (a covariance with more than two axes, an x with more than n numbers) are
    rejected with a ``ValueError`` naming the estimate. Nothing is copied or modified here;
    the validation of the fusion copies. An other estimate's ``x`` of shape (n,) or (n, 1)
    of the filter's n is given the filter's own style (a view; the same numbers), so that
    the usual call (filterpy's (n, 1) state, an (n,) track) takes the validation's fast
    path, which needs the means in one style; the fused ``x`` keeps the filter's style.
    """
    pairs = []
    style = None  # the shape of this filter's x when it is (n,) or (n, 1)
    for i, item in enumerate(estimates):
        # (a plain 2-tuple is an (x, P) pair as it is: split_estimate's answer, without
        # its attribute look-ups)
        x, P = item if type(item) is tuple and len(item) == 2 else split_estimate(
            item, i, labels)
        if (isinstance(x, np.ndarray) and isinstance(P, np.ndarray) and P.ndim == 2
                and x.shape in ((P.shape[0],), (P.shape[0], 1))):
            # the usual filterpy shapes: nothing to check here
            if i == 0:
                style = x.shape
            elif style is not None and x.shape != style and P.shape[0] == style[0]:
                x = x.reshape(style)
            pairs.append((x, P))
            continue
        try:
            x_shape, P_shape = np.shape(x), np.shape(P)
        except ValueError:  # ragged input: the validation names it
            pairs.append((x, P))
            continue
        if len(P_shape) > 2:
            raise ValueError(
                f"{labels[i]}'s P has shape {P_shape}, a batch of covariances; a filter fuses "
                "single estimates (use cifilter.fuse for batches)"
            )
        if len(P_shape) == 2 and P_shape[0] == P_shape[1]:
            n, size = P_shape[0], int(np.prod(x_shape, dtype=int))
            if size != n:
                raise ValueError(
                    f"{labels[i]}'s x has shape {x_shape} ({size} numbers), but its P is "
                    f"{n}x{n}; a filter fuses single estimates whose x holds n numbers"
                )
            if x_shape not in ((n,), (n, 1)):
                x = np.reshape(x, (n,))
        pairs.append((x, P))
    return pairs


def _own_model(filt):
    """The filter's linear model (F, Q, H, R) for ``horizon=`` without ``model=``."""
    missing = [name for name in ("F", "Q", "H", "R")
               if not isinstance(getattr(filt, name, None), (np.ndarray, int, float))]
    if missing:
        raise ValueError(
            f"horizon= needs the filter's linear model, but {type(filt).__name__} has no "
            f"matrix {', '.join(missing)}; pass model=dict(F=..., Q=..., H=..., R=...)"
        )
    return {name: getattr(filt, name) for name in ("F", "Q", "H", "R")}


def _lag_times(lag, count):
    """``times``, ``at`` for ``lag=``: this filter at 0, other ``i`` at ``-lag_i``."""
    if type(lag) is int and count == 2:  # the usual call
        return (0.0, -float(lag)), 0.0
    lags = list(lag) if isinstance(lag, (list, tuple)) else [lag] * (count - 1)
    if len(lags) != count - 1:
        raise ValueError(f"lag has {len(lags)} entries but there are {count - 1} other "
                         "estimates; give one lag per other estimate, or one for all")
    steps = [k if type(k) is int else check_int(k, "lag") for k in lags]
    return (0.0,) + tuple(-float(k) for k in steps), 0.0


def _own_step_model(filt):
    """The filter's ``F`` and ``Q`` as a motion model of whole steps (``lag=``)."""
    F, Q = getattr(filt, "F", None), getattr(filt, "Q", None)
    if type(F) is np.ndarray and type(Q) is np.ndarray and F.dtype.char == Q.dtype.char == "d":
        return StepMotion(F, Q)  # (the usual filter: float64 arrays as they are)
    missing = [name for name in ("F", "Q")
               if not isinstance(getattr(filt, name, None), np.ndarray)]
    if missing:
        raise ValueError(
            f"lag= predicts or retrodicts with the filter's F and Q, but "
            f"{type(filt).__name__} has no matrix {', '.join(missing)}; give times=, at= "
            "and motion= (dt -> (F, Q)) instead"
        )
    # (not copied: StepMotion neither keeps nor changes them past the call, and its cache
    # is keyed by their bytes at the call)
    return StepMotion(np.asarray(filt.F, dtype=float), np.asarray(filt.Q, dtype=float))


def _own_residual(filt, residual, add):
    """The filter's ``residual_x`` and ``state_add`` (UKF) unless given; plain subtraction
    and addition count as none (the rule then fuses the means themselves)."""
    if residual is None and add is None:
        residual = getattr(filt, "residual_x", None)
        add = getattr(filt, "state_add", None)
    if residual is np.subtract:
        residual = None
    if add is np.add:
        add = None
    return residual, add


class FusionMixin:
    """Adds :meth:`fuse` to a filterpy-style filter.

    The filter must have attributes ``x`` (state, any shape holding n numbers, e.g.
    ``(n, 1)`` or ``(n,)``) and ``P`` (``(n, n)`` covariance). Put the mixin first in the
    bases so that its method is found: ``class MyFilter(FusionMixin, SomeFilterpyFilter)``.

    Attributes
    ----------
    last_fusion : FusionResult or None
        The result of the latest successful :meth:`fuse` (None before the first).

    Examples
    --------
    >>> import numpy as np
    >>> from filterpy.kalman import InformationFilter
    >>> from cifilter import FusionMixin
    >>> class FusingKF(FusionMixin, InformationFilter):
    ...     pass
    """

    last_fusion: Optional[FusionResult] = None

    # The filter's own attributes (set by the filterpy class the mixin is combined with).
    x: Any
    P: Any
    x_post: Any
    P_post: Any

    def fuse(self, other: Any, method: str = "ci", *, H: Any = None,
             residual: Optional[Callable[..., Any]] = None,
             add: Optional[Callable[..., Any]] = None, times: Optional[Sequence[float]] = None,
             at: Optional[float] = None, motion: Optional[Callable[..., Any]] = None,
             lag: Union[int, Sequence[int], None] = None, horizon: Optional[int] = None,
             model: Any = None, future: Any = None, **options: Any) -> FusionResult:
        """Fuse this filter's estimate with other estimates whose correlation is unknown.

        The filter's own ``(x, P)`` is the first input of the fusion rule; its ``x`` (and
        that of the other estimates) may have any shape holding its n numbers, such as
        filterpy's ``(n, 1)``, ``(n,)`` or ``(1, n)``. On success the
        filter's ``x`` and ``P`` are replaced by the fused estimate (``x`` keeps its
        filterpy shape), ``x_post`` and ``P_post`` are set to copies as ``update`` does,
        and the result is stored in ``last_fusion``. The operation is atomic: if the
        fusion raises, the filter is exactly as before. ``other`` is never modified.

        Parameters
        ----------
        other : filter, (x, P) pair, or list of them
            The estimates to fuse with: another filter (anything with ``.x`` and ``.P``),
            an ``(x, P)`` pair, or a list of filters and pairs.
        method : str, optional
            A registered fusion rule (see :func:`cifilter.available_methods`), default
            ``"ci"``.
        H : array_like, shape (m, n), or sequence, optional
            ``other`` estimates ``H x`` of this filter's state (m numbers, for instance a
            position-only track of a position-velocity filter); for a list of others, one
            entry per other (None for an estimate of the full state). This is
            :func:`cifilter.fuse`'s ``H=`` with None for this filter, for the rules that
            accept it (``"ci"``, ``"naive"``, ``"optimal"``, ``"split-ci"``).
        residual, add : callable, optional
            ``residual(a, b)`` (``a - b`` in the state space) and ``add(x, dx)``: the
            others are fused as residuals relative to this filter's state and the fused
            residual is added to it (:func:`cifilter.fuse`'s ``residual=``, ``add=``). By
            default an :class:`UnscentedKalmanFilter` uses its own ``residual_x`` and, where
            filterpy has it, ``state_add`` (plain subtraction and addition mean none).
        times : sequence of float, optional
            The time of each estimate, this filter's first (:func:`cifilter.fuse`'s
            ``times=``).
        at : float, optional
            The time to fuse at; default this filter's own time ``times[0]`` (the fused
            estimate replaces the filter's, so it describes the filter's time).
        motion : callable, optional
            ``motion(dt) -> (F, Q)`` bringing an estimate ``dt`` forward
            (:func:`cifilter.fuse`'s ``motion=``).
        lag : int or sequence of int, optional
            ``other`` describes the state ``lag`` of this filter's steps ago: ``lag > 0``
            predicts it ``lag`` steps with the filter's ``F`` and ``Q`` (exact);
            ``lag < 0`` means ``|lag|`` steps ahead, brought back with ``F^-|lag|`` and the
            accumulated ``Q_|lag| = sum_j F^j Q F^jT`` by the retrodiction bound of
            ``docs/methods/time.rst`` (a ValueError if ``F`` is singular); 0 no shift. One
            per other, or one for all. Instead of ``times``/``at``/``motion``.
        horizon : int, optional
            Choose the rule's weights for the bound ``horizon`` predict/update steps after
            the fusion (Ajgl et al. 2014), for the rules that support it (``"ci"``, and
            ``"pci"`` with ``rho``), using the filter's own ``F``, ``Q``, ``H``, ``R`` or
            ``model``. This is :func:`cifilter.fuse`'s ``horizon=``: ``info["rule"]`` is
            ``"horizon"`` and ``info["horizon"]`` holds the choice (``steps``,
            ``criterion``, ``value``, and for comparison ``value_recursive`` and
            ``weights_recursive``, the criterion at the horizon with the weights that are
            optimal now, and those weights). ``horizon=0`` is the ordinary rule.
        model : mapping or object, optional
            The model of the steps after the fusion, instead of the filter's own: a mapping
            or an object (such as another ``KalmanFilter``) with ``F`` and ``Q`` and
            optionally ``H``, ``R`` (None or absent: no measurements) and ``G``; ``H`` and
            ``R`` may be per-step lists (see :func:`cifilter.horizon.propagate_bound`).
            Needed for filters without matrices ``F``, ``Q``, ``H``, ``R`` (the EKF and UKF).
        future : mapping or object, optional
            Former name of ``model`` (deprecated; a ``DeprecationWarning``).
        **options
            Options of the rule (e.g. ``criterion="det"`` or ``omega="fast"`` for
            ``"ci"``).

        Returns
        -------
        FusionResult
            The fusion result (also stored in ``last_fusion``).

        Raises
        ------
        TypeError
            ``other`` is not an estimate or a list of estimates; an unknown option.
        ValueError
            Dimension mismatch, non-finite values, a covariance that is not symmetric
            positive definite, batched inputs, or a bad option value; ``horizon`` with a
            method other than ``"ci"`` and ``"pci"`` or together with ``omega`` (``"ci"``)
            or ``delta`` (``"pci"``), ``"pci"`` without ``rho``, ``model`` without
            ``horizon``, a filter without a linear model and no ``model``; ``H``,
            ``residual`` or ``times``/``lag`` for a rule that does not accept them, ``lag``
            together with ``times``, ``lag`` for a filter without ``F`` and ``Q``, a singular
            ``F`` for ``lag < 0``. Messages name the estimate: ``"this filter's P"``,
            ``"other's x"`` or ``"other[i]'s P"`` (for a list).

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import KalmanFilter
        >>> kf = KalmanFilter(dim_x=2, dim_z=1)
        >>> kf.P = np.diag([1.0, 4.0])
        >>> result = kf.fuse((np.ones(2), np.diag([4.0, 1.0])))
        >>> kf.x.shape, float(np.trace(kf.P)), float(result.omega[0])
        ((2, 1), 3.2, 0.5)

        Choosing omega for the bound after ten more steps of this filter:

        >>> kf.F, kf.H = np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[1.0, 0.0]])
        >>> result = kf.fuse((np.ones(2), np.diag([4.0, 1.0])), horizon=10)
        >>> result.info["rule"], result.info["horizon"]["steps"]
        ('horizon', 10)

        The same with partial-correlation CI for a correlation coefficient bound of 0.5:

        >>> result = kf.fuse((np.ones(2), np.diag([4.0, 1.0])), method="pci", rho=0.5,
        ...                  horizon=10)
        >>> result.method, result.info["rule"], bool(result.info["converged"])
        ('pci', 'horizon', True)

        A position-only estimate (``H`` picks the position) that is two steps old:

        >>> kf.Q = 0.01 * np.eye(2)
        >>> result = kf.fuse((np.array([0.5]), np.array([[0.2]])), H=np.array([[1.0, 0.0]]))
        >>> result = kf.fuse((np.ones(2), np.eye(2)), lag=2)
        >>> result.info["at"], kf.x.shape
        (0.0, (2, 1))
        """
        if _is_plain_pair(other):  # the usual call: what the two lines below give it
            others, labels = [other], _LABELS
        else:
            others = _as_estimate_list(other)
            labels = _labels(1 + len(others), not (len(others) == 1 and others[0] is other))
        estimates = _single_estimates([(self.x, self.P)] + others, labels)
        if future is not None:
            if model is not None:
                raise ValueError("give model= only (future= is its former name)")
            warnings.warn("kf.fuse(..., future=) is now model=, as in cifilter.fuse",
                          DeprecationWarning, stacklevel=2)
            model = future
        if horizon is not None and model is None:
            model = _own_model(self)
        if H is not None:
            H = [None, H] if len(others) == 1 and others[0] is other else [None] + list(H)
        residual, add = _own_residual(self, residual, add)
        if lag is not None:
            if times is not None or at is not None or motion is not None:
                raise ValueError("give lag= (steps of this filter) or times=, at= and "
                                 "motion=, not both")
            times, at = _lag_times(lag, len(estimates))
            if any(times):
                motion = _own_step_model(self)
            else:  # lag 0: no shift
                times = at = None
        elif times is not None and at is None and hasattr(times, "__len__") and len(times):
            at = times[0]  # the fused estimate replaces this filter's: its time
        result = fuse_estimates(estimates, method, options, horizon=horizon, model=model,
                                labels=labels, H=H, residual=residual, add=add, times=times,
                                at=at, motion=motion)
        x_shape = np.shape(self.x)
        x = result.x  # (a read-only array)
        if x.size != math.prod(x_shape) or result.P.shape != np.shape(self.P):
            raise ValueError(
                f"fusion gave x of shape {x.shape} and P of shape {np.shape(result.P)}; a "
                f"filter with x of shape {x_shape} fuses single (unbatched) estimates only"
            )
        # Everything that can fail (including the copies) has run; now change the filter.
        x_new, P_new = np.array(x.reshape(x_shape)), np.array(result.P)
        x_post, P_post = x_new.copy(), P_new.copy()
        self.x, self.P, self.x_post, self.P_post = x_new, P_new, x_post, P_post
        self.last_fusion = result
        return result


class KalmanFilter(FusionMixin, _FilterpyKF):
    """filterpy's ``KalmanFilter`` with :meth:`~FusionMixin.fuse`.

    Same constructor and behaviour as ``filterpy.kalman.KalmanFilter``; see its
    documentation for ``x``, ``P``, ``F``, ``Q``, ``H``, ``R``, ``predict`` and ``update``.

    Parameters
    ----------
    dim_x : int
        Number of state variables.
    dim_z : int
        Number of measurement inputs.
    dim_u : int, optional
        Size of the control input (default 0).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import KalmanFilter
    >>> kf = KalmanFilter(dim_x=2, dim_z=1)
    >>> kf.F = np.array([[1.0, 1.0], [0.0, 1.0]])
    >>> kf.H = np.array([[1.0, 0.0]])
    >>> kf.predict(); kf.update(np.array([[1.0]]))
    >>> _ = kf.fuse((np.array([1.0, 0.0]), np.eye(2)), method="ci")
    """


class ExtendedKalmanFilter(FusionMixin, _FilterpyEKF):
    """filterpy's ``ExtendedKalmanFilter`` with :meth:`~FusionMixin.fuse`.

    Same constructor and behaviour as ``filterpy.kalman.ExtendedKalmanFilter``.

    Parameters
    ----------
    dim_x : int
        Number of state variables.
    dim_z : int
        Number of measurement inputs.
    dim_u : int, optional
        Size of the control input (default 0).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import ExtendedKalmanFilter
    >>> ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    >>> _ = ekf.fuse((np.zeros(2), np.eye(2)))
    """


class UnscentedKalmanFilter(FusionMixin, _FilterpyUKF):
    """filterpy's ``UnscentedKalmanFilter`` with :meth:`~FusionMixin.fuse`.

    Same constructor and behaviour as ``filterpy.kalman.UnscentedKalmanFilter``; its
    state ``x`` is a 1-D array and stays one after fusion.

    Parameters
    ----------
    dim_x : int
        Number of state variables.
    dim_z : int
        Number of measurement inputs.
    dt : float
        Time step.
    hx : callable
        Measurement function.
    fx : callable
        State transition function.
    points : object
        Sigma point generator, e.g. ``filterpy.kalman.MerweScaledSigmaPoints``.
    sqrt_fn, x_mean_fn, z_mean_fn, residual_x, residual_z, state_add : callable, optional
        As in filterpy: matrix square root, state and measurement means, residuals and
        state addition (for angles and other non-Euclidean states; ``state_add`` exists
        from filterpy 2.0 on).

    Examples
    --------
    >>> import numpy as np
    >>> from filterpy.kalman import MerweScaledSigmaPoints
    >>> from cifilter import UnscentedKalmanFilter
    >>> points = MerweScaledSigmaPoints(2, alpha=0.1, beta=2.0, kappa=1.0)
    >>> ukf = UnscentedKalmanFilter(2, 1, 1.0, hx=lambda x: x[:1], fx=lambda x, dt: x,
    ...                             points=points)
    >>> _ = ukf.fuse((np.ones(2), np.eye(2)))
    >>> ukf.x.shape
    (2,)
    """
