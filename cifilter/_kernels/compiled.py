"""Compiled (numba) kernels of the Covariance Intersection family, one problem per item.

Imported only by :mod:`cifilter._kernels.dispatch` when the numba backend is used (importing
cifilter never imports this module, nor numba). Each kernel is a driver around one per-item function
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

from .._numerics.criteria import GAP_TOL
from .._numerics.information import DIAGONAL_TRUST
from .._numerics.validation import SYMMETRY_RTOL
from .primitives import (
    EPS,
    KIND_DET,
    KIND_NONE,
    KIND_TRACE,
    KIND_WEIGHTED,
    add_gram,
    cholesky,
    diagonal_spread_squared,
    interval_gap,
    jacobi_eigh,
    lower_inverse,
    lower_times,
    minimize_interval,
    numerically_positive_definite,
    pair_derivative,
    report,
    rounding_scale,
    slope_rounding,
    times_lower,
)
from .shift import shift_single

_CHUNK = 128  # items per scratch allocation

# ci_pair's modes (bits) and the columns of its scalar output
MODE_CHECK = 1
MODE_GAINS = 2
S_OMEGA, S_ITERATIONS, S_GAP, S_FLOOR, S_COMPUTED, S_VALUE, S_LOG_VALUE, S_STATUS = range(8)
STATUS_NOT_FINITE = 4
STATUS_NOT_SYMMETRIC = 5
STATUS_NOT_POSITIVE = 6
STATUS_SHIFT = 10  # shifted_pair: 10 plus shift.shift_single's status
NO_OVERFLOW = 2.0**1023  # ``_numerics.validation``: 2 P overflows from here on

_jit = njit(cache=True, error_model="numpy", fastmath=False, nogil=True)
_jit_parallel = njit(cache=True, error_model="numpy", fastmath=False, parallel=True)


@_jit
def _pair_item(b, x, P, L, W, kind, gains, out_s, out_x, out_P, out_K, work2, work1):
    """One item of :func:`ci_pair` on checked, factored input (``work*``: its scratch
    arrays; ``out_s[b]``: the scalars, see :func:`ci_pair`)."""
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
    lower_inverse(L1, L1i, n)
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
    if not jacobi_eigh(S, lam, U, n):
        out_s[b, S_STATUS] = 1
        return
    lower_times(L1, U, T, n)
    usable = True
    lam_lo = math.inf
    lam_hi = -math.inf
    for k in range(n):
        if not (lam[k] > 0.0) or not math.isfinite(lam[k]):
            usable = False
        lam_lo = min(lam_lo, lam[k])
        lam_hi = max(lam_hi, lam[k])
    conditioning = max(diagonal_spread_squared(L1, n), diagonal_spread_squared(L2, n))
    if (not usable or not (lam_hi / lam_lo <= DIAGONAL_TRUST)
            or not (conditioning <= DIAGONAL_TRUST)):
        out_s[b, S_STATUS] = 1
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
    sigma = max(lam_hi, rounding_scale(L1i, P[b, 1], n))
    # A tie to rounding: f' within its rounding of zero at both ends (e.g. P_1 = P_2,
    # whose computed eigenvalues are 1 + O(cond eps)). Which end, or the flat 1/2, the
    # interval search then takes depends on the sign of rounding noise, which differs
    # between the Jacobi eigenvalues here and LAPACK's: the numpy path decides (1/2), so
    # that both backends break the tie alike.
    g0, _ = pair_derivative(0.0, a, ca, n, kind)
    g1, _ = pair_derivative(1.0, a, ca, n, kind)
    if (abs(g0) <= slope_rounding(lam, 0.0, c, n, kind, sigma)
            and abs(g1) <= slope_rounding(lam, 1.0, c, n, kind, sigma)):
        out_s[b, S_STATUS] = 3
        return
    omega, iterations = minimize_interval(a, ca, n, kind, scale)
    if not math.isfinite(omega):
        omega = 0.5
    slope, _ = pair_derivative(omega, a, ca, n, kind)
    # the certificate of the numpy path (``_criteria.pair_certificate``)
    rounding = slope_rounding(lam, omega, c, n, kind, sigma)
    product = 2.0 * EPS * (abs(slope) + rounding)
    gap = max(interval_gap(omega, slope - rounding),
              interval_gap(omega, slope + rounding)) + product
    computed = interval_gap(omega, slope)
    floor = rounding + product
    if kind != KIND_DET:
        value = 0.0
        for k in range(n):
            value += c[k] * (a[k] + 1.0) / (1.0 + omega * a[k])
        gap = gap / value
        computed = computed / value
        floor = floor / value
    if not gap <= GAP_TOL:  # not certified here (or not finite): the numpy path decides
        out_s[b, S_STATUS] = 1
        return
    # assembly (_fuse_diagonalised): K1 = omega T diag(e) (U^T L1^-1)
    if omega == 1.0:
        for i in range(n):
            for j in range(n):
                K1[i, j] = 1.0 if i == j else 0.0
    else:
        for k in range(n):
            e[k] = lam[k] / (1.0 + omega * (lam[k] - 1.0))
        times_lower(U.T, L1i, Tmp, n)
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
    times_lower(K1, L1, M1, n)
    times_lower(Tmp, L2, M2, n)
    for i in range(n):
        for j in range(n):
            M1[i, j] = M1[i, j] / r1 if omega > 0.0 else 0.0
            M2[i, j] = M2[i, j] / r2 if omega < 1.0 else 0.0
            Pf[i, j] = 0.0
    add_gram(M1, Pf, n)
    add_gram(M2, Pf, n)
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
        if gains:
            for j in range(n):
                out_K[b, 0, i, j] = K1[i, j]
                out_K[b, 1, i, j] = (1.0 if i == j else 0.0) - K1[i, j]
    out_s[b, S_OMEGA] = omega
    out_s[b, S_ITERATIONS] = iterations
    out_s[b, S_GAP] = gap
    out_s[b, S_FLOOR] = floor
    out_s[b, S_COMPUTED] = computed
    if kind != KIND_NONE and not report(Pf, R, W, n, kind, out_s[:, S_VALUE],
                                        out_s[:, S_LOG_VALUE], b):
        out_s[b, S_STATUS] = 2
        return
    out_s[b, S_STATUS] = 0


@_jit
def _lapack_cholesky(A, R, n):
    """Lower Cholesky factor of the lower triangle of ``A`` into ``R`` in LAPACK's order
    (``dpotf2``: a dot product, then one subtraction; the column scaled by the reciprocal
    of its diagonal), so that it mostly equals ``dpotrf``'s factor bit for bit (on random
    4x4 matrices 2 in 3 factors, against 1 in 17 for :func:`primitives.cholesky`); False
    if not positive definite. (A candidate for ``primitives``.)"""
    for j in range(n):
        s = 0.0
        for k in range(j):
            s += R[j, k] * R[j, k]
        s = A[j, j] - s
        if not (s > 0.0) or not math.isfinite(s):
            return False
        d = math.sqrt(s)
        R[j, j] = d
        r = 1.0 / d
        for i in range(j):
            R[i, j] = 0.0
        for i in range(j + 1, n):
            t = 0.0
            for k in range(j):
                t += R[i, k] * R[j, k]
            R[i, j] = (A[i, j] - t) * r
    return True


@_jit
def _checked_pair(b, x, P, L, n, out_s):
    """Check item ``b`` of :func:`ci_pair` as the validation does
    (``_numerics.validation``'s single-problem path): finite means, covariances finite with
    entries below ``2**1023``, symmetric within ``SYMMETRY_RTOL`` (symmetrised in place as
    ``(P + P^T) * 0.5`` when not exactly symmetric) and Cholesky-factorisable, with finite
    factors, written to ``L[b]``. False (with a status) when a test fails."""
    for i in range(2):
        for k in range(n):
            if not math.isfinite(x[b, i, k]):
                out_s[b, S_STATUS] = STATUS_NOT_FINITE
                return False
        exact = True
        asymmetry = 0.0
        scale = 0.0
        for r in range(n):
            for c in range(n):
                if not abs(P[b, i, r, c]) < NO_OVERFLOW:  # (NaN fails too)
                    out_s[b, S_STATUS] = STATUS_NOT_FINITE
                    return False
        for r in range(n):
            scale = max(scale, abs(P[b, i, r, r]))
            for c in range(r + 1, n):
                d = abs(P[b, i, r, c] - P[b, i, c, r])
                if d != 0.0:
                    exact = False
                asymmetry = max(asymmetry, d)
        if not exact:
            if asymmetry > SYMMETRY_RTOL * scale:
                out_s[b, S_STATUS] = STATUS_NOT_SYMMETRIC
                return False
            for r in range(n):
                for c in range(r + 1, n):
                    s = (P[b, i, r, c] + P[b, i, c, r]) * 0.5
                    P[b, i, r, c] = s
                    P[b, i, c, r] = s
        if not _lapack_cholesky(P[b, i], L[b, i], n):
            out_s[b, S_STATUS] = STATUS_NOT_POSITIVE
            return False
        for r in range(n):
            for c in range(r + 1):
                if not math.isfinite(L[b, i, r, c]):
                    out_s[b, S_STATUS] = STATUS_NOT_POSITIVE
                    return False
    return True


@_jit
def _pair_items(start, stop, x, P, L, W, kind, mode, out_s, out_x, out_P, out_K):
    """Items ``start`` to ``stop`` of :func:`ci_pair` (scratch allocated once)."""
    n = x.shape[2]
    work2 = np.empty((10, n, n))
    work1 = np.empty((5, n))
    for b in range(start, stop):
        if mode & MODE_CHECK and not _checked_pair(b, x, P, L, n, out_s):
            continue
        _pair_item(b, x, P, L, W, kind, mode & MODE_GAINS != 0, out_s, out_x, out_P, out_K,
                   work2, work1)


@_jit_parallel
def ci_pair(x, P, L, W, kind, mode, out_s, out_x, out_P, out_K):
    """Criterion-optimal CI of two estimates per item (``_ci_weights._diagonalised_weights``
    and ``_fuse_diagonalised``), with the criterion report of the fused covariance and the
    certificate's parts (``_criteria.pair_certificate``: gap, floor, computed gap).

    ``x`` (B, 2, n), ``P`` and ``L`` (B, 2, n, n); ``mode``: ``MODE_CHECK`` checks and
    factors the raw input first (``P`` symmetrised in place, ``L`` written; see
    :func:`_checked_pair`), else ``L`` holds the Cholesky factors of ``P``; ``MODE_GAINS``
    writes the gains into ``out_K`` (B, 2, n, n) (else it is not touched and may be empty).
    ``out_s`` (B, 8): per item omega, iterations, gap, floor, computed gap, value, log value
    and status (columns ``S_*``): 0 done; 1 the diagonalisation is not trusted or does not
    certify the tolerance (the numpy path certifies and re-solves from Cholesky factors); 2
    the fused covariance is not numerically positive definite; 3 a tie to rounding (the
    numpy path breaks it); with ``MODE_CHECK`` 4 a value is not finite (or too large), 5 a
    covariance is not symmetric, 6 not positive definite (the validation explains).
    """
    size = x.shape[0]
    chunks = (size + _CHUNK - 1) // _CHUNK
    for chunk in prange(chunks):
        _pair_items(chunk * _CHUNK, min(size, (chunk + 1) * _CHUNK), x, P, L, W, kind, mode,
                    out_s, out_x, out_P, out_K)


@_jit
def ci_pair_serial(x, P, L, W, kind, mode, out_s, out_x, out_P, out_K):
    """:func:`ci_pair` without threads (small batches and single calls)."""
    _pair_items(0, x.shape[0], x, P, L, W, kind, mode, out_s, out_x, out_P, out_K)


@_jit
def shifted_pair(x, P, moved, M, N, backward, W, kind, mode, out_s, out_x, out_P, out_K):
    """:func:`ci_pair_serial` of one pair whose estimate ``moved`` (0 or 1) is first brought
    by ``M``, ``N`` (:func:`cifilter._kernels.shift.shift_single`: checked, then
    ``M P M^T + N`` forward or the retrodiction bound back), in one call: the short way of
    ``kf.fuse(other, lag=k)``.

    ``x`` (1, 2, n) and ``P`` (1, 2, n, n) are the caller's copies (the moved estimate is
    replaced in them), ``M``, ``N`` (n, n), ``backward`` a bool, the rest as
    :func:`ci_pair_serial`'s. Returns the retrodiction's split ``alpha`` (1.0 forward).
    ``out_s[0, S_STATUS]`` is :data:`STATUS_SHIFT` plus ``shift_single``'s status when the
    shift fails (then nothing else is written), else the pair's status.
    """
    n = x.shape[2]
    L = np.empty((1, 2, n, n))
    x_moved, P_moved = np.empty(n), np.empty((n, n))
    status, alpha = shift_single(x[0, moved], P[0, moved], M, N, backward, L[0, 0],
                                 x_moved, P_moved)
    if status != 0:
        out_s[0, S_STATUS] = STATUS_SHIFT + status
        return alpha
    for i in range(n):
        x[0, moved, i] = x_moved[i]
        for j in range(n):
            P[0, moved, i, j] = P_moved[i, j]
    # (the private driver, not the kernel ci_pair_serial: a kernel loaded from numba's
    # cache cannot be linked into a function compiled afresh in the same process)
    _pair_items(0, 1, x, P, L, W, kind, mode, out_s, out_x, out_P, out_K)
    return alpha


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
        lower_inverse(L[b, k], Li[k], n)
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
    if not cholesky(J, R, n) or not numerically_positive_definite(R, n):
        out_status[b] = 1
        return
    lower_inverse(R, Ri, n)
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
        lower_times(Ri, Li[k].T, C, n)
        times_lower(C.T, Ri, Bk.T, n)  # Bk = Ri^T C, written as its transpose C^T Ri
        times_lower(Bk, Li[k], M, n)  # M is scratch until the covariance below
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
        times_lower(out_K[b, k], L[b, k], M, n)
        for i in range(n):
            for j in range(n):
                M[i, j] = M[i, j] / r
        add_gram(M, Pf, n)
    for i in range(n):
        out_x[b, i] = xf[i]
        for j in range(i, n):
            s = 0.5 * (Pf[i, j] + Pf[j, i])
            out_P[b, i, j] = s
            out_P[b, j, i] = s
            Pf[i, j] = s
            Pf[j, i] = s
    if kind != KIND_NONE and not report(Pf, R, W, n, kind, out_value, out_log, b):
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


# --------------------------------------------------------------------------- N >= 3
# The active-set Newton method of ``_optimize.minimize_convex_simplex`` (its phase 2, which
# runs alone below ``INTERIOR_MIN_COUNT`` estimates) for one problem, on the factors of
# ``_information.information_factors``, stopped at the same certified gap
# (``gtol = GAP_TOL / 4`` relative to ``|f|``, absolute for det), and certified at the end
# with the numpy path's certificate (``_criteria.gradient_rounding``,
# ``_criteria.gap_certificate``). Where that certificate does not reach ``GAP_TOL``, where
# the weights are not determined to ``_WEIGHT_AGREEMENT`` by the rounding of the gradients
# (a nearly singular reduced Hessian: ties, nearly flat criteria), or where a step or a
# factorisation fails, the item is handed back to the numpy path, which decides as always.
_MANY_MAX_ITER = 200
_MANY_GTOL = 0.25 * GAP_TOL
# An item is kept only where ||H_r^-1||_F r <= this: r the bound of the gradients'
# rounding, H_r the Hessian reduced to the face of the positive weights, so the weights
# move by at most about this under that rounding (on either backend): both agree to it.
_WEIGHT_AGREEMENT = 1e-10
_RCOND = 1e-13  # ``_optimize._RCOND``


@_jit
def _many_information(Li, w, count, n, J, R, Ri):
    """J = sum_k w_k L_k^-T L_k^-1 (lower triangle), its Cholesky factor R and R^-1;
    False where J is not numerically positive definite."""
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(count):
                if w[k] == 0.0:
                    continue
                t = 0.0
                for m in range(i, n):
                    t += Li[k, m, i] * Li[k, m, j]
                s += w[k] * t
            J[i, j] = s
    if not cholesky(J, R, n) or not numerically_positive_definite(R, n):
        return False
    lower_inverse(R, Ri, n)
    return True


@_jit
def _many_value(Ri, W, wi, n, kind):
    """``_criteria.criterion_of_factor``: trace(W P) or log det P for P = Ri^T Ri."""
    value = 0.0
    if kind == KIND_DET:
        for i in range(n):
            value += math.log(abs(Ri[i, i]))
        return 2.0 * value
    if kind == KIND_TRACE:
        for i in range(n):
            for j in range(i + 1):
                value += Ri[i, j] * Ri[i, j]
        return value
    for k in range(n):
        for i in range(n):
            for j in range(n):
                value += W[wi, i, j] * Ri[k, i] * Ri[k, j]
    return value


@_jit
def _many_evaluate(Li, w, W, wi, count, n, kind, J, R, Ri, C, B, G, V, g, H, hessian):
    """f, and g_k = -df/dw_k, H (``_ci_weights._simplex_weights``'s evaluate) at w.

    C_k = R^-1 L_k^-T, B_k = R^-T C_k; trace: g_k = ||B_k||^2, H_ij = 2 <B_i C_i^T, B_j C_j^T>;
    weighted: g_k = trace(W B_k B_k^T), H_ij = <G_i, W G_j> + <G_j, W G_i> with G = B C^T
    (the symmetrised ``2 trace_curvature``); det: g_k = ||C_k||^2, H_ij = <C_i C_i^T, C_j C_j^T>.
    Returns (ok, f).
    """
    if not _many_information(Li, w, count, n, J, R, Ri):
        return False, 0.0
    f = _many_value(Ri, W, wi, n, kind)
    if not hessian:
        return True, f
    for k in range(count):
        for i in range(n):
            for j in range(n):
                s = 0.0
                for m in range(min(i, j) + 1):
                    s += Ri[i, m] * Li[k, j, m]
                C[k, i, j] = s
        for i in range(n):
            for j in range(n):
                s = 0.0
                for m in range(i, n):
                    s += Ri[m, i] * C[k, m, j]
                B[k, i, j] = s
        s = 0.0
        if kind == KIND_DET:
            for i in range(n):
                for j in range(n):
                    s += C[k, i, j] * C[k, i, j]
        elif kind == KIND_TRACE:
            for i in range(n):
                for j in range(n):
                    s += B[k, i, j] * B[k, i, j]
        else:
            for i in range(n):
                for j in range(n):
                    t = 0.0
                    for m in range(n):
                        t += B[k, i, m] * B[k, j, m]
                    s += W[wi, i, j] * t
        g[k] = s
        # G_k = B_k C_k^T (trace criteria) or C_k C_k^T (det); V_k = W G_k (weighted)
        left = C[k] if kind == KIND_DET else B[k]
        for i in range(n):
            for j in range(n):
                s = 0.0
                for m in range(n):
                    s += left[i, m] * C[k, j, m]
                G[k, i, j] = s
        if kind == KIND_WEIGHTED:
            for i in range(n):
                for j in range(n):
                    s = 0.0
                    for m in range(n):
                        s += W[wi, i, m] * G[k, m, j]
                    V[k, i, j] = s
    factor = 1.0 if kind == KIND_DET else 2.0
    for a in range(count):
        for b in range(a + 1):
            s = 0.0
            if kind == KIND_WEIGHTED:
                for i in range(n):
                    for j in range(n):
                        s += 0.5 * (G[a, i, j] * V[b, i, j] + G[b, i, j] * V[a, i, j])
            else:
                for i in range(n):
                    for j in range(n):
                        s += G[a, i, j] * G[b, i, j]
            H[a, b] = factor * s
            H[b, a] = factor * s
    return True, f


@_jit
def _reduced_newton(H, g, free, w, count, Hr, Lr, rhs, d, index, spread):
    """The Newton step on the face of the free weights, in the coordinates of all free
    weights but the pivot p (the largest free weight; d_p = -sum of the others):
    H_r d_r = g_r with H_r = Z^T H Z, g_r = g_i - g_p. Returns (ok, mu, ||H_r^-1||_F);
    mu = g_p - (H d)_p is the common gradient level of the face. ok False where H_r is not
    numerically positive definite, or where the squared diagonal spread of its Cholesky
    factor (a lower bound of its condition number) exceeds ``spread``."""
    p = -1
    for i in range(count):
        if free[i] and (p < 0 or w[i] > w[p]):
            p = i
    for i in range(count):
        d[i] = 0.0
    k = 0
    for i in range(count):
        if free[i] and i != p:
            index[k] = i
            k += 1
    inverse_norm = 0.0
    if k > 0:
        for a in range(k):
            i = index[a]
            rhs[a] = g[i] - g[p]
            for b in range(k):
                j = index[b]
                Hr[a, b] = H[i, j] - H[i, p] - H[p, j] + H[p, p]
        if not cholesky(Hr, Lr, k) or not numerically_positive_definite(Lr, k):
            return False, 0.0, math.inf
        if not diagonal_spread_squared(Lr, k) <= spread:
            return False, 0.0, math.inf
        # solve Lr Lr^T y = rhs
        for a in range(k):
            s = rhs[a]
            for b in range(a):
                s -= Lr[a, b] * rhs[b]
            rhs[a] = s / Lr[a, a]
        for a in range(k - 1, -1, -1):
            s = rhs[a]
            for b in range(a + 1, k):
                s -= Lr[b, a] * rhs[b]
            rhs[a] = s / Lr[a, a]
        total = 0.0
        for a in range(k):
            d[index[a]] = rhs[a]
            total += rhs[a]
        d[p] = -total
        # ||H_r^-1||_F = ||Lr^-1||_F^2 at most: Lr^-1 into Hr (free now)
        lower_inverse(Lr, Hr, k)
        for a in range(k):
            for b in range(a + 1):
                inverse_norm += Hr[a, b] * Hr[a, b]
    s = 0.0
    for j in range(count):
        s += H[p, j] * d[j]
    return True, g[p] - s, inverse_norm


@_jit
def _pinv_newton(H, g, free, count, kkt, vectors, lam, rhs, solution, d):
    """``_optimize._face_newton`` (without compression) for one problem: the minimum-norm
    solution of the normalised KKT system ``[H_FF / c, 1; 1^T, 0] [d; nu] = [g_F / c; 0]``
    (identity rows for the fixed weights) by its pseudo-inverse with numpy's cut-off
    ``1e-13`` of the largest eigenvalue (a symmetric matrix: its singular values are the
    eigenvalues' moduli), so that directions in which f is flat get no step. Returns
    (ok, mu) with mu = nu c, the common gradient level of the face."""
    curvature = 0.0
    for i in range(count):
        if free[i]:
            curvature = max(curvature, H[i, i])
    curvature = max(curvature, 2.2250738585072014e-308)
    m = count + 1
    for i in range(count):
        for j in range(count):
            if free[i] and free[j]:
                kkt[i, j] = H[i, j] / curvature
            else:
                kkt[i, j] = 1.0 if (i == j and not free[i]) else 0.0
        kkt[i, count] = 1.0 if free[i] else 0.0
        kkt[count, i] = kkt[i, count]
        rhs[i] = g[i] / curvature if free[i] else 0.0
    kkt[count, count] = 0.0
    rhs[count] = 0.0
    if not jacobi_eigh(kkt, lam, vectors, m):
        return False, 0.0
    top = 0.0
    for k in range(m):
        top = max(top, abs(lam[k]))
    for i in range(m):
        solution[i] = 0.0
    for k in range(m):
        if abs(lam[k]) > _RCOND * top:
            s = 0.0
            for i in range(m):
                s += vectors[i, k] * rhs[i]
            s /= lam[k]
            for i in range(m):
                solution[i] += vectors[i, k] * s
    for i in range(count):
        d[i] = solution[i] if free[i] else 0.0
    return True, solution[count] * curvature


@_jit
def _scaled_condition(A, Ai, n):
    """``_criteria.scaled_condition`` of one triangular factor and its inverse."""
    total = 0.0
    for j in range(n):
        r = 0.0
        for m in range(n):
            r += A[j, m] * A[j, m]
        r = math.sqrt(r)
        for i in range(n):
            t = Ai[i, j] * r
            total += t * t
    return n * total


@_jit
def _many_item(b, x, L, W, kind, out_w, out_iter, out_gap, out_floor, out_computed, out_x,
               out_P, out_K, out_value, out_log, out_status, references, Li, C, B, G, V,
               work2, work1, workN, workNN, free, index, work3):
    """One item of :func:`ci_many_optimal` (the rest: its scratch arrays)."""
    count = x.shape[1]
    n = x.shape[2]
    wi = b if W.shape[0] > 1 else 0
    J = work2[0]
    R = work2[1]
    Ri = work2[2]
    w = workN[0]
    g = workN[1]
    d = workN[2]
    trial = workN[3]
    rhs = workN[4]
    gt = workN[5]
    lam = workN[6]
    solution = workN[7]
    previous_d = workN[8]
    H = workNN[0]
    Hr = workNN[1]
    Lr = workNN[2]
    kkt = workNN[3]
    vectors = workNN[4]
    out_status[b] = 1  # handed back unless certified below
    kappa_inputs = 0.0
    for k in range(count):
        lower_inverse(L[b, k], Li[k], n)
        kappa_inputs = max(kappa_inputs, _scaled_condition(L[b, k], Li[k], n))
    for k in range(count):
        w[k] = 1.0 / count
        free[k] = True
    iterations = 0
    certified = False
    f = 0.0
    previous_gap = math.inf
    previous_last = False
    previous_t = 0.0
    previous_slope = 0.0
    evaluate = True
    for _ in range(2 * _MANY_MAX_ITER + 2):
        if evaluate:
            ok, f = _many_evaluate(Li, w, W, wi, count, n, kind, J, R, Ri, C, B, G, V, g, H,
                                   True)
            if not ok or not math.isfinite(f):
                return
        evaluate = True
        along = 0.0
        top = -math.inf
        g_scale = 0.0
        for k in range(count):
            along += w[k] * g[k]
            top = max(top, g[k])
            g_scale = max(g_scale, abs(g[k]))
        gap = max(top - along, 0.0)
        f_scale = max(abs(f), 1.0) if kind == KIND_DET else abs(f)
        if gap <= _MANY_GTOL * (1.0 if kind == KIND_DET else abs(f)):
            certified = True
            break
        if iterations >= _MANY_MAX_ITER:
            return
        # After a step that kept more than half of its slope along its direction (f nearly
        # linear there, the Hessian overstating its curvature), numpy continues along the
        # same line by the secant of the derivative, up to the boundary (its "extend").
        extend = False
        now = 0.0
        if previous_t > 0.0 and -previous_slope > 64.0 * EPS * f_scale:
            for k in range(count):
                now -= g[k] * previous_d[k]
            extend = now < 0.5 * previous_slope
        ok, mu, _ = _reduced_newton(H, g, free, w, count, Hr, Lr, rhs, d, index, 1e10)
        if not ok:  # a singular face (more weights than the criterion resolves): pinv
            ok, mu = _pinv_newton(H, g, free, count, kkt, vectors, lam, rhs, solution, d)
            if not ok:
                return
        if extend:
            for k in range(count):
                d[k] = previous_d[k]
        step = 0.0
        slope = 0.0  # of f along d: -g.d
        for k in range(count):
            step = max(step, abs(d[k]))
            slope -= g[k] * d[k]
        small_step = step < 1e-12 and not extend
        rounding = -slope <= 2.5e-13 * f_scale and not extend
        # release every fixed weight (tied to rounding) whose gradient lies furthest
        # above the level of the free ones, once the face is solved (as numpy)
        most = 0.0
        for k in range(count):
            if not free[k]:
                most = max(most, g[k] - mu)
        release = most > 1e-12 * g_scale
        iterations += 1
        if (small_step or rounding) and release:
            for k in range(count):
                if not free[k] and g[k] - mu > 1e-12 * g_scale and (
                        g[k] - mu >= most * (1.0 - 1e-9)):
                    free[k] = True
            previous_t = 0.0
            previous_last = False
            evaluate = False  # the same point: the next iteration solves the larger face
            continue
        last = False
        if small_step or rounding:
            # a step at the rounding level is taken unchecked (numpy's "last"); a zero
            # step, or one that did not halve the gap, is where numpy turns to
            # Frank-Wolfe: handed back
            if step <= 4.0 * EPS or (previous_last and not gap <= 0.5 * previous_gap):
                return
            last = True
        elif not (slope < 0.0):
            return
        t_max = math.inf
        for k in range(count):
            if free[k] and d[k] < 0.0:
                t_max = min(t_max, w[k] / -d[k])
        if not (t_max > 0.0):
            # blocked at zero (a weight just released): a step towards the vertices of the
            # largest gradient, as numpy
            shares = 0
            for k in range(count):
                if g[k] >= top - 1e-12 * g_scale:
                    shares += 1
            slope = 0.0
            for k in range(count):
                target = 0.0
                if g[k] >= top - 1e-12 * g_scale:
                    target = 1.0 / shares
                    free[k] = True
                d[k] = target - w[k]
                slope -= g[k] * d[k]
            t_max = math.inf
            for k in range(count):
                if free[k] and d[k] < 0.0:
                    t_max = min(t_max, w[k] / -d[k])
            if not (t_max > 0.0) or not (slope < 0.0):
                return
        t = min(1.0, t_max)
        if extend:
            further = t_max
            if now > previous_slope:
                further = previous_t * now / (previous_slope - now)
            if math.isnan(further):
                further = 0.0
            t = min(max(further, 0.0), t_max)
        if not last:
            accepted = False
            for _search in range(60):
                for k in range(count):
                    trial[k] = max(w[k] + t * d[k], 0.0)
                ok, f_trial = _many_evaluate(Li, trial, W, wi, count, n, kind, J, R, Ri, C,
                                             B, G, V, gt, H, False)
                if ok and f_trial <= f + 1e-4 * t * slope + 1e-15 * abs(f):
                    accepted = True
                    break
                t *= 0.5
            if not accepted:
                return
        blocked = t == t_max
        previous_t = t if not (blocked or last) else 0.0
        previous_slope = slope
        previous_last = last
        previous_gap = gap
        total = 0.0
        for k in range(count):
            previous_d[k] = d[k]  # the direction, for the extension test above
            value = max(w[k] + t * d[k], 0.0)
            if blocked and free[k] and d[k] < 0.0 and w[k] / -d[k] == t_max:
                value = 0.0
                free[k] = False
            w[k] = value
            total += value
        for k in range(count):
            w[k] /= total
    if not certified:
        return
    # the certificate of the numpy path at these weights (``_fuse_and_certify``): f, g, R
    # and R^-1 are those of the last evaluation, at w
    g_max = 0.0
    along = 0.0
    for k in range(count):
        g_max = max(g_max, abs(g[k]))
        along += w[k] * g[k]
    kappa = _scaled_condition(R, Ri, n) + kappa_inputs
    r = 4.0 * (n + 1) * EPS * kappa * g_max
    top = -math.inf
    shifted = -math.inf
    for k in range(count):
        top = max(top, g[k])
        shifted = max(shifted, g[k] + 2.0 * r * (1.0 - w[k]))
    summed = count * EPS * abs(along)
    computed = max(top - along, 0.0)
    gap = max(shifted - along, 0.0) + summed
    floor = 2.0 * r + summed
    if kind != KIND_DET:
        gap /= f
        floor /= f
        computed /= f
    if not gap <= GAP_TOL:
        return
    # the weights must be determined by the gradients to _WEIGHT_AGREEMENT (both backends
    # then return them to it): the Hessian reduced to the face of the positive weights
    for k in range(count):
        free[k] = w[k] > 0.0
    ok, _, inverse_norm = _reduced_newton(H, g, free, w, count, Hr, Lr, rhs, d, index,
                                          math.inf)
    if not ok or not inverse_norm * r <= _WEIGHT_AGREEMENT:
        return
    out_iter[b] = iterations
    out_gap[b] = gap
    out_floor[b] = floor
    out_computed[b] = computed
    # the reference estimate (``_information.reference_estimates``) and the fusion
    best = -1
    best_precision = -math.inf
    for k in range(count):
        out_w[b, k] = w[k]
        precision = -1.0
        if w[k] > 0.0:
            s = 0.0
            for i in range(n):
                for j in range(i + 1):
                    s += L[b, k, i, j] * L[b, k, i, j]
            precision = w[k] / s
            if not math.isfinite(precision):
                precision = 0.0 if math.isnan(precision) else 1.7976931348623157e308
        if precision > best_precision:
            best_precision = precision
            best = k
    references[b] = best
    _weighted_item(b, x, L, out_w, references, W, kind, out_x, out_P, out_K, out_value,
                   out_log, out_status, work2, work1, work3)
    if out_status[b] != 0:
        out_status[b] = 2


@_jit_parallel
def ci_many_optimal(x, L, W, kind, out_w, out_iter, out_gap, out_floor, out_computed, out_x,
                    out_P, out_K, out_value, out_log, out_status, references):
    """Criterion-optimal CI of N >= 3 estimates per item (``_ci_weights._simplex_weights``,
    the active-set phase, and ``_fuse_and_certify``), with the certificate's parts and the
    criterion report of the fused covariance.

    ``out_status``: 0 done; 1 not certified here (the numpy path solves the item); 2 the
    fused information or covariance at the weights is not numerically positive definite.
    """
    size = x.shape[0]
    count = x.shape[1]
    n = x.shape[2]
    chunks = (size + _CHUNK - 1) // _CHUNK
    for chunk in prange(chunks):
        Li = np.empty((count, n, n))
        C = np.empty((count, n, n))
        B = np.empty((count, n, n))
        G = np.empty((count, n, n))
        V = np.empty((count, n, n))
        work2 = np.empty((8, n, n))
        work1 = np.empty((1, n))
        workN = np.empty((9, count + 1))
        workNN = np.empty((5, count + 1, count + 1))
        free = np.empty(count, dtype=np.bool_)
        index = np.empty(count, dtype=np.int64)
        work3 = np.empty((count, n, n))
        for b in range(chunk * _CHUNK, min(size, (chunk + 1) * _CHUNK)):
            _many_item(b, x, L, W, kind, out_w, out_iter, out_gap, out_floor, out_computed,
                       out_x, out_P, out_K, out_value, out_log, out_status, references, Li,
                       C, B, G, V, work2, work1, workN, workNN, free, index, work3)


@_jit
def ci_many_optimal_serial(x, L, W, kind, out_w, out_iter, out_gap, out_floor, out_computed,
                           out_x, out_P, out_K, out_value, out_log, out_status, references):
    """:func:`ci_many_optimal` without threads (small batches)."""
    count = x.shape[1]
    n = x.shape[2]
    Li = np.empty((count, n, n))
    C = np.empty((count, n, n))
    B = np.empty((count, n, n))
    G = np.empty((count, n, n))
    V = np.empty((count, n, n))
    work2 = np.empty((8, n, n))
    work1 = np.empty((1, n))
    workN = np.empty((9, count + 1))
    workNN = np.empty((5, count + 1, count + 1))
    free = np.empty(count, dtype=np.bool_)
    index = np.empty(count, dtype=np.int64)
    work3 = np.empty((count, n, n))
    for b in range(x.shape[0]):
        _many_item(b, x, L, W, kind, out_w, out_iter, out_gap, out_floor, out_computed,
                   out_x, out_P, out_K, out_value, out_log, out_status, references, Li, C, B,
                   G, V, work2, work1, workN, workNN, free, index, work3)
