"""Batched Covariance Intersection: numpy and numba backends against per-item loops.

Everything in one run, on the same data, in the same process (ratios are what carry over
between machines):

* the first-call cost of the compiled kernels: a fresh process with an empty numba cache
  (the JIT compile) and a second one with the cache filled (what later processes pay);
* 4x4 pairs (``--pairs``, default 100 000): trace-optimal CI batched with the numpy and the
  numba backend (fusions/s, the ratio), the same for ``det``, for given weights and for
  the naive fusion; the kernel alone and the front door's validation alone (what bounds
  the batched call); a per-pair loop of scipy ``minimize_scalar`` fusions (the way one
  would write it without cifilter) and Stone Soup's per-pair merge
  (``stonesoup.mixturereducer.CovarianceIntersection.merge_components``, given weights:
  Stone Soup has no weight optimisation; it is given cifilter's optimal weights);
* N = 4 estimates of 6x6 (``--sets``, default 20 000): optimal (trace) and given weights,
  numpy and numba backends, and Stone Soup's merge per set;
* the public path against a minimal reference kernel carried by this file (issue 24's
  target: the compiled public path within 2x of it): trace-optimal CI of the same 4x4
  pairs by a numba kernel compiled at first use here, with nothing but the arithmetic
  (Cholesky of P1, P2 whitened by it, cyclic Jacobi on the whitened 4x4, safeguarded
  Newton on omega in the diagonal basis, ``P = T diag(e) T^T`` and the fused mean; no
  validation, no gains, no certificate; ``prange`` over one contiguous chunk per thread).
  It prints the ratio public / reference for the numpy and the numba backend and how far
  their answers are from the reference's (max ``|d omega|``, max relative ``|d P|``).

The loops are timed on a subset (``--loop-items``) and scaled; the output says so.

    python benchmarks/bench_ci.py                 # the full run (about a minute or two)
    python benchmarks/bench_ci.py --pairs 20000 --sets 5000 --loop-items 500
"""

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cifilter  # noqa: E402
from cifilter._numerics.validation import as_estimates  # noqa: E402


def make_sets(size, count, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((size, count, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    return rng.standard_normal((size, count, n)), Ps


def scipy_loop(xs, Ps):
    """One scipy-optimised CI fusion per pair (xatol 1e-8): the baseline without cifilter."""
    omegas = np.empty(len(xs))
    for k in range(len(xs)):
        I1, I2 = np.linalg.inv(Ps[k, 0]), np.linalg.inv(Ps[k, 1])

        def trace_bound(w, I1=I1, I2=I2):
            return np.trace(np.linalg.inv(w * I1 + (1 - w) * I2))

        w = minimize_scalar(trace_bound, bounds=(0.0, 1.0), method="bounded",
                            options={"xatol": 1e-8}).x
        P = np.linalg.inv(w * I1 + (1 - w) * I2)
        _ = P @ (w * I1 @ xs[k, 0] + (1 - w) * I2 @ xs[k, 1])
        omegas[k] = w
    return omegas


def stonesoup_loop(xs, Ps, weights):
    """Stone Soup's CI merge of each problem's GaussianStates with the given weights."""
    from stonesoup.mixturereducer.gaussianmixture import CovarianceIntersection
    from stonesoup.types.state import GaussianState

    states = [[GaussianState(x[:, None], P) for x, P in zip(xk, Pk)] for xk, Pk in zip(xs, Ps)]
    start = time.perf_counter()
    out = [CovarianceIntersection.merge_components(*s, weights=w)
           for s, w in zip(states, weights)]
    return time.perf_counter() - start, out


def best_of(repeats, function):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return min(times), result


_FIRST_CALL = """
import sys, time
sys.path.insert(0, {root!r})
start = time.perf_counter()
import numpy as np
import cifilter
rng = np.random.default_rng(0)
A = rng.standard_normal((3000, 2, 4, 4))  # above THREADED_MIN: the threaded kernels
Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
xs = rng.standard_normal((3000, 2, 4))
out = []
with cifilter.use_backend("numba"):
    for label, call in [
        ("optimal, threaded", lambda: cifilter.covariance_intersection(xs, Ps)),
        ("optimal, serial", lambda: cifilter.covariance_intersection(xs[:10], Ps[:10])),
        ("given weights, threaded",
         lambda: cifilter.covariance_intersection(xs, Ps, omega=0.5)),
        ("given weights, serial",
         lambda: cifilter.covariance_intersection(xs[:10], Ps[:10], omega=0.5)),
    ]:
        t = time.perf_counter()
        call()
        out.append(f"{{label}}={{time.perf_counter() - t:.2f}}")
print(";".join(out))
"""


def first_call_times():
    """(cold, warm): per-kernel first-call seconds with an empty and with a filled cache."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        code = _FIRST_CALL.format(root=str(ROOT))
        runs = []
        for _ in range(2):
            done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                  text=True, check=True)
            runs.append(dict(item.split("=") for item in done.stdout.strip().split(";")))
    return runs


# ------------------------------------------------------------------ the reference kernel
_REFERENCE = {}


def reference_kernel(n):
    """The minimal trace-optimal CI kernel (numba) for dimension ``n`` (a constant of the
    compiled code, so its loops unroll), compiled at its first call.

    Per pair: ``P1 = L L^T``; ``M = L^-1 P2 L^-T = U diag(d) U^T`` by cyclic Jacobi
    (symmetric two-row updates; a rotation is skipped where ``a_pq^2 <= eps^2/4 |a_pp a_qq|``;
    until a sweep rotates nothing); with ``T = L U``, ``P1 = T T^T`` and
    ``P2 = T diag(d) T^T``, so the CI bound of weight w is ``P = T diag(e) T^T``,
    ``e_k = d_k / (1 + w (d_k - 1))``, and ``trace P = sum_k c_k e_k`` (``c_k`` the squared
    norms of T's columns) is convex in w: its derivative's sign at 0 and 1 decides the ends,
    else Newton steps inside the bracket (bisection when a step leaves it) until a step is
    below 1e-13, the public path's tolerance. The fused mean is
    ``T diag(e) (w y_1 + (1 - w) y_2 / d)`` with ``y_i = U^T L^-1 x_i``. Scratch per chunk;
    ``prange`` over contiguous chunks.
    """
    if n in _REFERENCE:
        return _REFERENCE[n]
    from numba import njit, prange

    eps = float(np.finfo(float).eps)

    @njit(cache=False)
    def chunk(xs, Ps, lo, hi, omega, x_out, P_out):
        L = np.zeros((n, n))
        W = np.empty((n, n))
        A = np.empty((n, n))
        U = np.empty((n, n))
        T = np.empty((n, n))
        d = np.empty(n)
        c = np.empty(n)
        e = np.empty(n)
        y1 = np.empty(n)
        y2 = np.empty(n)
        for b in range(lo, hi):
            P1 = Ps[b, 0]
            P2 = Ps[b, 1]
            for j in range(n):  # Cholesky of P1
                s = P1[j, j]
                for k in range(j):
                    s -= L[j, k] * L[j, k]
                ljj = np.sqrt(s)
                L[j, j] = ljj
                for i in range(j + 1, n):
                    s = P1[i, j]
                    for k in range(j):
                        s -= L[i, k] * L[j, k]
                    L[i, j] = s / ljj
            for col in range(n):  # W = L^-1 P2
                for i in range(n):
                    s = P2[i, col]
                    for k in range(i):
                        s -= L[i, k] * W[k, col]
                    W[i, col] = s / L[i, i]
            for col in range(n):  # A = L^-1 W^T = L^-1 P2 L^-T
                for i in range(n):
                    s = W[col, i]
                    for k in range(i):
                        s -= L[i, k] * A[k, col]
                    A[i, col] = s / L[i, i]
            for i in range(n):
                for j in range(n):
                    U[i, j] = 1.0 if i == j else 0.0
                    if j < i:
                        A[i, j] = A[j, i] = 0.5 * (A[i, j] + A[j, i])
            for _sweep in range(60):  # cyclic Jacobi (symmetric updates, Golub & Van Loan)
                rotated = False
                for p in range(n - 1):
                    for q in range(p + 1, n):
                        apq, app, aqq = A[p, q], A[p, p], A[q, q]
                        if apq * apq <= 0.25 * eps * eps * abs(app * aqq):
                            continue  # negligible (Demmel & Veselic's relative test)
                        rotated = True
                        theta = (aqq - app) / (2.0 * apq)
                        t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                        if theta < 0.0:
                            t = -t
                        cs = 1.0 / np.sqrt(t * t + 1.0)
                        sn = t * cs
                        tau = sn / (1.0 + cs)
                        A[p, p] = app - t * apq
                        A[q, q] = aqq + t * apq
                        A[p, q] = A[q, p] = 0.0
                        for k in range(n):
                            if k != p and k != q:
                                akp, akq = A[k, p], A[k, q]
                                A[k, p] = A[p, k] = akp - sn * (akq + tau * akp)
                                A[k, q] = A[q, k] = akq + sn * (akp - tau * akq)
                        for k in range(n):
                            ukp, ukq = U[k, p], U[k, q]
                            U[k, p] = ukp - sn * (ukq + tau * ukp)
                            U[k, q] = ukq + sn * (ukp - tau * ukq)
                if not rotated:
                    break
            for k in range(n):  # T = L U and the squared norms of its columns
                d[k] = A[k, k]
                c[k] = 0.0
                for i in range(n):
                    s = 0.0
                    for j in range(i + 1):
                        s += L[i, j] * U[j, k]
                    T[i, k] = s
                    c[k] += s * s
            g0 = 0.0  # the derivative of trace P at w = 0 and 1
            g1 = 0.0
            for k in range(n):
                g0 -= c[k] * d[k] * (d[k] - 1.0)
                g1 -= c[k] * (d[k] - 1.0) / d[k]
            if g0 >= 0.0:
                w = 0.0
            elif g1 <= 0.0:
                w = 1.0
            else:  # safeguarded Newton inside the bracket, to |step| < 1e-13 (the public
                low, high, w = 0.0, 1.0, 0.5  # path's tolerance on omega)
                for _ in range(100):
                    g = 0.0
                    h = 0.0
                    for k in range(n):
                        dk = d[k] - 1.0
                        den = 1.0 + w * dk
                        term = c[k] * d[k] * dk / (den * den)
                        g -= term
                        h += 2.0 * term * dk / den
                    if g > 0.0:
                        high = w
                    else:
                        low = w
                    step = -g / h
                    settled = abs(step) < 1e-13 or g == 0.0
                    if low < w + step < high:
                        w = w + step
                    elif not settled:
                        w = 0.5 * (low + high)
                    if settled or high - low < 1e-13:
                        break
            omega[b] = w
            for k in range(n):
                e[k] = d[k] / (1.0 + w * (d[k] - 1.0))
            for i in range(n):  # y_i = U^T L^-1 x_i
                s1 = xs[b, 0, i]
                s2 = xs[b, 1, i]
                for k in range(i):
                    s1 -= L[i, k] * y1[k]
                    s2 -= L[i, k] * y2[k]
                y1[i] = s1 / L[i, i]
                y2[i] = s2 / L[i, i]
            for k in range(n):
                s1 = 0.0
                s2 = 0.0
                for i in range(n):
                    s1 += U[i, k] * y1[i]
                    s2 += U[i, k] * y2[i]
                W[0, k] = e[k] * (w * s1 + (1.0 - w) * s2 / d[k])  # z in diagonal coordinates
            for i in range(n):
                s = 0.0
                for k in range(n):
                    s += T[i, k] * W[0, k]
                x_out[b, i] = s
                for j in range(i + 1):
                    s = 0.0
                    for k in range(n):
                        s += T[i, k] * e[k] * T[j, k]
                    P_out[b, i, j] = s
                    P_out[b, j, i] = s

    @njit(parallel=True, cache=False)
    def kernel(xs, Ps, chunks, omega, x_out, P_out):
        size = xs.shape[0]
        for part in prange(chunks):
            chunk(xs, Ps, part * size // chunks, (part + 1) * size // chunks, omega, x_out,
                  P_out)

    _REFERENCE[n] = kernel
    return kernel


def reference_ci(xs, Ps, chunks):
    """Trace-optimal CI of pairs ``xs`` (size, 2, n), ``Ps`` (size, 2, n, n) by the reference
    kernel: ``(omega, x, P)``."""
    size, n = xs.shape[0], xs.shape[-1]
    omega, x, P = np.empty(size), np.empty((size, n)), np.empty((size, n, n))
    reference_kernel(n)(xs, Ps, chunks, omega, x, P)
    return omega, x, P


def rate(count, seconds):
    """Fusions per second, in M/s or k/s."""
    per_second = count / seconds
    if per_second >= 1e5:
        return f"{per_second / 1e6:6.2f} M/s"
    return f"{per_second / 1e3:6.1f} k/s"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=100_000)
    parser.add_argument("--sets", type=int, default=20_000)
    parser.add_argument("--loop-items", type=int, default=2000,
                        help="items timed in the per-item loops (scaled to the batch)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-compile", action="store_true",
                        help="skip the first-call (compile) measurement")
    args = parser.parse_args()

    import numba

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}, numba {numba.__version__} "
          f"({numba.get_num_threads()} threads)")
    if not args.no_compile:
        cold, warm = first_call_times()
        print("first call of each kernel in a new process (s), empty cache -> filled cache:")
        for label in cold:
            print(f"  {label:26s} {float(cold[label]):7.2f} -> {float(warm[label]):5.2f}")
        print(f"  {'total':26s} {sum(map(float, cold.values())):7.2f} -> "
              f"{sum(map(float, warm.values())):5.2f}")

    def compare(label, count, call, repeats=args.repeats):
        with cifilter.use_backend("numba"):
            call()  # compile / load from the cache
        times = {}
        for _ in range(repeats):  # interleaved: both backends see the same machine load
            for backend in ("numpy", "numba"):
                with cifilter.use_backend(backend):
                    t, _ = best_of(1, call)
                times[backend] = min(times.get(backend, np.inf), t)
        print(f"  {label:34s} numpy {times['numpy']:7.3f} s ({rate(count, times['numpy'])})"
              f"  numba {times['numba']:7.3f} s ({rate(count, times['numba'])})"
              f"  {times['numpy'] / times['numba']:5.1f}x")
        return times

    # ------------------------------------------------------------ 4x4 pairs
    xs, Ps = make_sets(args.pairs, 2, 4, args.seed)
    print(f"\n{args.pairs} pairs of 4x4 estimates (best of {args.repeats}):")
    compare("CI, optimal trace", args.pairs, lambda: cifilter.covariance_intersection(xs, Ps))
    compare("CI, optimal det", args.pairs,
            lambda: cifilter.covariance_intersection(xs, Ps, criterion="det"))
    compare("CI, given weights (0.5)", args.pairs,
            lambda: cifilter.covariance_intersection(xs, Ps, omega=0.5))
    compare("CI, omega='fast'", args.pairs,
            lambda: cifilter.covariance_intersection(xs, Ps, omega="fast"))
    compare("naive fusion", args.pairs, lambda: cifilter.naive_fusion(xs, Ps))

    # ------------------------------------------------------------ the reference kernel
    chunks = numba.get_num_threads()
    start = time.perf_counter()
    reference_ci(xs[:2], Ps[:2], 1)  # compile
    compile_seconds = time.perf_counter() - start
    timed = {"reference": np.inf, "numpy": np.inf, "numba": np.inf}
    results = {}
    for _ in range(args.repeats):  # interleaved: the three see the same machine load
        t, (omega_ref, x_ref, P_ref) = best_of(1, lambda: reference_ci(xs, Ps, chunks))
        timed["reference"] = min(timed["reference"], t)
        for backend in ("numpy", "numba"):
            with cifilter.use_backend(backend):
                t, results[backend] = best_of(
                    1, lambda: cifilter.covariance_intersection(xs, Ps))
            timed[backend] = min(timed[backend], t)
    print(f"  minimal reference kernel (this file; numba, {chunks} chunks, compiled in "
          f"{compile_seconds:.1f} s): {timed['reference']:.3f} s "
          f"({rate(args.pairs, timed['reference'])})")
    scale = np.sqrt(np.diagonal(P_ref, axis1=-2, axis2=-1).max(axis=-1))
    for backend in ("numpy", "numba"):
        result = results[backend]
        d_omega = np.abs(result.omega[:, 0] - omega_ref).max()
        d_P = (np.abs(result.P - P_ref).max(axis=(-2, -1))
               / np.abs(P_ref).max(axis=(-2, -1))).max()
        d_x = (np.abs(result.x - x_ref).max(axis=-1) / scale).max()
        print(f"    public path, {backend} backend: {timed[backend]:.3f} s, "
              f"{timed[backend] / timed['reference']:5.1f}x the reference; max |d omega| "
              f"{d_omega:.1e}, max rel. |d P| {d_P:.1e}, max |d x| / sd {d_x:.1e}")

    # what bounds the batched call: the front door's validation, and the kernel alone
    validation, est = best_of(args.repeats, lambda: as_estimates(xs, Ps))
    from cifilter._kernels import compiled as _kernels_ci

    size, n = args.pairs, 4
    W = np.zeros((1, 1, 1))
    kernel_ci = getattr(_kernels_ci, "ci_pair", None)
    if kernel_ci is not None:  # the kernel with the validation folded in (issue 24)
        mode_check, mode_gains = _kernels_ci.MODE_CHECK, _kernels_ci.MODE_GAINS

        def kernel_alone(mode, gains):
            scalars, x_out, P_out = np.empty((size, 8)), np.empty((size, n)), np.empty((size, n, n))
            K_out = np.empty((size if gains else 0, 2, n, n))
            x, P = np.array(xs), np.array(Ps)  # (the checking mode symmetrises in place)
            start = time.perf_counter()
            kernel_ci(x, P, np.array(est.L), W, 0, mode, scalars, x_out, P_out, K_out)
            return time.perf_counter() - start, scalars

        solve = min(kernel_alone(mode_gains, True)[0] for _ in range(args.repeats))
        checked = min(kernel_alone(mode_check | mode_gains, True)[0] for _ in range(args.repeats))
        lean, scalars = min((kernel_alone(mode_check, False) for _ in range(args.repeats)),
                            key=lambda pair: pair[0])
        print(f"  parts of the numba call: validation (as_estimates) {validation:.3f} s; "
              f"kernel ci_pair on validated input with gains {solve:.3f} s "
              f"({rate(size, solve)}), checking the raw input itself {checked:.3f} s "
              f"({rate(size, checked)}), checking and without gains {lean:.3f} s "
              f"({rate(size, lean)}); {int((scalars[:, 7] != 0).sum())} items handed back "
              "to numpy")
    else:  # an older tree (--tree-less runs of an older checkout): its kernel
        outs = [np.empty(size), np.zeros(size, dtype=int), np.empty(size), np.empty((size, n)),
                np.empty((size, n, n)), np.empty((size, 2, n, n)), np.empty(size),
                np.empty(size), np.empty(size, dtype=np.int8)]
        try:
            kernel, _ = best_of(args.repeats, lambda: _kernels_ci.ci_pair_optimal(
                est.x, est.P, est.L, W, 0, *outs))
            print(f"  parts of the numba call: validation (as_estimates) {validation:.3f} s, "
                  f"kernel alone {kernel:.3f} s ({rate(size, kernel)}), "
                  f"{int((outs[-1] != 0).sum())} items handed back to numpy")
        except (TypeError, AttributeError) as error:  # a changed private kernel: go on
            print(f"  parts of the numba call: validation (as_estimates) {validation:.3f} s; "
                  f"kernel alone not timed ({error})")

    with cifilter.use_backend("numba"):
        result = cifilter.covariance_intersection(xs, Ps)
    m = min(args.loop_items, args.pairs)
    scale = args.pairs / m
    loop, loop_omega = best_of(1, lambda: scipy_loop(xs[:m], Ps[:m]))
    soup, soup_out = stonesoup_loop(xs[:m], Ps[:m], result.omega[:m])
    print(f"  {'scipy minimize_scalar loop':34s} {loop * scale:7.2f} s "
          f"({rate(args.pairs, loop * scale)})"
          f"  (timed on {m}, scaled; max |omega - cifilter| "
          f"{np.abs(result.omega[:m, 0] - loop_omega).max():.1e}, its xatol is 1e-8)")
    P_soup = np.array([s.covar for s in soup_out])
    print(f"  {'Stone Soup merge, given weights':34s} {soup * scale:7.2f} s "
          f"({rate(args.pairs, soup * scale)})"
          f"  (timed on {m}, scaled; max rel. |P - cifilter| "
          f"{(np.abs(P_soup - result.P[:m]).max() / np.abs(result.P[:m]).max()):.1e})")

    # ------------------------------------------------------------ N = 4 of 6x6
    xs, Ps = make_sets(args.sets, 4, 6, args.seed + 1)
    print(f"\n{args.sets} sets of N = 4 estimates of 6x6 (best of {args.repeats}):")
    compare("CI, optimal trace (simplex)", args.sets,
            lambda: cifilter.covariance_intersection(xs, Ps), repeats=max(1, args.repeats // 2))
    compare("CI, given weights (1/4 each)", args.sets,
            lambda: cifilter.covariance_intersection(xs, Ps, omega=np.full(4, 0.25)))
    compare("naive fusion", args.sets, lambda: cifilter.naive_fusion(xs, Ps))
    with cifilter.use_backend("numpy"):
        result = cifilter.covariance_intersection(xs, Ps)
    m = min(args.loop_items, args.sets)
    soup, _ = stonesoup_loop(xs[:m], Ps[:m], result.omega[:m])
    print(f"  {'Stone Soup merge, given weights':34s} {soup * args.sets / m:7.2f} s "
          f"({rate(args.sets, soup * args.sets / m)})  (timed on {m}, scaled)")


if __name__ == "__main__":
    main()
