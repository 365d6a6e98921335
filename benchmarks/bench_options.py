"""Latency of ``kf.fuse`` with the front door's options of issue 22, against plain ``kf.fuse``.

One fusion of a 4-state constant-velocity filter (the model of ``bench_latency.py``) with
one other track, timed in the same process and the same run:

* ``plain``: ``kf.fuse(other)`` (a 4-state track), the baseline;
* ``H=``: ``kf.fuse(position_track, H=H)`` (a 2-D position-only track);
* ``lag=+1``, ``lag=+3``: a track 1 or 3 steps old, predicted with the filter's F and Q;
* ``lag=-1``, ``lag=-3``: a track 1 or 3 steps ahead, retrodicted with the bound;
* ``residual=``: ``kf.fuse(other, residual=...)`` with a heading-wrapping residual;
* ``plain, +1 done`` ... ``plain, -3 done``: plain ``kf.fuse`` of the other track predicted
  or retrodicted (the bound, written out) beforehand, the CI problem of the ``lag=`` row of
  the same steps: the difference to it is the cost of the option itself;

for the criteria ``trace`` and ``det``. Every call is timed on its own and the rows'
calls are interleaved one by one (``--repeat`` rounds of ``--number`` calls of each row,
each round in a new, seeded order), so that a disturbance of the shared machine, and the
cache footprint of the call before, hit every row alike; each row reports its
least disturbed call (the minimum, timeit's advice) and its median call, each divided by
the baseline of the same criterion. With ``--blocks`` each row's calls of a round run in
a row instead (the rows in a new seeded order each round): the latency of a tracker that
calls one kind of fusion in a loop, its code and data warm, where the interleaved order
also charges each row for the cache misses of running after other kinds of call. The
issue's target: ``H=`` and ``lag=`` cost at most 1.5x
the plain call. Run it with

    python benchmarks/bench_options.py
    python benchmarks/bench_options.py --number 300 --repeat 15
    python benchmarks/bench_options.py --backend numba   # the compiled kernels, warmed up
    python benchmarks/bench_options.py --backend numba --blocks   # one kind of call at a time

``--backend`` selects the backend of the CI family (``cifilter.set_backend``; default
``auto``, under which single calls run on the compiled kernels once they are in numba's
cache and on numpy before; ``numba`` runs the compiled kernels on single calls, compiled
during the warm-up if no cache has them; ``numpy`` never runs them). A tree other than the
installed one is timed with ``--tree PATH`` (put first on ``sys.path``), so that an older
checkout is measured by the same script.
"""

import argparse
import sys
import time

import numpy as np

cifilter = None  # imported by run(), from --tree when given


def _model():
    dt = 1.0
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    Q = np.kron(np.eye(2), q) * 0.1
    Q = Q[[0, 2, 1, 3]][:, [0, 2, 1, 3]]  # state (x, y, vx, vy)
    return F, Q


def _estimates():
    rng = np.random.default_rng(7)
    A = rng.standard_normal((2, 4, 4))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(4)
    return rng.standard_normal((2, 4)), Ps


def _steps(F, Q):
    def motion(steps):
        F_k, Q_k = F, Q
        for _ in range(round(float(steps)) - 1):
            F_k, Q_k = F @ F_k, F @ Q_k @ F.T + Q
        return F_k, Q_k
    return motion


def _predicted(other, F, Q, k):
    F_k, Q_k = _steps(F, Q)(k)
    return F_k @ other[0], F_k @ other[1] @ F_k.T + Q_k


def _retrodicted(other, F, Q, k):
    """The bound of docs/methods/time.rst (T5)-(T6), written out."""
    F_k, Q_k = _steps(F, Q)(k)
    F_inv = np.linalg.inv(F_k)
    A, B = F_inv @ other[1] @ F_inv.T, F_inv @ Q_k @ F_inv.T
    alpha = np.sqrt(np.trace(A)) / (np.sqrt(np.trace(A)) + np.sqrt(np.trace(B)))
    P = A / alpha + B / (1 - alpha)
    return F_inv @ other[0], 0.5 * (P + P.T)


def wrap_first(a, b):
    d = a - b
    d[0] = (d[0] + np.pi) % (2 * np.pi) - np.pi
    return d


def rows(criterion):
    """(label, other, options) for one criterion."""
    xs, Ps = _estimates()
    other = (xs[1], Ps[1])
    H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    position = (H @ xs[1], H @ Ps[1] @ H.T)
    base = {"criterion": criterion}
    F, Q = _model()
    # the "done" rows: the other track brought forward or back beforehand, fused plainly:
    # the CI problem the lag= row of the same steps solves (it changes with the shift)
    return [
        ("plain", other, base),
        ("H=", position, dict(base, H=H)),
        ("lag=+1", other, dict(base, lag=1)),
        ("lag=+3", other, dict(base, lag=3)),
        ("lag=-1", other, dict(base, lag=-1)),
        ("lag=-3", other, dict(base, lag=-3)),
        ("residual=", other, dict(base, residual=wrap_first)),
        ("plain, +1 done", _predicted(other, F, Q, 1), base),
        ("plain, +3 done", _predicted(other, F, Q, 3), base),
        ("plain, -1 done", _retrodicted(other, F, Q, 1), base),
        ("plain, -3 done", _retrodicted(other, F, Q, 3), base),
    ]


def _import(tree=None):
    global cifilter
    if tree:
        sys.path.insert(0, tree)
    import cifilter as module

    cifilter = module
    return module


def run(number=200, repeat=9, criteria=("trace", "det"), backend=None, tree=None,
        blocks=False):
    """Per row: the least disturbed call (the minimum over ``number * repeat`` timed
    calls) and the median call, with the rows' calls interleaved (``blocks``: each row's
    ``number`` calls of a round in a row, the rows in a new order each round)."""
    cifilter = _import(tree)
    if backend is not None:
        cifilter.set_backend(backend)
    F, Q = _model()
    xs, Ps = _estimates()
    x0, P0 = xs[0].reshape(4, 1).copy(), Ps[0].copy()
    kf = cifilter.KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.Q = F, Q
    table = [(criterion, label, other, options) for criterion in criteria
             for label, other, options in rows(criterion)]
    samples = {(criterion, label): [] for criterion, label, _, _ in table}
    solvers = {}
    clock = time.perf_counter
    for criterion, label, other, options in table:  # warm up, and record the solver
        for _ in range(20):
            kf.x, kf.P = x0, P0
            kf.fuse(other, **options)
        solvers[(criterion, label)] = kf.last_fusion.info.get("solver", "")
    # Each round times the rows in a new order (seeded): a row timed always right after the
    # same one inherits that one's cache footprint (in a fixed order, the plain call of the
    # lag=+3 problem, timed after residual=, took 1.26x the plain call it otherwise matches).
    order = np.random.default_rng(0)
    for _ in range(repeat):
        if blocks:  # one row at a time, as a tracker that calls one fusion in a loop
            schedule = [index for index in order.permutation(len(table))
                        for _ in range(number)]
        else:
            schedule = [index for _ in range(number)
                        for index in order.permutation(len(table))]
        for index in schedule:
            criterion, label, other, options = table[index]
            kf.x, kf.P = x0, P0
            start = clock()
            kf.fuse(other, **options)
            samples[(criterion, label)].append(clock() - start)
    best = {key: min(values) for key, values in samples.items()}
    median = {key: float(np.median(values)) for key, values in samples.items()}
    return best, median, solvers


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--number", type=int, default=200, help="calls per timing loop")
    parser.add_argument("--repeat", type=int, default=9, help="timing loops (the best counts)")
    parser.add_argument("--backend", choices=("auto", "numpy", "numba"),
                        help="backend of the CI family (cifilter.set_backend)")
    parser.add_argument("--tree", help="import cifilter from this source tree")
    parser.add_argument("--blocks", action="store_true",
                        help="time each row's calls of a round in a row (warm), not "
                             "interleaved with the other rows' calls")
    args = parser.parse_args(argv)
    best, median, solvers = run(args.number, args.repeat, backend=args.backend,
                                tree=args.tree, blocks=args.blocks)
    print(f"cifilter from {cifilter.__file__}, backend {cifilter.get_backend()}")
    print(f"{'criterion':10s} {'call':12s} {'best us':>8s} {'/ plain':>8s} {'median us':>10s} "
          f"{'/ plain':>8s}  solver")
    for (criterion, label), seconds in best.items():
        middle = median[(criterion, label)]
        print(f"{criterion:10s} {label:12s} {seconds * 1e6:8.1f} "
              f"{seconds / best[(criterion, 'plain')]:8.2f} {middle * 1e6:10.1f} "
              f"{middle / median[(criterion, 'plain')]:8.2f}  {solvers[(criterion, label)]}")


if __name__ == "__main__":
    main()
