"""Compiled (numba) building blocks shared by the kernels of :mod:`cifilter._kernels`.

Small jitted functions on one problem's square matrices (``n`` the dimension, scratch given
by the caller): a Cholesky factorisation and its numerical positive definiteness, triangular
products and inverses, a cyclic Jacobi eigensolver, and the pieces of the two-estimate
weight search in a diagonal basis (derivatives, the safeguarded Newton, the certified gap,
the criterion report). Each mirrors the numpy path's formula named in its docstring.
Imported only by the kernels' modules (importing cifilter never imports numba).
"""

import math

import numpy as np
from numba import njit

from .._numerics.criteria import SLOPE_ROUNDING

__all__ = ["EPS", "KIND_DET", "KIND_NONE", "KIND_TRACE", "KIND_WEIGHTED", "add_gram", "cholesky",
           "diagonal_spread_squared", "interval_gap", "jacobi_eigh", "jacobi_rotation", "jit",
           "lower_inverse",
           "lower_times", "minimize_interval", "numerically_positive_definite",
           "pair_derivative", "report", "rounding_scale", "slope_rounding", "times_lower"]

KIND_TRACE, KIND_DET, KIND_WEIGHTED, KIND_NONE = 0, 1, 2, 3
EPS = float(np.finfo(float).eps)
_XTOL = 1e-13  # minimize_convex_interval's defaults
_MAX_ITER = 100

jit = njit(cache=True, error_model="numpy", fastmath=False, nogil=True)


@jit
def cholesky(A, R, n):
    """Lower Cholesky factor of the lower triangle of A into R; False if not PD."""
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= R[j, k] * R[j, k]
        if not (s > 0.0) or not math.isfinite(s):
            return False
        d = math.sqrt(s)
        R[j, j] = d
        for i in range(j):
            R[i, j] = 0.0
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= R[i, k] * R[j, k]
            R[i, j] = t / d
    return True


@jit
def numerically_positive_definite(R, n):
    """``_information.numerically_positive_definite`` of one factor."""
    lo = math.inf
    hi = 0.0
    for i in range(n):
        for j in range(n):
            if not math.isfinite(R[i, j]):
                return False
        d = abs(R[i, i])
        lo = min(lo, d)
        hi = max(hi, d)
    return (hi / lo) ** 2 < 1.0 / (n * EPS)


@jit
def diagonal_spread_squared(L, n):
    lo = math.inf
    hi = 0.0
    for i in range(n):
        d = abs(L[i, i])
        lo = min(lo, d)
        hi = max(hi, d)
    return (hi / lo) ** 2


@jit
def lower_inverse(L, X, n):
    """X = L^-1 for lower triangular L (forward substitution, column by column)."""
    for j in range(n):
        for i in range(j):
            X[i, j] = 0.0
        X[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * X[k, j]
            X[i, j] = s / L[i, i]


@jit
def lower_times(L, A, out, n):
    """out = L A for lower triangular L (n, n) and A of n rows (its columns: out's), L's
    zeros above the diagonal skipped."""
    for i in range(n):
        for j in range(A.shape[1]):
            s = 0.0
            for k in range(i + 1):
                s += L[i, k] * A[k, j]
            out[i, j] = s


@jit
def times_lower(A, L, out, n):
    """out = A L for lower triangular L (n, n) and A of n columns (its rows: out's), L's
    zeros above the diagonal skipped."""
    for i in range(A.shape[0]):
        for j in range(n):
            s = 0.0
            for k in range(j, n):
                s += A[i, k] * L[k, j]
            out[i, j] = s


@jit
def add_gram(M, out, n):
    """out += M M^T."""
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += M[i, k] * M[j, k]
            out[i, j] += s


@jit
def jacobi_rotation(theta):
    """``(t, c, s)`` of the Jacobi rotation that annihilates an off-diagonal entry, given
    ``theta = (a_qq - a_pp) / (2 a_pq)``: the smaller root ``t = tan(phi)`` of
    ``t^2 + 2 theta t - 1 = 0`` (``1 / (2 theta)`` where ``theta^2`` would overflow),
    ``c = cos(phi)``, ``s = sin(phi)`` (Golub & Van Loan, Algorithm 8.5.1). Shared by the
    two-sided rotations of :func:`jacobi_eigh` and the one-sided ones of the generalised
    CI kernel."""
    if abs(theta) > 1e150:
        t = 0.5 / theta
    else:
        t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
        if theta < 0.0:
            t = -t
    c = 1.0 / math.sqrt(t * t + 1.0)
    return t, c, t * c


@jit
def jacobi_eigh(A, lam, V, n):
    """Eigen-decomposition of the symmetric A (destroyed) by cyclic Jacobi rotations.

    A rotation is skipped where ``|a_pq| <= eps/2 sqrt(|a_pp a_qq|)`` (the criterion of
    Demmel & Veselić, which gives small eigenvalues to high relative accuracy); each
    rotation updates the two rows and columns it touches (the symmetric form of Golub &
    Van Loan, Alg. 8.5.2). Returns False if the sweeps do not converge (the caller then
    hands the item back to the numpy path).
    """
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
    tol2 = 0.25 * EPS * EPS
    converged = False
    for _ in range(60):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                app = A[p, p]
                aqq = A[q, q]
                if apq * apq <= tol2 * abs(app * aqq):
                    continue
                rotated = True
                t, c, s = jacobi_rotation((aqq - app) / (2.0 * apq))
                tau = s / (1.0 + c)
                A[p, p] = app - t * apq
                A[q, q] = aqq + t * apq
                A[p, q] = 0.0
                A[q, p] = 0.0
                for k in range(n):
                    if k != p and k != q:
                        akp = A[k, p]
                        akq = A[k, q]
                        value_p = akp - s * (akq + tau * akp)
                        value_q = akq + s * (akp - tau * akq)
                        A[k, p] = value_p
                        A[p, k] = value_p
                        A[k, q] = value_q
                        A[q, k] = value_q
                for k in range(n):
                    vkp = V[k, p]
                    vkq = V[k, q]
                    V[k, p] = vkp - s * (vkq + tau * vkp)
                    V[k, q] = vkq + s * (vkp - tau * vkq)
        if not rotated:
            converged = True
            break
    for i in range(n):
        lam[i] = A[i, i]
    return converged


@jit
def pair_derivative(omega, a, ca, n, kind):
    """f' and f'' of the diagonalised two-estimate criterion (``_diagonalised_weights``)."""
    g = 0.0
    h = 0.0
    if kind == KIND_DET:
        for k in range(n):
            ratio = a[k] / (1.0 + omega * a[k])
            g -= ratio
            h += ratio * ratio
        return g, h
    for k in range(n):
        den = 1.0 + omega * a[k]
        term = ca[k] / (den * den)
        g -= term
        h += term * a[k] / den
    return g, 2.0 * h


@jit
def slope_rounding(lam, omega, c, n, kind, sigma):
    """``_criteria.slope_rounding`` of one problem: the bound of the slope's rounding."""
    total = 0.0
    for k in range(n):
        D = 1.0 + omega * (lam[k] - 1.0)
        if kind == KIND_DET:
            total += 1.0 / (D * D)
        else:
            total += abs(c[k]) * abs((2.0 * lam[k] - 1.0) * D
                                     - 2.0 * omega * lam[k] * (lam[k] - 1.0)) / (D * D * D)
    return SLOPE_ROUNDING * n * EPS * sigma * total


@jit
def rounding_scale(L1i, P2, n):
    """``_criteria.rounding_scale`` of one problem: ``||L_1^-1||_F^2 ||P_2||_F``."""
    a = 0.0
    b = 0.0
    for i in range(n):
        for j in range(n):
            a = max(a, abs(L1i[i, j]))
            b = max(b, abs(P2[i, j]))
    na = 0.0
    nb = 0.0
    for i in range(n):
        for j in range(n):
            t = L1i[i, j] / a
            na += t * t
            t = P2[i, j] / b
            nb += t * t
    return (a * a * b) * na * math.sqrt(nb)


@jit
def interval_gap(t, slope):
    """``_optimize.interval_gap``."""
    return 0.5 * (abs(slope) + (2.0 * t - 1.0) * slope)


@jit
def minimize_interval(a, ca, n, kind, scale):
    """``_optimize.minimize_convex_interval`` for one problem: (omega, iterations)."""
    g0, _ = pair_derivative(0.0, a, ca, n, kind)
    g1, _ = pair_derivative(1.0, a, ca, n, kind)
    tiny = 1e-13 * scale
    if abs(g0) <= tiny and abs(g1) <= tiny:
        return 0.5, 0
    if g0 >= 0.0:
        return 0.0, 0
    if g1 <= 0.0:
        return 1.0, 0
    w = 0.5
    lo = 0.0
    hi = 1.0
    iterations = 0
    for _ in range(_MAX_ITER):
        g, h = pair_derivative(w, a, ca, n, kind)
        if g < 0.0:
            lo = w
        if g > 0.0:
            hi = w
        step = -g / h
        newton = w + step
        settled = abs(step) < _XTOL or g == 0.0
        if newton > lo and newton < hi and math.isfinite(newton):
            w = newton
        elif not settled:
            w = 0.5 * (lo + hi)
        iterations += 1
        if settled or hi - lo < _XTOL:
            break
    return w, iterations


@jit
def report(P, R, W, n, kind, out_value, out_log, b):
    """``_criteria.criterion_report`` of one fused covariance; False if P is not
    numerically positive definite (the numpy path then raises its error)."""
    if not cholesky(P, R, n) or not numerically_positive_definite(R, n):
        return False
    if kind == KIND_DET:
        log_det = 0.0
        for i in range(n):
            log_det += math.log(R[i, i])
        log_det *= 2.0
        out_log[b] = log_det
        out_value[b] = math.exp(log_det)
    elif kind == KIND_TRACE:
        value = 0.0
        for i in range(n):
            value += P[i, i]
        out_value[b] = value
    elif kind == KIND_WEIGHTED:
        wi = b if W.shape[0] > 1 else 0
        value = 0.0
        for i in range(n):
            for j in range(n):
                value += W[wi, i, j] * P[j, i]
        out_value[b] = value
    return True
