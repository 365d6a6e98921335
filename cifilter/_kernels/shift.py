"""Compiled (numba) time shift of one estimate: the short way of ``kf.fuse(other, lag=k)``.

:func:`shift_single` does what the time alignment
(:mod:`cifilter._numerics.alignment`) does for one estimate of the full state brought by a
:class:`~cifilter._numerics.alignment.StepMotion`: it checks the covariance as the short
way of :func:`~cifilter._numerics.alignment.aligned_pair` does (exactly symmetric, a
Cholesky factor that exists and is finite, a trace below ``2**1023``), and brings the
estimate forward (the exact prediction ``(M L)(M L)^T + N``) or back (the retrodiction bound
``(M L)(M L)^T / alpha + N / (1 - alpha)`` with the trace-minimising ``alpha``, eqs.
(T5)-(T6) of ``docs/methods/time.rst``), from the factor ``L`` of the covariance, as
:func:`~cifilter._numerics.alignment.predicted` and
:func:`~cifilter._numerics.alignment.retrodicted` do; ``M``, ``N`` are the motion's
``F^k``, ``Q_k`` or ``F^-k``, ``F^-k Q_k F^-kT`` (cached by the motion). Same formulas,
summed in another order than BLAS's: the results agree with the numpy path's to rounding.
The kernel :func:`cifilter._kernels.compiled.shifted_pair` calls it to bring one estimate
of a pair this way and solve the pair in the same compiled call, so that
``kf.fuse(other, lag=k)`` costs one call from Python, as ``kf.fuse(other)`` does.
Imported only when it runs (importing cifilter never imports numba).
"""

import math

from .primitives import cholesky, jit, times_lower

__all__ = ["shift_single"]

_LARGEST_ENTRY = 2.0 ** 1023


@jit
def shift_single(x, P, M, N, backward, L, x_out, P_out):
    """Bring one estimate ``(x, P)`` (n,), (n, n) by ``M``, ``N`` (n, n) into ``x_out``,
    ``P_out``; ``L`` (n, n) scratch. Returns ``(status, alpha)``: status 0 done, 1 ``P``
    not exactly symmetric (or NaN), 2 no finite Cholesky factor or trace not below
    ``2**1023``, 3 a non-finite result; ``alpha`` the retrodiction's split (1.0 forward)."""
    n = x.shape[0]
    trace = 0.0
    for i in range(n):
        trace += P[i, i]
        for j in range(i):
            if not P[i, j] == P[j, i]:
                return 1, 1.0
    if not trace < _LARGEST_ENTRY:
        return 2, 1.0
    if not cholesky(P, L, n):
        return 2, 1.0
    A = P_out  # (scratch until P is formed below: A is read before P_out is written)
    times_lower(M, L, A, n)
    a = 0.0
    for i in range(n):
        for j in range(n):
            a += A[i, j] * A[i, j]
    b = 0.0
    for i in range(n):
        b += N[i, i]
    share = 1.0
    if backward and b != 0.0:
        share = math.sqrt(a) / (math.sqrt(a) + math.sqrt(b))
    # P = A A^T / share + N / (1 - share) (backward) or A A^T + N (forward), lower half
    # first, then mirrored: exactly symmetric
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(n):
                s += A[i, k] * A[j, k]
            L[i, j] = s
    for i in range(n):
        for j in range(i + 1):
            if backward:
                value = L[i, j] / share
                if b > 0.0:
                    value += N[i, j] / (1.0 - share)
            else:
                value = L[i, j] + 0.5 * (N[i, j] + N[j, i])
            L[i, j] = value
    for i in range(n):
        s = 0.0
        for k in range(n):
            s += M[i, k] * x[k]
        x_out[i] = s
        if not math.isfinite(s):
            return 3, share
    for i in range(n):
        for j in range(i + 1):
            value = L[i, j]
            if not math.isfinite(value):
                return 3, share
            P_out[i, j] = value
            P_out[j, i] = value
    return 0, share

