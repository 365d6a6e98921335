"""Compiled (numba) kernels of the Covariance Intersection family, one problem per item.

Imported only by :mod:`cifilter._kernels.dispatch` when the numba backend is used (importing
cifilter never imports this module). Each kernel is a driver around one per-item function
that runs the numpy path's method with the same formulas in the same order
(``rules._ci_weights``, ``_numerics.information``, ``_numerics.optimize``): threaded,
``prange`` over chunks of the batch with the scratch arrays allocated once per chunk (none
inside the per-item loop), or ``*_serial`` for small batches, where waking a thread pool
costs more than the batch. Each item gets a ``status``: 0 done, else the item is handed back
to the numpy path (a diagonalisation that is not trusted, a fused information or covariance
that is not numerically positive definite: there the numpy path decides, re-solves or raises
its usual error).
"""

import math

import numpy as np
from numba import njit, prange

from .._numerics.criteria import GAP_TOL, SLOPE_ROUNDING
from .._numerics.information import DIAGONAL_TRUST

KIND_TRACE, KIND_DET, KIND_WEIGHTED, KIND_NONE = 0, 1, 2, 3
_EPS = float(np.finfo(float).eps)
_XTOL = 1e-13  # minimize_convex_interval's defaults
_MAX_ITER = 100
_CHUNK = 128  # items per scratch allocation

_jit = njit(cache=True, error_model="numpy", fastmath=False, nogil=True)
_jit_parallel = njit(cache=True, error_model="numpy", fastmath=False, parallel=True)


@_jit
def _cholesky(A, R, n):
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


@_jit
def _numerically_positive_definite(R, n):
    """``_information._numerically_positive_definite`` of one factor."""
    lo = math.inf
    hi = 0.0
    for i in range(n):
        for j in range(n):
            if not math.isfinite(R[i, j]):
                return False
        d = abs(R[i, i])
        lo = min(lo, d)
        hi = max(hi, d)
    return (hi / lo) ** 2 < 1.0 / (n * _EPS)


@_jit
def _diagonal_spread_squared(L, n):
    lo = math.inf
    hi = 0.0
    for i in range(n):
        d = abs(L[i, i])
        lo = min(lo, d)
        hi = max(hi, d)
    return (hi / lo) ** 2


@_jit
def _lower_inverse(L, X, n):
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


@_jit
def _lower_times(L, A, out, n):
    """out = L A for lower triangular L (its zeros above the diagonal are skipped)."""
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(i + 1):
                s += L[i, k] * A[k, j]
            out[i, j] = s


@_jit
def _times_lower(A, L, out, n):
    """out = A L for lower triangular L (its zeros above the diagonal are skipped)."""
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(j, n):
                s += A[i, k] * L[k, j]
            out[i, j] = s


@_jit
def _add_gram(M, out, n):
    """out += M M^T."""
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += M[i, k] * M[j, k]
            out[i, j] += s


@_jit
def _jacobi_eigh(A, lam, V, n):
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
    tol2 = 0.25 * _EPS * _EPS
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
                theta = (aqq - app) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
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


@_jit
def _pair_derivative(omega, a, ca, n, kind):
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


@_jit
def _slope_rounding(lam, omega, c, n, kind, sigma):
    """``_criteria.slope_rounding`` of one problem: the bound of the slope's rounding."""
    total = 0.0
    for k in range(n):
        D = 1.0 + omega * (lam[k] - 1.0)
        if kind == KIND_DET:
            total += 1.0 / (D * D)
        else:
            total += abs(c[k]) * abs((2.0 * lam[k] - 1.0) * D
                                     - 2.0 * omega * lam[k] * (lam[k] - 1.0)) / (D * D * D)
    return SLOPE_ROUNDING * n * _EPS * sigma * total


@_jit
def _rounding_scale(L1i, P2, n):
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


@_jit
def _interval_gap(t, slope):
    """``_optimize.interval_gap``."""
    return 0.5 * (abs(slope) + (2.0 * t - 1.0) * slope)


@_jit
def _minimize_interval(a, ca, n, kind, scale):
    """``_optimize.minimize_convex_interval`` for one problem: (omega, iterations)."""
    g0, _ = _pair_derivative(0.0, a, ca, n, kind)
    g1, _ = _pair_derivative(1.0, a, ca, n, kind)
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
        g, h = _pair_derivative(w, a, ca, n, kind)
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


@_jit
def _report(P, R, W, n, kind, out_value, out_log, b):
    """``_criteria.criterion_report`` of one fused covariance; False if P is not
    numerically positive definite (the numpy path then raises its error)."""
    if not _cholesky(P, R, n) or not _numerically_positive_definite(R, n):
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


@_jit
def _pair_item(b, x, P, L, W, kind, out_omega, out_iter, out_gap, out_floor, out_computed,
               out_x, out_P, out_K, out_value, out_log, out_status, work2, work1):
    """One item of :func:`ci_pair_optimal` (``work*``: its scratch arrays)."""
    n = x.shape[2]
    L1i = work2[0]
    S = work2[1]
    Tmp = work2[2]
    U = work2[3]
    T = work2[4]
    K1 = work2[5]
    M1 = work2[6]
    M2 = work2[7]
    Pf = work2[8]
    R = work2[9]
    lam = work1[0]
    a = work1[1]
    c = work1[2]
    ca = work1[3]
    e = work1[4]
    L1 = L[b, 0]
    L2 = L[b, 1]
    _lower_inverse(L1, L1i, n)
    # S = L1^-1 P2 L1^-T, symmetrised
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += L1i[i, k] * P[b, 1, k, j]
            Tmp[i, j] = s
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += Tmp[i, k] * L1i[j, k]
            S[i, j] = s
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (S[i, j] + S[j, i])
            S[i, j] = s
            S[j, i] = s
    if not _jacobi_eigh(S, lam, U, n):
        out_status[b] = 1
        return
    _lower_times(L1, U, T, n)
    usable = True
    lam_lo = math.inf
    lam_hi = -math.inf
    for k in range(n):
        if not (lam[k] > 0.0) or not math.isfinite(lam[k]):
            usable = False
        lam_lo = min(lam_lo, lam[k])
        lam_hi = max(lam_hi, lam[k])
    conditioning = max(_diagonal_spread_squared(L1, n), _diagonal_spread_squared(L2, n))
    if (not usable or not (lam_hi / lam_lo <= DIAGONAL_TRUST)
            or not (conditioning <= DIAGONAL_TRUST)):
        out_status[b] = 1
        return
    for k in range(n):
        a[k] = lam[k] - 1.0
    if kind == KIND_DET:
        scale = float(n)
    else:
        wi = b if W.shape[0] > 1 else 0
        scale = 0.0
        for k in range(n):
            s = 0.0
            if kind == KIND_TRACE:
                for i in range(n):
                    s += T[i, k] * T[i, k]
            else:
                for i in range(n):
                    for j in range(n):
                        s += T[i, k] * W[wi, i, j] * T[j, k]
            c[k] = s
            ca[k] = s * (a[k] + 1.0) * a[k]
        tr2 = 0.0
        tr1 = 0.0
        for k in range(n):
            tr2 += c[k] * (a[k] + 1.0)
            tr1 += c[k]
        scale = tr2 + tr1
    # The rounding of the slope (``_criteria.slope_rounding``, the numpy path's bound).
    sigma = max(lam_hi, _rounding_scale(L1i, P[b, 1], n))
    # A tie to rounding: f' within its rounding of zero at both ends (e.g. P_1 = P_2,
    # whose computed eigenvalues are 1 + O(cond eps)). Which end, or the flat 1/2, the
    # interval search then takes depends on the sign of rounding noise, which differs
    # between the Jacobi eigenvalues here and LAPACK's: the numpy path decides (1/2), so
    # that both backends break the tie alike.
    g0, _ = _pair_derivative(0.0, a, ca, n, kind)
    g1, _ = _pair_derivative(1.0, a, ca, n, kind)
    if (abs(g0) <= _slope_rounding(lam, 0.0, c, n, kind, sigma)
            and abs(g1) <= _slope_rounding(lam, 1.0, c, n, kind, sigma)):
        out_status[b] = 3
        return
    omega, iterations = _minimize_interval(a, ca, n, kind, scale)
    if not math.isfinite(omega):
        omega = 0.5
    slope, _ = _pair_derivative(omega, a, ca, n, kind)
    # the certificate of the numpy path (``_criteria.pair_certificate``)
    rounding = _slope_rounding(lam, omega, c, n, kind, sigma)
    product = 2.0 * _EPS * (abs(slope) + rounding)
    gap = max(_interval_gap(omega, slope - rounding),
              _interval_gap(omega, slope + rounding)) + product
    computed = _interval_gap(omega, slope)
    floor = rounding + product
    if kind != KIND_DET:
        value = 0.0
        for k in range(n):
            value += c[k] * (a[k] + 1.0) / (1.0 + omega * a[k])
        gap = gap / value
        computed = computed / value
        floor = floor / value
    if not gap <= GAP_TOL:  # not certified here (or not finite): the numpy path decides
        out_status[b] = 1
        return
    # assembly (_fuse_diagonalised): K1 = omega T diag(e) (U^T L1^-1)
    if omega == 1.0:
        for i in range(n):
            for j in range(n):
                K1[i, j] = 1.0 if i == j else 0.0
    else:
        for k in range(n):
            e[k] = lam[k] / (1.0 + omega * (lam[k] - 1.0))
        _times_lower(U.T, L1i, Tmp, n)
        for i in range(n):
            for j in range(n):
                s = 0.0
                for k in range(n):
                    s += (T[i, k] * e[k]) * Tmp[k, j]
                K1[i, j] = omega * s
    # M1 = K1 L1 / sqrt(omega), M2 = (I - K1) L2 / sqrt(1 - omega)
    r1 = math.sqrt(omega) if omega > 0.0 else 0.0
    r2 = math.sqrt(1.0 - omega) if omega < 1.0 else 0.0
    for i in range(n):  # Tmp = I - K1 (Tmp is free once K1 is formed)
        for j in range(n):
            Tmp[i, j] = (1.0 if i == j else 0.0) - K1[i, j]
    _times_lower(K1, L1, M1, n)
    _times_lower(Tmp, L2, M2, n)
    for i in range(n):
        for j in range(n):
            M1[i, j] = M1[i, j] / r1 if omega > 0.0 else 0.0
            M2[i, j] = M2[i, j] / r2 if omega < 1.0 else 0.0
            Pf[i, j] = 0.0
    _add_gram(M1, Pf, n)
    _add_gram(M2, Pf, n)
    for i in range(n):
        for j in range(i, n):
            s = 0.5 * (Pf[i, j] + Pf[j, i])
            out_P[b, i, j] = s
            out_P[b, j, i] = s
            Pf[i, j] = s
            Pf[j, i] = s
    for i in range(n):
        s = 0.0
        for k in range(n):
            s += K1[i, k] * (x[b, 0, k] - x[b, 1, k])
        out_x[b, i] = x[b, 1, i] + s
        for j in range(n):
            out_K[b, 0, i, j] = K1[i, j]
            out_K[b, 1, i, j] = (1.0 if i == j else 0.0) - K1[i, j]
    out_omega[b] = omega
    out_iter[b] = iterations
    out_gap[b] = gap
    out_floor[b] = floor
    out_computed[b] = computed
    if kind != KIND_NONE and not _report(Pf, R, W, n, kind, out_value, out_log, b):
        out_status[b] = 2
        return
    out_status[b] = 0


@_jit_parallel
def ci_pair_optimal(x, P, L, W, kind, out_omega, out_iter, out_gap, out_floor, out_computed,
                    out_x, out_P, out_K, out_value, out_log, out_status):
    """Criterion-optimal CI of two estimates per item (``_ci_weights._diagonalised_weights``
    and ``_fuse_diagonalised``), with the criterion report of the fused covariance and the
    certificate's parts (``_criteria.pair_certificate``: gap, floor, computed gap).

    ``out_status``: 0 done; 1 the diagonalisation is not trusted or does not certify the
    tolerance (the numpy path certifies and re-solves from Cholesky factors); 2 the fused
    covariance is not numerically positive definite; 3 a tie to rounding (the numpy path
    breaks it).
    """
    size = x.shape[0]
    n = x.shape[2]
    chunks = (size + _CHUNK - 1) // _CHUNK
    for chunk in prange(chunks):
        work2 = np.empty((10, n, n))
        work1 = np.empty((5, n))
        for b in range(chunk * _CHUNK, min(size, (chunk + 1) * _CHUNK)):
            _pair_item(b, x, P, L, W, kind, out_omega, out_iter, out_gap, out_floor,
                       out_computed, out_x, out_P, out_K, out_value, out_log, out_status,
                       work2, work1)


@_jit
def ci_pair_optimal_serial(x, P, L, W, kind, out_omega, out_iter, out_gap, out_floor,
                           out_computed, out_x, out_P, out_K, out_value, out_log, out_status):
    """:func:`ci_pair_optimal` without threads (small batches)."""
    n = x.shape[2]
    work2 = np.empty((10, n, n))
    work1 = np.empty((5, n))
    for b in range(x.shape[0]):
        _pair_item(b, x, P, L, W, kind, out_omega, out_iter, out_gap, out_floor,
                   out_computed, out_x, out_P, out_K, out_value, out_log, out_status,
                   work2, work1)


@_jit
def _weighted_item(b, x, L, weights, references, W, kind, out_x, out_P, out_K, out_value,
                   out_log, out_status, work2, work1, work3):
    """One item of :func:`weighted_fusion` (``work*``: its scratch arrays)."""
    count = x.shape[1]
    n = x.shape[2]
    J = work2[0]
    R = work2[1]
    Ri = work2[2]
    C = work2[3]
    Bk = work2[4]
    M = work2[5]
    Pf = work2[6]
    rem = work2[7]
    xf = work1[0]
    Li = work3
    for k in range(count):
        _lower_inverse(L[b, k], Li[k], n)
    # J = sum_k w_k L_k^-T L_k^-1 (lower triangle)
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(count):
                t = 0.0
                for m in range(i, n):
                    t += Li[k, m, i] * Li[k, m, j]
                s += weights[b, k] * t
            J[i, j] = s
    if not _cholesky(J, R, n) or not _numerically_positive_definite(R, n):
        out_status[b] = 1
        return
    _lower_inverse(R, Ri, n)
    reference = references[b]
    for i in range(n):
        for j in range(n):
            rem[i, j] = 1.0 if i == j else 0.0
        xf[i] = x[b, reference, i]
    for k in range(count):
        if k == reference:
            continue
        w = weights[b, k]
        # K_k = w_k (B_k L_k^-1), B_k = R^-T C_k, C_k = R^-1 L_k^-T (as numpy)
        _lower_times(Ri, Li[k].T, C, n)
        _times_lower(C.T, Ri, Bk.T, n)  # Bk = Ri^T C, written as its transpose C^T Ri
        _times_lower(Bk, Li[k], M, n)  # M is scratch until the covariance below
        for i in range(n):
            for j in range(n):
                value = w * M[i, j]
                out_K[b, k, i, j] = value
                rem[i, j] -= value
    for i in range(n):
        for j in range(n):
            out_K[b, reference, i, j] = rem[i, j]
    for k in range(count):
        if k == reference:
            continue
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += out_K[b, k, i, j] * (x[b, k, j] - x[b, reference, j])
            xf[i] += s
    for i in range(n):
        for j in range(n):
            Pf[i, j] = 0.0
    for k in range(count):
        w = weights[b, k]
        if not w > 0.0:
            continue
        r = math.sqrt(w)
        _times_lower(out_K[b, k], L[b, k], M, n)
        for i in range(n):
            for j in range(n):
                M[i, j] = M[i, j] / r
        _add_gram(M, Pf, n)
    for i in range(n):
        out_x[b, i] = xf[i]
        for j in range(i, n):
            s = 0.5 * (Pf[i, j] + Pf[j, i])
            out_P[b, i, j] = s
            out_P[b, j, i] = s
            Pf[i, j] = s
            Pf[j, i] = s
    if kind != KIND_NONE and not _report(Pf, R, W, n, kind, out_value, out_log, b):
        out_status[b] = 2
        return
    out_status[b] = 0


@_jit_parallel
def weighted_fusion(x, L, weights, references, W, kind, out_x, out_P, out_K, out_value,
                    out_log, out_status):
    """``_information.weighted_fusion`` per item (any N, given weights), with the criterion
    report of the fused covariance unless ``kind`` is ``KIND_NONE``.

    ``references`` (int64, per item): the estimate whose gain is ``I`` minus the others
    (``_information.reference_estimates``, computed by the caller).

    ``out_status``: 0 done; 1 the fused information is not numerically positive definite;
    2 the fused covariance is not.
    """
    size = x.shape[0]
    n = x.shape[2]
    chunks = (size + _CHUNK - 1) // _CHUNK
    for chunk in prange(chunks):
        work2 = np.empty((8, n, n))
        work1 = np.empty((1, n))
        work3 = np.empty((x.shape[1], n, n))
        for b in range(chunk * _CHUNK, min(size, (chunk + 1) * _CHUNK)):
            _weighted_item(b, x, L, weights, references, W, kind, out_x, out_P, out_K,
                           out_value, out_log, out_status, work2, work1, work3)


@_jit
def weighted_fusion_serial(x, L, weights, references, W, kind, out_x, out_P, out_K,
                           out_value, out_log, out_status):
    """:func:`weighted_fusion` without threads (small batches)."""
    n = x.shape[2]
    work2 = np.empty((8, n, n))
    work1 = np.empty((1, n))
    work3 = np.empty((x.shape[1], n, n))
    for b in range(x.shape[0]):
        _weighted_item(b, x, L, weights, references, W, kind, out_x, out_P, out_K,
                       out_value, out_log, out_status, work2, work1, work3)
