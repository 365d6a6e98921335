"""Batched optimal CI of N = 2, 3, ..., 10 estimates: the cost per item against N = 2.

Issue 24's target: optimal CI of N = 3 at most 4x N = 2 per item (batched), N = 10
reported. Everything is measured in one run on the same machine: batches of ``--size``
problems of N random n x n estimates (n = ``--dim``, default 4), trace- and det-optimal,
through the public ``covariance_intersection`` under each backend (``numpy`` and ``numba``;
the kernels are compiled, or loaded from numba's cache, before timing). Per row: the
microseconds per item (best of ``--repeats``), the ratio to N = 2 under the same backend
and criterion, the share of items converged and the solver's median iterations.

    python benchmarks/bench_many.py                       # N = 2, 3, 4, 6, 10; 20 000 items
    python benchmarks/bench_many.py --counts 2 3 --size 50000 --backends numba

``--dims`` measures instead where the kernels lose to numpy (LAPACK) by dimension, the
crossover behind ``cifilter._kernels.dispatch.AUTO_MAX_DIM``: trace-optimal CI of
``--size`` problems (default 4096, so that the threaded kernels run) of N = ``--counts``
estimates of each n in ``--dim-list``, under ``numpy``, under ``numba`` with BLAS pinned to
one thread around the threaded kernels (``dispatch.PIN_BLAS``, the default) and under
``numba`` without the pinning, interleaved, best of ``--repeats``; per row the microseconds
per item and numpy's time over each numba variant (above 1: the kernels win).

    python benchmarks/bench_many.py --dims --counts 2 3 --size 4096
"""

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cifilter  # noqa: E402
from cifilter._kernels import dispatch  # noqa: E402
from cifilter.backend import compile_kernels, numba_available  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_ci import make_sets  # noqa: E402  (the same random sets as bench_ci)


def best_of(repeats, call):
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = call()
        best = min(best, time.perf_counter() - start)
    return best, result


def by_dimension(args):
    """The crossover by n (see the module docstring)."""
    print(f"{'N':>3} {'n':>3} {'numpy us':>9} {'pinned us':>10} {'unpinned us':>12} "
          f"{'numpy/pinned':>13} {'numpy/unpinned':>15}")
    for count in args.counts:
        for n in args.dim_list:
            xs, Ps = make_sets(args.size, count, n, args.seed + n)
            best = {"numpy": np.inf, "pinned": np.inf, "unpinned": np.inf}
            for _ in range(args.repeats):
                for name in best:
                    dispatch.PIN_BLAS = name != "unpinned"
                    with cifilter.use_backend("numpy" if name == "numpy" else "numba"):
                        seconds, _ = best_of(1, lambda xs=xs, Ps=Ps: (
                            cifilter.covariance_intersection(xs, Ps)))
                    best[name] = min(best[name], seconds)
            dispatch.PIN_BLAS = True
            us = {name: 1e6 * value / args.size for name, value in best.items()}
            print(f"{count:>3} {n:>3} {us['numpy']:>9.2f} {us['pinned']:>10.2f} "
                  f"{us['unpinned']:>12.2f} {best['numpy'] / best['pinned']:>12.2f}x "
                  f"{best['numpy'] / best['unpinned']:>14.2f}x", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[2, 3, 4, 6, 10])
    parser.add_argument("--size", type=int, default=20000)
    parser.add_argument("--dim", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--criteria", nargs="+", default=["trace", "det"])
    parser.add_argument("--backends", nargs="+", default=["numpy", "numba"])
    parser.add_argument("--dims", action="store_true",
                        help="measure the numpy/numba crossover by dimension instead")
    parser.add_argument("--dim-list", type=int, nargs="+", default=[2, 4, 6, 8, 10, 12, 16, 32])
    args = parser.parse_args()
    backends = [b for b in args.backends if b != "numba" or numba_available()]
    if "numba" in backends:
        compile_kernels()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.2f}; numpy {np.__version__}; {args.size} items of "
          f"{args.dim}x{args.dim}, best of {args.repeats}")
    if args.dims:
        by_dimension(args)
        return
    print(f"{'backend':<7} {'crit':<6} {'N':>3} {'us/item':>9} {'x N=2':>7} {'conv':>6} "
          f"{'iter':>5} {'solver':>12}")
    for backend in backends:
        for criterion in args.criteria:
            base = None
            for count in args.counts:
                xs, Ps = make_sets(args.size, count, args.dim, args.seed + count)
                with cifilter.use_backend(backend):
                    seconds, r = best_of(args.repeats, lambda xs=xs, Ps=Ps, c=criterion: (
                        cifilter.covariance_intersection(xs, Ps, c)))
                per_item = 1e6 * seconds / args.size
                if count == 2 or base is None:
                    base = per_item
                print(f"{backend:<7} {criterion:<6} {count:>3} {per_item:>9.2f} "
                      f"{per_item / base:>6.1f}x {r.info['converged'].mean():>6.3f} "
                      f"{int(np.median(r.info['iterations'])):>5} {r.info['solver']:>12}",
                      flush=True)


if __name__ == "__main__":
    main()
