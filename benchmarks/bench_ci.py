"""Batched trace-optimal Covariance Intersection against a per-pair Python loop.

The batched call optimises the weights of all pairs at once (cifilter.covariance_intersection
on arrays of shape (pairs, 2, 4) and (pairs, 2, 4, 4)). The baseline fuses one pair at a time
the way one would without cifilter: invert both covariances, minimise trace(P(omega)) with
scipy.optimize.minimize_scalar (bounded, xatol=1e-8, the same tolerance the issue asks of
cifilter), then form P and x. Both run in the same process on the same data; the script prints
the timings, their ratio and the largest difference in omega.

    python benchmarks/bench_ci.py            # 100 000 pairs, full loop (about 30 s)
    python benchmarks/bench_ci.py --pairs 20000 --loop-pairs 2000
"""

import argparse
import os
import platform
import time

import numpy as np
from scipy.optimize import minimize_scalar

import cifilter


def make_pairs(pairs, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((pairs, 2, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    xs = rng.standard_normal((pairs, 2, n))
    return xs, Ps


def loop_fusion(xs, Ps):
    """One scipy-optimised CI fusion per pair: the baseline."""
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


def best_of(repeats, function):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return min(times), result


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=100_000)
    parser.add_argument("--loop-pairs", type=int, default=None,
                        help="pairs timed in the loop (default: all); the loop's time is "
                             "scaled to --pairs and the output says so")
    parser.add_argument("--dim", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    loop_pairs = args.pairs if args.loop_pairs is None else min(args.loop_pairs, args.pairs)

    xs, Ps = make_pairs(args.pairs, args.dim, args.seed)
    batched_time, result = best_of(3, lambda: cifilter.covariance_intersection(xs, Ps))
    loop_time, loop_omega = best_of(1, lambda: loop_fusion(xs[:loop_pairs], Ps[:loop_pairs]))
    loop_total = loop_time * args.pairs / loop_pairs

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}")
    print(f"pairs: {args.pairs} of {args.dim}x{args.dim} covariances, trace criterion")
    print(f"batched cifilter.covariance_intersection: {batched_time:8.3f} s "
          f"(best of 3; iterations max {int(result.info['iterations'].max())}, "
          f"all converged {bool(result.info['converged'].all())})")
    scaled = "" if loop_pairs == args.pairs else f" (timed on {loop_pairs} pairs, scaled)"
    print(f"loop of minimize_scalar fusions:          {loop_total:8.3f} s{scaled}")
    print(f"speed-up: {loop_total / batched_time:.1f}x")
    print(f"max |omega_batched - omega_loop|: "
          f"{np.abs(result.omega[:loop_pairs, 0] - loop_omega).max():.2e} "
          "(the loop's xatol is 1e-8)")


if __name__ == "__main__":
    main()
