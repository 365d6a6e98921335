"""Covariance union, largest ellipsoid and sampling CI: one batched call against a loop.

For each rule the batched call fuses all pairs at once (arrays of shape (pairs, 2, n) and
(pairs, 2, n, n)); the baseline calls the same public function once per pair, the way a
tracker without batching would. Both run in the same process on the same data; the script
prints the timings, their ratio and the largest difference between the two answers.

    python benchmarks/bench_union_le_sci.py                 # 2000 pairs of 4x4 (about 30 s)
    python benchmarks/bench_union_le_sci.py --pairs 500 --loop-pairs 200
"""

import argparse
import os
import platform

import numpy as np
from bench_ci import best_of  # the benchmarks' timing helper (run as a script from benchmarks/)

import cifilter


def make_pairs(pairs, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((pairs, 2, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    xs = rng.standard_normal((pairs, 2, n))
    return xs, Ps


RULES = {
    "cu (trace)": lambda xs, Ps: cifilter.covariance_union(xs, Ps),
    "cu (det)": lambda xs, Ps: cifilter.covariance_union(xs, Ps, criterion="det"),
    "le": lambda xs, Ps: cifilter.largest_ellipsoid(xs, Ps),
    # each pair draws its own directions in the loop, the batch draws them all at once:
    # the same number of samples, different draws, so the answers differ by sampling
    "sci": lambda xs, Ps: cifilter.sampling_ci(xs, Ps, rng=0),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--loop-pairs", type=int, default=None,
                        help="pairs timed in the loop (default: all); the loop's time is "
                             "scaled to --pairs and the output says so")
    parser.add_argument("--dim", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    loop_pairs = args.pairs if args.loop_pairs is None else min(args.loop_pairs, args.pairs)
    xs, Ps = make_pairs(args.pairs, args.dim, args.seed)

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}")
    print(f"pairs: {args.pairs} of {args.dim}x{args.dim} covariances"
          + ("" if loop_pairs == args.pairs else f" (loop timed on {loop_pairs}, scaled)"))
    print(f"{'rule':<12} {'batched [s]':>12} {'loop [s]':>10} {'speed-up':>9} "
          f"{'max |dP| / |P|':>15}")
    for name, rule in RULES.items():
        batched_time, batched = best_of(3, lambda rule=rule: rule(xs, Ps))
        loop_time, looped = best_of(1, lambda rule=rule: [
            rule(list(xs[k]), list(Ps[k])) for k in range(loop_pairs)])
        loop_total = loop_time * args.pairs / loop_pairs
        P_loop = np.array([r.P for r in looped])
        difference = (np.abs(P_loop - batched.P[:loop_pairs]).max()
                      / np.abs(batched.P[:loop_pairs]).max())
        print(f"{name:<12} {batched_time:12.3f} {loop_total:10.3f} "
              f"{loop_total / batched_time:8.1f}x {difference:15.2e}")


if __name__ == "__main__":
    main()
