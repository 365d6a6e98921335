"""Fusing many Stone Soup track pairs: cifilter (batched and per pair) against Stone Soup.

Each pair is two ``GaussianState`` track estimates of a 4-state target (random covariances,
condition numbers up to 1e3). Timed in the same process on the same pairs:

* Stone Soup's ``CovarianceIntersection.merge_components`` with equal weights (its default;
  pseudo-inverses), one pair at a time;
* Stone Soup's ``ChernoffUpdater.update`` at omega = 0.5, one hypothesis at a time (the
  track-to-track fusion update of a Stone Soup tracker);
* ``cifilter.stonesoup.FusionUpdater.update`` with optimal omega, one hypothesis at a time
  (the drop-in for the line above);
* ``cifilter.stonesoup.OptimalCovarianceIntersection.merge_components`` with optimal
  weights, one pair at a time;
* ``cifilter.fuse(method="ci")`` on all pairs at once (the states' arrays stacked to
  (pairs, n) and (pairs, n, n)), optimal trace weights, plus the conversion of the results
  back to ``GaussianState`` objects.

It prints the time per pair, the ratio to Stone Soup's merge, and the mean trace of the
fused covariance (equal weights against optimal weights).

    python benchmarks/bench_stonesoup.py              # 2000 pairs, 5 rounds (about a minute)
    python benchmarks/bench_stonesoup.py --pairs 500
"""

import argparse
import os
import platform
import time

import numpy as np
from stonesoup.mixturereducer.gaussianmixture import CovarianceIntersection
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.types.detection import GaussianDetection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.prediction import GaussianStatePrediction
from stonesoup.types.state import GaussianState
from stonesoup.updater.chernoff import ChernoffUpdater

import cifilter
from cifilter.stonesoup import FusionUpdater, OptimalCovarianceIntersection, to_gaussian_state


def make_pairs(pairs, n, seed):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((pairs, 2, n, n)))
    spectra = 10.0 ** rng.uniform(0.0, 3.0, (pairs, 2, n))
    Ps = (Q * spectra[..., None, :]) @ np.swapaxes(Q, -1, -2)
    Ps = (Ps + np.swapaxes(Ps, -1, -2)) / 2
    xs = rng.standard_normal((pairs, 2, n))
    states = [(GaussianState(xs[k, 0][:, None], Ps[k, 0]),
               GaussianState(xs[k, 1][:, None], Ps[k, 1])) for k in range(pairs)]
    return states


def hypotheses(states):
    out = []
    for a, b in states:
        model = LinearGaussian(a.ndim, list(range(a.ndim)), a.covar)
        detection = GaussianDetection(a.state_vector, a.covar, measurement_model=model)
        out.append(SingleHypothesis(GaussianStatePrediction(b.state_vector, b.covar), detection))
    return out


def stack(states):
    xs = np.array([[np.asarray(a.state_vector)[:, 0], np.asarray(b.state_vector)[:, 0]]
                   for a, b in states])
    Ps = np.array([[a.covar, b.covar] for a, b in states])
    return xs, Ps


def batched(states):
    """Stack the states, fuse all pairs in one call, return GaussianStates."""
    xs, Ps = stack(states)
    result = cifilter.fuse([(xs[:, 0], Ps[:, 0]), (xs[:, 1], Ps[:, 1])], method="ci")
    fused = [to_gaussian_state(result.x[k], result.P[k]) for k in range(len(states))]
    return fused, result


def interleaved(cases, repeats):
    """Best time of each case over ``repeats`` rounds; every round runs all cases in turn,
    so a load change on a shared machine affects them alike. A case is ``(function,
    setup)``: ``function(setup())`` is timed, the setup (fresh hypotheses) is not."""
    best = {name: np.inf for name in cases}
    out = {}
    for _ in range(repeats):
        for name, (function, setup) in cases.items():
            data = setup() if setup is not None else None
            start = time.perf_counter()
            out[name] = function(data) if setup is not None else function()
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: (best[name], out[name]) for name in cases}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    states = make_pairs(args.pairs, 4, args.seed)

    chernoff, ours = ChernoffUpdater(None), FusionUpdater()
    stacked = stack(states)
    fresh = lambda: hypotheses(states)  # noqa: E731  (updates write into hypotheses)
    cases = interleaved({
        "stonesoup CovarianceIntersection (equal w)": (
            lambda: [CovarianceIntersection.merge_components(a, b) for a, b in states], None),
        "stonesoup ChernoffUpdater (omega=0.5)": (
            lambda hs: [chernoff.update(h) for h in hs], fresh),
        "cifilter FusionUpdater (optimal omega)": (
            lambda hs: [ours.update(h) for h in hs], fresh),
        "cifilter OptimalCovarianceIntersection": (
            lambda: [OptimalCovarianceIntersection.merge_components(a, b) for a, b in states],
            None),
        "cifilter.fuse batched (+ GaussianStates)": (lambda: batched(states), None),
        "cifilter.fuse batched (arrays only)": (
            lambda: cifilter.fuse([(stacked[0][:, 0], stacked[1][:, 0]),
                                   (stacked[0][:, 1], stacked[1][:, 1])], method="ci"), None),
    }, args.repeats)
    core_seconds, core_result = cases.pop("cifilter.fuse batched (arrays only)")

    base = cases["stonesoup CovarianceIntersection (equal w)"][0]
    print(f"{args.pairs} pairs of 4-state tracks; best of {args.repeats}; "
          f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{os.cpu_count()} cpus")
    print(f"{'method':44s} {'us/pair':>9s} {'x merge':>8s} {'mean tr(P)':>11s}")
    print("-" * 75)
    for name, (seconds, out) in cases.items():
        fused = out[0] if isinstance(out, tuple) else out
        trace = np.mean([np.trace(s.covar) for s in fused])
        print(f"{name:44s} {1e6 * seconds / args.pairs:9.1f} {seconds / base:8.2f} "
              f"{trace:11.3f}")
    print(f"{'cifilter.fuse batched (arrays only)':44s} "
          f"{1e6 * core_seconds / args.pairs:9.1f} {core_seconds / base:8.2f} "
          f"{np.mean(np.trace(core_result.P, axis1=-2, axis2=-1)):11.3f}")
    result = cases["cifilter.fuse batched (+ GaussianStates)"][1][1]
    per_pair = cases["cifilter OptimalCovarianceIntersection"][1]
    difference = max(np.abs(result.P[k] - per_pair[k].covar).max() / np.abs(result.P[k]).max()
                     for k in range(args.pairs))
    print(f"batched and per-pair cifilter agree to {difference:.1e} (relative, max over pairs);"
          f" converged: {bool(np.all(result.info['converged']))}")


if __name__ == "__main__":
    main()
