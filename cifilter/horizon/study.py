"""Batch versus recursive CI over a range of horizons: :func:`horizon_study` and its
result :class:`HorizonStudy` (Figs. 3, 4, 6 and 7 of Ajgl et al. 2014).

See ``docs/methods/horizon.rst``.
"""

import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, Union, cast

import numpy as np
from numpy.typing import NDArray

from .._numerics.criteria import criterion_value, parse_criterion
from .._numerics.validation import Estimates, as_covariances, check_int
from ._core import (
    Problem,
    as_rho,
    bind_arguments,
    documented_signature,
    fused_bound,
    problem_of,
    solve,
)
from ._model import (
    as_model,
    at_horizon,
    check_steps_available,
    checked_bound,
    criterion_at,
    horizon_terms,
    stack_terms,
)
from .model import steady_state_covariance

if TYPE_CHECKING:  # matplotlib is an optional dependency (for plot only)
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure, SubFigure

__all__ = ["HorizonStudy", "horizon_study"]


@dataclass(frozen=True, repr=False)
class HorizonStudy:
    """Batch versus recursive CI over a range of horizons (result of :func:`horizon_study`).

    The parameters are also the attributes of the result. Trailing axes run over the
    horizons; leading axes are the batch of fusion problems.

    Parameters
    ----------
    horizons : ndarray, shape (K,)
        The horizons ``kappa``.
    omega : ndarray, shape (..., K)
        The batch-optimal omega for each horizon.
    batch : ndarray, shape (..., K)
        The criterion of the propagated bound with the horizon-optimal omega.
    recursive : ndarray, shape (..., K)
        The criterion with omega fixed at its horizon-0 optimum (the recursive approach).
    omega_recursive : ndarray, shape (...)
        The omega of the recursive approach (criterion-optimal CI at the fusion time).
    criterion : str
        ``"trace"``, ``"det"`` or ``"weighted-trace"``.
    P_batch, P_recursive : ndarray, shape (..., K, n, n)
        The propagated bounds of the two approaches.
    steady_P : ndarray, shape (..., n, n), or None
        The local filter's steady posterior covariance (discrete algebraic Riccati
        equation), the limit of both bounds; None for per-step measurement models.
    steady_value : ndarray, shape (...), or None
        Its criterion (the limit of ``batch`` and ``recursive``).
    omega_limit : ndarray, shape (...)
        The limit of the batch-optimal omega as the horizon grows (NaN if it has none, for
        instance when the closed loop's dominant mode rotates, or for per-step models).
    rho : ndarray, shape (..., 2), or None
        The correlation coefficient bounds of partial CI as used (``sqrt(rho_A rho_B)``
        twice), or None for CI; with ``rho`` the omega fields hold ``delta_1``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.horizon import horizon_study
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> s = horizon_study(np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13]), F, Q,
    ...                   np.array([[1.0, 0.0]]), 1.0, horizons=10, criterion="det")
    >>> bool(np.all(s.batch <= s.recursive)), round(float(s.omega_limit), 3)
    (True, 0.042)
    """

    horizons: NDArray[np.int_]
    omega: NDArray[np.float64]
    batch: NDArray[np.float64]
    recursive: NDArray[np.float64]
    omega_recursive: NDArray[np.float64]
    criterion: str
    P_batch: NDArray[np.float64]
    P_recursive: NDArray[np.float64]
    steady_P: Optional[NDArray[np.float64]]
    steady_value: Optional[NDArray[np.float64]]
    omega_limit: NDArray[np.float64]
    rho: Optional[NDArray[np.float64]] = None

    def __repr__(self) -> str:
        return (f"HorizonStudy(criterion={self.criterion!r}, horizons {self.horizons[0]}.."
                f"{self.horizons[-1]}, batch shape={np.shape(self.omega_recursive)})")

    def plot(self, axes: Optional[Sequence["Axes"]] = None,
             label: Optional[str] = None) -> Union["Figure", "SubFigure"]:
        """Draw omega and the two criteria against the horizon (as Figs. 3 and 4).

        Parameters
        ----------
        axes : sequence of two matplotlib.axes.Axes, optional
            Where to draw omega and the criterion; new axes in a new figure by default.
        label : str, optional
            Prefix of the legend labels (for instance the filter's name).

        Returns
        -------
        matplotlib.figure.Figure
            The figure of the axes.

        Raises
        ------
        ValueError
            If the study is batched (draw one problem: index the inputs first) or ``axes``
            does not hold two axes.

        Examples
        --------
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import matplotlib.pyplot as plt
        >>> import numpy as np
        >>> from cifilter.horizon import horizon_study
        >>> s = horizon_study(np.eye(2), 2 * np.eye(2), 0.9 * np.eye(2), np.eye(2),
        ...                   np.array([[1.0, 0.0]]), 1.0, horizons=5)
        >>> fig = s.plot(label="A")
        >>> plt.close(fig)
        """
        if np.ndim(self.omega_recursive) != 0:
            raise ValueError("plot draws one fusion problem; this study is batched with shape "
                             f"{np.shape(self.omega_recursive)}")
        import matplotlib.pyplot as plt

        if axes is None:
            _, axes = plt.subplots(1, 2, figsize=(9, 3.5), layout="constrained")
        if len(axes) != 2:
            raise ValueError(f"axes must hold two matplotlib axes, got {len(axes)}")
        prefix = f"{label}: " if label else ""
        ax_omega, ax_value = axes
        ax_omega.plot(self.horizons, self.omega, "o-", ms=3, label=f"{prefix}batch (optimal)")
        ax_omega.axhline(float(self.omega_recursive), ls="--", color="gray",
                         label=f"{prefix}recursive (fixed at 0)")
        if np.isfinite(self.omega_limit):
            ax_omega.axhline(float(self.omega_limit), ls=":", color="k",
                             label=f"{prefix}limit")
        weight = "$\\omega$" if self.rho is None else "$\\delta_1$ (partial CI)"
        ax_omega.set(xlabel="horizon $\\kappa$", ylabel=weight, ylim=(-0.02, 1.02))
        ax_value.plot(self.horizons, self.batch, "-", label=f"{prefix}batch")
        ax_value.plot(self.horizons, self.recursive, "--", label=f"{prefix}recursive")
        if self.steady_value is not None:
            ax_value.axhline(float(self.steady_value), ls=":", color="k",
                             label=f"{prefix}steady state")
        ax_value.set(xlabel="horizon $\\kappa$", ylabel=f"{self.criterion} of the bound")
        for ax in axes:
            ax.legend(fontsize="small")
        return ax_omega.figure


def _as_horizons(horizons):
    if isinstance(horizons, numbers.Integral) and not isinstance(horizons, bool):
        return np.arange(check_int(horizons, "horizons", low=0) + 1)
    values = np.asarray(horizons)
    if values.ndim != 1 or values.size == 0 or not np.issubdtype(values.dtype, np.integer):
        raise ValueError("horizons must be a non-negative integer K (meaning 0..K) or a "
                         f"non-empty 1-D sequence of integers, got {horizons!r}")
    if np.any(values < 0):
        raise ValueError(f"horizons must be >= 0, got {values.min()}")
    return values.astype(int)


# Horizons at which the limit of omega is looked for; converged when the last two agree.
_LIMIT_HORIZONS = (200, 400)


def horizon_study(*args: Any, **kwargs: Any) -> HorizonStudy:
    """Batch versus recursive Covariance Intersection for a range of horizons.

    For each horizon ``kappa``, the batch approach of Ajgl et al. (2014) chooses omega for the
    bound after ``kappa`` filter steps (:func:`optimal_omega`); the recursive approach fixes
    omega at its ``kappa = 0`` optimum and filters on (eqs. 31-33). The study also gives the
    steady-state limit of both bounds (the local filter's discrete algebraic Riccati
    equation) and the limit of the batch-optimal omega.

    Called as ``horizon_study(Ps, F, Q, H, R, horizons, criterion="trace", G=None, *,
    limit=True, rho=None)`` or pairwise as ``horizon_study(PA, PB, F, Q, H, R, horizons,
    ...)``; the pairwise form is recognised by the horizons (an integer or a 1-D sequence
    of integers) as the seventh positional argument, or by six positional arguments
    before ``horizons=``.

    Parameters
    ----------
    Ps : sequence of two array_like or array_like, shape (..., 2, n, n)
        Covariances (bounds) of the two estimates; omega weighs the first. In the pairwise
        form, ``PA`` and ``PB`` (..., n, n) as two arguments.
    F, Q, H, R, G : array_like
        The model of the fusing filter (see :func:`propagate_bound`); per-step sequences of
        ``H`` and ``R`` need one entry per step up to the largest horizon.
    horizons : int or sequence of int
        ``K`` for the horizons 0, 1, ..., K, or the horizons themselves.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise.
    limit : bool, optional
        Compute ``omega_limit`` (default True; it costs a 400-step recursion).
    rho : float or array_like, shape (..., 2) or (..., 1), optional
        Correlation coefficient bound(s) of partial CI (see :func:`optimal_omega`); the
        omega fields then hold ``delta_1``. None (default): Covariance Intersection.

    Returns
    -------
    HorizonStudy
        Arrays ``horizons``, ``omega``, ``batch``, ``recursive`` (and the bounds, the steady
        state and the limit of omega) and a ``plot()`` method.

    Raises
    ------
    ValueError
        Bad covariances, model, criterion or horizons; a bound or criterion value that float64
        cannot hold at one of the horizons (named in the message).
    IllConditionedError
        As :func:`optimal_omega`.
    TypeError
        Non-numeric input, or arguments that fit neither form.

    Notes
    -----
    One Riccati run gives the horizon terms of every horizon, and the convex problems of
    all horizons and batch items are solved together. For a fixed omega the batch and the
    recursive bounds coincide (Sec. III of the paper), so ``batch <= recursive`` at every
    horizon, with equality at ``kappa = 0``. ``omega_limit`` is the optimum at horizons 200
    and 400 when the two agree to 1e-8. ``steady_P`` is None when the Riccati equation has
    no stabilising solution. Details: ``docs/methods/horizon.rst``.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014, Sec. IV.B,
       eqs. (29)-(35), Figs. 3, 4, 6 and 7.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, eqs. (24), (33) (with ``rho``).

    Examples
    --------
    Fig. 3, filter B with the trace criterion:

    >>> import numpy as np
    >>> from cifilter.horizon import horizon_study
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> s = horizon_study(np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13]), F, Q,
    ...                   np.array([[0.0, 1.0]]), 3.0, horizons=[0, 1, 50])
    >>> s.omega.round(3).tolist(), round(float(s.omega_limit), 3)
    ([0.412, 0.779, 0.853], 0.853)

    The same with partial CI for ``rho = 0.5``:

    >>> s = horizon_study(np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13]), F, Q,
    ...                   np.array([[0.0, 1.0]]), 3.0, horizons=[0, 1, 50], rho=0.5)
    >>> s.omega.round(3).tolist(), round(float(s.omega_limit), 3)
    ([0.433, 0.639, 0.657], 0.657)

    The ``Ps`` form takes the two covariances as one argument:

    >>> s = horizon_study([np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])], F, Q,
    ...                   np.array([[0.0, 1.0]]), 3.0, horizons=[0, 1, 50], limit=False)
    >>> s.omega.round(3).tolist()
    [0.412, 0.779, 0.853]
    """
    Ps, a = bind_arguments("horizon_study", args, kwargs, "horizons", ("limit", "rho"))
    horizons = _as_horizons(a["horizons"])
    est = as_covariances(Ps, name="Ps")
    if est.count != 2:
        raise ValueError(f"horizon_study compares two estimates, got {est.count}")
    rho = as_rho(a.get("rho"), 2, est.batch_shape)
    rho_k = None if rho is None else rho[..., None, :]
    n = est.dim
    kind, W = parse_criterion(a["criterion"], n)
    model = as_model(a["F"], a["Q"], a["H"], a["R"], a["G"], n)
    check_steps_available(model, int(horizons.max()))
    distinct = sorted(set(horizons.tolist()) | {0})
    limit = bool(a.get("limit", True)) and model.steps is None
    limit_at = [h for h in _LIMIT_HORIZONS if h not in distinct] if limit else []
    everything = sorted(set(distinct) | set(limit_at))
    collected = dict(zip(everything, horizon_terms(model, everything[-1], n,
                                                     collect=everything)))
    terms = stack_terms([collected[h] for h in horizons])
    problem = problem_of(est)
    problem_k = Problem._make(None if p is None else _along_horizons(p) for p in problem)
    weights, _ = solve(problem_k, terms, kind, W, rho_k, horizons)
    recursive_w, _ = solve(problem, collected[0], kind, W, rho, 0)
    P_hat = fused_bound(problem_k, terms, weights, rho_k)
    where = at_horizon(horizons, np.broadcast_to(weights, P_hat.shape[:-2] + weights.shape[-1:]))
    P_batch = checked_bound(P_hat, terms.exponent, where)
    batch_value = criterion_at(P_hat, terms.exponent, kind, W, where)
    P_hat = fused_bound(problem_k, terms, recursive_w[..., None, :], rho_k)
    P_recursive = checked_bound(P_hat, terms.exponent, at_horizon(horizons))
    recursive_value = criterion_at(P_hat, terms.exponent, kind, W, at_horizon(horizons))
    batch_shape = P_batch.shape[:-3]
    omega_limit = np.full(batch_shape, np.nan)
    if limit:
        tail = stack_terms([collected[h] for h in _LIMIT_HORIZONS])
        w_tail, _ = solve(problem_k, tail, kind, W, rho_k, _LIMIT_HORIZONS)
        first, last = w_tail[..., 0, 0], w_tail[..., 1, 0]
        omega_limit = np.where(np.abs(first - last) < 1e-8, last, np.nan)
    steady_P = steady_value = None
    if model.steps is None:
        try:
            steady_P = steady_state_covariance(model.F, model.noise,
                                               *(model.constant or (None, None)))
        except ValueError:  # no stabilising solution: the bounds have no finite limit
            steady_P = None
        else:
            steady_value = criterion_value(steady_P, kind, W)
    omega_recursive = recursive_w[..., 0]
    return HorizonStudy(
        horizons=horizons,
        omega=weights[..., 0],
        batch=batch_value,
        recursive=recursive_value,
        omega_recursive=np.broadcast_to(omega_recursive, batch_shape).copy(),
        criterion=kind,
        P_batch=P_batch,
        P_recursive=P_recursive,
        steady_P=steady_P,
        steady_value=steady_value,
        omega_limit=omega_limit,
        rho=None if rho is None else np.broadcast_to(rho, batch_shape + (2,)).copy(),
    )


def _along_horizons(part):
    """A new batch axis (of length one) before the estimates' axis, for the horizons."""
    if isinstance(part, Estimates):
        return Estimates(part.x[..., None, :, :], part.P[..., None, :, :, :],
                         part.L[..., None, :, :, :], part.column)
    return part[..., None, :, :, :]


# The signature of the Ps form, for inspect.signature, help and the documentation; the cast
# because mypy does not know the attribute on functions (attr-defined).
cast(Any, horizon_study).__signature__ = documented_signature(
    "horizons", {"limit": True, "rho": None}, HorizonStudy)
