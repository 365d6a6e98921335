"""A track-to-track fusion centre against Stone Soup's pipeline: scores and scans per second.

Part 1, the scenario (``cifilter.network.multi_target``: five targets, two crossing, two
radars and a camera running their own local trackers, missed detections, short-lived false
tracks; full-state tracks on time, what Stone Soup's feeder takes). On the same simulated
source tracks:

* ``cifilter.tracking.TrackFuser`` with each rule (``ci``, ``naive``, ...);
* Stone Soup's own track-fusion pipeline: the source tracks as ``Track`` objects through
  ``Tracks2GaussianDetectionFeeder`` (one source per tracker iteration, so that a central
  track can take one track of every source in a scan) into a ``MultiTargetTracker`` with
  ``GNNWith2DAssignment`` over a ``DistanceHypothesiser`` (Mahalanobis, gate at the same
  chi-square probability as the fuser's), a ``MultiMeasurementInitiator`` (two updates to
  confirm) and an ``UpdateTimeDeleter`` (the fuser's deletion delay), with
  ``ChernoffUpdater`` at omega = 0.5, and the same with ``cifilter.stonesoup.FusionUpdater``
  (optimal omega).

Each is scored by ``cifilter.tracking.score_tracking`` (GOSPA with c = 50 m, ANEES of the
matched tracks, position RMSE, ID switches, false and missed tracks per scan) and timed
(wall time of the whole loop per scan, the conversion of the source tracks included).
Stone Soup's tracks are all scored (its tracker reports only tracks its initiator has
confirmed).

Part 2, scans per second with 200 central tracks and 4 sources: 200 targets on a grid, 4
sensors with every target detected (``p_detect = 1``, no false tracks), so that every scan
after the first brings 800 source tracks for 200 central tracks. ``TrackFuser.update`` per
scan (``ci`` and ``naive``) against Stone Soup's pipeline (ChernoffUpdater) on the same
scans, in the same run; the first scans (births, confirmation) are not timed.

    python benchmarks/bench_tracking.py                 # both parts (a few minutes)
    python benchmarks/bench_tracking.py --part 1 --runs 3
    python benchmarks/bench_tracking.py --part 2 --scans 6 --stonesoup-scans 3
"""

import argparse
import datetime
import os
import platform
import time

import numpy as np
from scipy import stats
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.deleter.time import UpdateTimeDeleter
from stonesoup.feeder.track import Tracks2GaussianDetectionFeeder
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.models.transition.linear import (
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
)
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.tracker.simple import MultiTargetTracker
from stonesoup.types.state import GaussianState
from stonesoup.types.track import Track
from stonesoup.updater.chernoff import ChernoffUpdater

from cifilter.network import (
    TargetScenario,
    TrackingSensor,
    multi_target,
    simulate_targets,
)
from cifilter.stonesoup import FusionUpdater
from cifilter.tracking import (
    CentralTrack,
    SourceTrack,
    TrackFuser,
    TrackingRun,
    format_tracking,
    score_sources,
    score_tracking,
)

T0 = datetime.datetime(2026, 1, 1)
GATE = 0.9999          # the fuser's default gate probability
DELETE_AFTER = 3       # the fuser's default deletion delay [scans]


def source_track_stream(data, scans, order):
    """Stone Soup ``Track`` objects of every (source, id), updated scan by scan; yields
    ``(time, tracks of one source)`` per source and scan (the tracker's iterations)."""
    tracks = {}
    for k in range(scans):
        when = T0 + datetime.timedelta(seconds=float(data.times[k]))
        by_source = {name: set() for name in order}
        for source, track_id, x, P, _, _ in data.reports[k]:
            track = tracks.get((source, track_id))
            if track is None:
                track = tracks[source, track_id] = Track(id=f"{source}:{track_id}")
            track.append(GaussianState(x.reshape(-1, 1), P, timestamp=when))
            by_source[source].add(track)
        for name in order:
            yield when, by_source[name]


def stone_soup_tracker(data, updater, scans):
    transition = CombinedLinearGaussianTransitionModel(
        [ConstantVelocity(data.scenario.q)] * 2)
    predictor = KalmanPredictor(transition)
    gate = float(np.sqrt(stats.chi2.ppf(GATE, 4)))
    hypothesiser = DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=gate)
    associator = GNNWith2DAssignment(hypothesiser)
    deleter = UpdateTimeDeleter(datetime.timedelta(seconds=DELETE_AFTER * data.scenario.dt))
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.zeros((4, 4))), deleter=deleter,
        data_associator=GNNWith2DAssignment(hypothesiser), updater=updater, min_points=2)
    order = [sensor.name for sensor in data.scenario.sensors]
    return MultiTargetTracker(
        initiator=initiator, deleter=deleter,
        detector=Tracks2GaussianDetectionFeeder(source_track_stream(data, scans, order)),
        data_associator=associator, updater=updater), len(order)


def run_stone_soup(data, updater, scans=None):
    """Stone Soup's pipeline over the scans: a TrackingRun (its tracks as central tracks)."""
    scans = data.steps if scans is None else scans
    tracker, per_scan = stone_soup_tracker(data, updater, scans)
    numbers = {}
    out, seconds = [], []
    start = time.perf_counter()
    for iteration, (_, tracks) in enumerate(tracker):
        if (iteration + 1) % per_scan:
            continue  # the scan ends with its last source
        now = time.perf_counter()
        seconds.append(now - start)
        start = now
        k = len(out)
        scan = []
        for track in tracks:
            number = numbers.setdefault(track.id, len(numbers) + 1)
            scan.append(CentralTrack(
                id=number, x=np.asarray(track.state_vector, float).ravel(),
                P=np.asarray(track.covar, float), time=float(data.times[k]), confirmed=True,
                sources={}, hits=len(track), misses=0, born=0.0))
        out.append(tuple(sorted(scan, key=lambda t: t.id)))
    return TrackingRun(type(updater).__name__, tuple(out), data.times[:scans].copy(),
                       np.array(seconds), {})


def run_cifilter(data, method, scans=None, **options):
    """TrackFuser over the scans, the SourceTrack conversion included in the time."""
    scans = data.steps if scans is None else scans
    fuser = TrackFuser(method, motion=data.scenario.motion, **options)
    out, seconds = [], []
    for k in range(scans):
        start = time.perf_counter()
        tracks = [SourceTrack(*report) for report in data.reports[k]]
        out.append(tuple(fuser.update(tracks, float(data.times[k]))))
        seconds.append(time.perf_counter() - start)
    return TrackingRun(method, tuple(out), data.times[:scans].copy(), np.array(seconds),
                       options)


def part_one(args):
    scenario = multi_target()
    rng = np.random.default_rng(args.seed)
    datas = [simulate_targets(scenario, rng=rng) for _ in range(args.runs)]
    rows = []
    for method in args.methods.split(","):
        options = {"rho": 0.5} if method == "pci" else {}
        runs = [run_cifilter(d, method, **options) for d in datas]
        row = score_tracking(runs, datas).as_row()
        row["method"] = method if "rho" not in options else f"{method} rho={options['rho']:g}"
        row["guarantee"] = "cifilter"
        rows.append(row)
    for label, make in (("chernoff-0.5", lambda: ChernoffUpdater(None, omega=0.5)),
                        ("FusionUpdater", lambda: FusionUpdater())):
        runs = [run_stone_soup(d, make()) for d in datas]
        row = score_tracking(runs, datas).as_row()
        row["method"] = label
        row["guarantee"] = "stonesoup"
        rows.append(row)
    print(f"Part 1: {scenario.description}; {args.runs} runs x {scenario.steps} scans, seed "
          f"{args.seed}; GOSPA c = 50 m; ms per scan: the whole loop per scan.\n"
          "The second column says whose pipeline (not the rule's guarantee).")
    print(format_tracking(rows + score_sources(datas)))


def grid_scenario(targets=200, steps=8):
    """200 targets on a 20 x 10 grid 300 m apart, 4 sensors that see every target."""
    rows = int(np.ceil(targets / 20))
    gx, gy = np.meshgrid(np.arange(20) * 300.0, np.arange(rows) * 300.0)
    positions = np.stack([gx.ravel(), gy.ravel()], axis=1)[:targets]
    angle = np.linspace(0, 2 * np.pi, targets, endpoint=False)
    initial = np.stack([positions[:, 0], 8 * np.cos(angle), positions[:, 1],
                        8 * np.sin(angle)], axis=1)
    sensors = tuple(TrackingSensor(f"s{i}", location, 5.0 + 3 * i, 20.0 - 3 * i,
                                   p_detect=1.0, false_rate=0.0)
                    for i, location in enumerate([(-500.0, -500.0), (6500.0, -500.0),
                                                  (-500.0, 3500.0), (6500.0, 3500.0)]))
    birth = np.zeros(targets, dtype=int)
    death = np.full(targets, steps + 1)
    return TargetScenario(initial, birth, death, sensors, (0, 1, steps - 1),
                          separation=300.0, steps=steps, region=(0.0, 6000.0, 0.0, 3000.0),
                          name="grid")


def part_two(args):
    scenario = grid_scenario(steps=args.scans)
    data = simulate_targets(scenario, rng=args.seed)
    warm = 2
    print(f"Part 2: {scenario.targets} targets, {len(scenario.sensors)} sources, "
          f"{len(data.reports[-1])} source tracks per scan; scans {warm + 1}..{args.scans} "
          f"timed (the first {warm} start and confirm the central tracks)")
    scans = min(args.stonesoup_scans, args.scans)
    results = {}
    for method in ("ci", "naive"):
        run = run_cifilter(data, method)
        live = [len(s) for s in run.tracks]
        confirmed = sum(t.confirmed for t in run.tracks[-1])
        per_scan = float(np.median(run.seconds[warm:]))
        same = float(np.median(run.seconds[warm:scans]))
        results[method] = same
        print(f"  cifilter TrackFuser {method:<6} {per_scan * 1e3:9.1f} ms/scan  "
              f"{1 / per_scan:8.2f} scans/s   (scans {warm + 1}..{scans}: "
              f"{same * 1e3:.1f} ms/scan)   central tracks {live[-1]} ({confirmed} "
              f"confirmed)")
    run = run_stone_soup(data, ChernoffUpdater(None, omega=0.5), scans)
    per_scan = float(np.median(run.seconds[warm:])) if scans > warm else float("nan")
    print(f"  stonesoup pipeline Chernoff {per_scan * 1e3:9.1f} ms/scan  "
          f"{1 / per_scan:8.3f} scans/s   tracks {len(run.tracks[-1])} (scans {warm + 1}.."
          f"{scans} timed)")
    print(f"  ratio stonesoup / cifilter ci on scans {warm + 1}..{scans}: "
          f"{per_scan / results['ci']:.0f}x")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", type=int, choices=(1, 2))
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--methods", default="ci,split-ci,pci,naive")
    parser.add_argument("--scans", type=int, default=8)
    parser.add_argument("--stonesoup-scans", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{os.cpu_count()} cpus (shared)")
    if args.part in (None, 1):
        part_one(args)
    if args.part in (None, 2):
        part_two(args)


if __name__ == "__main__":
    main()
