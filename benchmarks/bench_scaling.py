"""CI and partial CI in the number of estimates N, against the naive fusion of the same.

For each N (default 2, 3, 10, 30, 100, 300, 1000) one problem of N random 3x3 estimates is
fused by trace-optimal Covariance Intersection (``cifilter.covariance_intersection``),
by partial CI (``cifilter.partial_ci``, ``rho`` 0.5, the Newton solver, default ``tol``
and ``max_iter``) and by the naive fusion (``cifilter.naive_fusion``) of the same
estimates, in the same process. The table gives seconds per call (best of ``--repeats``,
fewer once a row has spent 2 s), the solver's iterations, ``converged``, the certified
gap, the number of nonzero weights, the trace of ``P`` and the ratio of the time to the
naive fusion's time measured beside it (ratios are what carry over between machines).

Each (rule, N) runs in a child process with a time limit (``--limit``, seconds); a call
that does not finish in it is reported as ``> limit`` and the run goes on.

    python benchmarks/bench_scaling.py
    python benchmarks/bench_scaling.py --counts 10 100 --repeats 3 --limit 60

Measured on 2 shared cores with ``OMP_NUM_THREADS=1`` (``docs/methods/simplex_solver.rst``
has the table): N = 1000 takes CI 13 iterations, 1.6 s (48 times the naive fusion), and
partial CI 17 iterations, 2.5 s (88 times), with the Gram form of the Hessian
(``trace_curvature``, ``log_det_curvature``); with the pairwise form before it 10.7 s
(687 times) and 12.9 s (990 times) in the same session, the same iterations and results.

``--solver FILE`` runs the rules with another implementation of
``cifilter/_numerics/optimize.py`` (for instance the previous one, from
``git show HEAD~1:cifilter/_numerics/optimize.py > /tmp/old_optimize.py``): its
``minimize_convex_simplex`` replaces the one the rules call, so that two solvers are
compared on the same machine in the same session.
"""

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cifilter  # noqa: E402

COUNTS = (2, 3, 10, 30, 100, 300, 1000)


def make_estimates(count, n, seed):
    """``count`` random estimates of dimension ``n``: ``P = A A^T + 0.1 I``, A standard normal."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((count, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    return rng.standard_normal((count, n)), Ps


def best_of(repeats, function, budget=2.0):
    """The shortest of ``repeats`` calls; no more calls once ``budget`` seconds are spent."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
        if sum(times) > budget:
            break
    return min(times), result


def use_solver(path):
    """Make the rules call ``minimize_convex_simplex`` from the module file ``path``."""
    spec = importlib.util.spec_from_file_location("replacement_optimize", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from cifilter.horizon import _ci as horizon_ci
    from cifilter.horizon import _pci as horizon_pci
    from cifilter.rules import _ci_weights, _partial_correlation

    for target in (_ci_weights, _partial_correlation, horizon_ci, horizon_pci):
        target.minimize_convex_simplex = module.minimize_convex_simplex


def measure(rule, count, args):
    """One row, in this process: the rule's time and the naive fusion's beside it."""
    if args.solver:
        use_solver(args.solver)
    xs, Ps = make_estimates(count, args.dim, args.seed)
    naive_time, _ = best_of(args.repeats, lambda: cifilter.naive_fusion(xs, Ps))
    if rule == "ci":
        def call():
            return cifilter.covariance_intersection(xs, Ps)
    else:
        def call():
            return cifilter.partial_ci(xs, Ps, args.rho)
    seconds, result = best_of(args.repeats, call)
    naive_again, _ = best_of(args.repeats, lambda: cifilter.naive_fusion(xs, Ps))
    naive_time = min(naive_time, naive_again)
    weights = result.omega if rule == "ci" else result.info["delta"]
    return {
        "seconds": seconds, "naive": naive_time,
        "iterations": int(result.info["iterations"]),
        "converged": bool(result.info["converged"]),
        "gap": float(result.info["gap"]),
        "support": int(np.count_nonzero(weights)),
        "value": float(np.trace(result.P)),
    }


def run_child(rule, count, args):
    command = [sys.executable, __file__, "--child", rule, str(count), "--dim", str(args.dim),
               "--seed", str(args.seed), "--repeats", str(args.repeats), "--rho", str(args.rho)]
    if args.solver:
        command += ["--solver", args.solver]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=args.limit,
                              check=False)
    except subprocess.TimeoutExpired:
        return None
    if done.returncode != 0:
        raise RuntimeError(f"{rule} N={count} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=list(COUNTS))
    parser.add_argument("--dim", type=int, default=3)
    parser.add_argument("--rho", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--limit", type=float, default=120.0,
                        help="seconds allowed for one (rule, N) child process (default 120)")
    parser.add_argument("--solver", default=None,
                        help="a module file whose minimize_convex_simplex the rules use")
    parser.add_argument("--child", nargs=2, metavar=("RULE", "N"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        rule, count = args.child
        print(json.dumps(measure(rule, int(count), args)))
        return

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}; solver: {args.solver or 'cifilter/_numerics/optimize.py'}")
    print(f"one problem of N random {args.dim}x{args.dim} estimates per row, best of "
          f"{args.repeats}; partial CI with rho = {args.rho}; limit {args.limit:g} s per row")
    print(f"{'rule':<5} {'N':>5} {'s/call':>10} {'naive s':>10} {'ratio':>9} {'iter':>5} "
          f"{'conv':>5} {'gap':>9} {'support':>7} {'trace P':>12}")
    for count in args.counts:
        for rule in ("ci", "pci"):
            row = run_child(rule, count, args)
            if row is None:
                print(f"{rule:<5} {count:>5} {'> ' + format(args.limit, 'g'):>10}")
                continue
            print(f"{rule:<5} {count:>5} {row['seconds']:>10.4f} {row['naive']:>10.5f} "
                  f"{row['seconds'] / row['naive']:>8.0f}x {row['iterations']:>5} "
                  f"{row['converged']!s:>5} {row['gap']:>9.1e} {row['support']:>7} "
                  f"{row['value']:>12.6g}", flush=True)


if __name__ == "__main__":
    main()
