"""Partial-correlation Covariance Intersection (Wu, Cai & Fu 2018).

When the estimates' correlation coefficient bound (eq. (8); Definition 2 for m vectors) is
at most ``rho``, the fused covariance bound of minimum trace among the bounds of Theorems 3
and 5 is

    P^-1 = sum_i w_i P_i^-1,   K_i = w_i P P_i^-1,   w_i^-1 = rho_i / delta_i + 1 - rho_i,

(eqs. (24), (33), (34); for two estimates eqs. (18)-(19) with ``delta_1 = 1 / (1 + gamma)``)
with ``delta`` on the simplex chosen by Newton's method on the convex problem (35) (or, on
request, by the alternating projections of Algorithms 1 and 2). ``rho = 1`` is standard
CI (``w = delta``), ``rho = 0`` the naive fusion (``w_i = 1``). The returned ``P`` is the
Theorem 5 bound of the returned gains, ``sum_i K_i P_i K_i^T / w_i`` (see
``docs/methods/pci.rst``), so it is a bound whatever rounding went into the gains; it is
formed from the inputs ``P_i`` in compensated arithmetic (:func:`gains_bound`), so that the
rounding of their Cholesky factors, amplified by large gains, does not enter it.
"""

from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.alignment import PartialEstimates
from .._numerics.information import (
    checked_cholesky,
    lower_inverse_stack,
    squared_norms,
    weighted_fusion,
)
from .._numerics.linalg import cholesky
from .._numerics.validation import (
    as_estimates,
    as_float_array,
    check_int,
    check_scalar,
    check_weights,
    restore_style,
)
from ..result import FusionResult
from ._partial_correlation import (
    alternating_delta,
    check_rho,
    effective_rho,
    gains_bound,
    newton_delta,
    partial_state_fusion,
    partial_state_roots,
    partial_weights,
    relative_gap,
)
from .bounds import correlation_bound

__all__ = ["partial_ci"]

_SOLVERS = ("newton", "alternating")


def partial_ci(xs: ArrayLike, Ps: ArrayLike, rho: ArrayLike, tol: float = 1e-10,
               max_iter: int = 100, *, solver: str = "newton",
               delta: Union[float, ArrayLike, None] = None) -> FusionResult:
    """Covariance Intersection for partially correlated estimates (Wu, Cai & Fu 2018).

    Fuses N estimates whose correlation coefficient bound is at most ``rho`` (eq. (8) for
    two estimates, Definition 2 / eq. (21) for N) into ``x = sum_i K_i x_i`` with

        P^-1 = sum_i w_i P_i^-1,   K_i = w_i P P_i^-1,   w_i^-1 = rho_i / delta_i + 1 - rho_i

    (eqs. (24), (33), (34)), ``delta`` on the simplex minimising ``Tr(P)``. ``P`` bounds the
    covariance of the fused error for every joint covariance within the bound; it is
    returned as the Theorem 5 bound of the returned gains, ``sum_i K_i P_i K_i^T / w_i``,
    which equals eq. (33) in exact arithmetic. It is formed from the input covariances
    (not their Cholesky factors) in compensated arithmetic, so it dominates the worst-case
    error covariance of the returned gains up to rounding of order ``N eps ||P||``,
    independently of the condition numbers, for input condition numbers up to 1e12 (the
    conditioning contract; beyond it the rule answers within the contract or raises
    IllConditionedError).

    * Two estimates: Theorem 3 and Algorithm 1, alternating eqs. (18)-(19),
      ``P = ((1 + gamma rho)^-1 P_1^-1 + (1 + rho / gamma)^-1 P_2^-1)^-1``, with eq. (14),
      ``gamma = sqrt(Tr(K_2 P_2 K_2^T) / Tr(K_1 P_1 K_1^T))``, from ``gamma = 1``. By Lemma 5
      the result is the trace-minimal bound over all gains ``K_1 + K_2 = I``. Per-estimate
      bounds ``(rho_1, rho_2)`` mean ``rho = sqrt(rho_1 rho_2)`` (Definition 2 for m = 2).
    * N >= 3 estimates: Theorem 5 and Algorithm 2, alternating eqs. (24), (33), (34) and
      (25) from ``delta_i = 1/N``.

    ``rho = 0`` gives the naive fusion ``(sum_i P_i^-1)^-1`` and ``rho = 1`` trace-optimal CI
    (Remark 3). Through :func:`cifilter.fuse` the rule also takes estimates of parts
    ``H_i x`` of the state (``H=``): ``P^-1 = sum_i w_i H_i^T P_i^-1 H_i`` with the same
    ``w_i``, derived in ``docs/methods/partial_state.rst``.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array of shape (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n). Symmetric
        positive definite.
    rho : float or array_like, shape (..., N) or (..., 1)
        Correlation coefficient bound(s) in [0, 1]: a scalar for all estimates, one bound
        per estimate (last axis N), or one per problem of a batch (last axis 1). Leading
        axes broadcast against the estimates' batch shape.
    tol : float, optional
        Convergence tolerance (default 1e-10): ``info["converged"]`` means that the
        certified relative gap to the minimum trace (``info["gap"]``) is at most ``tol``
        (the alternating projections also require that no ``delta_i`` moved by more than
        ``tol`` in the last iteration).
    max_iter : int, optional
        Iteration limit (default 100). The bound is valid at every iterate; an unconverged
        problem (``info["converged"]`` False) only has a trace that may not be minimal,
        by at most ``info["gap"]`` relative.
    solver : {"newton", "alternating"}, optional
        ``"newton"`` (default): minimise ``Tr(P)`` over ``delta`` (problem (35)) by an
        active-set Newton method on the simplex (from 12 estimates on started on the face an
        interior-point phase finds), stopping each problem at a certified gap;
        a few iterations whatever N and ``rho``, exact on the boundary of the simplex
        (where an estimate is ignored). ``"alternating"``: the paper's alternating
        projections, Algorithm 1 for two estimates and Algorithm 2 for more (linear
        convergence: hundreds of iterations where an estimate is nearly ignored).
    delta : array_like, shape (..., N), or float, optional
        Fuse with these ``delta`` (on the simplex; a float ``d`` means ``(d, 1 - d)`` for
        two estimates) instead of the trace-optimal ones, as ``omega=`` does for
        :func:`covariance_intersection`: the weights are then eq. (24), ``P`` eq. (33) and
        the gains eq. (34). Every ``delta`` gives a valid bound (Lemma 7); this is how a
        ``delta`` chosen for another criterion, such as the bound after future filtering
        (:func:`cifilter.horizon.horizon_weights` with ``rho=``), is applied. ``tol``,
        ``max_iter`` and ``solver`` are then not used.

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``weights`` (..., N) the ``w_i`` of eq. (24) (they do not sum to one unless
        ``rho = 1``; ``omega`` is None: the rule's own parameter is ``delta``), ``gains``
        (..., N, n, n) the ``K_i`` (they sum to the identity), and ``info`` with ``delta``
        (..., N), ``gamma`` (...; two estimates only, ``delta_1 = 1/(1+gamma)``), ``rho``
        (..., N) as used (for two estimates ``sqrt(rho_1 rho_2)`` twice; 0 for a bound at
        or below ``eps^2 / (4 N^2)``, whose effect on the bound is below rounding, so the
        answer is exactly that of ``rho_i = 0``), ``value`` (the
        trace of ``P``), ``gap`` (a certified bound on the relative excess of ``Tr(P)`` over
        its minimum, also for a given ``delta``), ``rule`` (``"optimal"``, or ``"fixed"``
        for a given ``delta``), and for the optimal ``delta`` also ``iterations`` and
        ``converged`` per problem, ``solver`` and ``algorithm`` (1 or 2, the paper's
        algorithm for this N).

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, ``rho`` outside [0, 1] or of the wrong length,
        ``tol`` not positive, ``max_iter`` below 1, an unknown ``solver``, ``delta`` off
        the simplex or of the wrong shape. :class:`~cifilter.IllConditionedError` (a
        ValueError) where the fused information or covariance is numerically singular
        (only beyond the conditioning contract, input condition numbers above 1e12).
    TypeError
        Non-numeric input, a non-integer ``max_iter``.

    See Also
    --------
    covariance_intersection : the case ``rho = 1``.
    naive_fusion : the case ``rho = 0``.
    cifilter.rules.bounds.correlation_bound : ``rho`` from a known cross-covariance, eq. (8).

    Notes
    -----
    A bound ``rho_i <= eps^2 / (4 N^2)`` (about 1e-33) is used as 0: it changes the worst
    admissible error variance by a factor at most ``1 + eps`` (``docs/methods/pci.rst``,
    "Bounds below rounding"), and keeping it would leave double precision (optimal
    ``delta_i ~ sqrt(rho_i)``, slopes ``~ 1/rho_i``).

    Each iteration costs one Cholesky factorisation per problem; all problems of a batch
    iterate together and stop individually. Algorithms 1 and 2 are block-coordinate
    descent on ``Tr(sum_i w_i^-1 K_i P_i K_i^T)``, so the trace decreases monotonically.
    Their convergence is linear: about 10 iterations (the paper's Remark 6) suffice for
    small ``rho`` or well-separated inputs, but several hundred can be needed when the
    optimum ignores an estimate (``delta_i -> 0``, never reached exactly); the
    documentation page gives measured counts. For two estimates
    Algorithm 1 is Algorithm 2 with ``delta = (1, gamma) / (1 + gamma)``: eqs. (18)-(19)
    are eqs. (33)-(34) and eq. (14) is eq. (25), so one implementation serves both.

    References
    ----------
    .. [1] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Lemmas 5 and 7, Theorems 3-6, Algorithms 1
       and 2, eqs. (14), (18)-(19), (24)-(25), (33)-(34), Remark 3, Example 3.

    Examples
    --------
    Example 3 of Wu, Cai & Fu (2018) with m = n = 3, q = 4, rho_0 = 0.5: the optimum is
    ``delta_i = 1/3`` and eq. (37), ``P = (1 + 2 rho_0) / (1 + 2/q) I = 4/3 I``.

    >>> import numpy as np
    >>> from cifilter import partial_ci
    >>> Ps = [np.diag(np.where(np.arange(3) == i, 1.0, 4.0)) for i in range(3)]
    >>> r = partial_ci([np.zeros(3)] * 3, Ps, rho=0.5)
    >>> r.info["delta"].round(12).tolist()
    [0.333333333333, 0.333333333333, 0.333333333333]
    >>> np.allclose(r.P, 4 / 3 * np.eye(3), rtol=1e-12), int(r.info["iterations"])
    (True, 0)

    (The start ``delta_i = 1/3`` is certified optimal: no Newton step is needed. The
    paper's Algorithm 2, ``solver="alternating"``, confirms it in one iteration.)

    Two estimates: ``rho = 1`` is CI (Example 2), ``rho = 0`` the naive fusion.

    >>> Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    >>> [round(float(np.trace(partial_ci([np.zeros(2)] * 2, [Pa, Pb], rho).P)), 9)
    ...  for rho in (1.0, 0.5, 0.0)]
    [3.2, 2.4, 1.6]

    A given ``delta`` (here the optimal one, so the result is the same):

    >>> r = partial_ci([np.zeros(2)] * 2, [Pa, Pb], 0.5, delta=[0.5, 0.5])
    >>> r.info["rule"], r.weights.round(6).tolist(), round(float(np.trace(r.P)), 9)
    ('fixed', [0.666667, 0.666667], 2.4)
    """
    est = as_estimates(xs, Ps)
    return _partial_ci(est, rho, tol, max_iter, solver=solver, delta=delta)


def _partial_ci(est, rho=None, tol=1e-10, max_iter=100, *, solver="newton", delta=None):
    """The ``"pci"`` rule on validated estimates (the core of :func:`partial_ci`).

    Estimates of parts ``H_i x`` of the state (``fuse(..., method="pci", H=...)``, a
    :class:`~cifilter._numerics.alignment.PartialEstimates`) take the same solvers on the
    square roots ``G_i`` of ``H_i^T P_i^-1 H_i`` (``docs/methods/partial_state.rst``,
    eqs. (H10)-(H12)); ``info["gains"]`` then holds the (..., n, m_i) gains and ``gains``
    is None unless every ``m_i = n``.
    """
    if rho is None:
        raise ValueError(
            "the 'pci' rule needs a correlation coefficient bound: fuse(..., method='pci', "
            "rho=...) with rho in [0, 1] (see cifilter.rules.bounds.correlation_bound)"
        )
    rho = check_rho(rho, est.count, est.batch_shape)
    tol = check_scalar(tol, "tol", low=0.0, low_open=True)
    max_iter = check_int(max_iter, "max_iter", low=1)
    if solver not in _SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(map(repr, _SOLVERS))}, got {solver!r}")
    two = est.count == 2
    used = effective_rho(rho)
    partial = isinstance(est, PartialEstimates)
    if partial:
        roots = partial_state_roots(est)
        L_inv = roots.G
    else:
        L_inv = lower_inverse_stack(est.L)
    converged = None
    if delta is None:
        if solver == "newton":
            delta, iterations = newton_delta(L_inv, used, tol, max_iter, partial=partial)
        else:
            delta, iterations, converged = alternating_delta(L_inv, used, tol, max_iter)
        info = {"rule": "optimal", "iterations": iterations, "solver": solver,
                "algorithm": 1 if two else 2}
    else:
        fixed = check_weights(delta, est.count, "delta")
        try:
            delta = np.array(np.broadcast_to(fixed, used.shape))
        except ValueError:
            raise ValueError(f"delta of shape {fixed.shape} does not broadcast against the "
                             f"batch shape {est.batch_shape} of the estimates") from None
        info = {"rule": "fixed"}
    weights = partial_weights(delta, used)
    if partial:
        x, P, partial_gains, factors = partial_state_fusion(est, roots, weights)
        n = est.dim
        gains = (np.stack(partial_gains, axis=-3)
                 if all(K.shape[-1] == n for K in partial_gains) else None)
    else:
        fused = weighted_fusion(est.x, est.L, weights, L_inv)
        x, gains, factors = fused.x, fused.gains, fused.factors
        # the bound of the returned gains from the inputs themselves (not from L_i L_i^T)
        P = gains_bound(gains, est.P, weights)
    checked_cholesky(P, "the fused covariance")
    spread = squared_norms(factors.B)
    trace = squared_norms(factors.R_inv)
    with np.errstate(over="ignore", invalid="ignore"):  # a fixed delta_i = 0, rho_i ~ 1e-300
        gap = relative_gap(delta, used, trace, spread)
    if info["rule"] == "optimal":
        # Newton: the certified gap decides; the alternating projections also require
        # delta at rest (the paper's test), which implies nothing beyond the gap.
        info["converged"] = (gap <= tol) if converged is None else converged
    info.update(delta=delta, rho=used, value=np.trace(P, axis1=-2, axis2=-1), gap=gap)
    if two:
        with np.errstate(divide="ignore"):
            info["gamma"] = delta[..., 1] / delta[..., 0]  # delta_1 = 1 / (1 + gamma)
    if partial:
        info["gains"] = partial_gains
    x = restore_style(x, est.column)
    return FusionResult(x, P, "pci", None, gains, info, weights)


def _truth_rho(joint, count=2, sizes=None):
    """The smallest common correlation coefficient bound, eq. (21), of a joint covariance.

    Used by simulations (the demo, :mod:`cifilter.network`), where the joint error covariance
    of the ``count`` estimates is known. With ``D = blockdiag(P_1, ..., P_m) = L L^T``,
    eq. (21) with ``rho_i = rho`` reads ``J - (1 - rho) D >= 0``, so the smallest ``rho`` is
    ``1 - lambda_min(L^-1 J L^-T)``. For two estimates this is eq. (8),
    ``sigma_max(X^-1 P_ab Y^-T)`` (the whitened joint has eigenvalues ``1 +- sigma``), which
    is computed directly. ``sizes`` (the block dimensions m_i, for estimates of parts
    ``H_i x`` of the state) splits the joint into unequal blocks; without it the blocks are
    of equal dimension.
    """
    J = as_float_array(joint, "joint")
    if sizes is None:
        if J.ndim < 2 or J.shape[-1] != J.shape[-2] or J.shape[-1] % count:
            raise ValueError(
                f"the 'pci' truth hook expects the joint covariance of {count} estimates of "
                f"equal dimension, (..., {count}n, {count}n), or sizes= (the dimension of "
                f"each); got shape {J.shape}"
            )
        sizes = [J.shape[-1] // count] * count
    sizes = [int(m) for m in sizes]
    if (len(sizes) != count or J.ndim < 2 or J.shape[-1] != J.shape[-2]
            or sum(sizes) != J.shape[-1]):
        raise ValueError(
            f"the 'pci' truth hook expects the joint covariance of {count} estimates of "
            f"dimensions {sizes}, ({sum(sizes)}, {sum(sizes)}); got shape {J.shape}"
        )
    ends = np.cumsum([0] + sizes)
    parts = [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:])]
    if count == 2:
        a, b = parts
        rho = np.asarray(correlation_bound(J[..., a, a], J[..., b, b], J[..., a, b]))
    else:
        W = np.zeros_like(J)
        for part in parts:
            W[..., part, part] = lower_inverse_stack(cholesky(J[..., part, part], "joint block"))
        whitened = W @ J @ np.swapaxes(W, -1, -2)
        whitened = 0.5 * (whitened + np.swapaxes(whitened, -1, -2))
        rho = 1.0 - np.linalg.eigvalsh(whitened)[..., 0]
    # The bound of a valid joint covariance is in [0, 1]; rounding may leave it by ~1e-16.
    return np.clip(rho, 0.0, 1.0)


def _pci_truth_options(joint, rng, count=2, sizes=None):
    return {"rho": _truth_rho(joint, count, sizes)[..., None]}


REGISTRATION: dict[str, Any] = dict(
    name="pci",
    function=partial_ci,
    core=_partial_ci,
    summary="partial-correlation CI given a correlation coefficient bound rho (needs rho=)",
    reference="Wu, Cai & Fu 2018, Theorems 3 and 5, Algorithms 1 and 2",
    guarantee="bound",
    truth_options=_pci_truth_options,
    weights="w_i = delta_i / (rho_i + (1 - rho_i) delta_i), eq. (24); they do not sum to one",
    front_door=("H", "residual"),
)
"""The record of the ``"pci"`` rule (registered by :mod:`cifilter.rules`).

Its ``front_door`` has ``H=`` (estimates of parts ``H_i x`` of the state: Lemma 7 and
Theorem 5 of Wu, Cai & Fu carry over with ``sum_i K_i H_i = I``, eqs. (H10)-(H12) of
``docs/methods/partial_state.rst``) and ``residual=``/``add=`` (the fused mean is an affine
combination of the means). Not ``times=``: a correlation coefficient bound ``rho`` of the
estimates does not survive the process noise a time shift adds to them.
"""
