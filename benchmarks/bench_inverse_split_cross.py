"""Batched Inverse CI, Split CI and assumed-correlation fusion against per-pair Python loops.

For each rule the batched call fuses all pairs at once (arrays of shape (pairs, 2, n) and
(pairs, 2, n, n)). The baselines fuse one pair at a time the way one would without
cifilter, with explicit inverses:

* ``ici``: trace(P(omega)) of the ICI equations minimised by
  scipy.optimize.minimize_scalar (bounded, xatol=1e-8), as the MATLAB code on
  bennoack.net/ICI does with fminbnd;
* ``split-ci``: det(P(omega)) of the split CI equations minimised the same way;
* ``cross``: the Bar-Shalom-Campo formula with Pab = 0.4 sqrtm(Pa) sqrtm(Pb).

Both run in the same process on the same data; the script prints the timings, their
ratio and the largest difference between the two answers.

    python benchmarks/bench_inverse_split_cross.py            # 20 000 pairs, loop of 2 000
    python benchmarks/bench_inverse_split_cross.py --pairs 5000 --loop-pairs 500
"""

import argparse
import os
import platform

import numpy as np
from bench_ci import best_of  # the benchmarks' timing helper (run as a script from benchmarks/)
from scipy.linalg import sqrtm
from scipy.optimize import minimize_scalar

import cifilter


def make_pairs(pairs, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((pairs, 2, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    B = rng.standard_normal((pairs, 2, n, n))
    Pi = 0.5 * (B @ np.swapaxes(B, -1, -2)) + 0.05 * np.eye(n)
    xs = rng.standard_normal((pairs, 2, n))
    return xs, Ps, Pi


def loop_ici(xs, Ps, _):
    inv = np.linalg.inv
    out = np.empty((len(xs),) + Ps.shape[-2:])
    for k in range(len(xs)):
        Pa, Pb = Ps[k]
        Ia, Ib = inv(Pa), inv(Pb)

        def trace_bound(w, Pa=Pa, Pb=Pb, Ia=Ia, Ib=Ib):
            return np.trace(inv(Ia + Ib - inv(w * Pa + (1 - w) * Pb)))

        w = minimize_scalar(trace_bound, bounds=(0.0, 1.0), method="bounded",
                            options={"xatol": 1e-8}).x
        G = inv(w * Pa + (1 - w) * Pb)
        P = inv(Ia + Ib - G)
        _ = P @ (Ia - w * G) @ xs[k, 0] + P @ (Ib - (1 - w) * G) @ xs[k, 1]
        out[k] = P
    return out


def loop_split(xs, Ps, Pi):
    inv = np.linalg.inv
    out = np.empty((len(xs),) + Ps.shape[-2:])
    for k in range(len(xs)):
        (P1i, P2i), (P1d, P2d) = Pi[k], Ps[k]

        def det_bound(w, P1i=P1i, P2i=P2i, P1d=P1d, P2d=P2d):
            return np.linalg.det(inv(inv(P1d / w + P1i) + inv(P2d / (1 - w) + P2i)))

        w = minimize_scalar(det_bound, bounds=(1e-9, 1 - 1e-9), method="bounded",
                            options={"xatol": 1e-8}).x
        X1, X2 = P1d / w + P1i, P2d / (1 - w) + P2i
        K = X1 @ inv(X1 + X2)
        _ = xs[k, 0] + K @ (xs[k, 1] - xs[k, 0])
        out[k] = (np.eye(len(X1)) - K) @ X1
    return out


def loop_cross(xs, Ps, _, rho=0.4):
    inv = np.linalg.inv
    out = np.empty((len(xs),) + Ps.shape[-2:])
    for k in range(len(xs)):
        Pa, Pb = Ps[k]
        Pab = rho * np.real(sqrtm(Pa)) @ np.real(sqrtm(Pb))
        D = inv(Pa + Pb - Pab - Pab.T)
        _ = xs[k, 0] + (Pa - Pab) @ D @ (xs[k, 1] - xs[k, 0])
        out[k] = Pa - (Pa - Pab) @ D @ (Pa - Pab).T
    return out


RULES = {
    "ici": (lambda xs, Ps, Pi: cifilter.inverse_covariance_intersection(xs, Ps), loop_ici),
    "split-ci": (lambda xs, Ps, Pi: cifilter.split_covariance_intersection(xs, Pi, Ps),
                 loop_split),
    "cross": (lambda xs, Ps, Pi: cifilter.cross_covariance_fusion(xs, Ps), loop_cross),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=20_000)
    parser.add_argument("--loop-pairs", type=int, default=2_000,
                        help="pairs timed in the loops (their time is scaled to --pairs)")
    parser.add_argument("--dim", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rules", nargs="*", default=list(RULES))
    args = parser.parse_args()
    loop_pairs = min(args.loop_pairs, args.pairs)
    xs, Ps, Pi = make_pairs(args.pairs, args.dim, args.seed)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}")
    print(f"pairs: {args.pairs} of {args.dim}x{args.dim} covariances; loops timed on "
          f"{loop_pairs} pairs and scaled")
    print(f"{'rule':<9} {'batched [s]':>12} {'loop [s]':>10} {'ratio':>8}  "
          f"{'max |P - P_loop| / max|P|':>26}  note")
    for name in args.rules:
        batched, loop = RULES[name]
        batched_time, result = best_of(2, lambda f=batched: f(xs, Ps, Pi))
        loop_time, loop_P = best_of(1, lambda f=loop: f(xs[:loop_pairs], Ps[:loop_pairs],
                                                        Pi[:loop_pairs]))
        loop_total = loop_time * args.pairs / loop_pairs
        difference = np.abs(result.P[:loop_pairs] - loop_P).max() / np.abs(loop_P).max()
        note = ""
        if "converged" in result.info:
            note = f"all converged {bool(np.all(result.info['converged']))}"
        print(f"{name:<9} {batched_time:12.3f} {loop_total:10.3f} "
              f"{loop_total / batched_time:8.1f}  {difference:26.2e}  {note}")


if __name__ == "__main__":
    main()
