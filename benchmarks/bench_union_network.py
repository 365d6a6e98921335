"""Covariance union on the problems of the network demo: as the demo calls it, batched, looped.

The default demo (``python -m cifilter demo``: six nodes, one neighbour at a time, feedback,
10 runs x 40 steps, seed 0) fuses with ``"cu"`` 5600 times in 240 calls of about 23
two-estimate problems. Their optimal means are hard: the two covariances differ by nearly
rank-deficient matrices, and most problems finish on the solver's smoothed continuation
(``docs/methods/union.rst``). This benchmark records those problems (a rule registered under
another name that calls :func:`cifilter.covariance_union` and keeps its inputs), then times
them three ways in the same run:

* as the demo calls it: one call per recorded batch;
* all problems in one call;
* one problem per call (``--loop-problems`` of them, scaled to all).

It prints the time per problem, the share certified (``converged``), the share finished on
the smoothed continuation and percentiles of the iterations.

    python benchmarks/bench_union_network.py
    python benchmarks/bench_union_network.py --runs 4 --loop-problems 200
"""

import argparse
import io
import os
import platform

import numpy as np
from bench_ci import best_of  # the benchmarks' timing helper (run as a script from benchmarks/)

import cifilter
from cifilter import covariance_union, register_method
from cifilter.cli.demo import run_network_demo


def record_demo_problems(runs, steps, seed):
    """The (xs, Ps) batches the demo's ``"cu"`` fusions receive, in call order."""
    batches = []

    def recording_union(xs, Ps, **options):
        batches.append((np.array(xs), np.array(Ps)))
        return covariance_union(xs, Ps, **options)

    register_method("cu-recorded", recording_union, guarantee="bound", replace=True,
                    summary="covariance union, inputs recorded (benchmark)")
    run_network_demo(seed=seed, runs=runs, steps=steps, methods=["cu-recorded"],
                     scenario="naveen-taylor", out=io.StringIO())
    return batches


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--loop-problems", type=int, default=500,
                        help="problems timed one per call; scaled to all, and said so")
    args = parser.parse_args()

    batches = record_demo_problems(args.runs, args.steps, args.seed)
    xs = np.concatenate([b[0] for b in batches])
    Ps = np.concatenate([b[1] for b in batches])
    total = len(xs)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, numpy {np.__version__}, "
          f"cifilter {cifilter.__version__}")
    print(f"{total} covariance-union problems of the demo ({args.runs} runs x {args.steps} "
          f"steps) in {len(batches)} calls (mean {total / len(batches):.1f} per call)\n")

    as_demo, results = best_of(1, lambda: [covariance_union(x, P) for x, P in batches])
    one_call, batched = best_of(1, lambda: covariance_union(xs, Ps))
    loop = min(args.loop_problems, total)
    looped, _ = best_of(1, lambda: [covariance_union(xs[i], Ps[i]) for i in range(loop)])
    looped *= total / loop

    info = {key: np.concatenate([np.atleast_1d(r.info[key]) for r in results])
            for key in ("converged", "smoothed", "iterations", "gap")}
    print(f"{'how':38s} {'total [s]':>10s} {'per problem [us]':>17s}")
    print(f"{'as the demo calls it (per batch)':38s} {as_demo:10.2f} "
          f"{1e6 * as_demo / total:17.0f}")
    print(f"{'all problems in one call':38s} {one_call:10.2f} {1e6 * one_call / total:17.0f}")
    scaled = "" if loop == total else f" ({loop} timed, scaled)"
    print(f"{'one problem per call' + scaled:38s} {looped:10.2f} {1e6 * looped / total:17.0f}")
    print(f"\nper batch vs one per call: {looped / as_demo:.1f}x; one call vs per batch: "
          f"{as_demo / one_call:.1f}x")
    print(f"certified (gap <= 1e-9): {info['converged'].mean():.2%}, largest gap "
          f"{info['gap'].max():.2e}; finished on the smoothed continuation: "
          f"{info['smoothed'].mean():.1%}")
    q = np.percentile(info["iterations"], [50, 90, 99, 100])
    print("iterations (continuation's Newton steps included): median {:.0f}, 90% {:.0f}, "
          "99% {:.0f}, max {:.0f}".format(*q))
    same = np.abs(np.trace(batched.P, axis1=-2, axis2=-1)
                  - np.concatenate([np.trace(r.P, axis1=-2, axis2=-1) for r in results]))
    print(f"trace(P), one call vs per batch: largest relative difference "
          f"{(same / np.trace(batched.P, axis1=-2, axis2=-1)).max():.1e} (both certified)")


if __name__ == "__main__":
    main()
