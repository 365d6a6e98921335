"""Compiled (numba) generalised CI of one full-state and one partial estimate (``H=``).

The pair that ``kf.fuse(other, H=H)`` produces: estimate ``a`` of the full state ``x``
(``x_a``, ``P_a = L_a L_a^T``, n x n) and estimate ``b`` of ``H x`` (``x_b``,
``P_b = L_b L_b^T``, m x m, ``H`` m x n with ``m <= n``). The kernel runs the method of
:func:`cifilter.rules._generalised_ci.generalised_ci`'s diagonalised pair path
(``docs/methods/partial_state.rst``, eqs. (H4), (H7), (H8)) in one compiled call:

* whitening by ``L_a``: the partial information becomes ``G^T G`` with
  ``G = L_b^-1 H L_a`` (m x n, rank m), whose singular value decomposition
  ``G = V S U^T`` comes from one-sided (Hestenes) Jacobi rotations of the rows of ``G``
  (no Gram matrix is formed, so the small singular values keep their relative accuracy
  and no condition number is squared);
* the weight ``w`` of ``a`` minimises ``sum_k c_k / (mu_k + w (1 - mu_k))`` (trace, or
  ``tr(W P)``) or ``-sum_k c_k log(mu_k + w (1 - mu_k))`` (log det) over [0, 1],
  ``mu_k = s_k^2``, the ``n - m`` directions beyond the rank (``mu = 0``) as one term: the
  same safeguarded Newton iteration as
  :func:`cifilter._numerics.optimize.minimize_convex_scalar` and the same certified gap
  (:func:`cifilter._numerics.optimize.interval_gap`, relative to the criterion for the
  trace criteria);
* the gains (H8) ``K_b = (1 - w) L_a U diag(d) S V^T L_b^-1``, ``K_a = I - K_b H``, the
  fused mean ``x_a + K_b (x_b - H x_a)`` and ``P = (K_a L_a)(K_a L_a)^T / w +
  (K_b L_b)(K_b L_b)^T / (1 - w)``, the bound of these gains (H4), exactly symmetric, and
  its criterion report from its Cholesky factor.

Where the numpy path would not take its diagonalised path (the nonzero ``mu`` or the
squared diagonals of either factor spread beyond
:data:`cifilter._numerics.information.DIAGONAL_TRUST`), or the result is not numerically
positive definite, or ``m > n``, :func:`partial_pair` returns None and the caller runs the
numpy path, which decides, re-solves or raises its usual error.

Imported only when the kernel runs (importing cifilter never imports numba).
"""

import math
from typing import Any, Optional

import numpy as np

from .._numerics.criteria import GAP_TOL
from .._numerics.information import DIAGONAL_TRUST
from .primitives import (
    EPS,
    KIND_DET,
    KIND_TRACE,
    KIND_WEIGHTED,
    diagonal_spread_squared,
    interval_gap,
    jacobi_rotation,
    jit,
    lower_inverse,
    lower_times,
    report,
    times_lower,
)

__all__ = ["generalised_pair", "partial_pair"]

_XTOL = 1e-13  # minimize_convex_scalar's defaults
_MAX_ITER = 100
_SWEEPS = 60
_NO_OVERFLOW = 2.0**1023  # (P + P^T overflows from here on: the validation decides)
_KINDS = {"trace": KIND_TRACE, "det": KIND_DET, "weighted-trace": KIND_WEIGHTED}


@jit
def _rows_svd(G, V, m, n):
    """One-sided Jacobi on the rows of G (m x n, m <= n), in place: afterwards the rows
    of G are orthogonal and ``G_in = V G`` (V m x m orthogonal), so the singular values are
    the row norms and the right singular vectors the normalised rows. A pair of rows is
    rotated while ``|g_p . g_q| > eps ||g_p|| ||g_q||``. False if the sweeps do not
    converge."""
    for i in range(m):
        for j in range(m):
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(_SWEEPS):
        rotated = False
        for p in range(m - 1):
            for q in range(p + 1, m):
                alpha = 0.0
                beta = 0.0
                gamma = 0.0
                for k in range(n):
                    alpha += G[p, k] * G[p, k]
                    beta += G[q, k] * G[q, k]
                    gamma += G[p, k] * G[q, k]
                if abs(gamma) <= EPS * math.sqrt(alpha) * math.sqrt(beta):
                    continue
                rotated = True
                _, c, s = jacobi_rotation((beta - alpha) / (2.0 * gamma))
                for k in range(n):
                    gp = G[p, k]
                    gq = G[q, k]
                    G[p, k] = c * gp - s * gq
                    G[q, k] = s * gp + c * gq
                for k in range(m):
                    vp = V[k, p]
                    vq = V[k, q]
                    V[k, p] = c * vp - s * vq
                    V[k, q] = s * vp + c * vq
        if not rotated:
            return True
    return False


@jit
def _derivative(w, mu, one_minus, c, q, det):
    """``(f', f'')`` of the pair's criterion at ``w`` (``_generalised_ci``'s
    ``_trace_derivative`` / ``_log_det_derivative``); ``(-inf, inf)`` where a denominator
    is not positive."""
    slope = 0.0
    curvature = 0.0
    for k in range(q):
        den = mu[k] + w * one_minus[k]
        if den <= 0.0:
            return -math.inf, math.inf
        ad = one_minus[k] / den
        if det:
            term = c[k] * ad
            slope -= term
            curvature += term * ad
        else:
            term = c[k] * ad / den
            slope -= term
            curvature += 2.0 * term * ad
    return slope, curvature


@jit
def _minimize(mu, one_minus, c, q, det, scale):
    """:func:`cifilter._numerics.optimize.minimize_convex_scalar` on :func:`_derivative`:
    ``(w, iterations)``."""
    g0, _ = _derivative(0.0, mu, one_minus, c, q, det)
    g1, _ = _derivative(1.0, mu, one_minus, c, q, det)
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
    for iteration in range(1, _MAX_ITER + 1):
        g, h = _derivative(w, mu, one_minus, c, q, det)
        if g < 0.0:
            lo = w
        elif g > 0.0:
            hi = w
        if h != 0.0:
            step = -g / h
        elif g != 0.0:
            step = math.copysign(math.inf, -g)
        else:
            step = math.nan
        newton = w + step
        settled = abs(step) < _XTOL or g == 0.0
        if lo < newton < hi and math.isfinite(newton):
            w = newton
        elif not settled:
            w = 0.5 * (lo + hi)
        if settled or hi - lo < _XTOL:
            return w, iteration
    return w, _MAX_ITER


@jit
def _checked(x, P, L, m):
    """The checks of the validation (``_numerics.alignment``'s single estimates) on one raw
    estimate whose covariance was factored by LAPACK as it is: finite mean, covariance
    entries finite and below ``2**1023``, exactly symmetric (a covariance asymmetric within
    the tolerance is left to the validation, which symmetrises it), and a finite factor.
    The status: 0 passed, 3 not finite, 4 not exactly symmetric, 5 a factor that is not
    finite (the validation then decides, or raises its error)."""
    for k in range(m):
        if not math.isfinite(x[k]):
            return 3
    for i in range(m):
        for j in range(m):
            if not abs(P[i, j]) < _NO_OVERFLOW:  # (NaN fails too)
                return 3
        for j in range(i):
            if P[i, j] != P[j, i]:
                return 4
    for i in range(m):
        for j in range(i + 1):
            if not math.isfinite(L[i, j]):
                return 5
    return 0


@jit
def generalised_pair(xa, Pa, La, xb, Pb, Lb, H, W, kind, check, out_x, out_P, out_Ka, out_Kb,
                     out_info):
    """Generalised CI of a full-state estimate ``a`` and a partial one ``b`` (one problem).

    ``xa`` (n), ``Pa``, ``La`` (n, n) and ``xb`` (m), ``Pb``, ``Lb`` (m, m): the means,
    covariances and lower Cholesky factors; ``H`` (m, n), ``m <= n``; ``W`` (1, n, n) the
    weight matrix of ``kind == KIND_WEIGHTED`` (else unused); every array C-contiguous
    float64. With ``check`` the raw means and covariances and the factors are checked first
    (:func:`_checked`); without, the estimates are validated ones (``Pa``, ``Pb`` are not
    read). Writes the fused mean ``out_x`` (n),
    ``out_P`` (n, n), the gains ``out_Ka`` (n, n) and ``out_Kb`` (n, m), and ``out_info`` =
    (w, iterations, gap, value, log value). Returns the status: 0 done; 1 not handled here
    (SVD sweeps not converged, the diagonalisation not trusted, a criterion or gap that is
    not finite); 2 the fused covariance is not numerically positive definite; 3 to 5 a
    failed check (:func:`_checked`). On a nonzero status the outputs are unspecified.
    """
    n = xa.shape[0]
    m = xb.shape[0]
    if m > n:
        return 1
    if check:
        status = _checked(xa, Pa, La, n)
        if status == 0:
            status = _checked(xb, Pb, Lb, m)
        if status != 0:
            return status
    if (diagonal_spread_squared(La, n) > DIAGONAL_TRUST
            or diagonal_spread_squared(Lb, m) > DIAGONAL_TRUST):
        return 1
    Lbi = np.empty((m, m))
    lower_inverse(Lb, Lbi, m)
    # G = L_b^-1 (H L_a)
    A = np.empty((m, n))
    times_lower(H, La, A, n)
    G = np.empty((m, n))
    lower_times(Lbi, A, G, m)
    V = np.empty((m, m))
    if not _rows_svd(G, V, m, n):
        return 1
    # the terms in descending mu (LAPACK's order), the directions beyond the rank last
    mu_rows = np.empty(m)
    for k in range(m):
        s = 0.0
        for j in range(n):
            s += G[k, j] * G[k, j]
        mu_rows[k] = s
    order = np.argsort(-mu_rows)
    q = m + 1 if m < n else m
    mu = np.zeros(q)
    one_minus = np.ones(q)
    c = np.zeros(q)
    for k in range(m):
        mu[k] = mu_rows[order[k]]
        one_minus[k] = 1.0 - mu[k]
    if not (mu[m - 1] > 0.0 and math.isfinite(mu[0])) or mu[0] > DIAGONAL_TRUST * mu[m - 1]:
        return 1
    # Y[:, k] = L_a g_k = s_k L_a u_k (the columns of T = L_a U times s_k)
    Y = np.empty((n, m))
    for k in range(m):
        row = order[k]
        for i in range(n):
            s = 0.0
            for j in range(i + 1):
                s += La[i, j] * G[row, j]
            Y[i, k] = s
    det = kind == KIND_DET
    scale = 0.0
    for k in range(m):
        if det:
            c[k] = 1.0
        elif kind == KIND_TRACE:
            s = 0.0
            for i in range(n):
                s += Y[i, k] * Y[i, k]
            c[k] = s / mu[k]
        else:
            s = 0.0
            for i in range(n):
                t = 0.0
                for j in range(n):
                    t += W[0, i, j] * Y[j, k]
                s += Y[i, k] * t
            c[k] = s / mu[k]
        scale += c[k]
    if m < n:
        if det:
            c[m] = float(n - m)
        else:
            # the directions beyond the rank: L_a (I - U_m U_m^T), U_m's columns g_k / s_k
            N = np.empty((n, n))
            for i in range(n):
                for j in range(n):
                    s = La[i, j] if j <= i else 0.0
                    for k in range(m):
                        s -= Y[i, k] * G[order[k], j] / mu[k]
                    N[i, j] = s
            rest = 0.0
            for j in range(n):
                if kind == KIND_TRACE:
                    for i in range(n):
                        rest += N[i, j] * N[i, j]
                else:
                    for i in range(n):
                        t = 0.0
                        for k in range(n):
                            t += W[0, i, k] * N[k, j]
                        rest += N[i, j] * t
            c[m] = rest
        scale += c[m]
    if det:
        scale = float(n)
    w, iterations = _minimize(mu, one_minus, c, q, det, scale)
    slope, _ = _derivative(w, mu, one_minus, c, q, det)
    gap = interval_gap(w, slope)
    d = np.empty(q)
    value = 0.0
    for k in range(q):
        den = mu[k] + w * one_minus[k]
        if not den > 0.0 or not math.isfinite(1.0 / den):
            return 1
        d[k] = 1.0 / den
        value += c[k] * d[k]
    if not det:
        gap /= value
    if not math.isfinite(gap):
        return 1
    # K_b = (1 - w) sum_k d_k (L_a g_k) v_k^T L_b^-1  (eq. (H8); v_k = V[:, order[k]])
    Z = np.zeros((n, m))
    if w != 1.0:
        for i in range(n):
            for j in range(m):
                s = 0.0
                for k in range(m):
                    s += Y[i, k] * ((1.0 - w) * d[k]) * V[j, order[k]]
                Z[i, j] = s
    times_lower(Z, Lbi, out_Kb, m)
    # M2 = K_b L_b
    M2 = np.empty((n, m))
    times_lower(out_Kb, Lb, M2, m)
    if w == 0.0:
        for i in range(n):
            for j in range(n):
                out_Ka[i, j] = 0.0
        for i in range(n):
            for j in range(i + 1):
                s = 0.0
                for k in range(m):
                    s += M2[i, k] * M2[j, k]
                out_P[i, j] = s
                out_P[j, i] = s
            s = 0.0
            for k in range(m):
                s += out_Kb[i, k] * xb[k]
            out_x[i] = s
    else:
        for i in range(n):
            for j in range(n):
                s = 0.0
                for k in range(m):
                    s += out_Kb[i, k] * H[k, j]
                out_Ka[i, j] = (1.0 if i == j else 0.0) - s
        M1 = np.empty((n, n))
        times_lower(out_Ka, La, M1, n)
        for i in range(n):
            for j in range(i + 1):
                s = 0.0
                for k in range(n):
                    s += M1[i, k] * M1[j, k]
                if w < 1.0:
                    s /= w
                    t = 0.0
                    for k in range(m):
                        t += M2[i, k] * M2[j, k]
                    s += t / (1.0 - w)
                out_P[i, j] = s
                out_P[j, i] = s
        innovation = np.empty(m)
        for k in range(m):
            s = xb[k]
            for j in range(n):
                s -= H[k, j] * xa[j]
            innovation[k] = s
        for i in range(n):
            s = 0.0
            for k in range(m):
                s += out_Kb[i, k] * innovation[k]
            out_x[i] = xa[i] + s
    out_info[0] = w
    out_info[1] = iterations
    out_info[2] = gap
    R = np.empty((n, n))
    if not report(out_P, R, W, n, kind, out_info[3:4], out_info[4:5], 0):
        return 2
    return 0


def _ready(array: np.ndarray) -> np.ndarray:
    """A C-contiguous, writeable float64 array (one compiled signature for every call; the
    validated arrays are float64, LAPACK's factors Fortran-ordered)."""
    flags = array.flags
    if flags.c_contiguous and flags.writeable:
        return array
    return np.array(array, dtype=np.float64, order="C")


_NO_W = np.zeros((1, 1, 1))


def partial_pair(xa: np.ndarray, Pa: np.ndarray, xb: np.ndarray, Pb: np.ndarray,
                 H: np.ndarray, kind: str, W: Optional[np.ndarray], factors: tuple,
                 check: bool = False) -> Optional[tuple]:
    """Criterion-optimal generalised CI of a full-state and a partial estimate, compiled.

    Parameters
    ----------
    xa, Pa : ndarray, shapes (n,) and (n, n)
        The full-state estimate's mean and covariance (float64).
    xb, Pb : ndarray, shapes (m,) and (m, m)
        The same of the estimate of ``H x`` (float64).
    H : ndarray, shape (m, n)
        The partial estimate's observation matrix (float64, finite: checked by the caller).
    kind : str
        ``"trace"``, ``"det"`` or ``"weighted-trace"``.
    W : ndarray or None
        The (n, n) weight matrix of ``"weighted-trace"`` (parsed).
    factors : tuple of ndarray
        ``(La, Lb)``, LAPACK's lower Cholesky factors of ``Pa`` and ``Pb``.
    check : bool, optional
        False (default): the estimates are validated ones (``Pa``, ``Pb`` are not read).
        True: they are raw, factored as given; the kernel checks them as the validation
        does (finite means, finite covariances below ``2**1023``, finite factors) and
        returns None where a check fails or a covariance is not exactly symmetric (the
        caller's validation then symmetrises it, or raises its error).

    Returns
    -------
    tuple or None
        ``(x, P, omega, info)``: the fused mean (n,) and covariance (n, n), the weight
        ``omega`` of the full-state estimate (a float; the partial one gets
        ``1 - omega``), and ``info`` with ``iterations``, ``converged``, ``gap`` (0-d
        arrays), ``solver`` (``"diagonalise"``), ``value`` (and ``log_value`` for
        ``"det"``) of the criterion report, and ``gains``, the pair ``(K_a, K_b)``
        ((n, n) and (n, m)). The same quantities, with the same meaning, as the numpy
        path's diagonalised pair. None where the kernel does not decide (``m > n``, a
        failed check, an untrusted diagonalisation, a fused covariance that is not
        numerically positive definite): the caller then runs the numpy path. Nothing
        given is modified.
    """
    n, m = xa.shape[0], xb.shape[0]
    if m > n:
        return None
    code = _KINDS.get(kind)
    if code is None:
        return None
    Wk = _NO_W if W is None else _ready(W.reshape(1, n, n))
    x, P, Ka, Kb = np.empty(n), np.empty((n, n)), np.empty((n, n)), np.empty((n, m))
    out = np.zeros(5)
    La, Lb = _ready(factors[0]), _ready(factors[1])
    if check:
        Pa, Pb = _ready(Pa), _ready(Pb)
    else:
        Pa, Pb = La, Lb  # (not read)
    if generalised_pair(_ready(xa), Pa, La, _ready(xb), Pb, Lb, _ready(H), Wk, code, check,
                        x, P, Ka, Kb, out):
        return None
    w, iterations, gap, value, log_value = out.tolist()
    info: dict[str, Any] = {"iterations": np.array(int(iterations)),
                            "converged": np.array(gap <= GAP_TOL), "gap": np.array(gap),
                            "solver": "diagonalise", "value": np.float64(value)}
    if code == KIND_DET:
        info["log_value"] = np.float64(log_value)
    info["gains"] = (Ka, Kb)
    return x, P, w, info
