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
  numpy and numba backends, and Stone Soup's merge per set.

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

    # what bounds the batched call: the front door's validation, and the kernel alone
    validation, est = best_of(args.repeats, lambda: as_estimates(xs, Ps))
    from cifilter._kernels import compiled as _kernels_ci

    size, n = args.pairs, 4
    outs = [np.empty(size), np.zeros(size, dtype=int), np.empty(size), np.empty((size, n)),
            np.empty((size, n, n)), np.empty((size, 2, n, n)), np.empty(size), np.empty(size),
            np.empty(size, dtype=np.int8)]
    W = np.zeros((1, 1, 1))
    kernel, _ = best_of(args.repeats, lambda: _kernels_ci.ci_pair_optimal(
        est.x, est.P, est.L, W, 0, *outs))
    print(f"  parts of the numba call: validation (as_estimates) {validation:.3f} s, "
          f"kernel alone {kernel:.3f} s ({rate(size, kernel)}), "
          f"{int((outs[-1] != 0).sum())} items handed back to numpy")

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
