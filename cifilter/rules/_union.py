"""Covariance union: the smallest common upper bound of covariances, and the fused mean.

For a candidate mean ``u`` every estimate ``(x_i, P_i)`` asks for ``U >= M_i`` with
``M_i = P_i + (u - x_i)(u - x_i)^T`` (Uhlmann 2003). For two matrices ``A``, ``B`` the
smallest such ``U`` has a closed form in both criteria (derivations:
``docs/methods/union.rst``):

* ``"det"``: with ``A = T T^T``, ``B = T diag(d) T^T``, ``U = T diag(max(1, d)) T^T``,
  computed as ``A + B - T diag(min(1, d)) T^T`` from the factor of the whitening shared
  with Ellipsoidal Intersection (:func:`cifilter.rules._ellipsoidal.whiten`);
* ``"trace"``: ``U = A + (B - A)_+ = (A + B)/2 + |B - A|/2`` (the positive part in an
  orthonormal eigenbasis ``V`` of ``B - A``).

Both are a per-direction maximum in coordinates ``y = T^-1 x`` (``T = V`` for the trace),
and the mean that minimises the criterion satisfies a per-direction rule in the same
coordinates: each coordinate of ``u`` is that of the mean of the dominating matrix, or lies
between the two means where they tie. :func:`optimal_pair_mean` iterates that rule with a
descent safeguard. Every function is batched over leading axes.
"""

from typing import NamedTuple

import numpy as np
from scipy.special import expit

from .._numerics.linalg import cholesky, ill_conditioned, positive_definite, symmetrize
from .._numerics.validation import Estimates
from ._ellipsoidal import gram, whiten

__all__ = [
    "CRITERIA", "PairUnion", "criterion_of", "mean_candidates_value", "optimal_pair_mean",
    "pair_union", "separable_start", "sequential_union",
]

CRITERIA = ("trace", "det")
"""Accepted criteria of :func:`cifilter.covariance_union`."""

# Eigen-directions whose two variances agree to this relative precision are ties: there the
# optimal mean may lie anywhere between the two means (the criterion has a kink).
TIE_TOL = 1e-9
# The optimal mean of two estimates is accepted when the certified relative gap of the trace
# criterion is at most GAP_TOL, or (det) when the mean rule's residual is at most
# RESIDUAL_TOL standard deviations of U: the optimum typically sits on a kink, approached
# linearly from both sides, and a residual r leaves an excess of the criterion of order r^2.
GAP_TOL = 1e-9
RESIDUAL_TOL = 1e-6
# Trace problems the per-direction iteration has not certified after SMOOTHING_AFTER
# iterations, or whose certified gap shrank less than 1/SLOW_PROGRESS-fold in one iteration,
# continue on the smoothed criterion (:func:`smoothed_trace_mean`): where the optimum sits
# on several kinks at once, or eigenvalues of M_2 - M_1 nearly meet there, the iteration
# converges only linearly. SMOOTHING_AFTER = 0: every trace problem not certified at its
# start goes to the continuation at once (90% of the network demo's 5600 problems ended
# there after up to 10 iterations; on 1500 random 4x4 pairs, in batches of 30, the
# continuation alone took 0.45-0.75 of the time of the iterations followed by it).
SMOOTHING_AFTER = 0
SLOW_PROGRESS = 0.1
# The smoothing parameters of the continuation, relative to the criterion's value: the last
# one leaves a duality gap of at most 0.28 n times it. The first ones are large because the
# continuation starts from the best candidate mean, not from the iteration's end.
SMOOTHING_STAGES = np.geomspace(1e-1, 1e-12, 12)
# From the stage whose relative smoothing is POLISH_BELOW on, the rows not yet certified try
# up to POLISH_STEPS Newton steps of the kink's KKT system (:func:`trace_newton_steps`) from
# the smoothed minimiser, kept only where the dual bound certifies them: near the optimum
# they converge quadratically where the smoothed path converges only as mu.
POLISH_BELOW = 1e-4
POLISH_STEPS = 2
# A row leaves a stage of the continuation when the part of its duality gap that is not the
# smoothing's own (|e - Z d|^2, :class:`SmoothedPoint`) is below STAGE_RESIDUAL mu.
STAGE_RESIDUAL = 1e-3


class PairUnion(NamedTuple):
    """The union ``U`` of two matrices and the coordinates in which it is a maximum.

    ``U = T diag(max(A_k, B_k)) T^T`` with ``A_k``, ``B_k`` the (diagonal) variances of the
    two matrices in the coordinates ``y = T_inv x``; ``a``, ``b`` are the two means in these
    coordinates and ``side`` (..., n) is +1 where ``B`` dominates, -1 where ``A`` does, 0
    at ties.
    """

    U: np.ndarray
    T: np.ndarray
    T_inv: np.ndarray
    a: np.ndarray
    b: np.ndarray
    side: np.ndarray
    scale: np.ndarray  # (..., n) standard deviation of U along each coordinate
    var_a: np.ndarray  # (..., n) variance of A along each coordinate
    var_b: np.ndarray  # (..., n) variance of B along each coordinate


def _outer_updated(P, x, u):
    """``M_i = P_i + (u - x_i)(u - x_i)^T`` for P (..., N, n, n), x (..., N, n), u (..., n)."""
    d = u[..., None, :] - x
    return symmetrize(P + d[..., :, None] * d[..., None, :])


def _difference(P, d1, d2):
    """``C = M_2 - M_1 = P_2 - P_1 + d_2 d_2^T - d_1 d_1^T`` for the offsets ``d_i = u - x_i``
    (rows of a batch): the matrix whose positive part the trace union adds to ``M_1``."""
    return symmetrize(P[:, 1] - P[:, 0] + d2[:, :, None] * d2[:, None, :]
                      - d1[:, :, None] * d1[:, None, :])


def trace_value(P, x, u):
    """``trace`` of the union of two estimates at the means ``u`` (rows of a batch), from the
    eigenvalues alone: ``trace(M_1) + sum_k max(c_k, 0)``, ``c`` the eigenvalues of
    ``M_2 - M_1`` (the trace of ``M_1 + (M_2 - M_1)_+``)."""
    d1, d2 = u - x[:, 0], u - x[:, 1]
    c = np.linalg.eigvalsh(_difference(P, d1, d2))
    return (np.trace(P[:, 0], axis1=-2, axis2=-1) + (d1 * d1).sum(-1)
            + np.maximum(c, 0.0).sum(-1))


def pair_union(A, B, xa, xb, kind):
    """The smallest upper bound of ``A`` and ``B`` (..., n, n) in ``kind`` (a :class:`PairUnion`).

    ``xa``, ``xb`` (..., n) are mapped to the union's coordinates (for the mean rule).
    """
    if kind == "det":
        P = np.stack([A, B], axis=-3)
        L = cholesky(P, "the covariances about the fused mean")
        est = Estimates(np.stack([xa, xb], axis=-2), P, L, False)
        w = whiten(est, factor=True)
        # T diag(max(1, d)) T^T = A + B - T diag(min(1, d)) T^T: at least (A + B)/2, so the
        # difference loses nothing (as EI's common covariance, docs/methods/ei.rst)
        U = symmetrize(w.S - gram(w.F))
        log_d = np.log(w.d)
        side = np.where(np.abs(log_d) <= TIE_TOL, 0, np.sign(log_d)).astype(int)
        scale = np.sqrt(np.maximum(w.d, 1.0))
        return PairUnion(U, w.T, w.T_inv, w.a, w.b, side, scale, np.ones_like(w.d), w.d)
    C = symmetrize(B - A)
    c, V = np.linalg.eigh(C)
    U = symmetrize(0.5 * (A + B) + (V * (0.5 * np.abs(c))[..., None, :]) @ V.swapaxes(-1, -2))
    size = np.maximum(np.abs(np.diagonal(A, axis1=-2, axis2=-1)).max(axis=-1),
                      np.abs(np.diagonal(B, axis1=-2, axis2=-1)).max(axis=-1))
    side = np.where(np.abs(c) <= TIE_TOL * size[..., None], 0, np.sign(c)).astype(int)
    V_t = V.swapaxes(-1, -2)
    a = np.einsum("...ij,...j->...i", V_t, xa)
    b = np.einsum("...ij,...j->...i", V_t, xb)
    scale = np.sqrt(np.maximum(np.einsum("...ki,...kl,...li->...i", V, U, V), 0.0))
    var_a = np.einsum("...ki,...kl,...li->...i", V, A, V)
    return PairUnion(U, V, V_t, a, b, side, scale, var_a, var_a + c)


def criterion_of(U, kind):
    """``trace(U)`` or ``log det U`` (..., ); IllConditionedError if ``U`` is not PD."""
    if kind == "trace":
        return np.trace(U, axis1=-2, axis2=-1)
    L = cholesky(U, "the covariance union")
    return 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)


def sequential_union(P, x, u, kind, order):
    """A common upper bound of all ``M_i`` (N >= 2): pairwise unions in ``order``.

    Each step's result bounds both of its arguments, so the last bounds every ``M_i``;
    for N = 2 it is the smallest, for N > 2 a bound that need not be the smallest.
    """
    M = _outer_updated(P, x, u)
    M = np.take_along_axis(M, order[..., :, None, None], axis=-3)
    U = M[..., 0, :, :]
    for i in range(1, M.shape[-3]):  # loop over the estimates, not over the batch
        U = pair_union(U, M[..., i, :, :], u, u, kind).U
    return U


def mean_candidates_value(P, x, candidates, kind, order):
    """Criterion of the union at each candidate mean (..., K, n) -> (..., K)."""
    K = candidates.shape[-2]
    if kind == "trace" and P.shape[-3] == 2:  # from the eigenvalues alone (trace_value)
        n = P.shape[-1]
        Pk = np.broadcast_to(P[..., None, :, :, :], P.shape[:-3] + (K, 2, n, n))
        xk = np.broadcast_to(x[..., None, :, :], x.shape[:-2] + (K, 2, n))
        return trace_value(Pk.reshape(-1, 2, n, n), xk.reshape(-1, 2, n),
                           candidates.reshape(-1, n)).reshape(candidates.shape[:-1])
    Pk = np.broadcast_to(P[..., None, :, :, :], P.shape[:-3] + (K,) + P.shape[-3:])
    xk = np.broadcast_to(x[..., None, :, :], x.shape[:-2] + (K,) + x.shape[-2:])
    ok = np.broadcast_to(order[..., None, :], order.shape[:-1] + (K, order.shape[-1]))
    return criterion_of(sequential_union(Pk, xk, candidates, kind, ok), kind)


def separable_start(P, x, kind):
    """A starting mean for two estimates: the per-direction optimum in the union's
    coordinates at equal means (exact when the means agree, and a good start otherwise).

    In each coordinate ``max(p_a + (y - a)^2, p_b + (y - b)^2)`` is smallest at the vertex of
    the dominating parabola, or where the two cross.
    """
    pair = pair_union(P[..., 0, :, :], P[..., 1, :, :], x[..., 0, :], x[..., 1, :], kind)
    a, b, pa, pb = pair.a, pair.b, pair.var_a, pair.var_b
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        cross = np.where(a != b, (pa - pb + a**2 - b**2) / (2.0 * (a - b)), a)
    y = np.where(pa >= pb + (a - b) ** 2, a, np.where(pb >= pa + (a - b) ** 2, b, cross))
    return np.einsum("...ij,...j->...i", pair.T, y)


def _mean_rule(pair, u):
    """The per-direction mean rule at ``u``: target mean and the stationarity residual.

    In the union's coordinates the target takes the coordinate of the dominating mean and,
    at ties, the current coordinate clipped to the interval between the two means. ``u`` is
    stationary exactly when it is its own target; the residual is measured in standard
    deviations of ``U`` (dimensionless).
    """
    y = np.einsum("...ij,...j->...i", pair.T_inv, u)
    low, high = np.minimum(pair.a, pair.b), np.maximum(pair.a, pair.b)
    target = np.where(pair.side > 0, pair.b,
                      np.where(pair.side < 0, pair.a, np.clip(y, low, high)))
    residual = np.abs(target - y) / pair.scale
    u_target = np.einsum("...ij,...j->...i", pair.T, target)
    return u_target, target, residual.max(axis=-1)


def trace_dual_bound(pair, P1, P2):
    """A certified lower bound of the smallest ``trace(U)`` over all means (two estimates).

    For any ``Z`` with ``0 <= Z <= I`` the Lagrange dual of the joint convex problem
    ``min trace U`` s.t. ``U >= M_i(u)`` (multipliers ``I - Z`` and ``Z``) is
    ``q(Z) = tr P_1 + tr(Z (P_2 - P_1)) + dx^T (Z - Z^2) dx``, ``dx = x_2 - x_1``
    (``docs/methods/union.rst``, "The trace criterion is convex"). With ``Z = V diag(s) V^T``
    in the union's eigenbasis ``V`` it is separable,
    ``q = sum_k (1 - s_k) p1_k + s_k p2_k + s_k (1 - s_k) beta_k^2``, and the best ``s_k`` in
    [0, 1] is closed form; at the optimum the bound is tight.
    """
    return _dual_bound(pair.T, pair.b - pair.a, P1, P2)


def _dual_bound(V, beta, P1, P2):
    """:func:`trace_dual_bound` for the eigenbasis ``V`` of ``M_2 - M_1`` and ``beta = V^T dx``."""
    p1 = np.einsum("...ki,...kl,...li->...i", V, P1, V)
    p2 = np.einsum("...ki,...kl,...li->...i", V, P2, V)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s = np.where(beta != 0, (p2 - p1 + beta**2) / (2.0 * beta**2),
                     np.where(p2 > p1, 1.0, 0.0))
    s = np.clip(s, 0.0, 1.0)
    return ((1.0 - s) * p1 + s * p2 + s * (1.0 - s) * beta**2).sum(axis=-1)


def trace_certificate(P, x, u):
    """The trace criterion at the means ``u`` (rows of a batch) and its certified lower bound
    (:func:`trace_dual_bound`), from one eigen-decomposition of ``C = M_2 - M_1``, which is
    also returned, ``(value, lower, (c, V))``, for :func:`trace_newton_steps` at ``u``."""
    d1, d2 = u - x[:, 0], u - x[:, 1]
    c, V = np.linalg.eigh(_difference(P, d1, d2))
    value = (np.trace(P[:, 0], axis1=-2, axis2=-1) + (d1 * d1).sum(-1)
             + np.maximum(c, 0.0).sum(-1))
    beta = np.einsum("rij,ri->rj", V, x[:, 1] - x[:, 0])
    return value, _dual_bound(V, beta, P[:, 0], P[:, 1]), (c, V)


def _step_candidates(P, x, u, step):
    """Step lengths to try first along ``u + t step``: 1 and the kinks in (0, 1].

    Along the line ``B - A`` is affine in ``t`` (the quadratic terms cancel), ``C(t) = C_0 +
    t C_1`` with ``C_1 = -(step dx^T + dx step^T)`` of rank two (``dx = x_2 - x_1``), so the
    criterion has at most two kinks on the line: where ``C(t)`` is singular,
    ``t = -1/lambda`` for the eigenvalues ``lambda`` of the 2 x 2 matrix ``J W^T C_0^-1 W``
    (``W = [step, dx]``, ``J = -[[0, 1], [1, 0]]``). Optima sit on kinks; trying them
    lands on the kink exactly instead of approaching it by halving.
    """
    C0 = _difference(P, u - x[:, 0], u - x[:, 1])
    W = np.stack([step, x[:, 1] - x[:, 0]], axis=-1)
    kinks = np.full((u.shape[0], 2), 1.0)
    try:
        G = W.swapaxes(-1, -2) @ np.linalg.solve(C0, W)
        lam = np.linalg.eigvals(-G[:, ::-1, :])  # J G with J = -[[0, 1], [1, 0]]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where((np.abs(lam.imag) <= 1e-12 * np.abs(lam)) & (lam.real != 0),
                         -1.0 / lam.real, 1.0)
        kinks = np.where((t > 0) & (t <= 1), t, 1.0)
    except np.linalg.LinAlgError:  # a singular C_0 (u on a kink already): halvings only
        pass
    return np.concatenate([np.ones((u.shape[0], 1)), kinks], axis=-1)


def trace_newton_steps(P, x, u, eigen=None, smooth=True):
    """Two Newton steps for the trace criterion of two estimates (rows of a batch).

    ``g(u) = const + (|u - x_1|^2 + |u - x_2|^2)/2 + ||C(u)||_* / 2`` with
    ``C(u) = M_2 - M_1``, whose derivative is ``-(delta dx^T + dx delta^T)``: the gradient
    and the Hessian of the nuclear norm follow from first- and second-order eigenvalue
    perturbation (``docs/methods/union.rst``, "Newton steps"). Returns the smooth Newton
    step (valid away from kinks) and the Newton step of the KKT system that keeps the
    smallest eigenvalue ``c_k`` at zero (the optimum on a kink, with multiplier ``lambda``
    in [-1/2, 1/2]); both are candidates, accepted only if they decrease ``g``. ``eigen``:
    the eigen-decomposition ``(c, V)`` of ``C(u)`` when the caller has it
    (:func:`trace_certificate`); ``smooth=False`` skips the smooth step (returned as None).
    """
    n = u.shape[-1]
    c, V = np.linalg.eigh(_difference(P, u - x[:, 0], u - x[:, 1])) if eigen is None else eigen
    beta = np.einsum("rij,ri->rj", V, x[:, 1] - x[:, 0])
    sign = np.sign(c)
    half = 0.5 * sign
    k = np.argmin(np.abs(c), axis=-1)
    is_k = np.arange(n) == k[:, None]
    # g_jl = -(beta_l v_j + beta_j v_l), (rows, j, l, n)
    G = -(beta[:, None, :, None] * V.swapaxes(-1, -2)[:, :, None, :]
          + beta[:, :, None, None] * V.swapaxes(-1, -2)[:, None, :, :])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        pair = (half[:, :, None] - half[:, None, :]) / (c[:, :, None] - c[:, None, :])
    off = ~np.eye(n, dtype=bool)
    pair = np.where(off & np.isfinite(pair), pair, 0.0)
    grad_smooth = 2.0 * u - x[:, 0] - x[:, 1]
    eye = np.broadcast_to(np.eye(n), (u.shape[0], n, n))
    newton = None
    if smooth:  # all eigenvalues with their signs (sum over pairs j < l, both orders / 2)
        H = 2.0 * eye + np.einsum("rjl,rjla,rjlb->rab", pair, G, G)
        grad = grad_smooth - np.einsum("rj,rj,rij->ri", sign, beta, V)
        newton = -_solve(H, grad)
    # KKT on the kink c_k = 0: c_k's own term replaced by lambda c_k
    a = -2.0 * np.take_along_axis(beta, k[:, None], 1) * np.take_along_axis(
        V, k[:, None, None], 2)[..., 0]
    grad_s = grad_smooth - np.einsum("rj,rj,rij->ri", np.where(is_k, 0.0, sign), beta, V)
    lam = np.clip(-np.einsum("ri,ri->r", a, grad_s)
                  / np.maximum(np.einsum("ri,ri->r", a, a), 1e-300), -0.5, 0.5)
    c_k = np.take_along_axis(c, k[:, None], 1)[:, 0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        to_k = (np.where(is_k, 0.0, half) - lam[:, None]) / (c - c_k[:, None])
    to_k = np.where(is_k | ~np.isfinite(to_k), 0.0, to_k)
    rest = np.where(is_k[:, :, None] | is_k[:, None, :], 0.0, pair)
    G_k = np.take_along_axis(G, k[:, None, None, None], 2)[:, :, 0, :]  # g_jk (rows, j, n)
    H_k = (2.0 * eye + np.einsum("rjl,rjla,rjlb->rab", rest, G, G)
           + 2.0 * np.einsum("rj,rja,rjb->rab", to_k, G_k, G_k))
    K = np.zeros((u.shape[0], n + 1, n + 1))
    K[:, :n, :n], K[:, :n, n], K[:, n, :n] = H_k, a, a
    rhs = -np.concatenate([grad_s + lam[:, None] * a, c_k[:, None]], axis=-1)
    kink = _solve(K, rhs)[:, :n]
    return newton, kink


def _det_pieces(P, x, u):
    """``(p0, Q, log_d)`` with ``grad log det U = p0 + sum_k sign(log d_k) Q_k`` for two
    estimates (rows): in the union's coordinates (``M_1 = T T^T``, ``M_2 = T diag(d) T^T``,
    ``w_k`` the columns of ``T^-T``, ``e_a = y - a``, ``e_b = y - b``)
    ``p0 = sum_k w_k (e_a,k + e_b,k / d_k)`` and ``Q_k = w_k (e_b,k / d_k - e_a,k)``
    (``grad log d_k = 2 Q_k``); ``log det U = (log det M_1 + log det M_2 + sum |log d_k|)/2``.
    """
    M = _outer_updated(P, x, u)
    L = cholesky(M, "the covariances about the fused mean")
    w = whiten(Estimates(x, M, L, False), factor=False)
    y = np.einsum("...ij,...j->...i", w.T_inv, u)
    e_a, e_b = y - w.a, y - w.b
    W = w.T_inv.swapaxes(-1, -2)  # columns w_k
    Q = W * (e_b / w.d - e_a)[..., None, :]  # (..., n, k): column k is Q_k
    p0 = np.einsum("...ik,...k->...i", W, e_a + e_b / w.d)
    return p0, Q, np.log(w.d)


def det_newton_steps(P, x, u):
    """The Newton steps of :func:`trace_newton_steps` for ``log det U`` (rows of a batch).

    The gradient pieces of :func:`_det_pieces` are exact; their Jacobians are taken by
    central differences (the pieces are smooth where the ``d_k`` are distinct), which is
    accurate enough for a step that is accepted only if it decreases the criterion.
    """
    n = u.shape[-1]
    p0, Q, log_d = _det_pieces(P, x, u)
    scale = np.sqrt(np.maximum(np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(axis=(-2, -1)),
                               np.finfo(float).tiny))
    h = 1e-6 * scale
    J0 = np.empty(u.shape + (n,))
    JQ = np.empty(Q.shape + (n,))
    for m in range(n):  # loop over the n coordinates, not over the batch
        step = np.zeros_like(u)
        step[:, m] = h
        p_plus, Q_plus, _ = _det_pieces(P, x, u + step)
        p_minus, Q_minus, _ = _det_pieces(P, x, u - step)
        J0[..., m] = (p_plus - p_minus) / (2 * h[:, None])
        # the pieces are sign-invariant in w_k, and the order of the d_k is kept for small h
        JQ[..., m] = (Q_plus - Q_minus) / (2 * h[:, None, None])
    sign = np.sign(log_d)
    grad = p0 + np.einsum("rik,rk->ri", Q, sign)
    H = J0 + np.einsum("rikm,rk->rim", JQ, sign)
    newton = -_solve(symmetrize(H), grad)
    k = np.argmin(np.abs(log_d), axis=-1)
    is_k = np.arange(n) == k[:, None]
    a = 2.0 * np.take_along_axis(Q, k[:, None, None], 2)[..., 0]  # grad log d_k
    sign_s = np.where(is_k, 0.0, sign)
    grad_s = p0 + np.einsum("rik,rk->ri", Q, sign_s)
    lam = np.clip(-np.einsum("ri,ri->r", a, grad_s)
                  / np.maximum(np.einsum("ri,ri->r", a, a), 1e-300), -0.5, 0.5)
    sigma = np.where(is_k, 2.0 * lam[:, None], sign)
    H_k = symmetrize(J0 + np.einsum("rikm,rk->rim", JQ, sigma))
    K = np.zeros((u.shape[0], n + 1, n + 1))
    K[:, :n, :n], K[:, :n, n], K[:, n, :n] = H_k, a, a
    log_dk = np.take_along_axis(log_d, k[:, None], 1)[:, 0]
    rhs = -np.concatenate([grad_s + lam[:, None] * a, log_dk[:, None]], axis=-1)
    return newton, _solve(K, rhs)[:, :n]


def _solve(M, b, columns=False):
    """Solve ``M x = b`` for a stack (``b`` (..., n), or (..., n, k) with ``columns``: one
    factorisation for the k right-hand sides); a stack with a singular member is solved by
    least squares (pseudo-inverse) instead, so that one degenerate problem (equal eigenvalues
    of opposite sign at zero) gives a finite step for every problem rather than an error."""
    with np.errstate(all="ignore"):
        M = np.where(np.isfinite(M), M, 0.0)
        b = np.where(np.isfinite(b), b, 0.0)
        B = b if columns else b[..., None]
        try:
            X = np.linalg.solve(M, B)
        except np.linalg.LinAlgError:
            X = np.einsum("...ij,...jk->...ik", np.linalg.pinv(M), B)
        return X if columns else X[..., 0]


def _smoothed_from_eigen(e, c, mu):
    """``|e|^2 + sum_k mu log(1 + exp(c_k / mu))``: ``trace(U) - trace(P_1)`` smoothed, from
    the eigenvalues ``c`` of ``C = M_2 - M_1`` at ``u = x_1 + e`` (rows of a batch)."""
    return (e * e).sum(-1) + (mu[:, None] * np.logaddexp(0.0, c / mu[:, None])).sum(-1)


class SmoothedPoint(NamedTuple):
    """What one eigen-decomposition of ``C`` at ``e`` gives the smoothed continuation."""

    lower: np.ndarray  # certified lower bound of the smallest trace(U) (dual, Z = sigmoid)
    value: np.ndarray  # trace(U) at e
    smoothed: np.ndarray  # the smoothed criterion (without trace(P_1))
    step: np.ndarray  # its Newton step
    residual: np.ndarray  # |e - Z d|^2 = |g|^2 / 4: the duality gap beyond the smoothing's
    tangent: np.ndarray  # d e / d mu along the path of smoothed minimisers (predictor)


def smoothed_point(trace_1, e, c, V, d, mu):
    """The bound, the values and the Newton step of the smoothed trace criterion at ``e``
    from ``C = V diag(c) V^T`` (rows of a batch; ``trace_1 = trace(P_1)``, ``d = x_2 - x_1``).

    In the eigenbasis, with ``s = sigmoid(c / mu)``, ``beta = V^T d`` and ``gamma = V^T e``:

    * dual bound at ``Z = V diag(s) V^T`` (feasible, ``0 < Z < I``; :func:`trace_dual_bound`):
      ``q = tr P_1 + sum_k s_k (c_k + 2 gamma_k beta_k - s_k beta_k^2)``, because
      ``V^T (P_2 - P_1) V`` has the diagonal ``c_k - beta_k^2 + 2 gamma_k beta_k``
      (``C = P_2 - P_1 + d d^T - e d^T - d e^T``). The gap to the value is
      ``sum_k (max(c_k, 0) - s_k c_k) + |gamma - s beta|^2``: the smoothing's part, at most
      ``0.28 mu`` per eigenvalue, and the ``residual`` ``|e - Z d|^2 = |g|^2 / 4``, which
      vanishes at the smoothed minimiser;
    * gradient ``g = 2 gamma - 2 s beta`` and Hessian ``H = 2 I + 2 (diag(Gamma beta^2) +
      diag(beta) Gamma diag(beta))`` with the divided differences ``Gamma_jk = (s_j - s_k) /
      (c_j - c_k)`` of the sigmoid (Daleckii-Krein; ``docs/methods/union.rst``);
    * the tangent of the path of smoothed minimisers, ``de/dmu = -H^-1 dg/dmu`` with
      ``dg/dmu = 2 beta s (1 - s) c / mu^2`` (exact at a smoothed minimiser; the predictor
      of the next stage).
    """
    n = c.shape[-1]
    m = mu[:, None]
    s = expit(c / m)
    beta = np.einsum("rij,ri->rj", V, d)
    gamma = np.einsum("rij,ri->rj", V, e)
    lower = trace_1 + (s * (c + 2.0 * gamma * beta - s * beta**2)).sum(-1)
    squared = (e * e).sum(-1)
    value = trace_1 + squared + np.maximum(c, 0.0).sum(-1)
    smoothed = squared + (m * np.logaddexp(0.0, c / m)).sum(-1)
    slope = s * (1.0 - s) / m
    gaps = c[:, :, None] - c[:, None, :]
    near = np.abs(gaps) <= 1e-12 * (np.abs(c).max(axis=-1) + mu)[:, None, None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        Gamma = np.where(near, 0.5 * (slope[:, :, None] + slope[:, None, :]),
                         (s[:, :, None] - s[:, None, :]) / gaps)
        grad_mu = 2.0 * beta * slope * c / m
    grad = 2.0 * gamma - 2.0 * s * beta
    eye = np.eye(n)
    H = 2.0 * (eye + np.einsum("rjk,rk->rj", Gamma, beta**2)[:, :, None] * eye
               + beta[:, :, None] * Gamma * beta[:, None, :])
    # both right-hand sides with one factorisation of H, in the eigenbasis of C
    solved = -_solve(H, np.stack([grad, grad_mu], axis=-1), columns=True)
    step, tangent = np.einsum("rij,rjs->sri", V, solved)
    residual = ((gamma - s * beta) ** 2).sum(-1)
    return SmoothedPoint(lower, value, smoothed, step, residual, tangent)


def smoothed_dual_bound(P, x, e, mu):
    """The certified lower bound of :func:`smoothed_point` at ``u = x_1 + e`` (rows)."""
    d = x[:, 1] - x[:, 0]
    c, V = np.linalg.eigh(_difference(P, e, e - d))
    return smoothed_point(np.trace(P[:, 0], axis1=-2, axis2=-1), e, c, V, d, mu).lower


def _first_decrease(value_at, rows, start, step, base, tiers, strict=True):
    """Per row, the first ``t`` of ``tiers`` (a sequence of arrays, in order) at which
    ``value_at(rows, start + t step)`` is below ``base`` (or equal, unless ``strict``); 0
    where none is.

    Each tier is one batched evaluation of the rows still searching, so a backtracking
    line search costs a few calls instead of one per halving; the result is that of trying
    the step lengths one at a time.
    """
    t = np.zeros(len(start))
    pending = np.arange(len(start))
    for tier in tiers:
        if pending.size == 0:
            break
        k = tier.size
        trial = start[pending, None, :] + tier[None, :, None] * step[pending, None, :]
        value = value_at(np.repeat(rows[pending], k), trial.reshape(-1, start.shape[-1]))
        value = np.where(np.isfinite(value), value, np.inf).reshape(-1, k)
        good = value < base[pending, None] if strict else value <= base[pending, None]
        found = good.any(axis=-1)
        t[pending[found]] = tier[np.argmax(good[found], axis=-1)]
        pending = pending[~found]
    return t


# Step lengths of the backtracking line searches after a failed full step, in the tiers in
# which they are tried: seven halvings, then the rest (a stalled row needs all of them).
HALVINGS = (0.5 ** np.arange(1, 8), 0.5 ** np.arange(8, 41))


def smoothed_trace_mean(P, x, u, value, tol=GAP_TOL, newton_steps=10):
    """Continue the trace problem of two estimates on a smoothed criterion (rows of a batch).

    ``trace((M_2 - M_1)_+)`` is replaced by ``sum_k mu log(1 + exp(c_k / mu))`` (smooth and
    convex), minimised by damped Newton steps while ``mu`` decreases through
    :data:`SMOOTHING_STAGES` times ``value``. At every Newton step the sigmoid of the
    eigenvalues gives a feasible dual point and so a certified lower bound; a row stops when
    it is certified to ``tol``, and leaves a stage when the gap beyond the smoothing's own,
    ``|e - Z d|^2``, is below :data:`STAGE_RESIDUAL` ``mu`` (the stage's gap is then within
    ``(0.28 n + STAGE_RESIDUAL) mu``), after ``newton_steps`` steps, or when no step
    decreases the smoothed criterion. From the second stage on, each row first follows the
    tangent of the path of smoothed minimisers to the new ``mu`` (a predictor, kept where it
    decreases the new criterion), so that a stage typically needs one or two Newton steps.
    Converges fast where the optimum sits on several kinks at once. One eigen-decomposition
    per step serves the certificate, the Newton step and the test of the full step
    (:func:`smoothed_point`). From the stage :data:`POLISH_BELOW` on, the rows not yet
    certified also try the Newton steps of the kink's KKT system (:func:`_polish`), which
    certify an optimum on one kink stages earlier; polishing stops for the batch at the
    first stage where it certifies no row. Returns ``(u, lower, steps)``: the means, the best lower
    bounds and the Newton steps per row.
    """
    e = u - x[:, 0]
    d = x[:, 1] - x[:, 0]
    trace_1 = np.trace(P[:, 0], axis1=-2, axis2=-1)
    # C(e) = M_2 - M_1 = C_0 - (e d^T + d e^T) is affine in e (the quadratic terms cancel)
    C_0 = symmetrize(P[:, 1] - P[:, 0] + d[:, :, None] * d[:, None, :])

    def difference(rows, e_rows):
        return C_0[rows] - (e_rows[:, :, None] * d[rows, None, :]
                            + d[rows, :, None] * e_rows[:, None, :])

    def move_where_lower(rows, trial, base, mu):
        """Move ``rows`` to ``trial`` where it is finite and the smoothed criterion there is
        at most ``base``, with the eigen-decompositions of ``C`` there; the mask moved."""
        finite = np.isfinite(trial).all(-1)
        trial = np.where(finite[:, None], trial, e[rows])
        c_trial, V_trial = np.linalg.eigh(difference(rows, trial))
        moved = finite & (_smoothed_from_eigen(trial, c_trial, mu) <= base)
        take = rows[moved]
        e[take], c[take], V[take] = trial[moved], c_trial[moved], V_trial[moved]
        return moved

    lower = np.full(len(e), -np.inf)
    steps = np.zeros(len(e), dtype=int)
    active = np.ones(len(e), dtype=bool)  # rows not yet certified
    c, V = np.linalg.eigh(difference(np.arange(len(e)), e))  # at every row's current mean
    tangent = np.zeros_like(e)  # de/dmu at each row's last point, and the mu it was taken at
    mu_last = np.zeros(len(e))
    polishing = True  # until a polish certifies no row
    for relative in SMOOTHING_STAGES:
        mu_all = relative * np.abs(value)
        stage = np.flatnonzero(active)  # rows still taking Newton steps on this stage
        if stage.size and relative < SMOOTHING_STAGES[0]:
            # predictor: follow the tangent to the new mu; kept where it decreases the new
            # smoothed criterion (the Newton steps below correct it)
            mu = mu_all[stage]
            move_where_lower(stage, e[stage] + (mu - mu_last[stage])[:, None] * tangent[stage],
                             _smoothed_from_eigen(e[stage], c[stage], mu), mu)
        for newton in range(newton_steps + 1):  # the last pass only certifies
            if stage.size == 0:
                break
            mu = mu_all[stage]
            now = smoothed_point(trace_1[stage], e[stage], c[stage], V[stage], d[stage], mu)
            tangent[stage], mu_last[stage] = now.tangent, mu
            lower[stage] = np.maximum(lower[stage], now.lower)
            certified = now.value - lower[stage] <= tol * now.value
            active[stage[certified]] = False
            keep = (~certified & (now.residual > STAGE_RESIDUAL * mu)
                    & np.isfinite(now.step).all(-1) & (newton < newton_steps))
            stage, step, base = stage[keep], now.step[keep], now.smoothed[keep]
            if stage.size == 0:
                break
            moved = move_where_lower(stage, e[stage] + step, base, mu_all[stage])
            rest = np.flatnonzero(~moved)  # the full step increases the criterion: backtrack
            if rest.size:
                t = _first_decrease(
                    lambda r, e_r, mu_all=mu_all: _smoothed_from_eigen(
                        e_r, np.linalg.eigvalsh(difference(r, e_r)), mu_all[r]),
                    stage[rest], e[stage[rest]], step[rest], base[rest], HALVINGS,
                    strict=False)
                shorter = rest[t > 0]
                rows = stage[shorter]
                e[rows] += t[t > 0, None] * step[shorter]
                c[rows], V[rows] = np.linalg.eigh(difference(rows, e[rows]))
                moved[shorter] = True
            steps[stage] += 1
            stage = stage[moved]  # a row whose step decreases nothing has stalled here
        if relative <= POLISH_BELOW and polishing:
            polishing = _polish(P, x, e, (c, V), lower, steps, active, tol)
        if not active.any():
            break
    return x[:, 0] + e, lower, steps


def _polish(P, x, e, eigen, lower, steps, active, tol):
    """Up to :data:`POLISH_STEPS` Newton steps of the kink's KKT system
    (:func:`trace_newton_steps`) from the smoothed minimisers ``x_1 + e`` of the active rows
    (:func:`smoothed_trace_mean`'s state, updated in place; ``eigen`` the eigen-decompositions
    ``(c, V)`` of ``C`` there, rows of the batch): a row moves to a step's end only
    where the dual bound there certifies it to ``tol`` (and is then no longer active); every
    bound found is kept in ``lower`` (a lower bound wherever it is taken). The other rows
    keep their smoothed minimisers and continue on the next stage. Returns whether a row
    was certified (the caller stops polishing once none is: where the optimum sits on
    several kinks, the single kink's KKT system does not model it)."""
    rows = np.flatnonzero(active)
    certified_rows = 0
    u = x[rows, 0] + e[rows]
    eigen = eigen[0][rows], eigen[1][rows]
    for _ in range(POLISH_STEPS):
        if rows.size == 0:
            break
        trial = u + trace_newton_steps(P[rows], x[rows], u, eigen, smooth=False)[1]
        finite = np.isfinite(trial).all(-1)
        trial[~finite] = u[~finite]
        value, bound, (c, V) = trace_certificate(P[rows], x[rows], trial)
        # (np.fmax: a NaN bound, of a degenerate row, is no bound)
        lower[rows] = np.fmax(lower[rows], bound)
        certified = finite & (value - lower[rows] <= tol * value)
        done = rows[certified]
        e[done] = trial[certified] - x[done, 0]
        active[done] = False
        steps[rows] += 1
        certified_rows += done.size
        rows, u, eigen = rows[~certified], trial[~certified], (c[~certified], V[~certified])
    return certified_rows > 0


def optimal_pair_mean(P, x, kind, start, *, tol=GAP_TOL, residual_tol=RESIDUAL_TOL,
                      max_iter=100):
    """The mean minimising the criterion of the union of two estimates, batched.

    Iterates ``u <- u + t (Phi(u) - u)`` with ``Phi`` the per-direction mean rule
    (:func:`_mean_rule`) and the best step ``t`` among the candidates, and the Newton steps
    of :func:`trace_newton_steps` or :func:`det_newton_steps` where they decrease more.
    Returns
    ``(u, pair, value, iterations, converged, gap, smoothed)``; ``gap`` is the certified
    relative gap of the trace criterion (NaN for ``"det"``, whose joint problem is not
    convex; there ``converged`` means stationary: residual of the mean rule at most
    ``residual_tol`` standard deviations of ``U``); ``smoothed`` marks the trace problems
    finished by :func:`smoothed_trace_mean` (those not certified after
    :data:`SMOOTHING_AFTER` iterations, or whose gap shrank less than
    ``1 / SLOW_PROGRESS``-fold in one). Candidate steps: halvings and the kinks of the line
    (:func:`_step_candidates`); a problem stops when no candidate decreases the criterion.
    """
    batch = x.shape[:-2]
    flat_P = P.reshape((-1,) + P.shape[-3:])
    flat_x = x.reshape((-1,) + x.shape[-2:])
    u = start.reshape((-1, x.shape[-1])).copy()
    size = u.shape[0]
    iterations = np.zeros(size, dtype=int)
    done = np.zeros(size, dtype=bool)
    converged = np.zeros(size, dtype=bool)
    gap = np.full(size, np.nan)

    def evaluate(u_rows, rows):
        M = _outer_updated(flat_P[rows], flat_x[rows], u_rows)
        pair = pair_union(M[:, 0], M[:, 1], flat_x[rows, 0], flat_x[rows, 1], kind)
        return pair, criterion_of(pair.U, kind)

    def value_at(rows, u_rows):  # the criterion alone, for comparing trial means
        if kind == "trace":
            return trace_value(flat_P[rows], flat_x[rows], u_rows)
        return evaluate(u_rows, rows)[1]

    everything = np.arange(size)
    # trace problems the iteration has not certified by SMOOTHING_AFTER continue on the
    # smoothed criterion below (the iteration is linear where several kinks meet)
    for _ in range(max_iter if kind == "det" else min(max_iter, SMOOTHING_AFTER)):
        rows = np.flatnonzero(~done)
        if rows.size == 0:
            break
        pair, value_rows = evaluate(u[rows], rows)
        u_target, _, residual = _mean_rule(pair, u[rows])
        if kind == "trace":
            lower = trace_dual_bound(pair, flat_P[rows, 0], flat_P[rows, 1])
            g = np.maximum(value_rows - lower, 0.0) / value_rows
            ok = g <= tol
            # a gap that shrank less than 1/SLOW_PROGRESS-fold in this iteration: the
            # iteration is linear here (several kinks, or nearly equal eigenvalues, at the
            # optimum); such rows continue on the smoothed criterion below
            slow = ~ok & (g > SLOW_PROGRESS * gap[rows])
            gap[rows] = g
            done[rows[slow]] = True
            ok_or_slow = ok | slow
        else:
            ok = ok_or_slow = residual <= residual_tol
        converged[rows[ok]] = True
        done[rows[ok]] = True
        moving = rows[~ok_or_slow]
        if moving.size == 0:
            break
        step = (u_target - u[rows])[~ok_or_slow]
        current = u[moving]
        # trial means are compared by value_at, the current one too (the same rounding)
        base = value_at(moving, current) if kind == "trace" else value_rows[~ok_or_slow]
        # the full step and the kinks of the line first; halvings only where they fail
        ts = _step_candidates(flat_P[moving], flat_x[moving], current, step)
        K = ts.shape[-1]
        candidate = current[:, None, :] + ts[..., None] * step[:, None, :]
        trial_value = value_at(np.repeat(moving, K), candidate.reshape(-1, candidate.shape[-1]))
        trial_value = np.where(np.isfinite(trial_value), trial_value, np.inf).reshape(-1, K)
        pick = np.argmin(trial_value, axis=-1)
        best_value = np.take_along_axis(trial_value, pick[:, None], axis=-1)[:, 0]
        accepted = best_value < base
        chosen = np.take_along_axis(candidate, pick[:, None, None], axis=1)[:, 0]
        u[moving[accepted]] = chosen[accepted]
        # Newton steps: quadratic convergence near the optimum
        steps = trace_newton_steps if kind == "trace" else det_newton_steps
        newton, kink = steps(flat_P[moving], flat_x[moving], current)
        candidate = np.stack([current + newton, current + kink], axis=1)
        candidate = np.where(np.isfinite(candidate), candidate, current[:, None, :])
        trial_value = value_at(np.repeat(moving, 2), candidate.reshape(-1, candidate.shape[-1]))
        trial_value = np.where(np.isfinite(trial_value), trial_value, np.inf)
        trial_value = trial_value.reshape(-1, 2)
        pick = np.argmin(trial_value, axis=-1)
        newton_value = np.take_along_axis(trial_value, pick[:, None], axis=-1)[:, 0]
        better = newton_value < np.where(accepted, best_value, base)
        chosen = np.take_along_axis(candidate, pick[:, None, None], axis=1)[:, 0]
        u[moving[better]] = chosen[better]
        accepted |= better
        rest = np.flatnonzero(~accepted)  # halvings of the rule's step where nothing decreased
        t = _first_decrease(value_at, moving[rest], current[rest], step[rest], base[rest],
                            HALVINGS)
        found = rest[t > 0]
        u[moving[found]] = current[found] + t[t > 0, None] * step[found]
        accepted[found] = True
        iterations[moving] += 1
        done[moving[~accepted]] = True  # no decrease left above rounding: stalled
    pair, value = evaluate(u, everything)
    _, _, residual = _mean_rule(pair, u)
    smoothed_rows = np.zeros(size, dtype=bool)
    if kind == "trace":
        lower = trace_dual_bound(pair, flat_P[:, 0], flat_P[:, 1])
        rows = np.flatnonzero(value - lower > tol * value)
        if rows.size and max_iter > SMOOTHING_AFTER:
            smoothed, smoothed_lower, steps = smoothed_trace_mean(
                flat_P[rows], flat_x[rows], u[rows], value[rows], tol)
            _, smoothed_value = evaluate(smoothed, rows)
            better = np.isfinite(smoothed_value) & (smoothed_value <= value[rows])
            u[rows[better]] = smoothed[better]
            iterations[rows] += steps  # the continuation's Newton steps
            smoothed_rows[rows] = True
            lower[rows] = np.maximum(lower[rows], smoothed_lower)  # both are valid bounds
            pair, value = evaluate(u, everything)
            lower = np.maximum(lower, trace_dual_bound(pair, flat_P[:, 0], flat_P[:, 1]))
        gap = np.maximum(value - lower, 0.0) / value
        converged = gap <= tol
    else:
        converged = residual <= residual_tol
    u, value, iterations, converged, gap, smoothed_rows = [
        a.reshape(batch + a.shape[1:])
        for a in (u, value, iterations, converged, gap, smoothed_rows)]
    pair = PairUnion(*[a.reshape(batch + a.shape[1:]) for a in pair])
    return u, pair, value, iterations, converged, gap, smoothed_rows


def check_union(U, name="the covariance union"):
    """Raise IllConditionedError unless every ``U`` is finite and positive definite."""
    if not positive_definite(U):
        raise ill_conditioned(name, np.inf, "is not numerically positive definite")
