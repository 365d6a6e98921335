"""Covariance Intersection weights: the fast non-iterative rules and the certified optimum.

The solvers trust their input: validated estimates
(:class:`cifilter._numerics.validation.Estimates`,
with Cholesky factors) and a parsed criterion (:func:`cifilter._numerics.criteria.parse_criterion`).
They serve the ``"ci"`` rule and the horizon-aware weights, which at horizon 0 are the same
problem. Derivations: ``docs/methods/ci.rst``.
"""

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from .._kernels import dispatch as kernels
from .._numerics.criteria import (
    GAP_TOL,
    GapCertificate,
    criterion_gradient,
    criterion_of_factor,
    gap_certificate,
    gap_converged,
    gradient_rounding,
    pair_certificate,
    rounding_scale,
    slope_rounding,
    slope_rounding_single,
)
from .._numerics.information import (
    DIAGONAL_TRUST,
    diagonal_spread_squared,
    information_factors,
    information_matrices,
    log_det_curvature,
    lower_inverse_stack,
    single_diagonalisation_trusted,
    squared_norms,
    trace_curvature,
    weighted_fusion,
)
from .._numerics.linalg import (
    cholesky,
    eigh_single,
    logdet_from_cholesky,
    lower_inverse_single,
    symmetrize,
)
from .._numerics.optimize import (
    minimize_convex_interval,
    minimize_convex_scalar,
    minimize_convex_simplex,
)

__all__ = ["FAST_OMEGA_RULES", "cached_identity", "optimal_weights", "pair_derivative"]


def _fast_weights(est):
    """Niehsen (2002): w_i proportional to 1 / trace(P_i) (eq. (2) of Weng & Djurić, journal)."""
    inverse_traces = 1.0 / np.trace(est.P, axis1=-2, axis2=-1)
    return inverse_traces / inverse_traces.sum(axis=-1, keepdims=True)


def _det_ratio_weights(est):
    """Eq. (7) of Weng & Djurić (2012), w_1 = |P_2| / (|P_1| + |P_2|), generalised to N.

    w_i is proportional to 1 / det(P_i); computed from log-determinants (a softmax) so
    that large or small determinants neither overflow nor underflow.
    """
    log_information_det = -logdet_from_cholesky(est.L)
    shifted = log_information_det - log_information_det.max(axis=-1, keepdims=True)
    weights = np.exp(shifted)
    return weights / weights.sum(axis=-1, keepdims=True)


def _improved_fast_weights(est):
    """Franken & Hupper (2005), improved fast CI.

    With I_i = P_i^-1 and I = sum_j I_j,

        w_i = (|I| - |I - I_i| + |I_i|) / (N |I| + sum_j (|I_j| - |I - I_j|)).

    For two estimates this is w_1 = (|I| - |I_2| + |I_1|) / (2 |I|). All determinants are
    divided by |I| (ratios from log-determinants), so nothing overflows. The weights are
    positive and sum to one: |I - I_i| < |I| because I_i is positive definite.
    """
    informations = information_matrices(est.L)
    total = symmetrize(informations.sum(axis=-3))
    log_total = logdet_from_cholesky(cholesky(total, "sum of information matrices"))
    log_own = -logdet_from_cholesky(est.L)
    # sum_{j != i} I_j summed directly: total - I_i cancels when the scales differ widely
    count = informations.shape[-3]
    others = np.stack([sum(informations[..., j, :, :] for j in range(count) if j != i)
                       for i in range(count)], axis=-3)
    log_others = logdet_from_cholesky(cholesky(others, "sum of the other information matrices"))
    own = np.exp(log_own - log_total[..., None])
    rest = np.exp(log_others - log_total[..., None])
    numerators = 1.0 - rest + own
    return numerators / numerators.sum(axis=-1, keepdims=True)


FAST_OMEGA_RULES = {
    "fast": _fast_weights,
    "improved-fast": _improved_fast_weights,
    "det-ratio": _det_ratio_weights,
}
"""Non-iterative weight rules accepted as ``omega=<name>``."""



class _Diagonalised(NamedTuple):
    """The two-estimate problem in the basis that diagonalises both covariances."""

    omega: np.ndarray  # (...,) proposed weight of the first estimate
    iterations: np.ndarray  # (...,)
    trusted: np.ndarray  # (...,) bool: accurate enough to certify and assemble from
    gap: np.ndarray  # (...,) certified gap from the diagonal form (valid where trusted)
    floor: np.ndarray  # (...,) its rounding floor (valid where trusted)
    computed: np.ndarray  # (...,) the gap of the computed slope (valid where trusted)
    lam: np.ndarray  # (..., n) generalised eigenvalues of (P_2, P_1)
    U: np.ndarray  # (..., n, n) eigenvectors of L_1^-1 P_2 L_1^-T
    T: np.ndarray  # (..., n, n) L_1 U: P_1 = T T^T, P_2 = T diag(lam) T^T


def _diagonalised_weights(est, kind, W, L1_inv):
    """Criterion-optimal omega for N = 2 by simultaneous diagonalisation (the fast path).

    With P_1 = L L^T and L^-1 P_2 L^-T = U diag(lam) U^T, T = L U gives
    P(omega) = T diag(d) T^T with d_k = lam_k / (1 + omega (lam_k - 1)), so the criterion
    is a sum of scalar terms: trace(W P) = sum_k c_k d_k with c = diag(T^T W T), and
    log det P = log det P_1 + sum_k log(d_k / lam_k) + const. Both are convex in omega;
    the derivative is closed-form and its root is found by safeguarded Newton iterations,
    O(n) per iteration. With ``w = (omega, 1 - omega)`` the certified gap
    is ``omega max(f', 0) + (1 - omega) max(-f', 0)``, taken at the worse of the slopes
    ``f' +- e``, ``e`` the bound of its rounding (:func:`slope_rounding`).
    The eigenvalues ``lam`` are those of a matrix whose condition number is up to
    cond(P_1) cond(P_2), so for ill-conditioned pairs they are rounding noise: such
    problems are not ``trusted`` and the caller solves them from Cholesky factors; so are
    those whose gap the rounding of the eigenvalues keeps above the tolerance (certified
    again from Cholesky factors, whose rounding is usually far smaller).
    """
    S = symmetrize(L1_inv @ est.P[..., 1, :, :] @ L1_inv.swapaxes(-1, -2))
    lam, U = np.linalg.eigh(S)
    T = est.L[..., 0, :, :] @ U
    n, size = est.dim, int(np.prod(est.batch_shape, dtype=int))
    lam_flat = lam.reshape(size, n)
    usable = np.all(lam_flat > 0.0, axis=-1) & np.all(np.isfinite(lam_flat), axis=-1)
    a = np.where(usable[:, None], lam_flat - 1.0, 0.0)
    if kind == "det":

        def derivatives(omega, index):
            ratio = a[index] / (1.0 + omega[:, None] * a[index])
            return -ratio.sum(axis=-1), (ratio**2).sum(axis=-1)

        scale = np.full(size, float(n))
    else:
        if kind == "trace":
            c = np.square(T).sum(axis=-2)
        else:
            c = np.einsum("...ik,...ij,...jk->...k", T, W, T)
        c = np.broadcast_to(c, est.batch_shape + (n,)).reshape(size, n)
        ca = c * (a + 1.0) * a

        def derivatives(omega, index):
            den = 1.0 + omega[:, None] * a[index]
            term = ca[index] / den**2
            return -term.sum(axis=-1), 2.0 * (term * a[index] / den).sum(axis=-1)

        scale = (c * (a + 1.0)).sum(axis=-1) + c.sum(axis=-1)  # tr(W P_2) + tr(W P_1)
    with np.errstate(all="ignore"):  # noise eigenvalues: such problems are not trusted
        omega, iterations, _ = minimize_convex_interval(derivatives, size, scale=scale)
        omega = np.where(usable & np.isfinite(omega), omega, 0.5)
        spread = lam_flat.max(axis=-1) / lam_flat.min(axis=-1)
        sigma = np.maximum(lam_flat.max(axis=-1),
                           rounding_scale(L1_inv, est.P[..., 1, :, :]).reshape(size))
        lam_used = np.where(usable[:, None], lam_flat, 1.0)
        c_used = None if kind == "det" else c
        # A tie to rounding (the slope within its rounding of zero at both ends, e.g.
        # P_1 = P_2): every omega is optimal to the precision of the inputs, and the end
        # the search would take is decided by the sign of rounding noise, which differs
        # between eigensolvers (LAPACK's here, the kernel's Jacobi rotations) and batch
        # routes. Such problems get omega = 1/2 (the compiled kernel hands them back here).
        index = np.arange(size)
        ends = [(np.full(size, end), derivatives(np.full(size, end), index)[0])
                for end in (0.0, 1.0)]
        tie = usable & np.logical_and.reduce(
            [np.abs(g_end) <= slope_rounding(lam_used, w_end, c_used, sigma)
             for w_end, g_end in ends])
        omega = np.where(tie, 0.5, omega)
        iterations = np.where(tie, 0, iterations)
        slope, _ = derivatives(omega, index)
        rounding = slope_rounding(lam_used, omega, c_used, sigma)
        cert = pair_certificate(omega, slope, rounding,
                                None if kind == "det" else
                                (c * (a + 1.0) / (1.0 + omega[:, None] * a)).sum(axis=-1))
    conditioning = np.maximum(diagonal_spread_squared(est.L[..., 0, :, :]),
                              diagonal_spread_squared(est.L[..., 1, :, :])).reshape(size)
    trusted = (usable & (spread <= DIAGONAL_TRUST) & (conditioning <= DIAGONAL_TRUST)
               & (cert.gap <= GAP_TOL))
    shape = est.batch_shape

    def kept(values):
        return np.where(trusted, values, np.inf).reshape(shape)

    return _Diagonalised(omega.reshape(shape), iterations.reshape(shape),
                         trusted.reshape(shape), kept(cert.gap), kept(cert.floor),
                         kept(cert.computed), lam, U, T)


def _fuse_diagonalised(est, L1_inv, d, weights):
    """CI of two estimates from their diagonalisation, as the bound of its gains.

    ``K_1 = omega P P_1^-1 = omega T diag(e) U^T L_1^-1`` with
    ``e_k = lam_k / (1 + omega (lam_k - 1))`` (because ``T^T L_1^-T = U^T``), ``K_2 = I - K_1``,
    and ``P = K_1 P_1 K_1^T / omega + K_2 P_2 K_2^T / (1 - omega)`` (the bound of these
    gains; see ``_information``), with ``K_1 L_1 = omega T diag(e) U^T``. Used only where
    the diagonalisation is trusted; two matrix products cheaper than the general assembly.
    """
    omega = weights[..., 0]
    n = est.dim
    e = d.lam / (1.0 + omega[..., None] * (d.lam - 1.0))
    TE = d.T * e[..., None, :]
    K1 = omega[..., None, None] * (TE @ (d.U.swapaxes(-1, -2) @ L1_inv))
    # An ignored estimate gets a gain of exactly zero (its term is not in the bound)
    K1 = np.where((omega == 1.0)[..., None, None], np.eye(n), K1)
    K2 = np.eye(n) - K1
    M1 = K1 @ est.L[..., 0, :, :]
    M2 = K2 @ est.L[..., 1, :, :]
    P = np.zeros(M1.shape)
    for M, w in ((M1, omega), (M2, 1.0 - omega)):
        w = w[..., None, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            M = np.where(w > 0.0, M / np.sqrt(w), 0.0)
        P += M @ M.swapaxes(-1, -2)
    x1, x2 = est.x[..., 0, :], est.x[..., 1, :]
    x = x2 + (K1 @ (x1 - x2)[..., None])[..., 0]
    return x, symmetrize(P), np.stack([K1, K2], axis=-3)


def _interval_weights(L_inv, kind, W, scale):
    """Criterion-optimal omega for N = 2 from Cholesky factors (the robust path).

    Safeguarded Newton on ``f(omega) = f(omega, 1 - omega)`` with ``f' = g_2 - g_1`` and,
    with ``E = P (P_1^-1 - P_2^-1) P = B_1 B_1^T - B_2 B_2^T`` and ``P^-1 = R R^T``,
    ``f'' = 2 trace(W E R R^T E)`` for the trace criteria and ``f'' = ||R^T E R||_F^2`` for
    log det P. Each iteration factorises the fused information, O(n^3), and nothing squares
    a condition number; bisection takes over wherever a Newton step is not trusted, so the
    bracket shrinks to ``xtol`` whatever the rounding in the derivatives.
    ``L_inv`` is (size, 2, n, n); returns omega, iterations (size,).
    """
    size = L_inv.shape[0]

    def derivatives(omega, index):
        weights = np.stack([omega, 1.0 - omega], axis=-1)
        factors = information_factors(L_inv[index], weights, failures="nan")
        g = criterion_gradient(factors, kind, None if W is None else W[index])
        B = factors.B
        E = B[:, 0] @ B[:, 0].swapaxes(-1, -2) - B[:, 1] @ B[:, 1].swapaxes(-1, -2)
        R = factors.R
        ER = E @ R
        if kind == "det":
            RER = R.swapaxes(-1, -2) @ ER
            curvature = squared_norms(RER)
        elif kind == "trace":
            curvature = 2.0 * squared_norms(ER)
        else:
            curvature = 2.0 * np.einsum("...ij,...jk,...ik->...", W[index], ER, ER)
        slope = g[:, 1] - g[:, 0]
        # A numerically singular fused information (only next to an end whose covariance is
        # itself that ill-conditioned) means an unbounded criterion there: the minimum lies
        # towards the other end, so the slope points away from this one.
        singular = np.isnan(factors.R[:, 0, 0])
        slope = np.where(singular, np.where(omega >= 0.5, np.inf, -np.inf), slope)
        return slope, np.where(singular, np.inf, curvature)

    with np.errstate(invalid="ignore"):  # -inf / inf steps: bisection takes over
        omega, iterations, _ = minimize_convex_interval(derivatives, size, scale=scale)
    return omega, iterations


def _simplex_weights(L_inv, kind, W, count, shape):
    """Criterion-optimal weights for any N by an active-set Newton method on the simplex.

    Gradient and Hessian of f(w) = trace(W P(w)), P(w) = (sum_i w_i I_i)^-1 (I_i = P_i^-1):
    g_i = -trace(W B_i B_i^T) and H_ij = 2 trace(B_i^T W B_j C_j^T C_i); for
    f(w) = log det P(w): g_i = -||C_i||^2 and H_ij = ||C_i^T C_j||^2, all from the factors
    of :func:`cifilter._numerics.information.information_factors` (no explicit inverses). The solver
    stops each problem at a certified gap of ``GAP_TOL``, so tied inputs (a singular
    Hessian along the ties) stop as soon as the criterion is optimal.
    """

    size = int(np.prod(shape, dtype=int))
    L_inv = L_inv.reshape((size,) + L_inv.shape[-3:])
    W = None if W is None else W.reshape((size,) + W.shape[-2:])

    def objective(w, index):
        R_inv = information_factors(L_inv[index], w).R_inv
        return criterion_of_factor(R_inv, kind, None if W is None else W[index])

    def evaluate(w, index):
        factors = information_factors(L_inv[index], w)
        Wi = None if W is None else W[index]
        f = criterion_of_factor(factors.R_inv, kind, Wi)
        g = criterion_gradient(factors, kind, Wi)
        if kind == "det":
            H = log_det_curvature(factors)
        else:
            H = 2.0 * trace_curvature(factors, Wi)
        return f, -g, symmetrize(H)

    weights, iterations, _ = minimize_convex_simplex(
        evaluate, objective, count, (size,), gtol=0.25 * GAP_TOL,
        absolute_gap=kind == "det", subset=True,
    )
    weights, iterations = weights.reshape(shape + (count,)), iterations.reshape(shape)
    return weights, iterations


def pair_derivative(a, c, kind):
    """``f'`` and ``f''`` of the diagonalised two-estimate criterion at a float omega, in
    Python floats (:func:`_diagonalised_weights` for one problem; ``a = lam - 1``)."""
    if kind == "det":
        def derivative(omega):
            g = h = 0.0
            for ak in a:
                ratio = ak / (1.0 + omega * ak)
                g -= ratio
                h += ratio * ratio
            return g, h
        return derivative
    ca = [ck * (ak + 1.0) * ak for ck, ak in zip(c, a)]

    def derivative(omega):
        g = h = 0.0
        for cak, ak in zip(ca, a):
            den = 1.0 + omega * ak
            term = cak / (den * den)
            g -= term
            h += term * ak / den
        return g, 2.0 * h
    return derivative


_IDENTITIES: dict[int, NDArray[np.float64]] = {}


def cached_identity(n):
    """A cached read-only identity matrix (the single-call path builds one per call)."""
    identity = _IDENTITIES.get(n)
    if identity is None:
        identity = np.eye(n)
        identity.flags.writeable = False
        _IDENTITIES[n] = identity
    return identity


def _single_pair(est, kind, W):
    """:func:`optimal_weights` for one problem of two estimates (no batch axes).

    The same method as the batched path (:func:`_diagonalised_weights`, then
    :func:`_fuse_diagonalised`) with LAPACK called directly and the scalar Newton
    iteration in Python floats: a single call costs tens of microseconds instead of
    hundreds. Returns None where the diagonalisation is not trusted (the batched path then
    decides from Cholesky factors).
    """
    L1, L2 = est.L[0], est.L[1]
    L1_inv = lower_inverse_single(L1)
    S = L1_inv @ est.P[1] @ L1_inv.T
    lam, U = eigh_single(0.5 * (S + S.T))
    lam_list = lam.tolist()
    if not single_diagonalisation_trusted(lam_list, (L1, L2)):
        return None
    T = L1 @ U
    a = [value - 1.0 for value in lam_list]
    if -1.0 in a:  # an eigenvalue below eps: 1 + omega a is 0 at omega = 1 (batched path)
        return None
    if kind == "det":
        c, scale = None, float(len(a))
    else:
        c = (np.square(T).sum(axis=0) if kind == "trace"
             else np.einsum("ik,ij,jk->k", T, W, T)).tolist()
        scale = sum(ck * (ak + 1.0) for ck, ak in zip(c, a)) + sum(c)
    derivative = pair_derivative(a, c, kind)
    inverse, covariance = L1_inv.ravel(), est.P[1].ravel()
    with np.errstate(over="ignore", under="ignore"):
        spread = float(inverse @ inverse) * math.sqrt(float(covariance @ covariance))
    if not math.isfinite(spread):  # beyond about 1e150: scaled norms
        spread = float(rounding_scale(L1_inv, est.P[1]))
    sigma = max(lam_list[-1], spread)
    if (abs(derivative(0.0)[0]) <= slope_rounding_single(lam_list, 0.0, c, sigma)
            and abs(derivative(1.0)[0]) <= slope_rounding_single(lam_list, 1.0, c, sigma)):
        omega, iterations = 0.5, 0  # a tie to rounding (_diagonalised_weights)
    else:
        omega, iterations, _ = minimize_convex_scalar(derivative, scale=scale)
    slope, _ = derivative(omega)
    rounding = slope_rounding_single(lam_list, omega, c, sigma)
    value = (None if kind == "det"
             else sum(ck * (ak + 1.0) / (1.0 + omega * ak) for ck, ak in zip(c, a)))
    gap, floor, computed = pair_certificate(float(omega), float(slope), rounding, value)
    if not gap <= GAP_TOL:  # not certified here: the Cholesky-based path decides
        return None
    # Assembly as in _fuse_diagonalised: K_1 = omega T diag(e) U^T L_1^-1, K_2 = I - K_1,
    # P = K_1 P_1 K_1^T / omega + K_2 P_2 K_2^T / (1 - omega), the bound of these gains.
    n = len(a)
    gains = np.empty((2, n, n))
    if omega == 1.0:
        gains[0] = cached_identity(n)
    else:
        e = [value / (1.0 + omega * ak) for value, ak in zip(lam_list, a)]
        np.matmul(T * e, U.T @ L1_inv, out=gains[0])
        gains[0] *= omega
    K1 = gains[0]
    np.subtract(cached_identity(n), K1, out=gains[1])
    if omega == 0.0:
        M = gains[1] @ L2
        P = M @ M.T
    elif omega == 1.0:
        M = K1 @ L1
        P = M @ M.T
    else:
        M1 = K1 @ L1
        M2 = gains[1] @ L2
        P = (M1 @ M1.T) / omega + (M2 @ M2.T) / (1.0 - omega)
    x1, x2 = est.x
    x = x2 + K1 @ (x1 - x2)
    weights = np.array([omega, 1.0 - omega])
    info = {"iterations": np.array(iterations),
            "converged": np.array(gap_converged(float(gap), float(floor), float(computed))),
            "gap": np.array(gap), "gap_floor": np.array(floor), "solver": "diagonalise"}
    return weights, info, (x, 0.5 * (P + P.T), gains)


def optimal_weights(est, kind, W, method="auto", L_inv=None, *, report=False,
                    compiled=True):
    """Criterion-optimal weights, certified: ``(weights, info, (x, P, gains))``.

    N = 2 (``"diagonalise"``): the O(n)-per-iteration diagonalised Newton method; where
    it is trusted its gap certifies it and the result is assembled from it; elsewhere
    (ill-conditioned pairs) the proposal is certified from Cholesky factors and, if that
    fails, solved again by the Cholesky-based interval method. N > 2 (``"simplex"``): the
    active-set Newton method on the simplex. The fused estimate is the bound of the
    returned gains in both cases (see ``_information``); ``info`` has ``iterations``,
    ``converged`` (:func:`cifilter._numerics.criteria.gap_converged`: optimal to the
    precision the inputs allow), ``gap`` (the certified gap, rounding included),
    ``gap_floor`` (its part due to the rounding of the inputs) and ``solver``.

    With ``report=True`` a fourth item is returned: the criterion report of ``P``
    (:func:`cifilter._numerics.criteria.criterion_report`) where the compiled kernels computed it,
    else None. ``compiled=False`` keeps the numpy path whatever the backend
    (:mod:`cifilter.backend`); the kernels hand the items they cannot certify back to it.
    """
    if compiled and est.count == 2 and method != "simplex":
        def numpy_path(sub, sub_W):
            return optimal_weights(sub, kind, sub_W, method, compiled=False)

        fast = kernels.optimal_pair(est, kind, W, numpy_path)
        if fast is not None:
            return fast if report else fast[:3]
    elif compiled and est.count > 2 and method in ("auto", "simplex"):
        def numpy_path(sub, sub_W):
            return optimal_weights(sub, kind, sub_W, method, compiled=False)

        fast = kernels.optimal_many(est, kind, W, numpy_path)
        if fast is not None:
            return fast if report else fast[:3]
    result = _optimal_weights(est, kind, W, method, L_inv)
    return result + (None,) if report else result


def _optimal_weights(est, kind, W, method, L_inv):
    """:func:`optimal_weights` on the numpy path."""
    if est.count == 2 and method != "simplex" and not est.batch_shape:
        single = _single_pair(est, kind, W)
        if single is not None:
            return single
    shape, n = est.batch_shape, est.dim
    Wb = None if W is None else np.broadcast_to(W, shape + (n, n))
    two = est.count == 2 and method != "simplex"
    if not two:
        if L_inv is None:
            L_inv = lower_inverse_stack(est.L)
        weights, iterations = _simplex_weights(L_inv, kind, Wb, est.count, shape)
        fused, cert = _fuse_and_certify(est, L_inv, weights, kind, Wb)
        result = (fused.x, fused.P, fused.gains)
    else:
        # (only the first inverse factor is needed unless some problem is not trusted)
        L1_inv = (lower_inverse_stack(est.L[..., 0, :, :]) if L_inv is None
                  else L_inv[..., 0, :, :])
        d = _diagonalised_weights(est, kind, W, L1_inv)
        weights = np.stack([d.omega, 1.0 - d.omega], axis=-1)
        iterations, cert = d.iterations, GapCertificate(d.gap, d.floor, d.computed)
        with np.errstate(all="ignore"):  # rows that are not trusted are replaced below
            result = _fuse_diagonalised(est, L1_inv, d, weights)
        if not np.all(d.trusted):
            if L_inv is None:
                L_inv = lower_inverse_stack(est.L)
            weights, iterations, cert, result = _resolve_untrusted(
                est, L_inv, kind, Wb, ~d.trusted, weights, iterations, cert, result)
    info = {
        "iterations": iterations,
        "converged": gap_converged(*cert),
        "gap": cert.gap,
        "gap_floor": cert.floor,
        "solver": "diagonalise" if two else "simplex",
    }
    return weights, info, result


def _resolve_untrusted(est, L_inv, kind, W, untrusted, weights, iterations, cert, result):
    """Certify (and where needed re-solve) the two-estimate problems ``untrusted`` from
    Cholesky factors, and assemble them with the general weighted fusion."""
    size = int(np.prod(est.batch_shape, dtype=int))
    index = np.flatnonzero(untrusted.reshape(size))

    def rows(array, tail):
        return array.reshape((size,) + array.shape[array.ndim - tail:])[index]

    sub = type(est)(rows(est.x, 2), rows(est.P, 3), rows(est.L, 3), est.column)
    sub_L_inv, sub_W = rows(L_inv, 3), None if W is None else rows(W, 2)
    sub_weights = rows(weights, 1)
    fused, sub_cert = _fuse_and_certify(sub, sub_L_inv, sub_weights, kind, sub_W,
                                        failures="nan")
    sub_iterations = rows(iterations, 0)
    if fused is None:
        if kind == "det":
            scale = np.full(index.size, float(est.dim))
        else:
            Wr = np.eye(est.dim) if sub_W is None else sub_W
            scale = np.einsum("...ij,...kji->...", Wr, sub.P)
        omega, more = _interval_weights(sub_L_inv, kind, sub_W, scale)
        redo = ~gap_converged(*sub_cert)
        sub_weights = np.where(redo[:, None], np.stack([omega, 1.0 - omega], axis=-1),
                               sub_weights)
        sub_iterations = sub_iterations + np.where(redo, more, 0)
        fused, sub_cert = _fuse_and_certify(sub, sub_L_inv, sub_weights, kind, sub_W)
    out = []
    for full, part in ((weights, sub_weights), (iterations, sub_iterations),
                       *zip(cert, sub_cert), *zip(result, (fused.x, fused.P, fused.gains))):
        flat = np.array(full).reshape((size,) + np.shape(full)[len(est.batch_shape):])
        flat[index] = part
        out.append(flat.reshape(np.shape(full)))
    weights, iterations, gap, floor, computed, x, P, gains = out
    return weights, iterations, GapCertificate(gap, floor, computed), (x, P, gains)


def _fuse_and_certify(est, L_inv, weights, kind, W, failures="raise"):
    """The weighted fusion at ``weights`` and the certificate of the criterion there
    (:class:`~cifilter._numerics.criteria.GapCertificate`: the Frank-Wolfe gap with the
    rounding of the gradients, :func:`~cifilter._numerics.criteria.gradient_rounding`).

    With ``failures="nan"`` a problem whose fused information is numerically singular at
    ``weights`` gets an infinite gap (to be re-solved) instead of raising, and the fusion
    is formed only if every problem is converged (else None is returned for it).
    """
    factors = information_factors(L_inv, weights, failures=failures)
    g = criterion_gradient(factors, kind, W)
    value = criterion_of_factor(factors.R_inv, kind, W)
    with np.errstate(invalid="ignore", over="ignore"):
        rounding = gradient_rounding(factors, est.L, L_inv, g)
        cert = gap_certificate(weights, g, value, kind, rounding)
    cert = GapCertificate(*(np.where(np.isnan(part), np.inf, part) for part in cert))
    if failures == "nan" and not np.all(gap_converged(*cert)):
        return None, cert
    return weighted_fusion(est.x, est.L, weights, L_inv, factors), cert
