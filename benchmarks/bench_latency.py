"""Single-call latency of every fusion method, next to filterpy's ``KalmanFilter.update``.

One 4x4 fusion of two estimates (a constant-velocity target in the plane), timed three
ways in the same process and the same run:

* ``kf.fuse``: the filter method, including the write-back into the filter;
* ``cifilter.fuse``: the front door;
* ``rule``: the rule's own public function (for ``horizon=`` the public
  :func:`cifilter.horizon.horizon_weights` followed by the rule with those weights);

each as the best of several timing loops of calls (per call), and each divided by the
time of filterpy's ``update`` on the same filter. Run it with

    python benchmarks/bench_latency.py            # the table
    python benchmarks/bench_latency.py --markdown # the same as a Markdown table (README)

A tree other than the installed one is timed with ``--tree PATH`` (it is put first on
``sys.path``), so an older checkout can be measured with the same script. ``--backend``
selects the backend of the CI family (``cifilter.set_backend``; default ``auto``, under
which single calls take the compiled route once the kernels are compiled or cached),
e.g. ``--backend numba --only "ci (trace),ci (det)"``
to time the compiled kernels on the single-call path.

``--interleaved`` times only the three single calls of issue 24 (``kf.fuse(other,
method="ci")``, ``cifilter.fuse`` on two ``(x, P)`` pairs and filterpy's ``update``) with
their calls interleaved one by one (``--repeat`` rounds of ``--number`` calls of each), so
that a disturbance of the shared machine hits each alike, and reports the minimum and the
median call of each, with the numpy backend, with ``"auto"`` (single calls on the
compiled route when the kernels are in numba's cache, else on numpy) and, when numba is
installed, with ``"numba"`` (the compiled kernels on the single call, after a warm-up);
``--profile`` adds a cProfile breakdown of ``kf.fuse`` by layer and the number of Python
calls per fuse:

    python benchmarks/bench_latency.py --interleaved --profile
"""

import argparse
import sys
import timeit

import numpy as np


def _setup(tree):
    if tree:
        sys.path.insert(0, tree)
    from filterpy.kalman import KalmanFilter as FilterpyKF

    import cifilter

    return cifilter, FilterpyKF


def _model():
    dt = 1.0
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 1] = 1.0
    q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    Q = np.kron(np.eye(2), q) * 0.1
    return F, H, Q, np.diag([0.5, 0.8])


def _estimates():
    rng = np.random.default_rng(7)
    A = rng.standard_normal((2, 4, 4))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(4)
    return rng.standard_normal((2, 4)), Ps


def _time(call, reset, number, repeat):
    def loop():
        for _ in range(number):
            reset()
            call()

    loop()  # warm up (imports, caches)
    times = timeit.repeat(loop, number=1, repeat=repeat)
    return min(times) / number  # the least disturbed loop (timeit's advice)


def cases(cifilter):
    """(label, method, options, horizon, rule call) for every registered method."""
    xs, Ps = _estimates()
    joint = np.zeros((8, 8))
    joint[:4, :4], joint[4:, 4:] = Ps
    joint[:4, 4:] = 0.3 * Ps[0]
    joint[4:, :4] = 0.3 * Ps[0].T
    both = [(xs[0], Ps[0]), (xs[1], Ps[1])]
    F, H, Q, R = _model()

    from cifilter.horizon import horizon_weights

    def horizon_rule(method, options):
        def call():
            choice = horizon_weights(Ps, F, Q, H, R, 5, rho=options.get("rho"))
            if method == "ci":
                return cifilter.covariance_intersection(xs, Ps, omega=choice.omega)
            return cifilter.partial_ci(xs, Ps, options["rho"], delta=choice.omega)
        return call

    def ei_call(rule, **options):
        try:  # the (xs, Ps) form; older versions only had (xa, Pa, xb, Pb)
            rule(xs, Ps, **options)
            return lambda: rule(xs, Ps, **options)
        except TypeError:
            return lambda: rule(xs[0], Ps[0], xs[1], Ps[1], **options)

    table = [
        ("ci (trace)", "ci", {}, None, lambda: cifilter.covariance_intersection(xs, Ps)),
        ("ci (det)", "ci", {"criterion": "det"}, None,
         lambda: cifilter.covariance_intersection(xs, Ps, criterion="det")),
        ('ci omega="fast"', "ci", {"omega": "fast"}, None,
         lambda: cifilter.covariance_intersection(xs, Ps, omega="fast")),
        ("naive", "naive", {}, None, lambda: cifilter.naive_fusion(xs, Ps)),
        ("optimal", "optimal", {"joint": joint}, None,
         lambda: cifilter.optimal_fusion(xs, joint)),
        ("pci rho=.5", "pci", {"rho": 0.5}, None, lambda: cifilter.partial_ci(xs, Ps, 0.5)),
        ("ei", "ei", {}, None, ei_call(cifilter.ellipsoidal_intersection)),
        ("pcei", "pcei", {}, None, ei_call(cifilter.pc_ellipsoidal_intersection)),
        ("bayes (100 samples)", "bayes", {"samples": 100, "rng": 0}, None,
         lambda: cifilter.bayesian_fusion(xs, Ps, samples=100, rng=0)),
        ("ci horizon=5", "ci", {}, 5, horizon_rule("ci", {})),
        ("pci rho=.5 horizon=5", "pci", {"rho": 0.5}, 5, horizon_rule("pci", {"rho": 0.5})),
    ]
    return both, table


def run(tree=None, number=200, repeat=7, only=None, backend=None):
    cifilter, FilterpyKF = _setup(tree)
    if backend is not None:
        cifilter.set_backend(backend)
    F, H, Q, R = _model()
    xs, Ps = _estimates()
    both, table = cases(cifilter)

    def make(cls):
        kf = cls(dim_x=4, dim_z=2)
        kf.F, kf.H, kf.Q, kf.R = F, H, Q, R
        kf.x, kf.P = xs[0].reshape(4, 1).copy(), Ps[0].copy()
        return kf

    reference = make(FilterpyKF)
    x0, P0 = reference.x, reference.P
    z = np.array([[0.3], [-0.2]])

    def reset_reference():
        reference.x, reference.P = x0, P0

    update = _time(lambda: reference.update(z), reset_reference, number, repeat)
    kf = make(cifilter.KalmanFilter)
    other = (xs[1], Ps[1])

    def reset_kf():
        kf.x, kf.P = x0, P0

    def nothing():
        pass

    rows = []
    for label, method, options, horizon, rule in table:
        if only and label not in only:
            continue
        scale = max(1, number // (20 if method in ("bayes", "pcei") or horizon else 1))
        count = number // scale if scale > 1 else number
        extra = {} if horizon is None else {"horizon": horizon}
        times = {}
        arguments = dict(extra, **options)
        front = dict(arguments)
        if horizon is not None:  # the front door takes the model of the steps after it
            front["model"] = dict(F=F, Q=Q, H=H, R=R)

        def through_filter(method=method, arguments=arguments):
            kf.fuse(other, method, **arguments)

        def through_front_door(method=method, front=front):
            cifilter.fuse(both, method, **front)

        times["kf.fuse"] = _time(through_filter, reset_kf, count, repeat)
        try:
            through_front_door()
            times["cifilter.fuse"] = _time(through_front_door, nothing, count, repeat)
        except TypeError:  # versions whose front door had no horizon= (or model=)
            times["cifilter.fuse"] = float("nan")
        times["rule"] = _time(rule, nothing, count, repeat)
        rows.append((label, times))
    return update, rows


def interleaved(tree=None, number=200, repeat=9, backends=None):
    """{backend: {label: (min, median)}} of the three single calls, interleaved; by default
    with the backends ``numpy``, ``auto`` and, when numba is installed, ``numba`` (whose
    kernels run on single calls; compiled, or loaded from numba's cache, in the warm-up)."""
    import time

    cifilter, FilterpyKF = _setup(tree)
    if backends is None:
        from cifilter.backend import numba_available

        backends = ("numpy", "auto") + (("numba",) if numba_available() else ())
    F, H, Q, R = _model()
    xs, Ps = _estimates()
    both = [(xs[0], Ps[0]), (xs[1], Ps[1])]
    other = (xs[1], Ps[1])
    z = np.array([[0.3], [-0.2]])
    x0, P0 = xs[0].reshape(4, 1).copy(), Ps[0].copy()

    def make(cls):
        kf = cls(dim_x=4, dim_z=2)
        kf.F, kf.H, kf.Q, kf.R = F, H, Q, R
        kf.x, kf.P = x0, P0
        return kf

    reference, kf = make(FilterpyKF), make(cifilter.KalmanFilter)

    def update():
        reference.x, reference.P = x0, P0
        start = clock()
        reference.update(z)
        return clock() - start

    def through_filter():
        kf.x, kf.P = x0, P0
        start = clock()
        kf.fuse(other, method="ci")
        return clock() - start

    def through_front_door():
        start = clock()
        cifilter.fuse(both)
        return clock() - start

    clock = time.perf_counter
    calls = (("update", update), ("kf.fuse", through_filter),
             ("cifilter.fuse", through_front_door))
    out = {}
    for backend in backends:
        cifilter.set_backend(backend)
        for _ in range(50):  # warm up (imports, caches, compilation under numba)
            for _, call in calls:
                call()
        samples: dict = {label: [] for label, _ in calls}
        for _ in range(repeat):
            for _ in range(number):
                for label, call in calls:
                    samples[label].append(call())
        out[backend] = {label: (min(v), float(np.median(v))) for label, v in samples.items()}
    cifilter.set_backend("auto")
    return out


# The layers of kf.fuse in the profile: (label, substrings of "file:function").
_LAYERS = (
    ("filter layer (kalman.py)", ("filters/kalman.py",)),
    ("registry (registry.py)", ("cifilter/registry.py",)),
    ("validation", ("_numerics/validation.py",)),
    ("alignment", ("_numerics/alignment.py",)),
    ("rule core (rules/)", ("cifilter/rules/",)),
    ("kernels and backend", ("_kernels/", "cifilter/backend.py")),
    ("other numerics", ("cifilter/_numerics/",)),
    ("result (result.py)", ("cifilter/result.py",)),
)


def profile(tree=None, calls=2000):
    """Self time of ``kf.fuse(other, method="ci")`` by layer (cProfile), per call, and
    the Python function calls per fuse; numpy's and the builtins' time is counted apart."""
    import cProfile
    import pstats

    cifilter, _ = _setup(tree)
    cifilter.set_backend("numpy")
    F, H, Q, R = _model()
    xs, Ps = _estimates()
    other = (xs[1], Ps[1])
    kf = cifilter.KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.H, kf.Q, kf.R = F, H, Q, R
    x0, P0 = xs[0].reshape(4, 1).copy(), Ps[0].copy()

    def loop():
        for _ in range(calls):
            kf.x, kf.P = x0, P0
            kf.fuse(other, method="ci")

    loop()
    profiler = cProfile.Profile()
    profiler.runcall(loop)
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    layers = {label: 0.0 for label, _ in _LAYERS}
    layers["numpy and builtins"] = 0.0
    total_calls = 0
    for (filename, _, _), (_, ncalls, self_time, _, _) in stats.items():
        total_calls += ncalls
        where = filename.replace("\\", "/")
        for label, keys in _LAYERS:
            if any(key in where for key in keys):
                layers[label] += self_time
                break
        else:
            layers["numpy and builtins"] += self_time
    cifilter.set_backend("auto")
    total = sum(layers.values())
    return {k: v / calls for k, v in layers.items()}, total / calls, (total_calls - 1) / calls


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", help="import cifilter from this source tree")
    parser.add_argument("--number", type=int, default=200, help="calls per timing loop")
    parser.add_argument("--repeat", type=int, default=7, help="timing loops (the best counts)")
    parser.add_argument("--markdown", action="store_true", help="print a Markdown table")
    parser.add_argument("--only", help="comma-separated labels of the rows to time")
    parser.add_argument("--backend", choices=("auto", "numpy", "numba"),
                        help="backend of the CI family (cifilter.set_backend)")
    parser.add_argument("--interleaved", action="store_true",
                        help="kf.fuse, cifilter.fuse and filterpy's update, interleaved")
    parser.add_argument("--profile", action="store_true",
                        help="with --interleaved: kf.fuse's profile by layer")
    args = parser.parse_args(argv)
    if args.interleaved:
        table = interleaved(args.tree, args.number, max(args.repeat, 9))
        for backend, row in table.items():
            base_min, base_median = row["update"]
            print(f"backend {backend}")
            for label, (low, middle) in row.items():
                print(f"  {label:14s} min {low * 1e6:7.1f} us ({low / base_min:5.2f}x update)"
                      f"  median {middle * 1e6:7.1f} us ({middle / base_median:5.2f}x update)")
        if args.profile:
            layers, total, count = profile(args.tree)
            print(f"cProfile of kf.fuse (numpy backend; profiled: {total * 1e6:.1f} us per "
                  f"call, {count:.0f} Python calls per fuse), self time per layer:")
            for label, seconds in layers.items():
                print(f"  {label:28s} {seconds * 1e6:7.1f} us")
        return
    only = None if args.only is None else set(args.only.split(","))
    update, rows = run(args.tree, args.number, args.repeat, only, args.backend)
    us = 1e6
    if args.markdown:
        print(f"filterpy `KalmanFilter.update`: {update * us:.1f} µs\n")
        print("| method | `kf.fuse` | `cifilter.fuse` | rule function | `kf.fuse` / `update` |")
        print("|---|---|---|---|---|")
        for label, t in rows:
            print(f"| {label} | {t['kf.fuse'] * us:.0f} µs | {t['cifilter.fuse'] * us:.0f} µs | "
                  f"{t['rule'] * us:.0f} µs | {t['kf.fuse'] / update:.1f}x |")
        return
    print(f"filterpy KalmanFilter.update: {update * us:8.1f} us")
    print(f"{'method':24s} {'kf.fuse':>10s} {'fuse':>10s} {'rule':>10s} {'kf.fuse/update':>15s}")
    for label, t in rows:
        print(f"{label:24s} {t['kf.fuse'] * us:8.1f}us {t['cifilter.fuse'] * us:8.1f}us "
              f"{t['rule'] * us:8.1f}us {t['kf.fuse'] / update:14.1f}x")


if __name__ == "__main__":
    main()
