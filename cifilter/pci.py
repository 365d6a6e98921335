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
``docs/methods/pci.rst``), so it is a bound whatever rounding went into the gains.
"""

import numpy as np

from ._information import (
    checked_cholesky,
    information_factors,
    lower_inverse_stack,
    squared_norms,
    trace_curvature,
    weighted_fusion,
)
from ._linalg import symmetrize
from ._optimize import minimize_convex_simplex
from ._validation import (
    as_estimates,
    as_float_array,
    check_finite,
    check_int,
    check_scalar,
    check_weights,
    restore_style,
)
from .bounds import correlation_bound
from .registry import register_method
from .result import FusionResult

__all__ = ["partial_ci"]

_SOLVERS = ("newton", "alternating")


def _check_rho(rho, count, batch_shape):
    """``rho`` as an array (..., N) in [0, 1] broadcast to ``batch_shape + (N,)``."""
    array = as_float_array(rho, "rho")
    check_finite(array, "rho")
    if array.ndim > 0 and array.shape[-1] not in (1, count):
        raise ValueError(
            f"rho must be a scalar or have shape (..., {count}) (one bound per estimate) or "
            f"(..., 1) (one per problem), got shape {array.shape}"
        )
    if np.any((array < 0.0) | (array > 1.0)):
        bad = array[(array < 0.0) | (array > 1.0)].ravel()[0]
        raise ValueError(f"rho must lie in [0, 1], got {bad}")
    if array.ndim == 0:
        array = array[None]
    try:
        return np.array(np.broadcast_to(array, batch_shape + (count,)))
    except ValueError:
        raise ValueError(
            f"rho of shape {array.shape} does not broadcast against the batch shape "
            f"{batch_shape} of the estimates"
        ) from None


def _effective_rho(rho):
    """The bounds the rule uses: for two estimates ``sqrt(rho_1 rho_2)`` for both.

    Definition 2 for two vectors is Lemma 3's condition with ``rho = sqrt(rho_1 rho_2)``,
    and Theorem 3 (the trace-minimal bound) takes one common ``rho``.
    """
    if rho.shape[-1] == 2:
        return np.sqrt(rho[..., :1] * rho[..., 1:]).repeat(2, axis=-1)
    return rho


def _partial_weights(delta, rho):
    """Eq. (24): ``w_i = delta_i / (rho_i + (1 - rho_i) delta_i)``, and 1 where ``rho_i = 0``.

    This is ``w_i^-1 = rho_i / delta_i + 1 - rho_i`` written without dividing by
    ``delta_i``, so that a weight driven to ``delta_i = 0`` gives ``w_i = 0`` (the estimate
    is ignored) unless ``rho_i = 0`` (uncorrelated: ``w_i = 1`` whatever ``delta_i``).
    """
    positive = rho > 0.0
    denominator = np.where(positive, rho + (1.0 - rho) * delta, 1.0)
    return np.where(positive, delta / denominator, 1.0)


def _weight_derivatives(delta, rho):
    """First and second derivatives of eq. (24) in ``delta_i``.

    ``w_i' = rho_i / (rho_i + (1 - rho_i) delta_i)^2`` and
    ``w_i'' = -2 rho_i (1 - rho_i) / (rho_i + (1 - rho_i) delta_i)^3``: the factors of
    ``d Delta / d delta_i`` in the proof of Lemma 8, where the paper omits the numerator
    ``rho_i`` (a misprint; the convexity argument is unaffected). Both are 0 for
    ``rho_i = 0``. They are formed from ``rho_i / base_i <= 1`` so that tiny ``rho_i`` and
    ``delta_i`` do not underflow to a division by zero.
    """
    positive = rho > 0.0
    base = np.where(positive, rho + (1.0 - rho) * delta, 1.0)
    ratio = np.where(positive, rho / base, 0.0)
    with np.errstate(over="ignore"):  # rho_i, delta_i ~ 1e-200: a huge gradient is right
        first = ratio / base
        second = -2.0 * (1.0 - rho) * first / base
    return first, second


def _bound_and_spread(delta, rho, L_inv):
    """``w`` (24), the factors of ``P`` (33) and ``Tr(P P_i^-1 P)`` for every estimate.

    ``Tr(P P_i^-1 P) = ||B_i||_F^2`` with ``B_i = P L_i^-T`` (see
    :func:`cifilter._information.information_factors`): a sum of squares, accurate to
    rounding whatever the conditioning.
    """
    w = _partial_weights(delta, rho)
    factors = information_factors(L_inv, w)
    spread = squared_norms(factors.B)
    return w, factors, spread


def _relative_gap(delta, rho, trace, spread):
    """Certified bound on ``(Tr P(delta) - min Tr P) / Tr P`` (a Frank-Wolfe gap).

    ``Tr P(delta)`` is convex on the simplex (Lemma 8; also for rho_i in {0, 1}), so with
    its gradient ``g_i = -w_i' Tr(P P_i^-1 P)``,
    ``min Tr P >= Tr P - (sum_i g_i delta_i - min_i g_i)``.
    """
    first, _ = _weight_derivatives(delta, rho)
    g = -first * spread
    # g_i delta_i = -Tr(P P_i^-1 P) w_i rho_i / base_i, finite even where g_i overflows
    positive = rho > 0.0
    base = np.where(positive, rho + (1.0 - rho) * delta, 1.0)
    along = -spread * _partial_weights(delta, rho) * np.where(positive, rho / base, 0.0)
    return np.maximum(along.sum(axis=-1) - g.min(axis=-1), 0.0) / trace


def _alternating_projection(L_inv, rho, tol, max_iter, start=None):
    """Algorithm 2 (and Algorithm 1, its two-estimate case), batched.

    Starting from ``delta_i = 1/N`` (Step 1) it repeats, for all unfinished problems at
    once: Step 2, ``w`` from eq. (24), ``P = (sum_i w_i P_i^-1)^-1`` (33) and
    ``K_i = w_i P P_i^-1`` (34); Step 3, ``delta`` from eq. (25),
    ``delta_i proportional to sqrt(rho_i Tr(K_i P_i K_i^T))``, with
    ``Tr(K_i P_i K_i^T) = w_i^2 Tr(P P_i^-1 P)``. Each sweep is a block-coordinate descent
    step of ``Tr(sum_i w_i^-1 K_i P_i K_i^T)`` over ``K`` (Theorem 5) and ``delta``
    (Lemma 7), so the trace never increases (Theorems 4 and 6).

    A problem stops when no ``delta_i`` moved by more than ``tol`` in the last sweep and
    the certified relative gap to the minimum trace is below ``tol``; the second test
    keeps a slowly creeping ``delta`` (linear convergence with a rate near one) from
    passing for converged.

    ``start`` replaces Step 1 (used to check a Newton solution). Returns ``delta``
    (..., N), ``iterations`` (...), the number of sweeps (Steps 2-3), and ``converged``.
    """
    batch, count = rho.shape[:-1], rho.shape[-1]
    size = int(np.prod(batch, dtype=int))
    L_inv = L_inv.reshape((size,) + L_inv.shape[-3:])
    rho = rho.reshape(size, count)
    if start is None:
        delta = np.full((size, count), 1.0 / count)
    else:
        delta = np.array(start, dtype=float).reshape(size, count)
    iterations = np.zeros(size, dtype=int)
    converged = np.zeros(size, dtype=bool)
    for _ in range(max_iter):
        active = np.flatnonzero(~converged)
        if active.size == 0:
            break
        d, r = delta[active], rho[active]
        w, factors, spread = _bound_and_spread(d, r, L_inv[active])  # Step 2
        gap = _relative_gap(d, r, squared_norms(factors.R_inv), spread)
        # sqrt(rho_i Tr(K_i P_i K_i^T)), factored so that a tiny rho_i does not underflow
        root = np.sqrt(r) * w * np.sqrt(spread)
        total = root.sum(axis=-1, keepdims=True)
        # Every rho_i = 0: delta plays no role (Remark 4); keep it.
        new = np.where(total > 0.0, root / np.where(total > 0.0, total, 1.0), d)  # (25)
        change = np.abs(new - d).max(axis=-1)
        delta[active] = new
        iterations[active] += 1
        converged[active] = (change <= tol) & (gap <= tol)
    return delta.reshape(batch + (count,)), iterations.reshape(batch), converged.reshape(batch)


_NEWTON_RHO_FLOOR = 1e-8


def _newton(L_inv, rho, tol, max_iter):
    """Minimise ``Tr P(delta)`` (eq. (35)) by the active-set Newton method on the simplex.

    Gradient ``g_i = -w_i' Tr(P I_i P)`` and Hessian
    ``H_ij = 2 w_i' w_j' Tr(P I_i P I_j P) - [i = j] w_i'' Tr(P I_i P)`` with
    ``I_i = P_i^-1`` and the derivatives of eq. (24) (see :func:`_weight_derivatives`),
    formed from the factors ``B_i = P L_i^-T`` and ``C_i = R^-1 L_i^-T``:
    ``Tr(P I_i P) = ||B_i||^2`` and ``Tr(P I_i P I_j P) = Tr(B_i^T B_j C_j^T C_i)``. Optima on
    the boundary of the simplex (an ignored estimate) are exact. Each problem stops when
    its certified gap (:func:`_relative_gap`) is at most ``tol``.

    Positive bounds below ``_NEWTON_RHO_FLOOR`` are raised to it for the Newton phase
    only: near the optimum ``delta_i ~ sqrt(rho_i)`` the curvature grows like
    ``rho_i^(-1/2)`` and would swamp the other directions (or overflow). Problems whose
    gap under the true bounds is then above ``tol`` continue with the sweeps of Algorithm 2
    (:func:`_alternating_projection`), whose multiplicative step (25) moves such a
    ``delta_i`` to its scale at once. Returns ``delta`` and the iterations (Newton steps
    plus sweeps) per problem.
    """
    true_rho = rho
    batch, count = rho.shape[:-1], rho.shape[-1]
    size = int(np.prod(batch, dtype=int))
    flat_L_inv = L_inv.reshape((size,) + L_inv.shape[-3:])
    floored = np.where(rho > 0.0, np.maximum(rho, _NEWTON_RHO_FLOOR), 0.0).reshape(size, count)

    def objective(delta, index):
        w = _partial_weights(delta, floored[index])
        R_inv = information_factors(flat_L_inv[index], w).R_inv
        return squared_norms(R_inv)

    def evaluate(delta, index):
        r = floored[index]
        _, factors, spread = _bound_and_spread(delta, r, flat_L_inv[index])
        first, second = _weight_derivatives(delta, r)
        curvature = trace_curvature(factors)  # Tr(P I_i P I_j P)
        H = 2.0 * first[..., :, None] * first[..., None, :] * curvature
        H = H - (second * spread)[..., None] * np.eye(count)
        trace = squared_norms(factors.R_inv)
        return trace, -first * spread, symmetrize(H)

    delta, steps, _ = minimize_convex_simplex(
        evaluate, objective, count, (size,), xtol=tol, max_iter=max_iter, gtol=tol,
        subset=True,
    )
    delta, steps = delta.reshape(batch + (count,)), steps.reshape(batch)
    _, factors, spread = _bound_and_spread(delta, true_rho, L_inv)
    trace = squared_norms(factors.R_inv)
    redo = (_relative_gap(delta, true_rho, trace, spread) > tol).reshape(-1)
    steps = np.array(steps).reshape(-1)
    if redo.any():
        size = steps.size
        flat = delta.reshape(size, count).copy()
        more, sweeps, _ = _alternating_projection(
            L_inv.reshape((size,) + L_inv.shape[-3:])[redo],
            true_rho.reshape(size, count)[redo], tol, max_iter, start=flat[redo],
        )
        flat[redo] = more
        steps[redo] += sweeps
        delta = flat.reshape(delta.shape)
    return delta, steps.reshape(batch)


def partial_ci(xs, Ps, rho, tol=1e-10, max_iter=100, *, solver="newton", delta=None):
    """Covariance Intersection for partially correlated estimates (Wu, Cai & Fu 2018).

    Fuses N estimates whose correlation coefficient bound is at most ``rho`` (eq. (8) for
    two estimates, Definition 2 / eq. (21) for N) into ``x = sum_i K_i x_i`` with

        P^-1 = sum_i w_i P_i^-1,   K_i = w_i P P_i^-1,   w_i^-1 = rho_i / delta_i + 1 - rho_i

    (eqs. (24), (33), (34)), ``delta`` on the simplex minimising ``Tr(P)``. ``P`` bounds the
    covariance of the fused error for every joint covariance within the bound; it is
    returned as the Theorem 5 bound of the returned gains, ``sum_i K_i P_i K_i^T / w_i``,
    which equals eq. (33) in exact arithmetic and stays a bound, up to rounding of the
    products, for input condition numbers up to 1e12 (the conditioning contract; beyond it
    the rule answers within the contract or raises IllConditionedError).

    * Two estimates: Theorem 3 and Algorithm 1, alternating eqs. (18)-(19),
      ``P = ((1 + gamma rho)^-1 P_1^-1 + (1 + rho / gamma)^-1 P_2^-1)^-1``, with eq. (14),
      ``gamma = sqrt(Tr(K_2 P_2 K_2^T) / Tr(K_1 P_1 K_1^T))``, from ``gamma = 1``. By Lemma 5
      the result is the trace-minimal bound over all gains ``K_1 + K_2 = I``. Per-estimate
      bounds ``(rho_1, rho_2)`` mean ``rho = sqrt(rho_1 rho_2)`` (Definition 2 for m = 2).
    * N >= 3 estimates: Theorem 5 and Algorithm 2, alternating eqs. (24), (33), (34) and
      (25) from ``delta_i = 1/N``.

    ``rho = 0`` gives the naive fusion ``(sum_i P_i^-1)^-1`` and ``rho = 1`` trace-optimal CI
    (Remark 3).

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
        active-set Newton method on the simplex, stopping each problem at a certified gap;
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
        ``omega`` (..., N) the weights ``w_i`` (they do not sum to one unless ``rho = 1``),
        ``gains`` (..., N, n, n) the ``K_i`` (they sum to the identity), and ``info`` with
        ``delta`` (..., N), ``gamma`` (...; two estimates only, ``delta_1 = 1/(1+gamma)``),
        ``rho`` (..., N) as used (for two estimates ``sqrt(rho_1 rho_2)`` twice),
        ``iterations`` and ``converged`` per problem, ``value`` (the trace of ``P``),
        ``gap`` (a certified bound on the relative excess of ``Tr(P)`` over its minimum),
        ``rule`` (``"optimal"``, or ``"fixed"`` for a given ``delta``), and for the optimal
        ``delta`` also ``solver`` and ``algorithm`` (1 or 2, the paper's algorithm for this
        N).

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
    cifilter.bounds.correlation_bound : ``rho`` from a known cross-covariance, eq. (8).

    Notes
    -----
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
    >>> r.info["rule"], r.omega.round(6).tolist(), round(float(np.trace(r.P)), 9)
    ('fixed', [0.666667, 0.666667], 2.4)
    """
    est = as_estimates(xs, Ps)
    rho = _check_rho(rho, est.count, est.batch_shape)
    tol = check_scalar(tol, "tol", low=0.0, low_open=True)
    max_iter = check_int(max_iter, "max_iter", low=1)
    if solver not in _SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(map(repr, _SOLVERS))}, got {solver!r}")
    two = est.count == 2
    used = _effective_rho(rho)
    L_inv = lower_inverse_stack(est.L)
    converged = None
    if delta is None:
        if solver == "newton":
            delta, iterations = _newton(L_inv, used, tol, max_iter)
        else:
            delta, iterations, converged = _alternating_projection(L_inv, used, tol, max_iter)
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
    weights = _partial_weights(delta, used)
    fused = weighted_fusion(est.x, est.L, weights, L_inv)
    checked_cholesky(fused.P, "the fused covariance")
    spread = squared_norms(fused.factors.B)
    trace = squared_norms(fused.factors.R_inv)
    with np.errstate(over="ignore", invalid="ignore"):  # a fixed delta_i = 0, rho_i ~ 1e-300
        gap = _relative_gap(delta, used, trace, spread)
    if info["rule"] == "optimal":
        # Newton: the certified gap decides; the alternating projections also require
        # delta at rest (the paper's test), which implies nothing beyond the gap.
        info["converged"] = (gap <= tol) if converged is None else converged
    x, P, gains = fused.x, fused.P, fused.gains
    info.update(delta=delta, rho=used, value=np.trace(P, axis1=-2, axis2=-1), gap=gap)
    if two:
        with np.errstate(divide="ignore"):
            info["gamma"] = delta[..., 1] / delta[..., 0]  # delta_1 = 1 / (1 + gamma)
    return FusionResult(restore_style(x, est.column), P, "pci", weights, gains, info)


def _registered_pci(xs, Ps, rho=None, tol=1e-10, max_iter=100, solver="newton",
                    delta=None):
    if rho is None:
        raise ValueError(
            "the 'pci' rule needs a correlation coefficient bound: fuse(..., method='pci', "
            "rho=...) with rho in [0, 1] (see cifilter.bounds.correlation_bound)"
        )
    return partial_ci(xs, Ps, rho, tol=tol, max_iter=max_iter, solver=solver, delta=delta)


def _truth_rho(joint):
    """Correlation coefficient bound, eq. (8), of the two halves of a joint covariance.

    Used by the demo: the joint error covariance ``[[P_a, P_ab], [P_ab^T, P_b]]`` of two
    tracks of equal dimension is known in a simulation, and the smallest admissible
    ``rho`` is ``sigma_max(X^-1 P_ab Y^-T)``.
    """
    J = as_float_array(joint, "joint")
    if J.ndim < 2 or J.shape[-1] != J.shape[-2] or J.shape[-1] % 2:
        raise ValueError(
            "the 'pci' truth hook expects the joint covariance of two estimates of equal "
            f"dimension, (..., 2n, 2n); got shape {J.shape}"
        )
    n = J.shape[-1] // 2
    rho = correlation_bound(J[..., :n, :n], J[..., n:, n:], J[..., :n, n:])
    # The bound of a valid joint covariance is at most 1; rounding may exceed it by ~1e-16.
    return np.minimum(np.asarray(rho), 1.0)


def _pci_truth_options(joint, rng):
    return {"rho": _truth_rho(joint)[..., None]}


register_method(
    "pci",
    _registered_pci,
    summary="partial-correlation CI given a correlation coefficient bound rho (needs rho=)",
    reference="Wu, Cai & Fu 2018, Theorems 3 and 5, Algorithms 1 and 2",
    guarantee="bound",
    truth_options=_pci_truth_options,
)
