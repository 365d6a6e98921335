"""Partial-correlation formulas of Wu, Cai & Fu (2018) and the solvers for ``delta``.

Shared by the ``"pci"`` rule and the horizon-aware partial CI: the correlation bounds
``rho`` (eq. (8), Definition 2), the weights of eq. (24) and their derivatives, the
certified gap of ``Tr P(delta)`` and its two minimisers: the active-set Newton method on
problem (35) and the alternating projections of Algorithms 1 and 2. The solvers trust
their input (validated inverse Cholesky factors ``L_inv`` of the covariances).
Derivations: ``docs/methods/pci.rst``.
"""


import numpy as np

from .._numerics.alignment import unobserved_directions
from .._numerics.information import (
    information_factors,
    single_diagonalisation_trusted,
    squared_norms,
    trace_curvature,
)
from .._numerics.linalg import eigh_single, ill_conditioned, lower_inverse_single, symmetrize
from .._numerics.optimize import (
    minimize_convex_scalar,
    minimize_convex_segment,
    minimize_convex_simplex,
)
from .._numerics.validation import as_float_array, check_finite
from ._generalised_ci import check_observable, generalised_assembly, square_roots

__all__ = [
    "NEWTON_RHO_FLOOR",
    "alternating_delta",
    "bound_and_spread",
    "check_rho",
    "effective_rho",
    "gains_bound",
    "negligible_rho",
    "newton_delta",
    "partial_state_bound",
    "partial_state_fusion",
    "partial_state_roots",
    "partial_weights",
    "relative_gap",
    "weight_derivatives",
]


def check_rho(rho, count, batch_shape):
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


def negligible_rho(count):
    """The largest bound ``rho_i`` whose effect on the bound is below one rounding unit.

    ``eps^2 / (4 N^2)`` (about 1.2e-33 for two estimates): setting every ``rho_i`` at or
    below it to 0 changes the worst admissible error variance along any direction by at
    most a factor ``1 + 2 sqrt(N sum_Z rho_i) <= 1 + eps`` (``docs/methods/pci.rst``,
    "Bounds below rounding"), so the bound of the zeroed problem dominates the true worst
    case to rounding, and the rule answers exactly as for ``rho_i = 0``.
    """
    return np.finfo(float).eps ** 2 / (4.0 * count * count)


def effective_rho(rho):
    """The bounds the rule uses: for two estimates ``sqrt(rho_1 rho_2)`` for both, and 0
    for a bound whose effect is below rounding (:func:`negligible_rho`).

    Definition 2 for two vectors is Lemma 3's condition with ``rho = sqrt(rho_1 rho_2)``,
    and Theorem 3 (the trace-minimal bound) takes one common ``rho``.
    """
    if rho.shape[-1] == 2:
        rho = np.sqrt(rho[..., :1] * rho[..., 1:]).repeat(2, axis=-1)
    return np.where(rho <= negligible_rho(rho.shape[-1]), 0.0, rho)


def partial_weights(delta, rho):
    """Eq. (24): ``w_i = delta_i / (rho_i + (1 - rho_i) delta_i)``, and 1 where ``rho_i = 0``.

    This is ``w_i^-1 = rho_i / delta_i + 1 - rho_i`` written without dividing by
    ``delta_i``, so that a weight driven to ``delta_i = 0`` gives ``w_i = 0`` (the estimate
    is ignored) unless ``rho_i = 0`` (uncorrelated: ``w_i = 1`` whatever ``delta_i``).
    """
    positive = rho > 0.0
    denominator = np.where(positive, rho + (1.0 - rho) * delta, 1.0)
    return np.where(positive, delta / denominator, 1.0)


def weight_derivatives(delta, rho):
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


# Veltkamp's splitting constant 2^27 + 1: a = hi + lo with hi, lo of 26 bits, so products of
# halves are exact in float64 (Dekker's two-product).
_SPLITTER = 134217729.0


def _split(a):
    """``(hi, lo)`` with ``a = hi + lo`` exactly, each of at most 26 significant bits."""
    c = _SPLITTER * a
    hi = c - (c - a)
    return hi, a - hi


def _two_product(a, a_split, b, b_split):
    """``(p, e)`` with ``p = fl(a b)`` and ``a b = p + e`` exactly (Dekker; no FMA needed)."""
    (ah, al), (bh, bl) = a_split, b_split
    p = a * b
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _compensated_sum(p, e):
    """``(s, c)`` with ``s + c`` the sum over the first axis of ``p + e``.

    ``p`` is summed by a chain of error-free two-sums (Knuth) whose rounding errors, with
    ``e``, go into ``c`` in ordinary arithmetic: the result is as accurate as a sum in
    twice the working precision (Ogita, Rump & Oishi's Sum2 / Dot2).
    """
    s = p[0]
    c = e.sum(axis=0)
    for term in p[1:]:
        t = s + term
        z = t - s
        c += (s - (t - z)) + (term - z)
        s = t
    return s, c


def _compensated_product(A, A_split, B, B_split):
    """``A B`` (..., n, n) as ``hi + lo``, as accurate as in twice the working precision.

    The summation index leads the products, ``A[..., i, k] B[..., k, j]`` at ``[k, ..., i, j]``,
    so that the summation runs over contiguous slices.
    """
    def column(M):  # M[..., i, k] -> [k, ..., i, 1]
        return np.moveaxis(M, -1, 0)[..., None]

    def row(M):  # M[..., k, j] -> [k, ..., 1, j]
        return np.moveaxis(M, -2, 0)[..., None, :]

    p, e = _two_product(column(A), tuple(column(part) for part in A_split),
                        row(B), tuple(row(part) for part in B_split))
    return _compensated_sum(p, e)


def _compensated_congruence(K, P):
    """``K P K^T`` (..., n, n) as accurate as if formed in twice the working precision.

    Products of ill-conditioned covariances and large gains cancel: ``K_i P_i K_i^T`` has
    norm ``w_i ||P||`` while its terms reach ``kappa(P_i) ||P||``, so ordinary arithmetic
    (or a Cholesky factor of ``P_i``, which carries the same rounding) loses
    ``kappa(P_i) eps`` of it. With Dot2 both products are accurate to ``eps^2`` of their
    terms, ``n eps^2 kappa ||P||``: far below ``eps ||P||`` for every condition number of the
    contract. ``P`` is scaled by a power of two (exact) so that the splitting cannot
    overflow.
    """
    exponent = np.frexp(np.abs(P).max(axis=(-2, -1), keepdims=True))[1]
    P = np.ldexp(P, -exponent)
    K_split = _split(K)
    Y_hi, Y_lo = _compensated_product(K, K_split, P, _split(P))  # Y = K P
    K_t = np.swapaxes(K, -1, -2)
    Z_hi, Z_lo = _compensated_product(Y_hi, _split(Y_hi), K_t,
                                      tuple(np.swapaxes(part, -1, -2) for part in K_split))
    Z = Z_hi + (Z_lo + Y_lo @ K_t)  # Y_lo's share in ordinary arithmetic: it is eps |Y|
    return np.ldexp(Z, exponent)


def gains_bound(gains, Ps, weights):
    """``P = sum_i K_i P_i K_i^T / w_i`` of the returned gains, from the input covariances.

    Theorem 5's bound of given gains (a bound for every joint covariance within the
    correlation bounds when ``w`` are eq. (24)'s weights of a ``delta`` on the simplex; the
    naive fusion's exact covariance for ``w_i = 1``). Each ``K_i P_i K_i^T`` is formed from
    ``P_i`` itself in compensated arithmetic (:func:`_compensated_congruence`), not from
    a Cholesky factor: ``L_i L_i^T`` differs from ``P_i`` by ``eps |L_i| |L_i^T|``, which the
    large entries of ``K_i`` turn into ``kappa(P_i) eps ||P||``. So ``P`` dominates the
    true worst-case error covariance of the returned gains to about ``N eps ||P||``
    (the rounding of the final sum), whatever the condition numbers; no condition number
    is squared (products only, no inverse). Exactly symmetric; a zero weight has a zero
    gain and no term.

    Parameters
    ----------
    gains : ndarray, shape (..., N, n, n)
    Ps : ndarray, shape (..., N, n, n)
        The covariances (symmetric; their symmetric part is used).
    weights : ndarray, shape (..., N)

    Returns
    -------
    ndarray, shape (..., n, n)
    """
    terms = symmetrize(_compensated_congruence(gains, Ps))
    positive = weights > 0.0
    scale = np.where(positive, 1.0 / np.where(positive, weights, 1.0), 0.0)
    return symmetrize(np.einsum("...k,...kij->...ij", scale, terms))


def partial_state_bound(gains, Ps, weights):
    """:func:`gains_bound` for estimates of ``H_i x``: ``P = sum_i K_i P_i K_i^T / w_i``.

    ``gains`` and ``Ps`` are tuples of N arrays, (..., n, m_i) and (..., m_i, m_i): each
    term from the input ``P_i`` in compensated arithmetic, as for full states (Lemma 7
    holds for rectangular gains, ``docs/methods/partial_state.rst``, eq. (H10)). Exactly
    symmetric; a zero weight has a zero gain and no term.
    """
    P = None
    for i, (K, Pi) in enumerate(zip(gains, Ps)):
        Pi = np.broadcast_to(Pi, K.shape[:-2] + Pi.shape[-2:])
        term = symmetrize(_compensated_congruence(K, Pi))
        w = weights[..., i, None, None]
        positive = w > 0.0
        term = np.where(positive, term / np.where(positive, w, 1.0), 0.0)
        P = term if P is None else P + term
    return symmetrize(P)


def partial_state_roots(est):
    """The square roots ``G_i`` (..., N, n, n) of estimates of ``H_i x``
    (:func:`cifilter.rules._generalised_ci.square_roots`), after the check that the
    estimates together observe the state (the error names the unobserved directions)."""
    roots = square_roots(est)
    check_observable(est, roots)
    return roots


def partial_state_fusion(est, roots, weights):
    """Partial CI's fused mean, gains and bound for estimates of ``H_i x`` at ``weights``.

    ``P^-1 = sum_i w_i H_i^T P_i^-1 H_i``, ``K_i = w_i P H_i^T P_i^-1`` (eqs. (H10)-(H11)
    of ``docs/methods/partial_state.rst``), with the gains of generalised CI's assembly
    (:func:`cifilter.rules._generalised_ci.generalised_assembly`: where some estimate is of
    the full state, the one of largest weight takes ``I - sum_j K_j H_j``) and ``P`` the
    bound of exactly these gains from the inputs (:func:`partial_state_bound`). Returns
    ``(x, P, gains, factors)``; ``gains`` a tuple of (..., n, m_i) arrays. Weights that
    drop the only estimate of some direction raise a ValueError naming the directions.
    """
    factors = information_factors(roots.G, weights, failures="nan")
    singular = np.isnan(factors.R[..., 0, 0])
    if np.any(singular):
        index = np.unravel_index(int(np.argmax(singular.ravel())), singular.shape)
        used = [i for i in range(est.count) if weights[index + (i,)] > 0.0]
        G = np.concatenate([roots.G[index + (i,)] for i in used], axis=0)
        directions = unobserved_directions(G)
        where = f" (problem {[int(i) for i in index]})" if index else ""
        if not directions:
            J = sum(weights[index + (i,)] * roots.G[index + (i,)].T @ roots.G[index + (i,)]
                    for i in used)
            raise ill_conditioned(
                f"with the given delta{where}: the fused information "
                "sum_i w_i H_i^T P_i^-1 H_i", np.linalg.cond(J))
        shown = ", ".join(str(v) for v in directions)
        raise ValueError(
            f"with the given delta{where}: sum_i w_i H_i^T P_i^-1 H_i is singular (a "
            f"delta_i = 0 with rho_i > 0 ignores estimate i); unobserved direction(s) of "
            f"the state (a basis of its null space, in state coordinates): {shown}"
        )
    x, _, gains = generalised_assembly(est, roots, weights, factors)
    full = list(est.full)
    if full:
        # Where every full-state estimate has weight 0 (delta_i = 0 at rho_i > 0), the
        # assembly's remainder I - sum_j K_j H_j (rounding, amplified by the condition
        # number) would be a gain with no term in the bound: ignore those estimates
        # exactly, as the other zero weights, and fuse the rest.
        dropped = weights[..., full].max(axis=-1) == 0.0
        if np.any(dropped):
            gains = list(gains)
            for i in full:
                gains[i] = np.where(dropped[..., None, None], 0.0, gains[i])
            total = sum((K @ xi[..., None])[..., 0] for K, xi in zip(gains, est.x))
            x = np.where(dropped[..., None], total, x)
            gains = tuple(gains)
    return x, partial_state_bound(gains, est.P, weights), gains, factors


def bound_and_spread(delta, rho, L_inv, failures="raise"):
    """``w`` (24), the factors of ``P`` (33) and ``Tr(P P_i^-1 P)`` for every estimate.

    ``Tr(P P_i^-1 P) = ||B_i||_F^2`` with ``B_i = P L_i^-T`` (see
    :func:`cifilter._numerics.information.information_factors`): a sum of squares, accurate to
    rounding whatever the conditioning. ``L_inv`` may also be the square roots ``G_i`` of
    estimates of ``H_i x`` (``G_i^T G_i = H_i^T P_i^-1 H_i``); ``failures="nan"`` gives NaN
    factors where the fused information is singular.
    """
    w = partial_weights(delta, rho)
    factors = information_factors(L_inv, w, failures=failures)
    spread = squared_norms(factors.B)
    return w, factors, spread


def relative_gap(delta, rho, trace, spread):
    """Certified bound on ``(Tr P(delta) - min Tr P) / Tr P`` (a Frank-Wolfe gap).

    ``Tr P(delta)`` is convex on the simplex (Lemma 8; also for rho_i in {0, 1}), so with
    its gradient ``g_i = -w_i' Tr(P P_i^-1 P)``,
    ``min Tr P >= Tr P - (sum_i g_i delta_i - min_i g_i)``.
    """
    first, _ = weight_derivatives(delta, rho)
    g = -first * spread
    # g_i delta_i = -Tr(P P_i^-1 P) w_i rho_i / base_i, finite even where g_i overflows
    positive = rho > 0.0
    base = np.where(positive, rho + (1.0 - rho) * delta, 1.0)
    along = -spread * partial_weights(delta, rho) * np.where(positive, rho / base, 0.0)
    return np.maximum(along.sum(axis=-1) - g.min(axis=-1), 0.0) / trace


def alternating_delta(L_inv, rho, tol, max_iter, start=None):
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
        w, factors, spread = bound_and_spread(d, r, L_inv[active])  # Step 2
        gap = relative_gap(d, r, squared_norms(factors.R_inv), spread)
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


NEWTON_RHO_FLOOR = 1e-8


def _weight_and_derivatives(delta, rho):
    """Eq. (24) and its first two derivatives at one float ``delta`` (``rho = 0``: 1, 0, 0)."""
    if rho == 0.0:
        return 1.0, 0.0, 0.0
    base = rho + (1.0 - rho) * delta
    first = rho / (base * base)
    return delta / base, first, -2.0 * (1.0 - rho) * first / base


def _single_pair_delta(L_inv, rho, max_iter):
    """Trace-optimal ``delta`` of one problem of two estimates in the diagonalised form.

    With ``P_1 = T T^T`` and ``P_2 = T diag(lam) T^T``, eq. (33) is
    ``P = T diag(lam_k / (w_1 lam_k + w_2)) T^T``, so ``Tr P = sum_k c_k lam_k / D_k`` with
    ``c_k = ||T e_k||^2`` and ``D_k = w_1 lam_k + w_2``: ``O(n)`` per Newton step in Python
    floats, with the interval method of two-estimate CI on ``delta = (t, 1 - t)``. Returns
    ``(delta (1, 2), steps (1,))``, or None where the diagonalisation is not trusted (the
    general path decides). The caller certifies the result with the true bounds.
    """
    L1 = lower_inverse_single(L_inv[0])
    G = L_inv[0] @ lower_inverse_single(L_inv[1])  # L_1^-1 L_2
    lam, U = eigh_single(G @ G.T)
    lam_list = lam.tolist()
    if not single_diagonalisation_trusted(lam_list, L_inv):
        return None
    c = np.square(L1 @ U).sum(axis=0).tolist()
    terms = [(ck * lk, lk) for ck, lk in zip(c, lam_list)]
    rho_1, rho_2 = float(rho[0]), float(rho[1])

    def derivative(t):
        w1, w1_t, w1_tt = _weight_and_derivatives(t, rho_1)
        w2, w2_s, w2_ss = _weight_and_derivatives(1.0 - t, rho_2)
        w2_t, w2_tt = -w2_s, w2_ss
        g = h = 0.0
        for cl, lk in terms:
            D = w1 * lk + w2
            D_t = w1_t * lk + w2_t
            D_tt = w1_tt * lk + w2_tt
            g -= cl * D_t / (D * D)
            h += cl * (2.0 * D_t * D_t / D - D_tt) / (D * D)
        return g, h

    scale = sum(cl / (0.5 * lk + 0.5) for cl, lk in terms)  # Tr P at w = (1/2, 1/2)
    with np.errstate(all="ignore"):
        t, steps, _ = minimize_convex_scalar(derivative, scale=scale, max_iter=max_iter)
    return np.array([[t, 1.0 - t]]), np.array([steps])


def _pair_newton(evaluate, objective, size, max_iter):
    """Two estimates: Newton on ``delta = (t, 1 - t)``, the same safeguarded interval
    method as two-estimate CI (:func:`cifilter._numerics.optimize.minimize_convex_segment`)."""
    everything = np.arange(size)
    # the magnitude of Tr P for the flatness test: its value in the middle of the segment
    scale = objective(np.full((size, 2), 0.5), everything)
    with np.errstate(invalid="ignore", divide="ignore"):
        delta, steps, _ = minimize_convex_segment(evaluate, size, scale=scale,
                                                  max_iter=max_iter)
    return delta, steps

def _released(delta, rho):
    """The start of the sweeps after the Newton phase: ``delta_i = 0`` with a bound below
    ``NEWTON_RHO_FLOOR`` raised to ``sqrt(rho_i)`` (then back onto the simplex).

    ``delta_i = 0`` is a fixed point of step (25) (``w_i = 0`` there), so a weight the
    floored Newton phase left at zero would stay there; but with the true ``rho_i`` the
    slope of ``Tr P`` at ``delta_i = 0`` is ``-Tr(P P_i^-1 P) / rho_i``, and the optimum
    lies near ``delta_i ~ sqrt(rho_i)`` (``docs/methods/pci.rst``), where the sweeps take it
    at once.
    """
    lift = (delta == 0.0) & (rho > 0.0) & (rho < NEWTON_RHO_FLOOR)
    start = np.where(lift, np.sqrt(rho), delta)
    return start / start.sum(axis=-1, keepdims=True)


def newton_delta(L_inv, rho, tol, max_iter, *, partial=False):
    """Minimise ``Tr P(delta)`` (eq. (35)) by the active-set Newton method on the simplex.

    Gradient ``g_i = -w_i' Tr(P I_i P)`` and Hessian
    ``H_ij = 2 w_i' w_j' Tr(P I_i P I_j P) - [i = j] w_i'' Tr(P I_i P)`` with
    ``I_i = P_i^-1`` and the derivatives of eq. (24) (see :func:`weight_derivatives`),
    formed from the factors ``B_i = P L_i^-T`` and ``C_i = R^-1 L_i^-T``:
    ``Tr(P I_i P) = ||B_i||^2`` and ``Tr(P I_i P I_j P) = Tr(B_i^T B_j C_j^T C_i)``. Optima on
    the boundary of the simplex (an ignored estimate) are exact. Each problem stops when
    its certified gap (:func:`relative_gap`) is at most ``tol``.

    Positive bounds below ``NEWTON_RHO_FLOOR`` are raised to it for the Newton phase only
    (why: ``docs/methods/pci.rst``, "The floor of rho in the Newton phase"); problems whose
    gap under the true bounds is then above ``tol`` continue with the sweeps of Algorithm 2
    (:func:`alternating_delta`). Two estimates run the interval Newton method of
    two-estimate CI on ``delta = (t, 1 - t)``. Returns ``delta`` and the iterations
    (Newton steps plus sweeps) per problem.

    ``partial=True``: ``L_inv`` holds the square roots ``G_i`` of estimates of ``H_i x``
    (``docs/methods/partial_state.rst``), whose fused information is singular where a zero
    weight drops the only estimate of some direction. Every N then runs the simplex method
    with the trace +inf at such points (its line searches reject them), and where its last,
    unchecked step lands on one, the best finite point it evaluated is taken, as for
    generalised CI.
    """
    true_rho = rho
    batch, count = rho.shape[:-1], rho.shape[-1]
    size = int(np.prod(batch, dtype=int))
    flat_L_inv = L_inv.reshape((size,) + L_inv.shape[-3:])
    floored = np.where(rho > 0.0, np.maximum(rho, NEWTON_RHO_FLOOR), 0.0).reshape(size, count)
    failures = "nan" if partial else "raise"
    best_f = np.full(size, np.inf)
    best_delta = np.full((size, count), 1.0 / count)

    def remember(delta, index, f):
        if not partial:
            return f
        f = np.where(np.isnan(f), np.inf, f)
        better = np.isfinite(f) & (f < best_f[index])
        best_f[index[better]] = f[better]
        best_delta[index[better]] = delta[better]
        return f

    def objective(delta, index):
        w = partial_weights(delta, floored[index])
        R_inv = information_factors(flat_L_inv[index], w, failures=failures).R_inv
        return remember(delta, index, squared_norms(R_inv))

    def evaluate(delta, index):
        r = floored[index]
        _, factors, spread = bound_and_spread(delta, r, flat_L_inv[index], failures)
        first, second = weight_derivatives(delta, r)
        curvature = trace_curvature(factors)  # Tr(P I_i P I_j P)
        H = 2.0 * first[..., :, None] * first[..., None, :] * curvature
        H = H - (second * spread)[..., None] * np.eye(count)
        trace = remember(delta, index, squared_norms(factors.R_inv))
        if not partial:
            return trace, -first * spread, symmetrize(H)
        singular = ~np.isfinite(trace)
        g = np.where(singular[:, None], 0.0, -first * spread)
        H = np.where(singular[:, None, None], np.eye(count), symmetrize(H))
        return trace, g, H

    single = _single_pair_delta(flat_L_inv[0], floored[0], max_iter) if (
        count == 2 and size == 1 and not partial) else None
    if single is not None:
        delta, steps = single
    elif count == 2 and not partial:
        delta, steps = _pair_newton(evaluate, objective, size, max_iter)
    else:
        # (partial estimates: singular faces give inf and NaN factors, rejected by design)
        with np.errstate(**({"invalid": "ignore", "over": "ignore"} if partial else {})):
            delta, steps, _ = minimize_convex_simplex(
                evaluate, objective, count, (size,), xtol=tol, max_iter=max_iter, gtol=tol,
                subset=True,
            )
    if partial:  # a last step onto a singular face: the best finite point evaluated
        landed = np.isnan(information_factors(flat_L_inv, partial_weights(
            delta.reshape(size, count), true_rho.reshape(size, count)),
            failures="nan").R[:, 0, 0])
        delta = np.where(landed[:, None], best_delta, delta.reshape(size, count))
    delta, steps = delta.reshape(batch + (count,)), steps.reshape(batch)
    _, factors, spread = bound_and_spread(delta, true_rho, L_inv)
    trace = squared_norms(factors.R_inv)
    redo = (relative_gap(delta, true_rho, trace, spread) > tol).reshape(-1)
    steps = np.array(steps).reshape(-1)
    if redo.any():
        size = steps.size
        flat = delta.reshape(size, count).copy()
        start = _released(flat[redo], true_rho.reshape(size, count)[redo])
        more, sweeps, _ = alternating_delta(
            L_inv.reshape((size,) + L_inv.shape[-3:])[redo],
            true_rho.reshape(size, count)[redo], tol, max_iter, start=start,
        )
        flat[redo] = more
        steps[redo] += sweeps
        delta = flat.reshape(delta.shape)
    return delta, steps.reshape(batch)
