"""The horizon-optimal weights: :func:`optimal_omega` (two estimates) and
:func:`horizon_weights` (N estimates), with CI or partial CI (``rho=``).

Both validate their input once and call the core shared with the front door's hooks
(:mod:`cifilter.horizon._core`). Method and proofs: ``docs/methods/horizon.rst``.
"""

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Optional, Union, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.criteria import parse_criterion
from .._numerics.validation import as_covariances, check_int
from ..rules._partial_correlation import partial_weights
from ._core import (
    PerStep,
    as_rho,
    bind_arguments,
    choose,
    documented_signature,
    problem_of,
)
from ._model import as_model

__all__ = ["HorizonOmega", "horizon_weights", "optimal_omega"]


@dataclass(frozen=True, repr=False)
class HorizonOmega:
    """The CI weight chosen for a horizon (result of :func:`optimal_omega`).

    The parameters are also the attributes of the result.

    Parameters
    ----------
    omega : ndarray, shape (...) or (..., N)
        The weight of the first estimate (:func:`optimal_omega`) or the weights of all N
        estimates (:func:`horizon_weights`). With ``rho`` (partial CI) these are
        ``delta`` (the simplex variable of eq. (24) of Wu, Cai & Fu 2018; ``delta = omega``
        for ``rho = 1``).
    value : ndarray, shape (...)
        The criterion of the propagated bound at the horizon with these weights (the
        determinant for ``"det"``).
    P : ndarray, shape (..., n, n)
        The propagated bound at the horizon (batch approach, eqs. 31-33).
    info : dict
        ``horizon``, ``criterion``, ``omega_recursive`` and ``value_recursive`` (the weights
        of the recursive approach, optimal at horizon 0, and the criterion they give at the
        horizon), ``iterations``, ``converged``, ``solver`` and ``gap`` (a certified bound
        on the excess of the criterion over its minimum: relative for the trace criteria
        and for partial CI, in ``log det`` for CI's ``"det"``). With ``rho`` also ``rho``
        (..., N) the bounds used (``sqrt(rho_1 rho_2)`` twice for a pair) and ``weights``
        (..., N) the information weights ``w_i`` of eq. (24) (they do not sum to one).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.horizon import optimal_omega
    >>> r = optimal_omega(np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.eye(2), 0.0,
    ...                   np.eye(2), np.diag([1.0, 2.0]), horizon=1)
    >>> round(float(r.omega), 12), round(float(r.info["omega_recursive"]), 12)
    (0.0, 0.5)
    """

    omega: NDArray[np.float64]
    value: NDArray[np.float64]
    P: NDArray[np.float64]
    info: dict[str, Any]

    def __repr__(self) -> str:
        return (f"HorizonOmega(omega={np.array2string(np.asarray(self.omega), precision=4)}, "
                f"value={np.array2string(np.asarray(self.value), precision=4)}, "
                f"horizon={self.info.get('horizon')})")


def optimal_omega(*args: Any, **kwargs: Any) -> HorizonOmega:
    """The CI weight that minimises the bound ``horizon`` filter steps after the fusion.

    The batch approach of Ajgl et al. (2014): the CI bound
    ``P_0(omega) = (omega P_A^-1 + (1 - omega) P_B^-1)^-1`` is carried through ``horizon``
    predict/update steps of the local filter (eqs. 16, 31-33) and ``omega`` minimises the
    criterion of the result. ``horizon = 0`` is ordinary criterion-optimal CI.

    Called as ``optimal_omega(Ps, F, Q, H, R, horizon, criterion="trace", G=None, *,
    rho=None)`` or pairwise as ``optimal_omega(PA, PB, F, Q, H, R, horizon, ...)``; the
    pairwise form is recognised by an integer horizon as the seventh positional argument,
    or by six positional arguments before ``horizon=``.

    Parameters
    ----------
    Ps : sequence of two array_like or array_like, shape (..., 2, n, n)
        Covariances (bounds) of the two estimates; ``omega`` weighs the first. In the
        pairwise form, ``PA`` and ``PB`` (..., n, n) as two arguments.
    F, Q, H, R, G : array_like
        The model of the filter that fuses and then filters on; see :func:`propagate_bound`
        (``H`` and ``R`` may be None or per-step sequences).
    horizon : int
        The horizon ``kappa >= 0`` whose bound is minimised.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        ``trace(P)``, ``det(P)`` or ``trace(W P)`` of the propagated bound.
    rho : float or array_like, shape (..., 2) or (..., 1), optional
        Correlation coefficient bound(s) of partial CI (Wu, Cai & Fu 2018), as for
        :func:`cifilter.partial_ci` (per-estimate bounds of a pair act through
        ``sqrt(rho_1 rho_2)``). Then the bound at the fusion time is eq. (33),
        ``(w_A P_A^-1 + w_B P_B^-1)^-1`` with the weights (24) of ``delta = (omega,
        1 - omega)``, and ``omega`` is the horizon-optimal ``delta_1``; apply it with
        ``partial_ci(..., rho, delta=...)``. None (default): Covariance Intersection.

    Returns
    -------
    HorizonOmega
        ``omega`` (...), the criterion ``value``, the propagated bound ``P`` and ``info``
        (including the recursive approach's omega and value for comparison, and the
        certified ``gap``).

    Raises
    ------
    ValueError
        Bad covariances, model or criterion (see :func:`propagate_bound`); a propagated bound
        or criterion value that float64 cannot hold at this horizon (the message names the
        horizon, the quantity and the optimal weights, which remain well defined).
    IllConditionedError
        The propagated bound, or a horizon term the ``"det"`` criterion needs, is not
        numerically positive definite (its condition number exceeds what float64 resolves).
    TypeError
        Non-numeric input, a non-integer horizon, or arguments that fit neither form.

    Notes
    -----
    The criterion is convex in omega at every horizon, so the optimum is global and
    certified (``info["gap"]``); the proof, the solvers and the partial-CI form are in
    ``docs/methods/horizon.rst``. Batched over leading axes of all inputs.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014, Sec. III,
       eqs. (13)-(16), (31)-(34), Figs. 3 and 6.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Lemma 7, eqs. (24), (33) (with ``rho``).

    Examples
    --------
    The dynamical example (eqs. 29-30, 34): at the fusion time the determinant picks
    ``omega = 0.6``; filter A, expecting its own measurements, almost ignores its estimate.

    >>> import numpy as np
    >>> from cifilter.horizon import optimal_omega
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> PA, PB = np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])
    >>> HA = np.array([[1.0, 0.0]])
    >>> round(float(optimal_omega(PA, PB, F, Q, HA, 1.0, 0, "det").omega), 6)
    0.6
    >>> round(float(optimal_omega(PA, PB, F, Q, HA, 1.0, 50, "det").omega), 4)
    0.0418
    >>> round(float(optimal_omega([PA, PB], F, Q, HA, 1.0, 50, "det").omega), 4)
    0.0418

    With a correlation coefficient bound of 0.5 (partial CI), ``delta_1`` moves less:

    >>> [round(float(optimal_omega(PA, PB, F, Q, HA, 1.0, k, "det", rho=0.5).omega), 4)
    ...  for k in (0, 50)]
    [0.5511, 0.2666]
    """
    Ps, a = bind_arguments("optimal_omega", args, kwargs, "horizon", ("rho",))
    horizon = check_int(a["horizon"], "horizon", low=0)
    est = as_covariances(Ps, name="Ps")
    if est.count != 2:
        raise ValueError(f"optimal_omega fuses two estimates, got {est.count}; use "
                         "horizon_weights for N estimates")
    choice = _choose(est, a, horizon, a.get("rho"))
    choice.info["omega_recursive"] = choice.info["omega_recursive"][..., 0]
    return HorizonOmega(choice.weights[..., 0], choice.value, choice.P, choice.info)


def horizon_weights(Ps: Union[ArrayLike, Sequence[ArrayLike]], F: ArrayLike, Q: ArrayLike,
                    H: PerStep, R: PerStep, horizon: int,
                    criterion: Union[str, ArrayLike] = "trace", G: Optional[ArrayLike] = None,
                    *, rho: Optional[ArrayLike] = None) -> HorizonOmega:
    """Horizon-optimal CI weights of N estimates (the generalisation of :func:`optimal_omega`).

    The CI bound ``(sum_i w_i P_i^-1)^-1`` is carried through ``horizon`` filter steps and
    the weights ``w`` on the simplex minimise the criterion of the result.

    Parameters
    ----------
    Ps : sequence of array_like or array_like, shape (..., N, n, n)
        Covariances of the N >= 2 estimates.
    F, Q, H, R, G : array_like
        The model of the filter that fuses; see :func:`propagate_bound`.
    horizon : int
        The horizon ``kappa >= 0``.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise.
    rho : float or array_like, shape (..., N) or (..., 1), optional
        Correlation coefficient bound(s) of partial CI (Wu, Cai & Fu 2018), as for
        :func:`cifilter.partial_ci`: the fused bound is eq. (33) with the weights (24) of
        ``delta`` and ``omega`` is the horizon-optimal ``delta``; apply it with
        ``partial_ci(..., rho, delta=omega)``. None (default): Covariance Intersection.

    Returns
    -------
    HorizonOmega
        ``omega`` of shape (..., N), ``value``, ``P`` and ``info`` (``omega_recursive`` is
        then (..., N) as well; with ``rho`` also ``rho`` and ``weights``).

    Raises
    ------
    ValueError
        Fewer than two estimates, bad covariances, model or criterion; a propagated bound or
        criterion value that float64 cannot hold (as :func:`optimal_omega`).
    IllConditionedError
        As :func:`optimal_omega`.
    TypeError
        Non-numeric input or a non-integer horizon.

    Notes
    -----
    With ``S_i = P_i^-1 + Gamma`` the bound is ``P_c + Psi (sum_i w_i S_i)^-1 Psi^T``,
    convex in ``w``. The trace criteria (and ``"det"`` at horizon 0) are CI problems of the
    matrices ``S_i^-1`` solved by the ``"ci"`` rule's solver, so horizon 0 gives the weights
    of :func:`cifilter.covariance_intersection`; ``"det"`` at a positive horizon has its own
    Newton solvers. With ``rho`` the active-set Newton method on the simplex minimises the
    criterion in ``delta``; at horizon 0 with the trace it is :func:`cifilter.partial_ci`'s
    solver. Positive bounds below 1e-8 are raised to 1e-8 for the iterations only (the
    reason is given in ``docs/methods/horizon.rst``); the bound and ``info["gap"]`` are
    those of the true ``rho``. ``rho_i = 0`` means ``w_i = 1`` whatever ``delta_i``; with
    ``rho = 0`` throughout every ``delta`` is optimal and the start ``1/N`` is kept.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014 (two estimates;
       the N-estimate form is this package's generalisation).
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Lemma 7, eqs. (24), (33), (34) (with ``rho``;
       the horizon-aware choice of ``delta`` is this package's generalisation).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.horizon import horizon_weights
    >>> Ps = [np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.diag([1.5, 1.5])]
    >>> r = horizon_weights(Ps, np.eye(2), 0.0, np.eye(2), np.diag([1.0, 2.0]), horizon=1)
    >>> r.omega.round(4).tolist()
    [0.0, 1.0, 0.0]

    Partial CI with bounds 0.3, 0.3 and 0 (the third estimate is uncorrelated, so its
    weight is 1 and it needs no ``delta``):

    >>> r = horizon_weights(Ps, np.eye(2), 0.0, np.eye(2), np.diag([1.0, 2.0]), horizon=1,
    ...                     rho=[0.3, 0.3, 0.0])
    >>> r.omega.round(4).tolist(), r.info["weights"].round(4).tolist()
    ([0.4713, 0.5287, 0.0], [0.7482, 0.789, 1.0])
    """
    horizon = check_int(horizon, "horizon", low=0)
    est = as_covariances(Ps, name="Ps")
    arguments = dict(F=F, Q=Q, H=H, R=R, G=G, criterion=criterion)
    choice = _choose(est, arguments, horizon, rho)
    return HorizonOmega(choice.weights, choice.value, choice.P, choice.info)


def _choose(est, a, horizon, rho):
    """Validate the model, criterion and rho once and run the shared core."""
    rho = as_rho(rho, est.count, est.batch_shape)
    kind, W = parse_criterion(a["criterion"], est.dim)
    model = as_model(a["F"], a["Q"], a["H"], a["R"], a["G"], est.dim)
    choice = choose(problem_of(est), model, horizon, kind, W, rho)
    info = dict(choice.info, horizon=horizon, criterion=kind,
                omega_recursive=choice.weights_recursive,
                value_recursive=choice.value_recursive)
    if rho is not None:
        info.update(rho=np.broadcast_to(rho, choice.weights.shape).copy(),
                    weights=partial_weights(choice.weights, rho))
    return choice._replace(info=info)


# A function's __signature__ is what inspect.signature, help and the documentation show; the
# cast because mypy does not know the attribute on functions (attr-defined).
cast(Any, optimal_omega).__signature__ = documented_signature("horizon", {"rho": None},
                                                              HorizonOmega)
