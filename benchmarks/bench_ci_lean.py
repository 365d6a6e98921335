"""The lean LAPACK single-pair CI (``cifilter.rules._ci_lean.lean_pair``) against the numpy
path of ``cifilter.covariance_intersection`` on one pair, and filterpy's
``KalmanFilter.update`` as the yardstick (issue 24).

One 4 x 4 pair (the estimates of ``benchmarks/bench_latency.py``), the numpy backend. The
calls are interleaved one by one (``--repeat`` rounds of ``--number`` calls of each), so
that a disturbance of the shared machine hits each alike; each call is timed on its own
and the best and the median call are reported, with their ratios to the numpy path's call
and to ``update`` measured in the same run:

    python benchmarks/bench_ci_lean.py
    python benchmarks/bench_ci_lean.py --number 500 --repeat 20

``--profile`` adds the numpy and LAPACK calls per ``lean_pair`` call (cProfile counts the
numpy functions and methods it sees; ufunc operators and the LAPACK wrappers are not
profiled and are listed apart from a count of the source).
"""

import argparse
import time

import numpy as np


def _estimates():
    rng = np.random.default_rng(7)
    A = rng.standard_normal((2, 4, 4))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(4)
    return rng.standard_normal((2, 4)), Ps


def run(number=200, repeat=10):
    """{label: (best, median)} per call, in seconds."""
    from filterpy.kalman import KalmanFilter

    import cifilter
    from cifilter.rules._ci_lean import lean_pair

    old = cifilter.backend.get_backend()
    cifilter.set_backend("numpy")
    xs, Ps = _estimates()
    x1, x2 = xs[0].copy(), xs[1].copy()
    P1, P2 = Ps[0].copy(), Ps[1].copy()
    W = np.diag([1.0, 1.0, 0.1, 0.1])
    sine, cosine = np.sqrt(4.4721e-4), np.sqrt(1.0 - 4.4721e-4)
    Q = np.array([[cosine, -sine], [sine, cosine]])
    late = (Q * [1.0, 5e6]) @ Q.T
    late = 0.5 * (late + late.T)
    assert lean_pair(x1[:2], np.eye(2), x2[:2], late, "trace") is None
    dt = 1.0
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F = np.eye(4)
    kf.F[0, 2] = kf.F[1, 3] = dt
    kf.H = np.zeros((2, 4))
    kf.H[0, 0] = kf.H[1, 1] = 1.0
    kf.R, kf.Q = np.diag([0.5, 0.8]), 0.1 * np.eye(4)
    x0, P0 = x1.reshape(4, 1).copy(), P1.copy()
    z = np.array([[0.3], [-0.2]])
    clock = time.perf_counter

    def update():
        kf.x, kf.P = x0, P0
        start = clock()
        kf.update(z)
        return clock() - start

    def timed(call, *args, **kwargs):
        def one():
            start = clock()
            call(*args, **kwargs)
            return clock() - start
        return one

    calls = (
        ("filterpy update", update),
        ("ci numpy (trace)", timed(cifilter.covariance_intersection, [x1, x2], [P1, P2])),
        ("lean_pair (trace)", timed(lean_pair, x1, P1, x2, P2, "trace")),
        ("ci numpy (det)", timed(cifilter.covariance_intersection, [x1, x2], [P1, P2],
                                 criterion="det")),
        ("lean_pair (det)", timed(lean_pair, x1, P1, x2, P2, "det")),
        ("ci numpy (W)", timed(cifilter.covariance_intersection, [x1, x2], [P1, P2],
                               criterion=W)),
        ("lean_pair (W)", timed(lean_pair, x1, P1, x2, P2, "weighted-trace", W)),
        # a pair it declines as late as it can (after the eigendecomposition: generalised
        # eigenvalues spread 5e6 with even Cholesky diagonals): what a hard pair pays
        # before the numpy path runs
        ("lean_pair declines", timed(lean_pair, x1[:2], np.eye(2), x2[:2], late, "trace")),
    )
    try:
        for _ in range(50):  # warm up
            for _, call in calls:
                call()
        samples: dict = {label: [] for label, _ in calls}
        for _ in range(repeat):
            for _ in range(number):
                for label, call in calls:
                    samples[label].append(call())
    finally:
        cifilter.set_backend(old)
    return {label: (min(v), float(np.median(v))) for label, v in samples.items()}


def numpy_calls(calls=2000):
    """Python-level calls per ``lean_pair`` (cProfile: functions, methods, builtins)."""
    import cProfile
    import pstats

    from cifilter.rules._ci_lean import lean_pair

    xs, Ps = _estimates()
    x1, x2, P1, P2 = xs[0].copy(), xs[1].copy(), Ps[0].copy(), Ps[1].copy()
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(calls):
        lean_pair(x1, P1, x2, P2, "trace")
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    return sum(ncalls for (_, _, _), (_, ncalls, _, _, _) in stats.items()) / calls


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--number", type=int, default=200, help="calls per round")
    parser.add_argument("--repeat", type=int, default=10, help="rounds")
    parser.add_argument("--profile", action="store_true",
                        help="also count the profiled Python-level calls per lean_pair")
    args = parser.parse_args(argv)
    table = run(args.number, args.repeat)
    update_best, update_median = table["filterpy update"]
    for label, (best, median) in table.items():
        line = (f"{label:19s} best {best * 1e6:7.1f} us ({best / update_best:5.2f}x update)"
                f"  median {median * 1e6:7.1f} us ({median / update_median:5.2f}x update)")
        if label.startswith("lean_pair ("):
            numpy_label = "ci numpy" + label[len("lean_pair"):]
            numpy_best, numpy_median = table[numpy_label]
            line += (f"  | vs {numpy_label}: best {best / numpy_best:4.2f}x,"
                     f" median {median / numpy_median:4.2f}x")
        print(line)
    if args.profile:
        print(f"profiled Python-level calls per lean_pair: {numpy_calls():.0f}")


if __name__ == "__main__":
    main()
