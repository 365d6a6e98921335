"""cifilter.network.targets: the multi-target scenario and its source tracks."""

from collections import defaultdict

import numpy as np
import pytest

from cifilter.network import (
    TargetData,
    TrackingSensor,
    multi_target,
    simulate_targets,
)


@pytest.fixture(scope="module")
def data():
    return simulate_targets(multi_target(), rng=3)


def test_shapes_and_report_layout(data):
    scenario = data.scenario
    assert isinstance(data, TargetData)
    assert scenario.targets == 5 and len(scenario.sensors) == 3
    assert data.truth.shape == (60, 5, 4) and data.alive.shape == (60, 5)
    assert data.times.tolist() == list(np.arange(60.0))
    assert len(data.reports) == len(data.origin) == 60
    for scan, (reports, origin) in enumerate(zip(data.reports, data.origin)):
        assert len(reports) == len(origin)
        keys = [(r[0], r[1]) for r in reports]
        assert len(set(keys)) == len(keys)             # one report per (source, id)
        for (source, track_id, x, P, time, H), target in zip(reports, origin):
            assert source in {"radar-1", "radar-2", "camera"}
            assert isinstance(track_id, int) and H is None
            assert x.shape == (4,) and P.shape == (4, 4)
            assert time == data.times[scan]
            assert np.array_equal(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
            assert -1 <= target < 5
    # truth is NaN exactly where a target is not alive
    assert np.array_equal(np.isnan(data.truth).any(axis=-1), ~data.alive)


def test_targets_appear_and_disappear(data):
    alive = data.alive
    assert alive[:, 0].all() and alive[:, 1].all()
    assert alive[0, 2] and not alive[-1, 2]            # disappears
    assert not alive[0, 3] and alive[-1, 3]            # appears
    assert not alive[0, 4] and alive[30, 4] and not alive[-1, 4]
    for scan in range(data.steps):
        for target in data.origin[scan]:
            if target >= 0 and not data.alive[scan, target]:
                # only a coasting track outlives its target, at most max_coast scans
                last = np.nonzero(data.alive[:, target])[0][-1]
                assert 0 < scan - last <= 3


def test_same_seed_same_data_other_seed_other_data():
    scenario = multi_target()
    one, two = simulate_targets(scenario, rng=8), simulate_targets(scenario, rng=8)
    assert np.array_equal(one.truth, two.truth, equal_nan=True)
    assert one.origin == two.origin
    for a, b in zip(one.reports, two.reports):
        assert [(r[0], r[1], r[4]) for r in a] == [(r[0], r[1], r[4]) for r in b]
        assert all(np.array_equal(r[2], s[2]) and np.array_equal(r[3], s[3])
                   for r, s in zip(a, b))
    other = simulate_targets(scenario, rng=9)
    assert not np.array_equal(one.truth, other.truth, equal_nan=True)
    generator = simulate_targets(scenario, rng=np.random.default_rng(8))
    assert np.array_equal(generator.truth, one.truth, equal_nan=True)


@pytest.mark.parametrize("separation", [0.0, 20.0])
def test_the_crossing_really_crosses(separation):
    data = simulate_targets(multi_target(separation=separation), rng=5)
    i, j, k = data.scenario.crossing
    gap = np.linalg.norm(data.truth[:, i, [0, 2]] - data.truth[:, j, [0, 2]], axis=-1)
    assert gap[k] == pytest.approx(separation, abs=1e-9)
    assert gap[0] > 50 and gap[-1] > 50              # apart before and after
    # they swap sides: the sign of the cross-track offset changes across scan k
    side = np.sign(data.truth[:, i, 2] - data.truth[:, j, 2])
    if separation == 0.0:
        assert side[k - 5] != side[k + 5]
    # target j still follows the constant-velocity model: its positions advance by its
    # velocities plus the small process noise
    step = data.truth[1:, j, [0, 2]] - data.truth[:-1, j, [0, 2]]
    assert np.abs(step - data.truth[:-1, j, [1, 3]]).max() < 2.0


def test_false_tracks_exist_and_are_short():
    data = simulate_targets(multi_target(false_rate=0.5), rng=2)
    scans = defaultdict(list)
    for scan, (reports, origin) in enumerate(zip(data.reports, data.origin)):
        for report, target in zip(reports, origin):
            if target < 0:
                scans[report[0], report[1]].append(scan)
    assert len(scans) > 30                            # 3 sensors x 60 scans x 0.5
    lengths = [len(s) for s in scans.values()]
    assert max(lengths) <= 3 and min(lengths) >= 1
    assert set(lengths) == {1, 2, 3}
    for seen in scans.values():                       # consecutive scans
        assert seen == list(range(seen[0], seen[0] + len(seen)))
    # a false track's number is never a true track's number of that sensor
    true_keys = {(r[0], r[1]) for reports, origin in zip(data.reports, data.origin)
                 for r, t in zip(reports, origin) if t >= 0}
    assert not true_keys & set(scans)


def test_local_numbers_belong_to_one_target_and_coasting_happens(data):
    owner = {}
    coasted = 0
    previous = {}
    for reports, origin in zip(data.reports, data.origin):
        for (source, track_id, _, P, _, _), target in zip(reports, origin):
            assert owner.setdefault((source, track_id), target) == target
            trace = np.trace(P[np.ix_([0, 2], [0, 2])])
            if target >= 0 and (source, track_id) in previous:
                coasted += trace > previous[source, track_id] * 1.05
            previous[source, track_id] = trace
    assert coasted > 0                                # missed detections: tracks coast
    # sensors number their own tracks: the same number at two sources
    numbers = defaultdict(set)
    for source, track_id in owner:
        numbers[source].add(track_id)
    assert numbers["radar-1"] & numbers["radar-2"]


def test_local_tracks_are_consistent():
    # the local filters know the model and the noise: NEES ~ chi-square(4) after start-up
    scenario = multi_target()
    values = defaultdict(list)
    for seed in range(12):
        data = simulate_targets(scenario, rng=seed)
        for scan in range(data.steps):
            truth = data.report_truth(scan)
            for report, target, true in zip(data.reports[scan], data.origin[scan], truth):
                if target >= 0 and np.isfinite(true).all():
                    error = report[2] - true
                    values[report[0]].append(error @ np.linalg.solve(report[3], error))
    for source, nees in values.items():
        assert len(nees) > 2000
        assert 3.5 < np.mean(nees) < 4.5, (source, np.mean(nees))
        # not overconfident in the tail either: chi-square(4) exceeds 18.47 with p = 0.001
        assert np.mean(np.array(nees) > 18.47) < 0.005


def test_partial_sources_send_the_position_with_h():
    scenario = multi_target()
    full = simulate_targets(scenario, rng=4)
    part = simulate_targets(scenario, rng=4, partial=["camera"])
    assert part.partial == ("camera",)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    seen = 0
    for a, b in zip(full.reports, part.reports):
        assert len(a) == len(b)
        for r, s in zip(a, b):
            if r[0] == "camera":
                assert s[2].shape == (2,) and s[3].shape == (2, 2)
                assert np.array_equal(s[5], H)
                assert np.array_equal(s[2], H @ r[2]) and np.array_equal(s[3], H @ r[3] @ H.T)
                seen += 1
            else:
                assert s[5] is None and np.array_equal(s[2], r[2])
    assert seen > 50


def test_late_reports_describe_earlier_scans():
    scenario = multi_target()
    on_time = simulate_targets(scenario, rng=6)
    late = simulate_targets(scenario, rng=6, lateness=2, late=["radar-2"])
    assert late.late == ("radar-2",)
    assert np.array_equal(late.truth, on_time.truth, equal_nan=True)
    delays = []
    for scan, reports in enumerate(late.reports):
        for report, target in zip(reports, late.origin[scan]):
            delay = late.times[scan] - report[4]
            if report[0] != "radar-2" or target < 0:
                assert delay == 0
            else:
                delays.append(delay)
    assert set(delays) == {0.0, 1.0, 2.0}
    # a late report is the local track's estimate of that earlier scan
    by_key = {(r[0], r[1], r[4]): r[2] for reports in on_time.reports for r in reports}
    for reports in late.reports:
        for r in reports:
            if r[0] == "radar-2" and (r[0], r[1], r[4]) in by_key:
                assert np.array_equal(r[2], by_key[r[0], r[1], r[4]])


def test_sensor_noise_by_hand():
    sensor = TrackingSensor("s", (10.0, 0.0), 2.0, 5.0)
    # target straight above the sensor: range along y, cross-range along x
    assert np.allclose(sensor.noise([10.0, 7.0]), np.diag([25.0, 4.0]), atol=1e-12)
    # at 45 degrees: u = (1, 1)/sqrt 2: 4 u u^T + 25 v v^T
    expected = 0.5 * (4.0 * np.ones((2, 2)) + 25.0 * np.array([[1.0, -1.0], [-1.0, 1.0]]))
    assert np.allclose(sensor.noise([13.0, 3.0]), expected, atol=1e-12)


def test_inputs_not_modified():
    scenario = multi_target()
    initial = scenario.initial.copy()
    simulate_targets(scenario, rng=1)
    assert np.array_equal(scenario.initial, initial)


@pytest.mark.parametrize("call, error, message", [
    (lambda: multi_target(targets=3), ValueError, "targets"),
    (lambda: multi_target(steps=4), ValueError, "steps"),
    (lambda: multi_target(dt=0.0), ValueError, "dt"),
    (lambda: simulate_targets(multi_target(), 10), ValueError, "crossing"),
    (lambda: simulate_targets(multi_target(), partial=["lidar"]), ValueError, "partial"),
    (lambda: simulate_targets(multi_target(), lateness=1, late=["x"]), ValueError, "late"),
    (lambda: simulate_targets(multi_target(), lateness=-1), ValueError, "lateness"),
    (lambda: simulate_targets(multi_target(), lateness=1.5), TypeError, "lateness"),
    (lambda: simulate_targets(multi_target(), rng="seed"), TypeError, "rng"),
    (lambda: TrackingSensor("s", (0.0,), 1.0, 1.0), ValueError, "location"),
    (lambda: TrackingSensor("s", (0.0, 0.0), 0.0, 1.0), ValueError, "sigma_range"),
    (lambda: TrackingSensor("s", (0.0, 0.0), 1.0, 1.0, p_detect=0.0), ValueError,
     "p_detect"),
    (lambda: multi_target(sensors=[TrackingSensor("a", (0.0, 0.0), 1.0, 1.0)] * 2),
     ValueError, "distinct"),
])
def test_bad_input(call, error, message):
    with pytest.raises(error, match=message):
        call()
