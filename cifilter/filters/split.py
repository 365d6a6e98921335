"""A Kalman filter that keeps its covariance split into independent and dependent parts,
for Split Covariance Intersection (Li, Nashashibi & Yang 2013)."""

import math
from numbers import Real
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.linalg import positive_definite
from .._numerics.validation import as_float_array, check_psd
from ..result import FusionResult
from ..rules.split_ci import split_covariance_intersection
from .kalman import KalmanFilter

__all__ = ["SplitCIKalmanFilter"]


def _split_estimate(item, index):
    """``(x, P_ind, P_dep)`` of another estimate: a split filter, a triple, or a plain
    filter or ``(x, P)`` pair (then wholly dependent)."""
    name = "other" if index is None else f"other[{index}]"
    if isinstance(item, SplitCIKalmanFilter):
        item._sync_split()
        return item.x, item.P_ind, item.P_dep
    if hasattr(item, "x") and hasattr(item, "P"):
        P = as_float_array(item.P, f"{name}'s P")
        return item.x, np.zeros_like(P), P
    if isinstance(item, (tuple, list)) and len(item) == 3:
        return tuple(item)
    if isinstance(item, (tuple, list)) and len(item) == 2:
        P = as_float_array(item[1], f"{name}'s P")
        return item[0], np.zeros_like(P), P
    raise TypeError(
        f"{name} must be a SplitCIKalmanFilter, an (x, P_ind, P_dep) triple, a filter or an "
        f"(x, P) pair (wholly dependent); got {type(item).__name__}"
    )


class SplitCIKalmanFilter(KalmanFilter):
    """A filterpy ``KalmanFilter`` whose covariance is split as ``P = P_ind + P_dep``.

    ``P_ind`` is the covariance of the part of the error that is independent of other
    filters' independent parts (measurement noise, process noise), ``P_dep`` the part that
    may be correlated with them (the prior, information received by fusion). ``predict``
    adds the process noise ``Q`` to the independent part, ``update`` the measurement noise
    ``R``; both propagate the two parts with the same ``F`` and gain as ``P``, so
    ``P = P_ind + P_dep`` always holds. :meth:`fuse` uses Split Covariance Intersection
    with another such filter or an explicit ``(x, P_ind, P_dep)`` triple. Everything else
    is :class:`cifilter.KalmanFilter` (and filterpy's ``KalmanFilter``).

    Parameters
    ----------
    dim_x : int
        Number of state variables.
    dim_z : int
        Number of measurement inputs.
    dim_u : int, optional
        Size of the control input (default 0).

    Attributes
    ----------
    P_ind : ndarray, shape (dim_x, dim_x)
        Independent part of ``P`` (initially zero).
    P_dep : ndarray, shape (dim_x, dim_x)
        Dependent part of ``P`` (initially ``P``).

    Notes
    -----
    If ``P`` is assigned directly (as filterpy code does, ``kf.P = ...``), the next
    ``predict``, ``update`` or ``fuse`` treats all of it as dependent (``P_ind = 0``), the
    conservative reading; use :meth:`set_split` to give both parts. A fusion with another
    rule (``fuse(other, method="ci")``) also leaves the fused ``P`` wholly dependent.
    With filterpy's fading memory (``alpha``) both parts are scaled by ``alpha**2``.

    References
    ----------
    .. [1] H. Li, F. Nashashibi and M. Yang, "Split covariance intersection filter:
       theory and its application to vehicle localization", IEEE TITS 14(4), 2013.

    Examples
    --------
    Two filters of one target whose priors are common (dependent) and whose measurements
    are their own (independent):

    >>> import numpy as np
    >>> from cifilter import SplitCIKalmanFilter
    >>> filters = []
    >>> for H in (np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]])):
    ...     kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
    ...     kf.F, kf.H, kf.Q, kf.R = np.eye(2), H, 0.01 * np.eye(2), np.eye(1)
    ...     kf.predict(); kf.update(np.array([[0.5]]))
    ...     filters.append(kf)
    >>> a, b = filters
    >>> result = a.fuse(b)
    >>> bool(np.allclose(a.P, a.P_ind + a.P_dep)), result.method
    (True, 'split-ci')
    """

    def __init__(self, dim_x: int, dim_z: int, dim_u: int = 0) -> None:
        super().__init__(dim_x, dim_z, dim_u)
        self.P_ind: NDArray[np.float64] = np.zeros((dim_x, dim_x))
        self.P_dep: NDArray[np.float64] = np.array(self.P, dtype=float)
        # the P the split belongs to
        self._split_of: NDArray[np.float64] = np.array(self.P, dtype=float)

    def set_split(self, P_ind: ArrayLike, P_dep: ArrayLike) -> None:
        """Set both parts of the covariance; ``P`` becomes their sum.

        Parameters
        ----------
        P_ind : array_like, shape (dim_x, dim_x)
            Independent part, symmetric positive semidefinite.
        P_dep : array_like, shape (dim_x, dim_x)
            Dependent part, symmetric positive semidefinite.

        Returns
        -------
        None
            The filter's ``P_ind``, ``P_dep`` and ``P`` are replaced (copies).

        Raises
        ------
        ValueError
            Wrong shape, non-finite, not symmetric positive semidefinite, or a sum that
            is not positive definite (nothing is changed then).

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import SplitCIKalmanFilter
        >>> kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
        >>> kf.set_split(np.eye(2), 2 * np.eye(2))
        >>> np.diag(kf.P).tolist()
        [3.0, 3.0]
        """
        n = self.dim_x
        ind = check_psd(P_ind, n, "P_ind")
        dep = check_psd(P_dep, n, "P_dep")
        if ind.shape != (n, n) or dep.shape != (n, n):
            raise ValueError(f"P_ind and P_dep must be {n}x{n} matrices")
        P = ind + dep
        if not positive_definite(P):
            raise ValueError("P_ind + P_dep must be positive definite")
        self._set_parts(ind, dep)

    def _set_parts(self, P_ind, P_dep):
        P = 0.5 * ((P_ind + P_dep) + (P_ind + P_dep).T)
        self.P_ind, self.P_dep, self.P = np.array(P_ind), np.array(P_dep), P
        self._split_of = P.copy()

    def _sync_split(self):
        """A ``P`` assigned directly is taken as wholly dependent (see the class notes)."""
        if np.shape(self.P) != self._split_of.shape or not np.array_equal(self.P,
                                                                           self._split_of):
            P = np.array(self.P, dtype=float)
            self.P_ind, self.P_dep, self._split_of = np.zeros_like(P), P.copy(), P.copy()

    def predict(self, u: Optional[ArrayLike] = None, B: Optional[ArrayLike] = None,
                F: Optional[np.ndarray] = None,
                Q: Optional[Union[np.ndarray, float]] = None) -> None:
        """Predict as filterpy does, with ``Q`` added to the independent part.

        Parameters
        ----------
        u : ndarray, optional
            Control vector.
        B : ndarray, optional
            Control transition matrix (default ``self.B``).
        F : ndarray, optional
            State transition matrix (default ``self.F``).
        Q : ndarray or float, optional
            Process noise (default ``self.Q``; a scalar means ``Q * I``).

        Returns
        -------
        None
            ``x``, ``P``, ``P_ind``, ``P_dep``, ``x_prior`` and ``P_prior`` are updated.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import SplitCIKalmanFilter
        >>> kf = SplitCIKalmanFilter(dim_x=1, dim_z=1)
        >>> kf.Q = 0.5 * np.eye(1)
        >>> kf.predict()
        >>> kf.P_ind.tolist(), kf.P_dep.tolist()
        ([[0.5]], [[1.0]])
        """
        self._sync_split()
        F_used = self.F if F is None else F
        if Q is None:
            Q_used = self.Q
        elif isinstance(Q, Real) or np.ndim(Q) == 0:
            Q_used = np.eye(self.dim_x) * Q
        else:
            Q_used = Q
        super().predict(u=u, B=B, F=F, Q=Q)
        a2 = self._alpha_sq
        P_ind = a2 * (F_used @ self.P_ind @ F_used.T) + Q_used
        P_dep = a2 * (F_used @ self.P_dep @ F_used.T)
        self._set_parts(P_ind, P_dep)
        self.P_prior = self.P.copy()

    def update(self, z: Optional[ArrayLike], R: Optional[Union[np.ndarray, float]] = None,
               H: Optional[np.ndarray] = None) -> None:
        """Update as filterpy does (Joseph form), with ``R`` added to the independent part.

        Parameters
        ----------
        z : ndarray or None
            Measurement; None skips the update (as in filterpy).
        R : ndarray or float, optional
            Measurement noise (default ``self.R``; a scalar means ``R * I``).
        H : ndarray, optional
            Measurement matrix (default ``self.H``).

        Returns
        -------
        None
            ``x``, ``P``, ``P_ind``, ``P_dep``, ``x_post`` and ``P_post`` are updated.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import SplitCIKalmanFilter
        >>> kf = SplitCIKalmanFilter(dim_x=1, dim_z=1)
        >>> kf.H = np.eye(1)
        >>> kf.update(np.array([[1.0]]))
        >>> kf.P_ind.tolist(), kf.P_dep.tolist()
        ([[0.25]], [[0.25]])
        """
        self._sync_split()
        super().update(z, R=R, H=H)
        if z is None:
            return
        if R is None:
            R = self.R
        elif isinstance(R, Real) or np.ndim(R) == 0:
            R = np.eye(self.dim_z) * R
        H = self.H if H is None else H
        I_KH = self._I - self.K @ H
        P_ind = I_KH @ self.P_ind @ I_KH.T + self.K @ R @ self.K.T
        P_dep = I_KH @ self.P_dep @ I_KH.T
        self._set_parts(P_ind, P_dep)
        self.P_post = self.P.copy()

    def fuse(self, other: Any, method: str = "split-ci", *,
             criterion: Optional[Union[str, ArrayLike]] = None, H: Optional[ArrayLike] = None,
             **options: Any) -> FusionResult:
        """Fuse with other estimates by Split Covariance Intersection (or another rule).

        With ``method="split-ci"`` (default) the filter's ``(x, P_ind, P_dep)`` is fused
        with the other estimates' parts by :func:`split_covariance_intersection`, and the
        fused ``P_ind``, ``P_dep`` replace the filter's. The operation is atomic: if it
        raises, the filter is unchanged. ``other`` is never modified.

        Parameters
        ----------
        other : SplitCIKalmanFilter, tuple, filter, or list of them
            Another split filter, an explicit ``(x, P_ind, P_dep)`` triple, or a plain
            filter or ``(x, P)`` pair (taken as wholly dependent); or a list of them
            (fused sequentially in order).
        method : str, optional
            ``"split-ci"`` (default), or any registered rule: that rule is then applied
            by :meth:`cifilter.FusionMixin.fuse` and the fused ``P`` is wholly dependent.
        criterion : {"det", "trace"} or array_like, optional
            The criterion for omega: split CI's default is ``"det"``; with another rule,
            that rule's own default unless given.
        H : array_like, shape (m, dim_x), optional
            The single other estimate observes ``H x`` (a partial estimate of dimension
            m); its parts are then m x m. With another ``method``, passed on as
            :meth:`cifilter.FusionMixin.fuse`'s ``H=`` (for the rules that accept it).
        **options
            Options of another rule, and the other front-door options of
            :meth:`cifilter.FusionMixin.fuse` (``residual``, ``add``, ``times``, ``at``,
            ``motion``, ``lag``, ``horizon``, ``model``); only with ``method`` other than
            ``"split-ci"``.

        Returns
        -------
        FusionResult
            The fusion result (also stored in ``last_fusion``); for split CI
            ``info["P_independent"]`` and ``info["P_dependent"]`` are the new parts.

        Raises
        ------
        TypeError
            ``other`` is not an estimate; an unknown option.
        ValueError
            Dimension mismatch, non-finite values, parts that are not positive
            semidefinite, or a bad option value.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import SplitCIKalmanFilter
        >>> kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
        >>> kf.set_split(np.diag([1.0, 4.0]), np.zeros((2, 2)))
        >>> r = kf.fuse((np.zeros(2), np.diag([4.0, 1.0]), np.zeros((2, 2))))
        >>> np.diag(kf.P).tolist()  # independent estimates: the Kalman update
        [0.8, 0.8]
        """
        if method != "split-ci":
            if H is not None:
                options = dict(options, H=H)
            result = _fuse_with_rule(self, other, method, criterion, options)
            P = np.array(self.P, dtype=float)
            self.P_ind, self.P_dep, self._split_of = np.zeros_like(P), P.copy(), P.copy()
            return result
        if options:
            raise TypeError(f"unknown option(s) for split CI: {', '.join(sorted(options))}")
        self._sync_split()
        if isinstance(other, list):
            items = [_split_estimate(item, i) for i, item in enumerate(other)]
        else:
            items = [_split_estimate(other, None)]
        x_shape = np.shape(self.x)
        n = self.dim_x
        x_self = np.reshape(np.asarray(self.x, dtype=float), (n,))
        xs = [x_self] + [item[0] for item in items]
        result = split_covariance_intersection(
            xs, [self.P_ind] + [item[1] for item in items],
            [self.P_dep] + [item[2] for item in items], H=H,
            criterion="det" if criterion is None else criterion)
        x = np.asarray(result.x)
        if x.size != math.prod(x_shape) or result.P.shape != (n, n):
            raise ValueError("a filter fuses single (unbatched) estimates only")
        # Everything that can fail has run; now change the filter.
        x_new = np.array(x.reshape(x_shape))
        self._set_parts(np.array(result.info["P_independent"]),
                        np.array(result.info["P_dependent"]))
        self.x = x_new
        self.x_post, self.P_post = x_new.copy(), self.P.copy()
        self.last_fusion = result
        return result


def _fuse_with_rule(filt, other, method, criterion, options):
    """:meth:`cifilter.FusionMixin.fuse` on a split filter (criterion passed if given)."""
    if criterion is not None:
        options = dict(options, criterion=criterion)
    return KalmanFilter.fuse(filt, other, method, **options)
