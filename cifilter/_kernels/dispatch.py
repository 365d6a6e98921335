"""Dispatch of the Covariance Intersection family to the compiled kernels (numba).

The functions here take validated estimates (as the numpy cores do), return None where
the backend (:mod:`cifilter.backend`) keeps the numpy path, and otherwise run the
kernels of :mod:`cifilter._kernels.compiled` (imported, and so compiled or loaded from the
on-disk cache, on first use only). Items a kernel hands back (``status != 0``: a
diagonalisation that is not trusted, a numerically singular fused information or fused
covariance) are solved by the numpy path, which certifies, re-solves or raises its usual
error for them, so results, ``info`` and errors are those of the numpy path.
"""

import contextlib
import math

import numpy as np

from .._numerics.criteria import criterion_report, gap_converged
from .._numerics.information import reference_estimates
from .._numerics.validation import Estimates
from ..backend import get_backend, numba_available, use_kernels
from . import background

__all__ = ["AUTO_MAX_DIM", "MANY_MAX_COUNT", "PIN_BLAS", "optimal_many", "optimal_pair",
           "pair_checked", "pair_single", "report", "shifted_pair_single", "single_ready",
           "weighted"]

_calls = {"kernels": 0, "numpy_while_compiling": 0, "handed_back": 0}


def _go(size, *arrays, count=True):
    """Whether this call runs on the kernels. Under ``"auto"`` only for problems of at most
    :data:`AUTO_MAX_DIM` dimensions (``arrays[0]`` the means, ``(..., n)``) and when the
    kernels are ready (compiled in this process or loaded from numba's cache): a call never
    waits for a compile; the first one that finds them missing starts the background
    compilation. ``count=False``: the call is not counted in :func:`report` (a route that
    hands the call to another one, which counts it)."""
    if not use_kernels(size, *arrays):
        return False
    if get_backend() == "auto" and arrays[0].shape[-1] > AUTO_MAX_DIM:
        return False
    if get_backend() == "auto" and not background.ready():
        if count:
            _calls["numpy_while_compiling"] += 1
        return False
    if count:
        _calls["kernels"] += 1
    return True


def report():
    """Where this process's eligible calls went: ``kernels`` (calls run on the kernels),
    ``numpy_while_compiling`` (calls under ``"auto"`` that numpy answered because the
    kernels were not ready), ``handed_back`` (items of optimal-weight calls that the kernels
    handed back to the numpy path), and the kernels' readiness (:func:`background.status`)."""
    return dict(_calls, **background.status())

_KINDS = {"trace": 0, "det": 1, "weighted-trace": 2, None: 3}


# Batches below this run on the serial kernels: waking the thread pool costs tens of
# microseconds on an idle machine and milliseconds on a loaded one (measured: 256 pairs took
# 9.5 ms threaded against 0.6 ms for 128 serial ones, on 2 cores shared with other jobs).
THREADED_MIN = 2048


# Under "auto", problems of more than this many dimensions go to the numpy (LAPACK) path:
# there the kernels' loops (cyclic Jacobi, unblocked products) stop beating LAPACK's blocked
# routines. Measured with ``python benchmarks/bench_many.py --dims`` (trace-optimal CI of
# 4096 pairs per batch, numpy and numba interleaved in one run, BLAS pinned to one thread
# around the threaded kernels; 2 cores shared with other jobs, load 13-15): numpy's time
# over the kernels' 7.5x at n = 2, 3.9x at 4, 1.8x at 8 to 12, 1.2x at 16, and with 2048
# pairs 0.94x at 24 and 1.07x at 32 (noise of that load: the unpinned kernels 1.25x and
# 2.4x there). The kernels win up to 16 and no longer clearly beyond.
AUTO_MAX_DIM = 16

# Limit BLAS to one thread around the threaded kernels (threadpoolctl, when installed):
# numba's threads and OpenBLAS's would otherwise share the cores (OpenBLAS's threads keep
# spinning after a call). A switch for ``benchmarks/bench_many.py`` to measure both.
PIN_BLAS = True
_blas: list = []


def _blas_pools():
    """threadpoolctl's BLAS pools of this process (None without threadpoolctl), once."""
    if not _blas:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:
            _blas.append(None)
        else:
            _blas.append(ThreadpoolController().select(user_api="blas"))
    return _blas[0]


def _threads(size):
    """A context for one kernel call: BLAS limited to one thread where both the kernel
    (threaded, numba with more than one thread) and BLAS (more than one thread) would run
    threads; otherwise nothing."""
    if not PIN_BLAS or size < THREADED_MIN:
        return contextlib.nullcontext()
    pools = _blas_pools()
    if pools is None or not any(pool.num_threads > 1 for pool in pools.lib_controllers):
        return contextlib.nullcontext()
    import numba

    if numba.get_num_threads() < 2:
        return contextlib.nullcontext()
    return pools.limit(limits=1)


def _kernel(name, size):
    """The kernel ``name``: threaded for large batches, else its serial twin."""
    from . import compiled

    return getattr(compiled, name if size >= THREADED_MIN else name + "_serial")


def _writable(array):
    """A C-contiguous, writeable float64 array (numba compiles a kernel once per layout
    and writeability of its arguments: one signature for every call)."""
    return np.require(array, np.float64, ("C", "W"))


def _size(est):
    return int(np.prod(est.batch_shape, dtype=int))


def _flat(est, size):
    def rows(array, tail):
        return _writable(array.reshape((size,) + array.shape[array.ndim - tail:]))

    return rows(est.x, 2), rows(est.P, 3), rows(est.L, 3)


def _flat_criterion(W, shape, size, n):
    """(W as (1 or size, n, n), W for the numpy path of a subset of rows)."""
    if W is None:
        return np.zeros((1, 1, 1)), lambda index: None
    if W.ndim == 2:
        return _writable(W[None]), lambda index: W
    Wb = _writable(np.broadcast_to(W, shape + (n, n)).reshape(size, n, n))
    return Wb, lambda index: Wb[index]


def _rows(est, x, P, L, index):
    """The problems ``index`` of the flattened batch as estimates for the numpy path; one
    problem without batch axes stays without them, so that it takes the numpy path's own
    single-problem route (as under the numpy backend) and gets the same rounding."""
    if not est.batch_shape:
        return Estimates(x[0], P[0], L[0], est.column)
    return Estimates(x[index], P[index], L[index], est.column)


def _solve_handed_back(est, x, P, L, status, numpy_path, sub_W, kind, outputs):
    """Solve the items a kernel handed back (``status != 0``) on the numpy path and write
    them into the kernel's ``outputs`` (weights, iterations, gap, floor, converged, x, P,
    gains, value, log_value), in place."""
    index = np.flatnonzero(status)
    _calls["handed_back"] += int(index.size)
    if not index.size:
        return
    (weights, iterations, gap, floor, converged, x_out, P_out, gains, value,
     log_value) = outputs
    sub = _rows(est, x, P, L, index)
    w_s, info_s, (x_s, P_s, K_s) = numpy_path(sub, sub_W(index))
    report_s = criterion_report(P_s, kind, sub_W(index))
    weights[index], iterations[index] = w_s, info_s["iterations"]
    gap[index], floor[index] = info_s["gap"], info_s["gap_floor"]
    converged[index] = info_s["converged"]
    x_out[index], P_out[index], gains[index] = x_s, P_s, K_s
    value[index] = report_s["value"]
    if kind == "det":
        log_value[index] = report_s["log_value"]


def _report(kind, value, log_value, shape):
    report = {"value": value.reshape(shape)}
    if kind == "det":
        report["log_value"] = log_value.reshape(shape)
    return report


def _pair_outputs(size, n, gains):
    """The output arrays of :func:`compiled.ci_pair`: scalars (size, 8), x, P, gains (an
    empty (0, 2, n, n) stack without gains: one signature either way)."""
    return (np.zeros((size, 8)), np.empty((size, n)), np.empty((size, n, n)),
            np.empty((size if gains else 0, 2, n, n)))


def _pair_scalars(scalars):
    """omega, iterations, gap, floor, computed gap, value, log value, status of
    :func:`compiled.ci_pair`'s scalar output (new arrays)."""
    columns = scalars.T
    return (columns[0].copy(), columns[1].astype(int), columns[2].copy(), columns[3].copy(),
            columns[4].copy(), columns[5].copy(), columns[6].copy(),
            columns[7].astype(np.int8))


def _run_pair(size, x, P, L, Wk, kind, mode, gains):
    scalars, x_out, P_out, K_out = _pair_outputs(size, x.shape[-1], gains)
    with _threads(size):
        _kernel("ci_pair", size)(x, P, L, Wk, _KINDS[kind], mode, scalars, x_out, P_out, K_out)
    return scalars, x_out, P_out, K_out


def _finish_pair(est, shape, size, n, x, P, L, W, kind, numpy_path, outputs):
    """optimal_pair's answer from the kernel's outputs, the handed-back items re-solved."""
    scalars, x_out, P_out, gains = outputs
    omega, iterations, gap, floor, computed, value, log_value, status = _pair_scalars(scalars)
    _, sub_W = _flat_criterion(W, shape, size, n)
    weights = np.stack([omega, 1.0 - omega], axis=-1)
    converged = gap_converged(gap, floor, computed)
    _solve_handed_back(est, x, P, L, status, numpy_path, sub_W, kind,
                       (weights, iterations, gap, floor, converged, x_out, P_out, gains,
                        value, log_value))
    info = {"iterations": iterations.reshape(shape), "converged": converged.reshape(shape),
            "gap": gap.reshape(shape), "gap_floor": floor.reshape(shape),
            "solver": "diagonalise"}
    result = (x_out.reshape(shape + (n,)), P_out.reshape(shape + (n, n)),
              gains.reshape(shape + (2, n, n)))
    return weights.reshape(shape + (2,)), info, result, _report(kind, value, log_value, shape)


def optimal_pair(est, kind, W, numpy_path):
    """Criterion-optimal CI of two estimates per batch item, or None (numpy backend).

    Returns ``(weights, info, (x, P, gains), report)`` as
    :func:`cifilter.rules._ci_weights.optimal_weights` with the criterion report of ``P``;
    ``numpy_path(sub_estimates, sub_W)`` solves the items the kernel hands back.
    """
    size = _size(est)
    if not _go(size, est.x, est.P, est.L):
        return None
    shape, n = est.batch_shape, est.dim
    x, P, L = _flat(est, size)
    Wk, _ = _flat_criterion(W, shape, size, n)
    from .compiled import MODE_GAINS

    outputs = _run_pair(size, x, P, L, Wk, kind, MODE_GAINS, True)
    return _finish_pair(est, shape, size, n, x, P, L, W, kind, numpy_path, outputs)


def pair_checked(xs, Ps, column, kind, W, numpy_path):
    """Criterion-optimal CI of two estimates per batch item from the raw input, validation
    folded into the kernel's pass, or None.

    ``xs`` (..., 2, n) or (..., 2, n, 1) (``column``) and ``Ps`` (..., 2, n, n), float64
    arrays as the caller gave them (copied here; never modified). The kernel checks every
    item as the validation does (finite, entries below ``2**1023``, symmetric within its
    tolerance, then symmetrised, Cholesky-factorisable by its own factorisation) and
    solves it as :func:`optimal_pair` does. Returns ``(weights, info, (x, P, gains),
    report)`` as :func:`optimal_pair`, with the items the kernel hands back solved by
    ``numpy_path`` from LAPACK's factors (as after the validation); None when the backend
    keeps to numpy or when some item fails a check (the caller then validates and raises
    the validation's error).
    """
    shape, n = Ps.shape[:-3], Ps.shape[-1]
    size = math.prod(shape)
    if not _go(size, Ps[..., 0, :], Ps, count=False):  # (the usual route counts these)
        return None
    x = np.array(xs[..., 0] if column else xs, dtype=np.float64, order="C").reshape(size, 2, n)
    P = np.array(Ps, dtype=np.float64, order="C").reshape(size, 2, n, n)
    L = np.empty(P.shape)
    Wk, _ = _flat_criterion(W, shape, size, n)
    from .compiled import MODE_CHECK, MODE_GAINS

    outputs = _run_pair(size, x, P, L, Wk, kind, MODE_CHECK | MODE_GAINS, True)
    status = outputs[0][:, 7]
    if (status >= 4.0).any():  # (the validation answers this call: the usual route)
        return None
    handed = np.flatnonzero(status)
    if handed.size:
        # the numpy path solves these (ill-conditioned, ties) from LAPACK's factors, as
        # after the validation: its answer there is sensitive to the factors' rounding
        try:
            L[handed] = np.linalg.cholesky(P[handed])
        except np.linalg.LinAlgError:
            return None
    _calls["kernels"] += 1
    est = Estimates(x.reshape(shape + (2, n)), P.reshape(shape + (2, n, n)),
                    L.reshape(shape + (2, n, n)), column)
    return _finish_pair(est, shape, size, n, x, P, L, W, kind, numpy_path, outputs)


_single: list = []  # (ci_pair_serial, shifted_pair, MODE_CHECK | MODE_GAINS), once imported
_NO_W = np.zeros((1, 1, 1))  # the criterion matrix of "trace" and "det" (not read)


def single_ready(n):
    """Whether a single two-estimate call of dimension ``n`` goes to the compiled kernel
    now: under ``"numba"`` (with numba installed; compiled on first use, as every kernel
    there), and under ``"auto"`` for ``n <= AUTO_MAX_DIM`` once the kernels are there
    (:func:`background.loaded`: compiled in this process or loaded from numba's cache; a
    single call never starts a compilation)."""
    name = get_backend()
    if name == "numba":
        return numba_available()
    return name == "auto" and n <= AUTO_MAX_DIM and background.loaded()


def pair_single(x1, P1, x2, P2, kind, W):
    """Criterion-optimal CI of one pair in one compiled call, from the raw input.

    ``x1``, ``x2`` float64 arrays of n numbers, ``P1``, ``P2`` float64 (n, n); ``W`` None or
    (n, n) (parsed). The kernel checks the input as the validation does (finite, symmetric
    within its tolerance, positive definite by its own Cholesky factorisation) and solves
    the pair as :func:`optimal_pair` does. Returns ``(scalars, x, P, gains)`` (scalars as
    ``compiled.ci_pair``'s: omega, iterations, gap, floor, computed gap, value, log value,
    status), or None when the caller must take the full path: a failed check (the
    validation raises its error) or an item the kernel hands back (the full path decides).
    For the backends that run it (the caller asks :func:`single_ready` first). Nothing
    given is modified (the kernel works on copies).
    The factors are the kernel's, not LAPACK's, so the results may differ from the full
    path's in the last bits.
    """
    if not _single:
        _import_single()
    x, P, Wk, outputs = _single_arrays(x1, P1, x2, P2, W)
    _calls["kernels"] += 1
    _single[0](x, P, np.empty(P.shape), Wk, _KINDS[kind], _single[2], *outputs)
    return _single_answer(outputs)


def shifted_pair_single(x1, P1, x2, P2, moved, M, N, backward, kind, W):
    """:func:`pair_single` of the pair with estimate ``moved`` (0 or 1) first brought by
    ``M``, ``N``, all in one compiled call (:func:`cifilter._kernels.compiled.shifted_pair`):
    the short way of ``kf.fuse(other, lag=k)``.

    ``M``, ``N`` (n, n) are a :class:`~cifilter._numerics.alignment.StepMotion`'s ``F^k``,
    ``Q_k`` (forward, ``backward`` False) or ``F^-k``, ``F^-k Q_k F^-kT`` (back, by the
    retrodiction bound). The moved estimate's covariance must be exactly symmetric, and is
    factored and checked as :func:`cifilter._numerics.alignment.aligned_pair` checks it.
    Returns ``(scalars, x, P, gains, alpha)`` (``alpha`` the retrodiction's split, None
    forward), or None for anything the full path must decide: a failed check of either
    estimate, or a pair the kernel hands back. Its brought estimate agrees with the numpy
    path's to rounding (the same formulas, summed in another order).
    """
    if not _single:
        _import_single()
    # (one compiled signature: read-only C-ordered M and N, as the StepMotion caches F^k
    # and Q_k; its F^-k comes from LU in Fortran order)
    if M.flags.writeable or not M.flags.c_contiguous:
        M = np.ascontiguousarray(M)
        M.flags.writeable = False
    if N.flags.writeable or not N.flags.c_contiguous:
        N = np.ascontiguousarray(N)
        N.flags.writeable = False
    x, P, Wk, outputs = _single_arrays(x1, P1, x2, P2, W)
    _calls["kernels"] += 1
    alpha = _single[1](x, P, moved, M, N, backward, Wk, _KINDS[kind], _single[2], *outputs)
    answer = _single_answer(outputs)
    if answer is None:
        return None
    return answer + ((alpha if backward else None),)


def _import_single():
    from .compiled import MODE_CHECK, MODE_GAINS, ci_pair_serial, shifted_pair

    _single.extend((ci_pair_serial, shifted_pair, MODE_CHECK | MODE_GAINS))


def _single_arrays(x1, P1, x2, P2, W):
    """The kernels' copies of one pair, its criterion matrix and the outputs."""
    n = P1.shape[0]
    x = np.concatenate((x1, x2), axis=None).reshape(1, 2, n)  # (new arrays)
    P = np.concatenate((P1, P2)).reshape(1, 2, n, n)
    Wk = _NO_W if W is None else _writable(W[None])
    return x, P, Wk, (np.empty((1, 8)), np.empty((1, n)), np.empty((1, n, n)),
                      np.empty((1, 2, n, n)))


def _single_answer(outputs):
    scalars, x_out, P_out, K_out = outputs
    if scalars[0, 7] != 0.0:
        return None
    return scalars[0], x_out[0], P_out[0], K_out[0]


# The compiled solver of N >= 3 estimates runs the numpy path's active-set phase, which the
# numpy path runs alone below ``_numerics.optimize.INTERIOR_MIN_COUNT`` estimates; from there
# on numpy's interior-point phase leads and the kernel is not used.
MANY_MAX_COUNT = 11


def optimal_many(est, kind, W, numpy_path):
    """Criterion-optimal CI of 3 to :data:`MANY_MAX_COUNT` estimates per batch item, or
    None (numpy backend, or another N).

    Returns ``(weights, info, (x, P, gains), report)`` as
    :func:`cifilter.rules._ci_weights.optimal_weights` with the criterion report of ``P``;
    ``numpy_path(sub_estimates, sub_W)`` solves the items the kernel hands back (those it
    cannot certify, whose weights the rounding of the gradients does not determine to
    1e-10, or whose fused information or covariance is not numerically positive definite).
    """
    count = est.count
    if not 3 <= count <= MANY_MAX_COUNT:
        return None
    size = _size(est)
    if not _go(size, est.x, est.P, est.L):
        return None
    shape, n = est.batch_shape, est.dim
    x, P, L = _flat(est, size)
    Wk, sub_W = _flat_criterion(W, shape, size, n)
    weights = np.zeros((size, count))
    gap, floor, computed, value, log_value = (np.empty(size) for _ in range(5))
    iterations = np.zeros(size, dtype=int)
    status = np.empty(size, dtype=np.int8)
    references = np.zeros(size, dtype=np.int64)
    x_out, P_out = np.empty((size, n)), np.empty((size, n, n))
    gains = np.empty((size, count, n, n))
    with _threads(size):
        _kernel("ci_many_optimal", size)(x, L, Wk, _KINDS[kind], weights, iterations, gap,
                                         floor, computed, x_out, P_out, gains, value,
                                         log_value, status, references)
    converged = gap_converged(gap, floor, computed)
    _solve_handed_back(est, x, P, L, status, numpy_path, sub_W, kind,
                       (weights, iterations, gap, floor, converged, x_out, P_out, gains,
                        value, log_value))
    info = {"iterations": iterations.reshape(shape), "converged": converged.reshape(shape),
            "gap": gap.reshape(shape), "gap_floor": floor.reshape(shape), "solver": "simplex"}
    result = (x_out.reshape(shape + (n,)), P_out.reshape(shape + (n, n)),
              gains.reshape(shape + (count, n, n)))
    return (weights.reshape(shape + (count,)), info, result,
            _report(kind, value, log_value, shape))


def weighted(est, weights, kind, W, numpy_path):
    """The weighted information fusion at given weights per batch item, or None.

    Returns ``((x, P, gains), report)`` as :func:`cifilter._numerics.information.weighted_fusion`,
    with the criterion report of ``P`` (None for ``kind=None``, the naive fusion);
    ``numpy_path(x, L, weights)`` fuses the items the kernel hands back (and raises the
    numpy path's error for those it cannot fuse either).
    """
    size = _size(est)
    if not _go(size, est.x, est.P, est.L, weights):
        return None
    shape, n, count = est.batch_shape, est.dim, est.count
    x, _, L = _flat(est, size)
    w = _writable(np.broadcast_to(weights, shape + (count,)).reshape(size, count))
    Wk, sub_W = _flat_criterion(W, shape, size, n)
    value, log_value = np.empty(size), np.empty(size)
    status = np.empty(size, dtype=np.int8)
    x_out, P_out = np.empty((size, n)), np.empty((size, n, n))
    gains = np.empty((size, count, n, n))
    # the numpy path's reference estimate (the remainder's gain), so that both round alike
    references = np.ascontiguousarray(reference_estimates(w, L), dtype=np.int64)
    with _threads(size):
        _kernel("weighted_fusion", size)(x, L, w, references, Wk, _KINDS[kind], x_out, P_out,
                                         gains, value, log_value, status)
    index = np.flatnonzero(status)
    if index.size:
        if est.batch_shape:
            fused = numpy_path(x[index], L[index], w[index])
        else:  # one problem: the numpy path's own single-problem route
            fused = numpy_path(x[0], L[0], w[0])
        x_out[index], P_out[index], gains[index] = fused.x, fused.P, fused.gains
        if kind is not None:
            report_s = criterion_report(fused.P, kind, sub_W(index))
            value[index] = report_s["value"]
            if kind == "det":
                log_value[index] = report_s["log_value"]
    result = (x_out.reshape(shape + (n,)), P_out.reshape(shape + (n, n)),
              gains.reshape(shape + (count, n, n)))
    report = None if kind is None else _report(kind, value, log_value, shape)
    return result, report
