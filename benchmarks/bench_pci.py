"""Batched partial-correlation CI against a per-item Python loop.

The batched call runs the alternating projections (Algorithm 1 for pairs, Algorithm 2 for
more estimates) of all problems together (cifilter.partial_ci on arrays (problems, N, n) and
(problems, N, n, n)); the baseline calls cifilter.partial_ci once per problem, the way one
would fuse one pair at a time. Both run in the same process on the same data with the same
tolerance; the script prints the timings, their ratio and the largest difference in the
trace of the bound. The Newton solver is timed the same way.

    python benchmarks/bench_pci.py                       # 20 000 problems (about 1 min)
    python benchmarks/bench_pci.py --problems 5000 --loop-problems 500
"""

import argparse
import os
import platform

import numpy as np
from bench_ci import best_of  # the benchmarks' directory is on the path of a script

import cifilter


def make_problems(problems, count, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((problems, count, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    xs = rng.standard_normal((problems, count, n))
    return xs, Ps


def loop_fusion(xs, Ps, rho, solver):
    """One partial_ci call per problem: the baseline."""
    return np.array([
        cifilter.partial_ci(xs[k], Ps[k], rho, solver=solver).info["value"]
        for k in range(len(xs))
    ])


def report(count, solver, xs, Ps, rho, loop_problems):
    """Time both ways on the same data and print one row."""
    problems = len(xs)
    batched_time, result = best_of(3, lambda: cifilter.partial_ci(xs, Ps, rho, solver=solver))
    loop_time, loop_values = best_of(
        1, lambda: loop_fusion(xs[:loop_problems], Ps[:loop_problems], rho, solver))
    loop_total = loop_time * problems / loop_problems
    iterations = result.info["iterations"]
    difference = np.abs(result.info["value"][:loop_problems] / loop_values - 1).max()
    print(f"{count:>2} {solver:<12} {batched_time:>11.3f} {loop_total:>9.2f} "
          f"{loop_total / batched_time:>8.1f}x "
          f"{int(np.median(iterations)):>5}/{int(iterations.max()):<6} "
          f"{result.info['converged'].mean():>9.1%} {difference:>13.1e}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=20_000)
    parser.add_argument("--loop-problems", type=int, default=2_000,
                        help="problems timed in the loop (default 2000); the loop's time is "
                             "scaled to --problems and the output says so")
    parser.add_argument("--dim", type=int, default=4)
    parser.add_argument("--rho", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    loop_problems = min(args.loop_problems, args.problems)

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}")
    print(f"problems: {args.problems} with {args.dim}x{args.dim} covariances, rho = {args.rho}, "
          f"tol 1e-10, max_iter 100; loop timed on {loop_problems} and scaled")
    print(f"{'N':>2} {'solver':<12} {'batched [s]':>11} {'loop [s]':>9} {'speed-up':>9} "
          f"{'iter med/max':>12} {'converged':>9} {'max |dTr|/Tr':>13}")
    for count in (2, 3):
        xs, Ps = make_problems(args.problems, count, args.dim, args.seed)
        for solver in ("alternating", "newton"):
            report(count, solver, xs, Ps, args.rho, loop_problems)

if __name__ == "__main__":
    main()
