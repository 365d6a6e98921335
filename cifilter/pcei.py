"""Probabilistically conservative Ellipsoidal Intersection (Naveen & Taylor).

PC-EI enlarges EI's common covariance until the independent parts of the two inputs
pass a chi-square test of having the same mean:

    C_c = C_EI + S S^T                                                 (eq. (18))
    minimise det C_c  subject to  psi(C_c) <= gamma = chi2.ppf(1 - alpha, n)   (eqs. (17), (19))

Eq. (19) minimises ``|S|``, which is degenerate for n > 1 (a rank-deficient ``S`` has
``|S| = 0``, and the optimal ``S S^T`` is often rank-deficient); the determinant of the
resulting common covariance is minimised instead.

The reduction used here (argued in detail on the documentation page):

1. In the whitened coordinates of eq. (12) (``Pa = I``, ``Pb = diag(d)``) the problem has
   the same solution mapped by ``T``: determinant ratios and ``psi`` are invariant.
2. With the common information ``J = C_c^-1`` as variable, ``C_c = C_EI + S S^T`` for some
   ``S`` if and only if ``0 < J <= J_EI``, and ``det C_c = 1 / det J``. Writing
   ``J = J_EI - N`` the problem is

       minimise  -log det(J_EI - N)   over  0 <= N < J_EI,  psi(N) <= gamma,

   a convex objective over a convex cone; only the constraint ``psi <= gamma`` is not
   convex everywhere. It is solved for all problems of a batch at once by a log-barrier
   interior-point method with exact gradients and Hessians (Newton steps on the
   n(n+1)/2 entries of ``N``), from several starting points, and the KKT conditions are
   reported.
3. Closed forms: if EI already satisfies the constraint the result is EI exactly; if
   the covariances are equal in every direction, ``N = e e^T / (2 gamma)`` (``e`` the
   whitened mean difference) is optimal; with Sijs & Lazar's mean the same holds on the
   tied directions for any tie pattern (resting on an inequality verified numerically,
   not proved), so the default rule never iterates.
"""

import numpy as np
from scipy import stats

from ._linalg import symmetrize
from ._validation import as_estimates, check_int, check_scalar, restore_style
from .ei import (
    DEFAULT_EPS,
    _as_pair,
    _check_options,
    _check_two,
    _gram,
    _inverse_root,
    _solve,
    as_full,
    check_result,
    covariance_regularised_base,
    decompose,
    ei_in_whitened,
    fuse_full,
    mean_ratio,
    mutual_mean_weights,
    ties,
    to_original,
    whiten,
)
from .result import FusionResult

__all__ = ["pc_ellipsoidal_intersection"]

_STEP_GRID = np.array([0.01, 0.03, 0.1, 0.2, 0.3, 0.45, 0.6, 0.75, 0.85, 0.92, 0.96, 0.98,
                       0.99, 0.995, 0.999, 1 - 1e-4, 1 - 1e-5, 1 - 1e-6, 1 - 1e-8])
_MU = 100.0  # barrier parameter growth per centring
# Newton decrement^2 / 2 that counts as centred; the objective is then within about
# _CENTRE_TOL / t of the centre, far below the gap (n + 1) / t.
_CENTRE_TOL = 1e-4
_AGREE_TOL = 1e-7  # starts whose objective is within this of the best "agree"
_KKT_TOL = 1e-3  # relative KKT residual below which a finished solve counts as converged


# --------------------------------------------------------------------------- symmetric basis
class _SymmetricBasis:
    """An orthonormal basis ``E_p`` of symmetric n x n matrices (``<E_p, E_r> = delta``).

    ``E_p = s_p (e_i e_j^T + e_j e_i^T)`` for ``p = (i, j)``, ``i >= j``, with
    ``s_p = 1/2`` on the diagonal and ``1/sqrt(2)`` off it. Coordinates are
    ``<G, E_p>``; every operation below is vectorised over leading batch axes.
    """

    def __init__(self, n):
        self.n = n
        self.i, self.j = np.tril_indices(n)
        self.q = self.i.size
        self.s = np.where(self.i == self.j, 0.5, np.sqrt(0.5))
        self.rows = np.arange(self.q)

    def coords(self, G):
        return 2.0 * self.s * G[..., self.i, self.j]

    def matrix(self, v):
        M = np.zeros(v.shape[:-1] + (self.n, self.n))
        M[..., self.i, self.j] = v * self.s
        M[..., self.j, self.i] += v * self.s
        return M

    def apply(self, v):
        """``E_p v`` for every p: (..., q, n)."""
        out = np.zeros(v.shape[:-1] + (self.q, self.n))
        out[..., self.rows, self.i] += self.s * v[..., self.j]
        out[..., self.rows, self.j] += self.s * v[..., self.i]
        return out

    def kron(self, W):
        """``<W E_p W, E_r>`` (the Hessian of -log det), (..., q, q)."""
        i, j = self.i[:, None], self.j[:, None]
        k, l = self.i[None, :], self.j[None, :]
        scale = 2.0 * self.s[:, None] * self.s[None, :]
        return scale * (W[..., k, i] * W[..., j, l] + W[..., k, j] * W[..., i, l])


# --------------------------------------------------------------------------- the problem
class _Problem:
    """Flattened, whitened PC problems: ``A = A0 + N``, ``B = B0 + N``, ``J = J0 - N``."""

    def __init__(self, A0, B0, J0, a, b, lam, log_gamma, mutual_mean):
        self.A0, self.B0, self.J0 = A0, B0, J0
        self.a, self.b, self.lam = a, b, lam
        self.log_gamma, self.mutual_mean = log_gamma, mutual_mean
        self.basis = _SymmetricBasis(A0.shape[-1])

    def take(self, index):
        return _Problem(self.A0[index], self.B0[index], self.J0[index], self.a[index],
                        self.b[index], self.lam[index], self.log_gamma[index],
                        self.mutual_mean)

    def decompose(self, N):
        with np.errstate(all="ignore"):
            return decompose(self.A0 + N, self.B0 + N, self.J0 - N, self.a, self.b, self.lam,
                             self.mutual_mean)

    def log_psi(self, N):
        with np.errstate(all="ignore"):
            return np.log(self.decompose(N).psi)

    def psi_derivatives(self, N):
        """psi, its gradient and Hessian in the coordinates of the basis.

        With ``dA = dB = dN``, ``dJ = -dN``, ``k = a + b - 2 m``, ``y = x_a + x_b - 2 x_s``
        and ``z = S^-1 J y`` (notation of :class:`~cifilter.ei.Decomposition`):
        ``dm = S^-1 dN k`` for both mutual means, and

            dpsi = tr(dN [m y^T + y m^T - k z^T - z k^T - x_a x_a^T - x_b x_b^T + 2 x_s x_s^T]).

        The Hessian differentiates this matrix once more along every basis matrix.
        """
        basis, A, B, J = self.basis, self.A0 + N, self.B0 + N, self.J0 - N
        parts = decompose(A, B, J, self.a, self.b, self.lam, self.mutual_mean)
        m, x_a, x_b, x_s = parts.m, parts.x_a, parts.x_b, parts.x_s
        # Explicit inverses for the derivatives: each is applied to q + 2 right-hand sides,
        # and one batched call is much cheaper than repeated solves.
        S_inv, A_inv, B_inv = symmetrize(np.linalg.inv(np.stack([parts.S, A, B])))
        k = self.a + self.b - 2.0 * m
        y = x_a + x_b - 2.0 * x_s
        z = np.einsum("...ij,...jk,...k->...i", S_inv, J, y)
        # E_p applied to the five vectors needed below, in one call
        E_k, E_ma, E_mb, E_ms, E_yz = np.moveaxis(basis.apply(np.stack(
            [k, m - x_a, m - x_b, m - x_s, y + 2.0 * z], axis=-2)), -3, 0)

        def outer(u, v):
            return u[..., :, None] * v[..., None, :]

        G = (outer(m, y) + outer(y, m) - outer(k, z) - outer(z, k)
             - outer(x_a, x_a) - outer(x_b, x_b) + 2.0 * outer(x_s, x_s))
        gradient = basis.coords(G)
        # Rows p of the arrays below are derivatives along E_p; for symmetric M,
        # (M^-1 v_p)^T = v_p^T M^-1, so "M^-1 applied to every row" is X @ M^-1.
        dm = E_k @ S_inv
        J_dm = dm @ J
        dx_a = (E_ma - J_dm) @ A_inv
        dx_b = (E_mb - J_dm) @ B_inv
        dx_s = 2.0 * (E_ms - J_dm) @ S_inv
        dy = dx_a + dx_b - 2.0 * dx_s
        dz = (dy @ J - E_yz) @ S_inv
        # d<G, E_r> along E_p: every term is a coordinate of u_p v^T + v u_p^T, which is
        # 2 u_p . (E_r v); all seven terms in one batched product.
        left = np.concatenate([dm, dy, 2.0 * dm, -dz, -dx_a, -dx_b, 2.0 * dx_s], axis=-1)
        applied = basis.apply(np.stack([y, m, z, k, x_a, x_b, x_s], axis=-2))  # (..., 7, q, n)
        right = np.concatenate(np.moveaxis(applied, -3, 0), axis=-1)
        hessian = 2.0 * left @ np.swapaxes(right, -1, -2)
        return parts.psi, gradient, symmetrize(hessian)


# --------------------------------------------------------------------------- barrier method
def _logdet(M):
    sign, value = np.linalg.slogdet(M)
    return np.where(sign > 0, value, -np.inf)


def _barrier(problem, N, t):
    """``t (-log det J) - log det N - log(-c)``, ``c = log(psi / gamma)``; inf outside."""
    with np.errstate(all="ignore"):
        c = problem.log_psi(N) - problem.log_gamma
        log_J, log_N = _logdet(np.stack([problem.J0 - N, N]))
        value = -t * log_J - log_N - np.log(-c)
    return np.where(np.isfinite(value) & (c < 0), value, np.inf)


def _max_step(X, D):
    """Largest ``s`` with ``X + s D`` positive definite (X positive definite), inf if none.

    It is ``-1 / lambda_min(L^-1 D L^-T)`` with ``X = L L^T``. X is the current iterate
    (N or J0 - N), positive definite by construction; should the Cholesky factorisation
    fail by rounding (N nearly singular), an eigen-decomposition is used instead.
    """
    try:
        L_inv = np.linalg.inv(np.linalg.cholesky(X))
        Z = L_inv @ D @ np.swapaxes(L_inv, -1, -2)
        valid = True
    except np.linalg.LinAlgError:
        values, vectors = np.linalg.eigh(X)
        valid = values[..., 0] > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            root = (vectors / np.sqrt(values)[..., None, :]) @ np.swapaxes(vectors, -1, -2)
        Z = np.where(valid[..., None, None], root @ D @ root, 0.0)
    smallest = np.linalg.eigvalsh(symmetrize(Z))[..., 0]
    with np.errstate(divide="ignore"):
        step = np.where(smallest < 0, -1.0 / smallest, np.inf)
    return np.where(valid, step, 0.0)


def _newton(problem, N, t):
    """Gradient and (convexified) Newton step of the barrier function."""
    basis = problem.basis
    W = symmetrize(np.linalg.inv(problem.J0 - N))
    N_inv = symmetrize(np.linalg.inv(N))
    psi, g_psi, H_psi = problem.psi_derivatives(N)
    c = np.log(psi) - problem.log_gamma
    g_c = g_psi / psi[..., None]
    H_c = H_psi / psi[..., None, None] - g_c[..., :, None] * g_c[..., None, :]
    tt = t[..., None]
    gradient = tt * basis.coords(W) - basis.coords(N_inv) - g_c / c[..., None]
    hessian = (tt[..., None] * basis.kron(W) + basis.kron(N_inv)
               + g_c[..., :, None] * g_c[..., None, :] / (c**2)[..., None, None]
               - H_c / c[..., None, None])
    hessian = symmetrize(hessian)
    definite = _positive_definite(hessian)
    step = np.empty_like(gradient)
    step[definite] = -np.linalg.solve(hessian[definite], gradient[definite][..., None])[..., 0]
    if not definite.all():
        # psi is not convex everywhere: where the Hessian is indefinite use |eigenvalues|,
        # which still gives a descent direction.
        values, vectors = np.linalg.eigh(hessian[~definite])
        scale = np.abs(values).max(axis=-1, keepdims=True)
        values = np.maximum(np.abs(values), 1e-14 * scale)
        step[~definite] = -np.einsum("...ij,...j->...i", vectors, np.einsum(
            "...ji,...j->...i", vectors, gradient[~definite]) / values)
    return gradient, step, c


def _positive_definite(H):
    """Which matrices of a stack are positive definite (pivots of a batched Cholesky).

    LAPACK's batched Cholesky raises for the whole stack when one member fails; this
    column loop (q <= 21 columns) reports each member.
    """
    q = H.shape[-1]
    L = np.zeros_like(H)
    ok = np.ones(H.shape[:-2], dtype=bool)
    for j in range(q):
        pivot = H[..., j, j] - np.einsum("...k,...k->...", L[..., j, :j], L[..., j, :j])
        ok &= pivot > 1e-14 * np.abs(H[..., j, j]) + np.finfo(float).tiny
        root = np.sqrt(np.where(ok, pivot, 1.0))
        L[..., j, j] = root
        L[..., j + 1:, j] = (H[..., j + 1:, j]
                             - np.einsum("...ik,...k->...i", L[..., j + 1:, :j], L[..., j, :j])
                             ) / root[..., None]
    return ok


def _interior_point(problem, N, tol, max_iter):
    """Log-barrier method for a flat batch of problems from strictly feasible ``N``.

    Minimises ``t f(N) - log det N - log(-c(N))`` (``f = -log det(J0 - N)``,
    ``c = log(psi / gamma)``) by damped Newton steps that stay inside the cones (at most
    99% of the way to their boundary), multiplying ``t`` by 100 whenever the iterate is
    centred, up to ``t = (n + 1) / tol``: then ``(n + 1) / t`` bounds the distance of the
    objective to that of the KKT point the path leads to. Returns ``N``, ``t``, Newton
    iterations and whether the last stage was reached and centred (or stalled at the
    rounding level) per problem.
    """
    size, n = N.shape[0], problem.basis.n
    N = N.copy()
    t_final = (n + 1) / tol
    # f(0) = -log det J0 is a lower bound of the optimum, so the start is at most
    # f(N0) - f(0) above it; starting with a gap (n + 1) / t of that size skips the
    # stages a tiny correction (nearly equal means) does not need.
    excess = _logdet(problem.J0) - _logdet(problem.J0 - N)
    t = np.clip((n + 1) / np.maximum(excess, 1e-300), 1.0, t_final)
    iterations = np.zeros(size, dtype=int)
    finished = np.zeros(size, dtype=bool)
    done = np.zeros(size, dtype=bool)
    for _ in range(max_iter):
        index = np.flatnonzero(~done)
        if index.size == 0:
            break
        sub = problem.take(index)
        N_i, t_i = N[index], t[index]
        with np.errstate(all="ignore"):
            gradient, step, _ = _newton(sub, N_i, t_i)
        decrement = -np.einsum("...i,...i->...", gradient, step)
        D = sub.basis.matrix(step)
        bound = np.minimum(_max_step(N_i, D), _max_step(sub.J0 - N_i, -D))
        s = np.minimum(1.0, 0.99 * bound)
        f0 = _barrier(sub, N_i, t_i)
        accepted = np.zeros(index.size, dtype=bool)
        for _ in range(50):  # Armijo backtracking, batched
            trial = _barrier(sub, N_i + s[:, None, None] * D, t_i)
            accepted |= trial <= f0 - 0.01 * s * decrement
            if accepted.all():
                break
            s = np.where(accepted, s, 0.5 * s)
        N[index] = N_i + np.where(accepted, s, 0.0)[:, None, None] * D
        iterations[index] += 1
        last = t_i >= t_final
        centred = decrement / 2 <= _CENTRE_TOL
        # The barrier value is ~t f, so at t ~ 1e9 its rounding (~1e-16 t) hides decreases
        # below ~1e-13 |value|: a step that cannot promise more has stalled at the
        # rounding level (Armijo would accept noise). Stalls move on; whether the result
        # is a KKT point is checked separately (_kkt_residual).
        stalled = ~accepted | (s * decrement < 1e-13 * np.maximum(1.0, np.abs(f0)))
        advance = centred | stalled
        finished[index] = last & advance
        done[index] = finished[index]
        t[index] = np.where(advance & ~last, np.minimum(t_i * _MU, t_final), t_i)
    return N, t, iterations, finished


def _kkt_residual(problem, N):
    """Relative KKT residual of ``min f  s.t.  c <= 0, N >= 0`` at ``N``.

    With ``Z = grad f + mu grad c`` (stationarity), the KKT conditions are ``Z >= 0`` and
    ``Z N = 0`` (and ``mu >= 0``, ``mu c = 0``, checked by construction: ``c`` is active at
    the solutions returned). ``mu >= 0`` is the least-squares solution of ``Z N = 0``;
    the residual is the larger of ``|Z N| / |N|`` and ``max(0, -lambda_min(Z))``, both
    relative to ``|grad f| + mu |grad c|``, the size of the terms that cancel in ``Z``
    (Frobenius norms, whitened coordinates).
    """
    with np.errstate(all="ignore"):
        grad_f = symmetrize(np.linalg.inv(problem.J0 - N))
        psi, g_psi, _ = problem.psi_derivatives(N)
        grad_c = problem.basis.matrix(g_psi / psi[..., None])
        F, C = grad_f @ N, grad_c @ N
        mu = np.maximum(0.0, -np.einsum("...ij,...ij->...", F, C)
                        / np.einsum("...ij,...ij->...", C, C))
        Z = grad_f + mu[..., None, None] * grad_c

        def norm(M):
            return np.linalg.norm(M, axis=(-2, -1))

        scale = norm(grad_f) + mu * norm(grad_c)
        complementarity = norm(Z @ N) / norm(N)
        dual = np.maximum(0.0, -np.linalg.eigvalsh(Z)[..., 0])
        return np.maximum(complementarity, dual) / scale


def _sqrtm(M):
    values, vectors = np.linalg.eigh(M)
    return (vectors * np.sqrt(np.maximum(values, 0.0))[..., None, :]) @ np.swapaxes(vectors,
                                                                                    -1, -2)


def _start_points(problem, tie):
    """Strictly feasible starting points along rays ``N = tau J0^1/2 D J0^1/2``.

    Directions ``D``: the identity (``J = (1 - tau) J0``, a uniform inflation of the common
    covariance), the whitened mean difference ``e`` (plus 5% of the identity), and, where
    some directions are tied, ``e`` restricted to them (the optimum when the covariances
    are equal everywhere). On each ray the first ``tau`` of a grid with ``psi < gamma``
    is taken. Returns (size, starts, n, n) and a (size, starts) feasibility mask.
    """
    size, n = problem.a.shape
    eye = np.eye(n)
    root = _sqrtm(problem.J0)
    e = problem.a - problem.b
    directions = [np.broadcast_to(eye, (size, n, n))]
    for v in (e, np.where(tie, e, 0.0)) if tie.any() else (e,):
        norm = np.linalg.norm(v, axis=-1, keepdims=True)
        v = np.where(norm > 0, v / np.where(norm > 0, norm, 1.0), 0.0)
        directions.append((v[..., :, None] * v[..., None, :] + 0.05 * eye) / 1.05)
    starts, feasible = [], []
    for D in directions:
        ray = root @ D @ root
        chosen, found = np.zeros((size, n, n)), np.zeros(size, dtype=bool)
        for tau in _STEP_GRID:
            c = problem.log_psi(tau * ray) - problem.log_gamma
            ok = ~found & np.isfinite(c) & (c < -1e-3)
            chosen[ok], found = tau * ray[ok], found | ok
            if found.all():
                break
        starts.append(chosen)
        feasible.append(found)
    return np.stack(starts, axis=1), np.stack(feasible, axis=1)


def _solve_batch(problem, tie, tol, max_iter):
    """Multi-start interior-point solution of a flat batch; picks the best start."""
    size, n = problem.a.shape
    N0, feasible = _start_points(problem, tie)
    count = N0.shape[1]
    result = {
        "N": np.zeros((size, n, n)), "feasible": feasible.any(axis=1),
        "iterations": np.zeros(size, dtype=int), "converged": np.zeros(size, dtype=bool),
        "kkt_residual": np.full(size, np.nan), "duality_gap": np.full(size, np.nan),
        "starts": feasible.sum(axis=1), "starts_agree": np.zeros(size, dtype=int),
    }
    rows, cols = np.nonzero(feasible)
    if rows.size == 0:
        return result
    flat = problem.take(rows)
    N, t, iterations, finished = _interior_point(flat, N0[rows, cols], tol, max_iter)
    objective = np.full((size, count), np.inf)
    objective[rows, cols] = -_logdet(flat.J0 - N)
    best = np.argmin(objective, axis=1)
    position = np.full((size, count), -1)
    position[rows, cols] = np.arange(rows.size)
    chosen = position[np.arange(size), best]
    ok = chosen >= 0
    pick = chosen[ok]
    result["N"][ok] = N[pick]
    result["iterations"][ok] = iterations[pick]
    residual = _kkt_residual(flat.take(pick), N[pick])
    result["kkt_residual"][ok] = residual
    result["converged"][ok] = finished[pick] & (residual <= _KKT_TOL)
    result["duality_gap"][ok] = (n + 1) / t[pick]
    best_value = objective[np.arange(size), best][:, None]
    result["starts_agree"] = np.sum(objective <= best_value + _AGREE_TOL, axis=1)
    return result


# --------------------------------------------------------------------------- the rule
def _gamma(alpha, n):
    """The threshold of eq. (17): ``P(chi2_n >= gamma) = alpha``."""
    return stats.chi2.ppf(1.0 - alpha, df=n)


def _flat(array, batch, size):
    return array.reshape((size,) + array.shape[len(batch):])


def _base(w, eps, regularizer):
    """Tied directions, b's whitened information and EI's J0, A0, B0 the search starts at.

    With the information regulariser, directions with ``|log d| <= eps`` are exact ties
    (``d = 1``), so that the constraint does not depend on how rounding split equal
    variances. With the covariance regulariser the base is eq. (11) with ``eps I``.
    """
    size, n = w.d.shape
    if regularizer == "covariance" and eps > 0:
        _, J0, A0, B0 = covariance_regularised_base(w, eps)
        return np.zeros((size, n), dtype=bool), w.lam, J0, A0, B0
    tie = ties(w.d, eps if regularizer == "information" else 0.0)
    lam = 1.0 / np.where(tie, 1.0, w.d)
    eye = np.eye(n)
    return (tie, lam, np.minimum(1.0, lam)[..., None] * eye,
            np.maximum(0.0, 1.0 - lam)[..., None] * eye,
            np.maximum(0.0, lam - 1.0)[..., None] * eye)


def _pc_in_whitened(w, gamma, eps, mutual_mean, regularizer, tol, max_iter):
    """PC-EI of whitened estimates (flat batch): the fused pieces and the diagnostics."""
    size, n = w.d.shape
    fused, psi_ei = ei_in_whitened(w, eps, mutual_mean, regularizer)
    tie, lam, J0, A0, B0 = _base(w, eps, regularizer)
    need = ~(psi_ei <= gamma)
    info = {
        "psi": np.where(need, np.nan, psi_ei), "threshold": np.full(size, gamma),
        "active": need.copy(), "feasible": np.ones(size, dtype=bool),
        "solver": np.full(size, "ei", dtype=object), "iterations": np.zeros(size, dtype=int),
        "converged": np.ones(size, dtype=bool), "kkt_residual": np.zeros(size),
        "duality_gap": np.zeros(size), "starts": np.zeros(size, dtype=int),
        "starts_agree": np.zeros(size, dtype=int),
    }
    N = np.zeros((size, n, n))
    # Closed form (see the module docstring): the constraint only needs common information
    # removed in the tied directions Z, where A = B = N; psi >= e_Z^T N_ZZ^-1 e_Z / 2, so
    # N_ZZ >= e_Z e_Z^T / (2 gamma), and N = e_Z e_Z^T / (2 gamma) attains it. This holds
    # when every direction is tied, and with Sijs & Lazar's mean (which leaves psi = 0 in
    # the untied directions of EI) for any tie pattern.
    sl_exact = mutual_mean == "sijs-lazar" and not (regularizer == "covariance" and eps > 0)
    closed = need & (tie.all(axis=-1) | sl_exact)
    e_tied = np.where(tie, w.a - w.b, 0.0)
    if closed.any():
        index = np.flatnonzero(closed)
        e = e_tied[index]
        ok = np.einsum("...i,...i->...", e, e) < 2.0 * gamma
        N[index[ok]] = e[ok, :, None] * e[ok, None, :] / (2.0 * gamma)
        info["feasible"][index] = ok
        info["psi"][index[ok]] = gamma
        info["solver"][index] = "closed-form"
    index = np.flatnonzero(need & ~closed)
    if index.size:
        problem = _Problem(A0[index], B0[index], J0[index], w.a[index], w.b[index],
                           lam[index], np.full(index.size, np.log(gamma)), mutual_mean)
        solved = _solve_batch(problem, tie[index], tol, max_iter)
        N[index] = solved.pop("N")
        for key, value in solved.items():
            info[key][index] = value
        info["solver"][index] = "interior-point"
        ok = solved["feasible"]
        info["psi"][index[ok]] = problem.take(ok).decompose(N[index[ok]]).psi
    # A solve that did not converge keeps EI's result (flagged): this happens with the
    # printed mean when two or more directions are tied, where A + B is singular on the
    # tied subspace at the optimum and psi cannot be evaluated accurately near it.
    use = np.flatnonzero(need & info["feasible"] & info["converged"])
    if use.size:
        # Assemble eqs. (7)-(8) with the new common information; keep EI elsewhere.
        w_use = type(w)(*(None if field is None else field[use] for field in w))._replace(
            d=1.0 / lam[use])
        J, A, B = J0[use] - N[use], A0[use] + N[use], B0[use] + N[use]
        # the fused information I + diag(lam) - J = (I + diag(lam) - J0) + N, positive
        # definite by construction
        M = (np.eye(n) + lam[use, :, None] * np.eye(n) - J0[use]) + N[use]
        pc = _fuse_pc(w_use, J, A, B, M, mutual_mean, eps, closed[use], tie[use])
        if not (regularizer == "covariance" and eps > 0):
            pc = pc._replace(P=_fused_covariance(w_use, N[use]))
        fused = as_full(fused)
        fused = type(fused)(*(_replace_rows(full, use, part) for full, part in zip(fused, pc)))
    return fused, info


def _fused_covariance(w, N):
    """The fused covariance for EI's common information less ``N`` (whitened).

    With ``P_EI = F F^T`` from :func:`~cifilter.ei.whiten` and ``K = T^-1 F``, eq. (8)
    gives ``P^-1 = P_EI^-1 + T^-T N T^-1``, so (Woodbury)

        P = F (I + K^T N K)^-1 F^T,

    a Gram matrix of a nonsingular factor (``I + K^T N K >= I``): positive definite by
    construction, EI's own covariance for ``N = 0`` and as accurate as it.
    """
    K = w.T_inv @ w.F
    R = _inverse_root(np.eye(N.shape[-1]) + np.swapaxes(K, -1, -2) @ N @ K,
                      "the fused information")
    return _gram(w.F @ R)


def _fuse_pc(w, J, A, B, M, mutual_mean, eps, closed, tie):
    """Fuse with PC's common information; closed-form problems have a singular ``A + B``.

    ``M`` is the fused information ``I + diag(lam) - J`` (whitened), positive definite
    by construction (``N >= 0`` added to EI's).

    There the mutual mean is the average in the tied directions (``A = B`` there, for
    both weightings) and EI's in the others (where ``N`` is zero).
    """
    size, n = w.d.shape
    R_a = np.zeros((size, n, n))
    if (~closed).any():
        general = np.flatnonzero(~closed)
        W_a, _ = mutual_mean_weights(A[general], B[general], mutual_mean)
        R_a[general] = _solve(A[general] + B[general], W_a)
    if closed.any():
        sub = type(w)(*(None if field is None else field[closed] for field in w))
        ratio = np.where(tie[closed], 0.5, mean_ratio(sub, eps, mutual_mean))
        R_a[closed] = ratio[..., None] * np.eye(n)
    return fuse_full(w, J, A, B, mutual_mean, R_a=R_a, information=M)


def _replace_rows(full, index, part):
    full = np.array(full, copy=True)
    full[index] = part
    return full


def pc_ellipsoidal_intersection(xa, Pa, xb, Pb, alpha=0.05, *, eps=DEFAULT_EPS,
                                mutual_mean="sijs-lazar", regularizer="information",
                                tol=1e-9, max_iter=300):
    """Fuse two estimates by probabilistically conservative Ellipsoidal Intersection.

    Starts from EI's common covariance ``C_EI`` (eq. (11)) and adds the smallest
    ``S S^T`` (eq. (18)) such that the independent parts of the inputs pass the
    chi-square test of eq. (17) at significance ``alpha``:

        minimise det(C_EI + S S^T)  subject to  psi(C_EI + S S^T) <= chi2.ppf(1 - alpha, n),

    then fuses with eqs. (7)-(8). A larger common covariance means less shared
    information and a smaller fused covariance than EI's.

    Parameters
    ----------
    xa, xb : array_like, shape (..., n) or (..., n, 1)
        The two means; leading axes are batch axes.
    Pa, Pb : array_like, shape (..., n, n)
        Their covariances, symmetric positive definite.
    alpha : float, optional
        Significance level in (0, 1), default 0.05: the probability that the test
        rejects independent parts with equal means. Smaller ``alpha`` gives a larger
        threshold, a looser constraint and a result closer to EI.
    eps : float, optional
        As in :func:`ellipsoidal_intersection` (default ``1e-8``). With
        ``regularizer="information"`` it is also the tolerance below which two variances
        count as equal (``|log d_k| <= eps``): such directions are treated as exact ties.
    mutual_mean : {"sijs-lazar", "as-printed"}, optional
        The common mean of eq. (13), see :func:`ellipsoidal_intersection`. It decides what
        the constraint does: with ``"sijs-lazar"`` (default) EI's independent parts always
        pass the test except in tied directions with different means, so PC-EI differs
        from EI only there; with ``"as-printed"`` they fail whenever the means differ.
    regularizer : {"information", "covariance"}, optional
        Where ``eps`` enters; ``"covariance"`` adds ``eps I`` to ``C_EI`` as in eq. (11).
    tol : float, optional
        Target gap ``(n + 1) / t`` of the barrier method (default 1e-9), a bound on how
        far ``log det C_c`` is above the KKT point's.
    max_iter : int, optional
        Newton iterations per start (default 300).

    Returns
    -------
    FusionResult
        As :func:`ellipsoidal_intersection` (``gains`` exact for the returned common
        covariance; PC-EI as a whole is not linear in the means because ``C_c`` depends
        on them), with ``info`` also holding, per problem: ``psi`` (eq. (17) at the
        result) and ``threshold`` (``gamma``), ``active`` (EI failed the test and the
        constraint moved ``C_c``), ``feasible`` (a common covariance passing the test was
        found; if not, the result is EI's and the hypothesis of equal means is rejected),
        ``solver`` (``"ei"``, ``"closed-form"`` or ``"interior-point"``), ``iterations``,
        ``converged`` (the barrier method finished with a KKT residual below 1e-3; if not,
        the result is EI's), ``kkt_residual`` (relative KKT residual of the original
        problem at the result, whitened coordinates), ``duality_gap`` (``(n + 1) / t``),
        ``starts`` (feasible starting points) and ``starts_agree`` (how many of them
        reached the best value within 1e-7), ``alpha``.

    Raises
    ------
    ValueError
        As :func:`ellipsoidal_intersection` (including
        :class:`~cifilter.IllConditionedError` rather than a covariance that is not
        positive definite), and ``alpha`` outside (0, 1), ``tol`` not in (0, 1),
        ``max_iter < 1``.
    TypeError
        Non-numeric input.

    See Also
    --------
    ellipsoidal_intersection : the unconstrained rule.

    Notes
    -----
    Eq. (19) minimises ``|S|`` over lower triangular ``S``; for n > 1 any rank-deficient
    ``S`` has ``|S| = 0`` and the optimal ``S S^T`` is often rank-deficient (for equal
    covariances it has rank one), so ``det C_c`` is minimised instead.

    If EI already passes the test the result is EI's exactly. If the covariances are
    equal in every direction, or with Sijs & Lazar's mean whenever some directions are
    tied, the optimum has a closed form (a rank-one correction on the tied directions).
    Otherwise (the printed mean, or the covariance regulariser) the problem is solved in
    the information ``J = C_c^-1`` of the common part, where the objective ``-log det J``
    is convex and ``C_c >= C_EI`` is the cone ``J <= J_EI``, by a batched log-barrier
    method with exact Hessians, from up to three starts. The constraint is not convex
    everywhere, so the result is a KKT point (reported) that the starts agree on; no
    global certificate exists.

    Neither EI nor PC-EI is conservative: see the documentation page for how often their
    NEES exceeds the chi-square bound.

    References
    ----------
    .. [1] A. Naveen and C. Taylor, "Decentralized data fusion with probabilistically
       conservative ellipsoidal intersection", eqs. (17)-(19), Section III.
    .. [2] J. Sijs and M. Lazar, "State fusion with unknown correlation: Ellipsoidal
       intersection", Automatica 48(8), 2012.

    Examples
    --------
    Section III, case 1 (equal variances, means +1 and -1). The common covariance of
    about 1.43 and fused variance of about 0.77 that the paper reports for "alpha = 0.05"
    are what the formulas give at alpha = 0.01:

    >>> import numpy as np
    >>> from cifilter import pc_ellipsoidal_intersection
    >>> r = pc_ellipsoidal_intersection([1.0], [[1.0]], [-1.0], [[1.0]], alpha=0.01)
    >>> round(float(r.info["common_P"][0, 0]), 4), round(float(r.P[0, 0]), 4)
    (1.4315, 0.7684)
    >>> A = r.info["independent_information"][:, 0, 0]
    >>> (r.info["independent_information_vector"][:, 0] / A).round(3).tolist()
    [3.317, -3.317]

    When EI already passes the test (equal means) the result is EI's:

    >>> r = pc_ellipsoidal_intersection(np.zeros(2), np.eye(2), np.zeros(2), 2 * np.eye(2))
    >>> r.info["solver"], np.diag(r.P).tolist()
    ('ei', [1.0, 1.0])
    """
    est = _as_pair(xa, Pa, xb, Pb)
    return _pcei(est, alpha, eps, mutual_mean, regularizer, tol, max_iter)


def _pcei(est, alpha, eps, mutual_mean, regularizer, tol, max_iter):
    eps = _check_options(mutual_mean, regularizer, eps)
    alpha = check_scalar(alpha, "alpha", low=0.0, high=1.0, low_open=True, high_open=True)
    tol = check_scalar(tol, "tol", low=0.0, high=1.0, low_open=True, high_open=True)
    max_iter = check_int(max_iter, "max_iter", low=1)
    w_full = whiten(est, factor=not (regularizer == "covariance" and eps > 0))
    batch, n = est.batch_shape, est.dim
    size = int(np.prod(batch, dtype=int))
    w = type(w_full)(*(None if field is None else _flat(field, batch, size)
                       for field in w_full))
    gamma = _gamma(alpha, n)
    fused, info = _pc_in_whitened(w, gamma, eps, mutual_mean, regularizer, tol, max_iter)
    x, P, gains, extra = to_original(w, fused, _flat(est.x, batch, size))
    check_result(P, est)
    info.update(extra)
    out = {key: value.reshape(batch + value.shape[1:]) for key, value in info.items()}
    x, P, gains = (v.reshape(batch + v.shape[1:]) for v in (x, P, gains))
    if not batch:
        out = {key: (value.item() if value.ndim == 0 else value) for key, value in out.items()}
    out.update(alpha=alpha, mutual_mean=mutual_mean, regularizer=regularizer, eps=eps)
    return FusionResult(restore_style(x, est.column), P, "pcei", None, gains, out)


def _pcei_core(est, alpha=0.05, eps=DEFAULT_EPS, mutual_mean="sijs-lazar",
               regularizer="information", tol=1e-9, max_iter=300):
    return _pcei(_check_two(est, "pcei"), alpha, eps, mutual_mean, regularizer, tol, max_iter)


def _registered_pcei(xs, Ps, alpha=0.05, eps=DEFAULT_EPS, mutual_mean="sijs-lazar",
                     regularizer="information", tol=1e-9, max_iter=300):
    return _pcei_core(as_estimates(xs, Ps), alpha, eps, mutual_mean, regularizer, tol,
                      max_iter)


REGISTRATION = dict(
    name="pcei",
    function=_registered_pcei,
    core=_pcei_core,
    summary="probabilistically conservative EI: common part bounded by a chi-square test",
    reference="Naveen & Taylor, eqs. 17-19; Sijs & Lazar 2012",
    guarantee="none",
)
"""The record of the ``"pcei"`` rule (registered by :mod:`cifilter._rules`)."""
