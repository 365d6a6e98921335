"""The network demo's Monte Carlo runs per second: batched over runs against per-run loops.

The six-node network of Naveen & Taylor (cifilter.network.naveen_taylor), every node
fusing its neighbours' estimates every step with feedback, all at once (one fusion of the
own and the received estimates per node and step). Three ways, on the same data:

* batched: ``cifilter.network.run_network`` on all runs at once (filters of all runs and
  nodes updated together, one ``cifilter.fuse`` call per group of (run, node) pairs);
* per-run loop, same code: ``run_network`` called once per run (one run per call), which
  isolates what batching over runs buys;
* per-run loop, filter objects: what a user would write without ``cifilter.network``: one
  ``cifilter.KalmanFilter`` per node and run, ``predict``/``update``, then
  ``kf.fuse(neighbours, method=...)`` on a snapshot of the neighbours' estimates. Its
  results are checked against the batched ones.

Loops run on ``--loop-runs`` runs and are scaled to runs/s. Rules with a truth hook
(``optimal``) are not in the filter-object loop (a node does not know the joint covariance).

    python benchmarks/bench_network.py                   # 60 runs x 40 steps, ci and naive
    python benchmarks/bench_network.py --methods ci,naive,optimal --runs 100
    python benchmarks/bench_network.py --sequential      # one received estimate at a time
"""

import argparse
import os
import platform

import numpy as np
from bench_ci import best_of  # the benchmarks' timing helper (run as a script from benchmarks/)

import cifilter
from cifilter import KalmanFilter
from cifilter.network import NetworkData, naveen_taylor, run_network, simulate_data


def per_run(scenario, data, runs, method, **config):
    return [run_network(scenario, one_run(data, r), method, **config) for r in range(runs)]


def per_run_objects(scenario, data, runs, method, sequential):
    return [filter_objects(scenario, data, r, method, sequential) for r in range(runs)]


def one_run(data, r):
    return NetworkData(data.truth[r:r + 1], tuple(z[r:r + 1] for z in data.measurements),
                       data.initial[r:r + 1])


def filter_objects(scenario, data, r, method, sequential):
    """One run with a cifilter.KalmanFilter per node and kf.fuse."""
    nodes, steps = scenario.nodes, data.steps
    filters = []
    for i in range(nodes):
        kf = KalmanFilter(dim_x=scenario.dim, dim_z=scenario.H[i].shape[0])
        kf.F, kf.Q, kf.H, kf.R = scenario.F, scenario.Q, scenario.H[i], scenario.R[i]
        kf.x, kf.P = data.initial[r, i].reshape(-1, 1).copy(), scenario.P0[i].copy()
        filters.append(kf)
    neighbours = [np.flatnonzero(scenario.adjacency[i]) for i in range(nodes)]
    out = np.empty((steps, nodes, scenario.dim))
    for k in range(steps):
        for i, kf in enumerate(filters):
            kf.predict()
            kf.update(data.measurements[i][r, k].reshape(-1, 1))
        snapshot = [(kf.x.copy(), kf.P.copy()) for kf in filters]
        for i, kf in enumerate(filters):
            if sequential:  # one received estimate at a time, in the senders' order
                for j in neighbours[i]:
                    kf.fuse(snapshot[j], method=method)
            else:
                kf.fuse([snapshot[j] for j in neighbours[i]], method=method)
        out[k] = [kf.x[:, 0] for kf in filters]
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=60)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--loop-runs", type=int, default=10)
    parser.add_argument("--methods", default="ci,naive")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sequential", action="store_true",
                        help="fuse the received estimates one at a time (as the demo)")
    args = parser.parse_args()
    print(f"cifilter {cifilter.__version__}, numpy {np.__version__}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    scenario = naveen_taylor()
    data = simulate_data(scenario, args.runs, args.steps, rng=args.seed)
    loop_runs = min(args.loop_runs, args.runs)
    mode = "one-at-a-time" if args.sequential else "all-at-once"
    print(f"six-node network, feedback every step, {mode} fusion, {args.steps} steps; "
          f"batched: {args.runs} runs (best of {args.repeat}), loops: {loop_runs} runs\n")
    header = (f"{'method':<8} {'batched [runs/s]':>17} {'loop, same code':>16} "
              f"{'loop, kf.fuse':>14} {'vs same code':>13} {'vs kf.fuse':>11}")
    print(header)
    print("-" * len(header))
    for method in args.methods.split(","):
        batched, track = best_of(args.repeat, lambda m=method: run_network(
            scenario, data, m, sequential=args.sequential))
        looped, _ = best_of(1, lambda m=method: per_run(scenario, data, loop_runs, m,
                                                        sequential=args.sequential))
        rate, rate_loop = args.runs / batched, loop_runs / looped
        objects = "-"
        ratio_objects = "-"
        if cifilter.get_method(method).truth_options is None:
            elapsed, results = best_of(1, lambda m=method: per_run_objects(
                scenario, data, loop_runs, m, args.sequential))
            worst = max(float(np.max(np.abs(results[r] - track.x[r])))
                        for r in range(loop_runs))
            if worst > 1e-6 * max(1.0, float(np.max(np.abs(track.x)))):
                raise SystemExit(f"{method}: filter objects disagree with the batched "
                                 f"network by {worst:.3g}")
            objects = f"{loop_runs / elapsed:.1f}"
            ratio_objects = f"{rate / (loop_runs / elapsed):.0f}x"
        print(f"{method:<8} {rate:>17.1f} {rate_loop:>16.1f} {objects:>14} "
              f"{rate / rate_loop:>12.0f}x {ratio_objects:>11}")


if __name__ == "__main__":
    main()
