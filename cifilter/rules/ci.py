"""Covariance Intersection (Julier & Uhlmann 1997) for two or N estimates.

The fused estimate of CI is

    P^-1 = sum_i w_i P_i^-1,    x = P sum_i w_i P_i^-1 x_i,    w on the simplex,

(eq. (2) of Wu, Cai & Fu 2018; the unnumbered CI equations of Weng & Djurić 2012 and of
the journal version, Sec. I), and ``P`` bounds the error covariance for every
cross-covariance of the inputs. The weights are chosen by minimising a criterion of
``P`` (trace, determinant or ``trace(W P)``) or by a fast non-iterative rule.
"""

from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._kernels import dispatch as kernels
from .._numerics.alignment import PartialEstimates
from .._numerics.criteria import criterion_report, parse_criterion
from .._numerics.information import weighted_fusion
from .._numerics.validation import as_covariances, as_estimates, check_weights, restore_style
from ..result import FusionResult
from ._ci_weights import FAST_OMEGA_RULES, optimal_weights
from ._generalised_ci import generalised_ci

__all__ = ["FAST_OMEGA_RULES", "ci_weights", "covariance_intersection"]


def ci_weights(Ps: ArrayLike, criterion: Union[str, ArrayLike] = "trace", *,
               method: str = "auto") -> tuple[NDArray[np.float64], dict[str, Any]]:
    """Criterion-optimal Covariance Intersection weights.

    Parameters
    ----------
    Ps : sequence of array_like or array_like, shape (..., N, n, n)
        Covariances of the N >= 2 estimates.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise: ``trace(P)``, ``det(P)`` or ``trace(W P)`` for a positive
        semidefinite weight matrix ``W``.
    method : {"auto", "diagonalise", "simplex"}, optional
        ``"diagonalise"`` (two estimates only) reduces the problem to one variable by a
        simultaneous diagonalisation of P_1 and P_2; ``"simplex"`` is the active-set
        Newton method for any N; ``"auto"`` picks the first for N = 2.

    Returns
    -------
    omega : ndarray, shape (..., N)
        The weights, on the simplex; optima on the boundary are exact.
    info : dict
        ``iterations``, ``converged`` (optimal to the precision the inputs allow: the
        certified gap at most ``max(1e-9, 2 * gap_floor)``), ``gap``, ``gap_floor`` per
        problem, ``solver``.

    Raises
    ------
    ValueError
        Bad covariances or criterion, or ``method="diagonalise"`` with N != 2.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import ci_weights
    >>> omega, info = ci_weights([np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])],
    ...                          criterion="det")
    >>> omega.round(6).tolist(), bool(info["converged"])
    ([0.6, 0.4], True)
    """
    est = as_covariances(Ps)
    kind, W = parse_criterion(criterion, est.dim)
    if method not in ("auto", "diagonalise", "simplex"):
        raise ValueError(f"method must be 'auto', 'diagonalise' or 'simplex', got {method!r}")
    if method == "diagonalise" and est.count != 2:
        raise ValueError("method='diagonalise' needs exactly two estimates")
    omega, info, _ = optimal_weights(est, kind, W, method)
    return omega, info


# --------------------------------------------------------------------------- public function
def covariance_intersection(xs: ArrayLike, Ps: ArrayLike,
                            criterion: Union[str, ArrayLike] = "trace",
                            omega: Union[float, str, ArrayLike, None] = None) -> FusionResult:
    """Covariance Intersection of two or more estimates with unknown cross-correlation.

    Computes ``P^-1 = sum_i w_i P_i^-1`` and ``x = P sum_i w_i P_i^-1 x_i`` with weights
    ``w`` on the probability simplex (Julier & Uhlmann 1997; eq. (2) of Wu, Cai & Fu 2018).
    ``P`` bounds the covariance of the fused error for every admissible cross-covariance.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array of shape (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n). Symmetric
        positive definite.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What the optimal weights minimise: ``trace(P)`` (default, the mean square error
        bound), ``det(P)`` (the volume of the bound), or ``trace(W P)`` for a positive
        semidefinite weight matrix ``W`` (e.g. to weight position over velocity).
    omega : None, float, array_like or str, optional
        ``None`` (default) minimises the criterion exactly over the simplex; the problem
        is convex and the optimum is found to 1e-12 in omega, on the boundary exactly.
        A float gives the weights ``(omega, 1 - omega)`` of two estimates; an array
        (..., N) gives all weights. A string selects a fast non-iterative rule:
        ``"fast"`` (Niehsen 2002, w_i proportional to 1/trace(P_i), eq. (2) of Weng &
        Djurić, journal version), ``"improved-fast"`` (Franken & Hupper 2005) or
        ``"det-ratio"`` (eq. (7) of Weng & Djurić 2012, w_i proportional to 1/det(P_i)).

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``omega`` (..., N), ``gains`` (..., N, n, n) with ``K_i = w_i P P_i^-1`` and
        ``info`` with ``criterion``, ``value`` (criterion at the result; for ``"det"``
        also ``log_value``, which does not overflow), ``rule`` (``"optimal"``,
        ``"fixed"`` or the fast rule's name), and for optimal weights ``iterations``,
        ``converged`` (the certified gap is at most ``max(1e-9, 2 * gap_floor)``, see
        ``docs/conventions.rst``), ``gap`` (a certified bound on
        the excess of the criterion over its minimum: relative for the trace criteria, in
        log det for ``"det"``) and ``solver``.

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, weights off the simplex, an unknown criterion
        or fast rule.
    IllConditionedError
        (a ValueError) The fused information or the fused covariance is numerically
        singular; only for inputs beyond the conditioning contract (condition numbers
        above 1e12).
    TypeError
        Non-numeric input.

    See Also
    --------
    ci_weights : the optimal weights alone.
    fuse : the same rule through the registry (``method="ci"``).

    Notes
    -----
    ``P`` is returned as the bound of the returned gains, ``sum_i K_i P_i K_i^T / w_i``
    (equal to ``(sum_i w_i P_i^-1)^-1`` in exact arithmetic), formed from Cholesky factors
    without squaring a condition number: for input condition numbers up to 1e12 it is
    finite, symmetric, positive definite and dominates the error covariance of the
    returned gains for every cross-covariance, up to rounding (the conditioning contract).
    For two estimates the optimal weight is proposed by a simultaneous diagonalisation of
    ``P_1`` and ``P_2`` that turns the criterion into a sum of scalar terms (one Newton
    iteration costs O(n) per problem) and certified by its gap; problems it does not
    certify are solved again from the Cholesky factors. For N > 2 an active-set Newton
    method on the simplex is used. Both stop at exact boundary optima (``omega = 0`` or
    ``1``). Derivations: ``docs/methods/ci.rst``, "Numerical formulation".

    References
    ----------
    .. [1] S. J. Julier and J. K. Uhlmann, "A non-divergent estimation algorithm in the
       presence of unknown correlations", ACC 1997.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 2018, eq. (2) and Example 2.
    .. [3] W. Niehsen, "Information fusion based on fast covariance intersection
       filtering", FUSION 2002.
    .. [4] D. Franken and A. Hupper, "Improved fast covariance intersection for
       distributed data fusion", FUSION 2005.
    .. [5] Z. Weng and P. M. Djurić, "A Bayesian approach to covariance estimation and
       data fusion", EUSIPCO 2012, eq. (7).

    Examples
    --------
    Example 2 of Wu, Cai & Fu (2018):

    >>> import numpy as np
    >>> from cifilter import covariance_intersection
    >>> r = covariance_intersection([np.zeros(2), np.zeros(2)],
    ...                             [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    >>> float(r.omega[0]), float(np.trace(r.P))
    (0.5, 3.2)
    >>> np.diag(r.gains[0]).round(6).tolist()
    [0.8, 0.2]
    """
    est = as_estimates(xs, Ps)
    return _covariance_intersection(est, criterion, omega)


def _covariance_intersection(est, criterion="trace", omega=None):
    """The ``"ci"`` rule on validated estimates (the core of :func:`covariance_intersection`).

    Estimates of parts of the state (``fuse(..., H=...)``, validated as
    :class:`~cifilter._numerics.alignment.PartialEstimates`) take generalised CI
    (:func:`cifilter.rules._generalised_ci.generalised_ci`, ``docs/methods/partial_state.rst``).
    """
    kind, W = parse_criterion(criterion, est.dim)
    if isinstance(est, PartialEstimates):
        return generalised_ci(est, kind, W, omega, tuple(FAST_OMEGA_RULES))
    info = {"criterion": kind}
    fused = report = None
    if omega is None:
        weights, solver_info, fused, report = optimal_weights(est, kind, W, report=True)
        info.update(rule="optimal", **solver_info)
    elif isinstance(omega, str):
        if omega not in FAST_OMEGA_RULES:
            raise ValueError(
                f"omega must be None, weights or one of {', '.join(map(repr, FAST_OMEGA_RULES))}; "
                f"got {omega!r}"
            )
        weights = FAST_OMEGA_RULES[omega](est)
        info["rule"] = omega
    else:
        weights = check_weights(omega, est.count, batch_shape=est.batch_shape)
        info["rule"] = "fixed"
    if fused is None:
        compiled = kernels.weighted(est, weights, kind, W, weighted_fusion)
        if compiled is None:
            assembled = weighted_fusion(est.x, est.L, weights)
            fused = (assembled.x, assembled.P, assembled.gains)
        else:
            fused, report = compiled
    x, P, gains = fused
    info.update(criterion_report(P, kind, W) if report is None else report)
    return FusionResult(restore_style(x, est.column), P, "ci", weights, gains, info)


REGISTRATION: dict[str, Any] = dict(
    name="ci",
    function=covariance_intersection,
    core=_covariance_intersection,
    summary="Covariance Intersection; omega minimises trace/det of the bound, or a fast rule",
    reference="Julier & Uhlmann 1997; Niehsen 2002; Franken & Hupper 2005",
    guarantee="bound",
    weights="omega, on the simplex: P^-1 = sum_i omega_i P_i^-1",
    front_door=("H", "residual", "times"),
)
"""The record of the ``"ci"`` rule (registered by :mod:`cifilter.rules`).

Its ``front_door`` options: ``H=`` (generalised CI, ``docs/methods/partial_state.rst``),
``residual=``/``add=`` and ``times=``/``at=``/``motion=`` (``docs/methods/time.rst``): CI's
bound holds for any correlation, so it holds for retrodicted bounds too.
"""
