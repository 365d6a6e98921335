"""The constrained common information of PC-EI (Naveen & Taylor, eqs. (17)-(19)).

PC-EI enlarges EI's common covariance, ``C_c = C_EI + S S^T`` (eq. (18)), as little as
possible (smallest ``det C_c``) such that the independent parts pass the chi-square test
``psi(C_c) <= gamma`` of eq. (17). In the whitened coordinates of
:func:`cifilter.rules._ellipsoidal.whiten` and with the common information ``J = J_EI - N`` as
variable this is ``min -log det(J_EI - N)`` over ``0 <= N < J_EI`` with ``psi(N) <=
gamma``: closed forms where the covariances tie (:func:`pc_in_whitened`) and otherwise a
batched log-barrier method with exact Newton steps (:func:`solve_batch`). The reduction,
the closed forms and the verification are argued on the documentation page
(``docs/methods/ei.rst``, "PC-EI: the probabilistically admissible constraint").
:func:`pc_fusion` is the whole rule on validated estimates.
"""

import functools

import numpy as np
from scipy import special

from .._numerics.linalg import lower_inverse, symmetrize
from ._ellipsoidal import (
    as_full,
    check_result,
    covariance_regularised_base,
    decompose,
    ei_fusion,
    ei_in_whitened,
    fuse_full,
    gram,
    inverse_root,
    mean_ratio,
    mutual_mean_weights,
    solve_spd,
    spd_inverse_stack,
    ties,
    to_original,
    whiten,
)

__all__ = ["ConstraintProblem", "SymmetricBasis", "chi_square_threshold", "constraint_base",
           "kkt_residual", "pc_fusion", "pc_in_whitened", "positive_definite", "solve_batch"]

_STEP_GRID = np.array([0.01, 0.03, 0.1, 0.2, 0.3, 0.45, 0.6, 0.75, 0.85, 0.92, 0.96, 0.98,
                       0.99, 0.995, 0.999, 1 - 1e-4, 1 - 1e-5, 1 - 1e-6, 1 - 1e-8])
_MU = 100.0  # barrier parameter growth per centring
# Newton decrement^2 / 2 that counts as centred; the objective is then within about
# _CENTRE_TOL / t of the centre, far below the gap (n + 1) / t.
_CENTRE_TOL = 1e-4
_AGREE_TOL = 1e-7  # starts whose objective is within this of the best "agree"
_KKT_TOL = 1e-3  # relative KKT residual below which a finished solve counts as converged


# --------------------------------------------------------------------------- symmetric basis
class SymmetricBasis:
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
class ConstraintProblem:
    """Flattened, whitened PC problems: ``A = A0 + N``, ``B = B0 + N``, ``J = J0 - N``."""

    def __init__(self, A0, B0, J0, a, b, lam, log_gamma, mutual_mean):
        self.A0, self.B0, self.J0 = A0, B0, J0
        self.a, self.b, self.lam = a, b, lam
        self.log_gamma, self.mutual_mean = log_gamma, mutual_mean
        self.basis = SymmetricBasis(A0.shape[-1])

    def take(self, index):
        return ConstraintProblem(self.A0[index], self.B0[index], self.J0[index], self.a[index],
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
        and ``z = S^-1 J y`` (notation of :class:`~cifilter.rules.ei.Decomposition`):
        ``dm = S^-1 dN k`` for both mutual means, and

            dpsi = tr(dN [m y^T + y m^T - k z^T - z k^T - x_a x_a^T - x_b x_b^T + 2 x_s x_s^T]).

        The Hessian differentiates this matrix once more along every basis matrix.
        """
        basis, A, B, J = self.basis, self.A0 + N, self.B0 + N, self.J0 - N
        parts = decompose(A, B, J, self.a, self.b, self.lam, self.mutual_mean)
        m, x_a, x_b, x_s = parts.m, parts.x_a, parts.x_b, parts.x_s
        # Inverses (Cholesky-based) for the derivatives: each is applied to q + 2
        # right-hand sides, and one batched call is much cheaper than repeated solves.
        S_inv, A_inv, B_inv = spd_inverse_stack(np.stack([parts.S, A, B]))
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
        L_inv = lower_inverse(np.linalg.cholesky(X))
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
    W, N_inv = spd_inverse_stack(np.stack([problem.J0 - N, N]))
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
    definite = positive_definite(hessian)
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


def positive_definite(H):
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
        # is a KKT point is checked separately (kkt_residual).
        stalled = ~accepted | (s * decrement < 1e-13 * np.maximum(1.0, np.abs(f0)))
        advance = centred | stalled
        finished[index] = last & advance
        done[index] = finished[index]
        t[index] = np.where(advance & ~last, np.minimum(t_i * _MU, t_final), t_i)
    return N, t, iterations, finished


def kkt_residual(problem, N):
    """Relative KKT residual of ``min f  s.t.  c <= 0, N >= 0`` at ``N``.

    With ``Z = grad f + mu grad c`` (stationarity), the KKT conditions are ``Z >= 0`` and
    ``Z N = 0`` (and ``mu >= 0``, ``mu c = 0``, checked by construction: ``c`` is active at
    the solutions returned). ``mu >= 0`` is the least-squares solution of ``Z N = 0``;
    the residual is the larger of ``|Z N| / |N|`` and ``max(0, -lambda_min(Z))``, both
    relative to ``|grad f| + mu |grad c|``, the size of the terms that cancel in ``Z``
    (Frobenius norms, whitened coordinates).
    """
    with np.errstate(all="ignore"):
        grad_f = spd_inverse_stack(problem.J0 - N)
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


def solve_batch(problem, tie, tol, max_iter):
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
    residual = kkt_residual(flat.take(pick), N[pick])
    result["kkt_residual"][ok] = residual
    result["converged"][ok] = finished[pick] & (residual <= _KKT_TOL)
    result["duality_gap"][ok] = (n + 1) / t[pick]
    best_value = objective[np.arange(size), best][:, None]
    result["starts_agree"] = np.sum(objective <= best_value + _AGREE_TOL, axis=1)
    return result


# --------------------------------------------------------------------------- the rule
@functools.lru_cache(maxsize=256)
def chi_square_threshold(alpha, n):
    """The threshold of eq. (17): ``P(chi2_n >= gamma) = alpha``: the inverse of the
    chi-square survival function, taken at ``alpha`` itself (``chi2.ppf(1 - alpha)`` would
    lose the digits of a small ``alpha`` in ``1 - alpha``). Cached: it costs more than a
    whole single EI fusion."""
    return float(special.chdtri(n, alpha))


def _flat(array, batch, size):
    return array.reshape((size,) + array.shape[len(batch):])


def constraint_base(w, eps, regularizer):
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


def pc_in_whitened(w, gamma, eps, mutual_mean, regularizer, tol, max_iter):
    """PC-EI of whitened estimates (flat batch): the fused pieces and the diagnostics."""
    size, n = w.d.shape
    fused, psi_ei = ei_in_whitened(w, eps, mutual_mean, regularizer)
    tie, lam, J0, A0, B0 = constraint_base(w, eps, regularizer)
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
        problem = ConstraintProblem(A0[index], B0[index], J0[index], w.a[index], w.b[index],
                           lam[index], np.full(index.size, np.log(gamma)), mutual_mean)
        solved = solve_batch(problem, tie[index], tol, max_iter)
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

    With ``P_EI = F F^T`` from :func:`~cifilter.rules.ei.whiten` and ``K = T^-1 F``, eq. (8)
    gives ``P^-1 = P_EI^-1 + T^-T N T^-1``, so (Woodbury)

        P = F (I + K^T N K)^-1 F^T,

    a Gram matrix of a nonsingular factor (``I + K^T N K >= I``): positive definite by
    construction, EI's own covariance for ``N = 0`` and as accurate as it.
    """
    K = w.T_inv @ w.F
    R = inverse_root(np.eye(N.shape[-1]) + np.swapaxes(K, -1, -2) @ N @ K,
                      "the fused information")
    return gram(w.F @ R)


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
        R_a[general] = solve_spd(A[general] + B[general], W_a)
    if closed.any():
        sub = type(w)(*(None if field is None else field[closed] for field in w))
        ratio = np.where(tie[closed], 0.5, mean_ratio(sub, eps, mutual_mean))
        R_a[closed] = ratio[..., None] * np.eye(n)
    return fuse_full(w, J, A, B, mutual_mean, R_a=R_a, information=M)


def _replace_rows(full, index, part):
    full = np.array(full, copy=True)
    full[index] = part
    return full


_PC_KEYS = ("psi", "threshold", "active", "feasible", "solver", "iterations", "converged",
            "kkt_residual", "duality_gap", "starts", "starts_agree")
_EI_KEYS = ("common_x", "common_P", "independent_information",
            "independent_information_vector")


def pc_fusion(est, alpha, eps, mutual_mean, regularizer, tol, max_iter):
    """PC-EI of two validated estimates with checked options: ``(x, P, gains, info)``.

    ``x`` is in row form (..., n); ``info`` holds the keys documented by
    :func:`cifilter.pc_ellipsoidal_intersection` (per problem; Python scalars when there
    are no batch axes). Where the constraint does not move the common covariance (EI
    passes the test, no feasible point, no convergence) the result is EI's exactly.
    """
    batch, n = est.batch_shape, est.dim
    gamma = chi_square_threshold(alpha, n)
    covariance = regularizer == "covariance" and eps > 0
    single_ei = None
    if not batch and not covariance:
        # One problem: EI first (the path for one problem); most often it passes the test.
        single_ei = ei_fusion(est, eps, mutual_mean, regularizer)
        psi = float(single_ei[3]["psi"])
        if psi <= gamma:
            x, P, gains, ei_info = single_ei
            info = _passing_info(psi, gamma)
            info.update((key, ei_info[key]) for key in _EI_KEYS)
            return x, P, gains, info
    size = int(np.prod(batch, dtype=int))
    w_full = whiten(est, factor=not covariance)
    w = type(w_full)(*(None if field is None else _flat(field, batch, size)
                       for field in w_full))
    fused, info = pc_in_whitened(w, gamma, eps, mutual_mean, regularizer, tol, max_iter)
    x, P, gains, extra = to_original(w, fused, _flat(est.x, batch, size))
    check_result(P, est)
    info.update(extra)
    out = {key: value.reshape(batch + value.shape[1:]) for key, value in info.items()}
    x, P, gains = (v.reshape(batch + v.shape[1:]) for v in (x, P, gains))
    if not batch:
        out = {key: (value.item() if value.ndim == 0 else value) for key, value in out.items()}
        if single_ei is not None and not (out["feasible"] and out["converged"]):
            # EI's result, as computed by EI itself for one problem
            x, P, gains, ei_info = single_ei
            out.update((key, ei_info[key]) for key in _EI_KEYS)
    return x, P, gains, out


def _passing_info(psi, gamma):
    """The diagnostics of one problem whose EI result passes the test (PC-EI is EI)."""
    return {"psi": psi, "threshold": gamma, "active": False, "feasible": True, "solver": "ei",
            "iterations": 0, "converged": True, "kkt_residual": 0.0, "duality_gap": 0.0,
            "starts": 0, "starts_agree": 0}
