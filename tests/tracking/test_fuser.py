"""The fusion node :class:`cifilter.tracking.TrackFuser`: association through crossings and
gaps, the life cycle of central tracks, batched fusion of late and partial-state sources,
conservative central tracks with ``"ci"``, and bad input that leaves the node unchanged.

The scenario is the small seeded one of ``helpers.py`` (two crossing targets, sources with
their own track ids).
"""

import copy

import numpy as np
import pytest
from scipy.stats import chi2

import cifilter
from cifilter.tracking import CentralTrack, SourceTrack, TrackFuser

from .helpers import IDS, POSITION, motion, target_of, two_targets


def run(scenario, method="ci", **options):
    """Every scan's central tracks and the fuser's diagnostics."""
    fuser = TrackFuser(method, motion=motion, **options)
    outputs, diagnostics = [], []
    for time, reports in scenario.scans:
        outputs.append(fuser.update(reports, time))
        diagnostics.append(fuser.last_scan)
    return fuser, outputs, diagnostics


def snapshot(fuser):
    """Everything the fuser holds, deep-copied (arrays compared by value), except the cache
    of the gate thresholds (a pure function of the gate and the size)."""
    return copy.deepcopy({k: v for k, v in vars(fuser).items() if k != "_thresholds"})


def assert_same_state(before, after):
    assert before.keys() == after.keys()
    for key in before:
        a, b = before[key], after[key]
        if key == "_tracks":
            assert len(a) == len(b)
            for ta, tb in zip(a, b):
                for field in ("id", "time", "confirmed", "hits", "misses", "born"):
                    assert getattr(ta, field) == getattr(tb, field)
                assert dict(ta.sources) == dict(tb.sources)
                np.testing.assert_array_equal(ta.x, tb.x)
                np.testing.assert_array_equal(ta.P, tb.P)
        else:
            assert repr(a) == repr(b), key


# --- one scan by hand ---------------------------------------------------------------------------

def test_first_scan_is_the_ci_fusion_of_the_sources():
    # CI of diag(1, 4) and diag(4, 1): weights 1/2, P = (diag(1, 1/4)/2 + diag(1/4, 1)/2)^-1
    # = 1.6 I, x = 1.6 (diag(1, 1/4) (1, 0) + diag(1/4, 1) (0, 1)) / 2 = (0.8, 0.8)
    fuser = TrackFuser("ci", motion=lambda dt: (np.eye(2), 0.1 * dt * np.eye(2)))
    scan = [SourceTrack("a", 7, np.array([1.0, 0.0]), np.diag([1.0, 4.0]), 0.0),
            SourceTrack("b", "x", np.array([0.0, 1.0]), np.diag([4.0, 1.0]), 0.0)]
    (central,) = fuser.update(scan, 0.0)
    assert isinstance(central, CentralTrack)
    assert (central.id, central.confirmed, dict(central.sources)) == (1, True, {"a": 7, "b": "x"})
    assert (central.hits, central.misses, central.born, central.time) == (1, 0, 0.0, 0.0)
    np.testing.assert_allclose(central.x, [0.8, 0.8], rtol=1e-12)
    np.testing.assert_allclose(central.P, 1.6 * np.eye(2), rtol=1e-12)
    assert central.info["weights"] == pytest.approx((0.5, 0.5), abs=1e-9)
    assert central.info["estimates"] == 2 and central.info["prediction"] is False
    assert fuser.last_scan["fuse_calls"] == 1 and fuser.last_scan["born"] == [1]
    assert not central.x.flags.writeable and not central.P.flags.writeable


def test_second_scan_fuses_the_prediction_for_ci_and_not_for_naive():
    def unit_motion(dt):
        return np.array([[1.0, dt], [0.0, 1.0]]), 0.1 * np.array([[dt**3 / 3, dt**2 / 2],
                                                                   [dt**2 / 2, dt]])
    first = [SourceTrack("a", 1, np.array([0.0, 1.0]), np.diag([1.0, 0.5]), 0.0),
             SourceTrack("b", 1, np.array([0.3, 1.1]), np.diag([2.0, 0.2]), 0.0)]
    second = [SourceTrack("a", 1, np.array([1.1, 1.0]), np.diag([0.8, 0.4]), 1.0),
              SourceTrack("b", 1, np.array([1.2, 0.9]), np.diag([1.5, 0.3]), 1.0)]
    for method, with_prediction in (("ci", True), ("naive", False)):
        fuser = TrackFuser(method, motion=unit_motion)
        (c0,) = fuser.update(first, 0.0)
        (c1,) = fuser.update(second, 1.0)
        F, Q = unit_motion(1.0)
        prediction = (F @ c0.x, F @ c0.P @ F.T + Q)
        estimates = [(t.x, t.P) for t in second]
        if with_prediction:
            estimates = [prediction, *estimates]
        expected = cifilter.fuse(estimates, method)
        assert c1.info["prediction"] is with_prediction
        assert c1.info["estimates"] == len(estimates)
        np.testing.assert_allclose(c1.x, expected.x, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(c1.P, expected.P, rtol=1e-10)


def test_the_ci_gate_keeps_a_pair_that_the_independence_gate_rejects():
    # 1-D, F = 1, Q = 0: the track born from (0, 1) predicts (0, 1); the same source then
    # reports (3, 1). Independence: 9 / (1 + 1) = 4.5 > chi2.ppf(0.9, 1) = 2.71, rejected;
    # any correlation: 9 / (1 + 1)^2 = 2.25, kept (the two may share all their error).
    def still(dt):
        return np.eye(1), np.zeros((1, 1))

    for association, kept in (("ci", True), ("naive", False)):
        fuser = TrackFuser("ci", motion=still, gate=0.9, association=association)
        fuser.update([SourceTrack("a", 1, [0.0], [[1.0]], 0.0)], 0.0)
        out = fuser.update([SourceTrack("a", 1, [3.0], [[1.0]], 1.0)], 1.0)
        if kept:
            assert [(c.id, dict(c.sources)) for c in out] == [(1, {"a": 1})]
            assert out[0].info["distances"]["a"] == pytest.approx(2.25, rel=1e-12)
        else:  # the old track coasts, the source track starts a new one
            assert [(c.id, dict(c.sources)) for c in out] == [(1, {}), (2, {"a": 1})]
    assert chi2.ppf(0.9, 1) == pytest.approx(2.7055, abs=1e-4)


def test_naive_brings_late_tracks_to_the_scan_time_itself():
    # "naive" does not take times=: the node predicts a late full-state track exactly
    scenario = two_targets(3, steps=3, late=("b",))
    fuser = TrackFuser("naive", motion=motion)
    for time, reports in scenario.scans:
        out = fuser.update(reports, time)
    F, Q = motion(1.0)
    mine = {r.source: r for r in reports if scenario.origin[r.source, r.id] == 0}
    expected = cifilter.fuse([(mine["a"].x, mine["a"].P),
                              (F @ mine["b"].x, F @ mine["b"].P @ F.T + Q)], "naive")
    np.testing.assert_allclose(out[0].x, expected.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out[0].P, expected.P, rtol=1e-10)


# --- association in the seeded scenario --------------------------------------------------------

@pytest.mark.parametrize("seed", range(4))
def test_ids_are_kept_through_the_crossing_and_a_gap_of_two_scans(seed):
    scenario = two_targets(seed, gap=(0, 12, 2))  # target 0 unreported at scans 12, 13
    _, outputs, _ = run(scenario, delete_after=3)
    for k, tracks in enumerate(outputs):
        assert [c.id for c in tracks] == [1, 2], k  # no other track is ever started
        assert all(c.confirmed for c in tracks)
        one, two = tracks
        assert target_of(two, scenario.origin) == 1
        if k in (12, 13):
            assert dict(one.sources) == {} and one.misses == k - 11 and one.info == {}
        else:
            assert target_of(one, scenario.origin) == 0
            assert dict(one.sources) == {"a": IDS["a"][0], "b": IDS["b"][0]}
    crossing = len(outputs) // 2  # the targets are at one place at the middle scan
    np.testing.assert_allclose(scenario.truth[crossing, 0, [0, 2]],
                               scenario.truth[crossing, 1, [0, 2]], rtol=1e-12)


def test_a_source_track_that_jumps_is_re_associated():
    # two targets 100 m apart; at scan 4 source "b" swaps its track ids
    targets = [np.array([0.0, 1.0, 0.0, 0.0]), np.array([0.0, 1.0, 100.0, 0.0])]
    P = np.diag([1.0, 0.1, 1.0, 0.1])
    fuser = TrackFuser("ci", motion=motion)
    for k in range(7):
        F, _ = motion(float(k))
        truth = [F @ x for x in targets]
        b_ids = ("t0", "t1") if k < 4 else ("t1", "t0")
        scan = [SourceTrack("a", 11, truth[0], P, float(k)),
                SourceTrack("a", 12, truth[1], P, float(k)),
                SourceTrack("b", b_ids[0], truth[0] + 0.1, P, float(k)),
                SourceTrack("b", b_ids[1], truth[1] + 0.1, P, float(k))]
        out = fuser.update(scan, float(k))
        assert [c.id for c in out] == [1, 2]
        assert dict(out[0].sources) == {"a": 11, "b": b_ids[0]}
        assert dict(out[1].sources) == {"a": 12, "b": b_ids[1]}
        if k == 4:
            assert fuser.last_scan["kept"] == 2 and fuser.last_scan["assigned"] == 2
    # a source track that jumps to a place without a central track starts one
    F, _ = motion(7.0)
    far = F @ np.array([0.0, 1.0, -300.0, 0.0])
    scan = [SourceTrack("a", 11, F @ targets[0], P, 7.0),
            SourceTrack("a", 12, F @ targets[1], P, 7.0),
            SourceTrack("b", "t1", F @ targets[0], P, 7.0),
            SourceTrack("b", "t0", far, P, 7.0)]
    out = fuser.update(scan, 7.0)
    assert [c.id for c in out] == [1, 2, 3]
    assert dict(out[2].sources) == {"b": "t0"} and not out[2].confirmed
    assert dict(out[1].sources) == {"a": 12}


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("length", [1, 2, 4])
def test_a_false_track_never_outlives_itself_by_more_than_the_deletion_delay(seed, length):
    first, delete_after = 6, 3
    scenario = two_targets(seed, steps=16, false=("a", first, length))
    last_false = first + length - 1
    _, outputs, _ = run(scenario, delete_after=delete_after)
    fed_by_false = {c.id for tracks in outputs for c in tracks
                    if target_of(c, scenario.origin) == -1}
    assert fed_by_false  # the false track did start a central track
    for cid in fed_by_false:
        alive = [k for k, tracks in enumerate(outputs) if any(c.id == cid for c in tracks)]
        confirmed = [k for k, tracks in enumerate(outputs)
                     if any(c.id == cid and c.confirmed for c in tracks)]
        assert alive[-1] - last_false <= delete_after
        if confirmed:
            # confirmed (2 of 3 scans): coasts until the delete_after-th miss deletes it
            assert length >= 2 and alive[-1] == last_false + delete_after - 1
        else:
            assert length == 1
    # the true targets' tracks are untouched
    for tracks in outputs:
        assert [c.id for c in tracks][:2] == [1, 2]


def test_confirmation_m_of_n_and_deletion_of_tentative_tracks():
    def motion_1d(dt):
        return np.eye(1), 0.01 * dt * np.eye(1)

    track = [SourceTrack("a", 1, [0.0], [[1.0]], 0.0)]
    # hit, miss, hit: confirmed at the third scan (2 of 3)
    fuser = TrackFuser(motion=motion_1d, confirm=(2, 3))
    assert [c.confirmed for c in fuser.update(track, 0.0)] == [False]
    assert [c.confirmed for c in fuser.update([], 1.0)] == [False]
    again = [SourceTrack("a", 1, [0.0], [[1.0]], 2.0)]
    assert [(c.confirmed, c.hits, c.misses) for c in fuser.update(again, 2.0)] == [(True, 2, 0)]
    # hit, miss, miss: 2 of 3 is out of reach at the third scan, deleted there
    fuser = TrackFuser(motion=motion_1d, confirm=(2, 3), delete_after=5)
    fuser.update(track, 0.0)
    assert len(fuser.update([], 1.0)) == 1
    assert fuser.update([], 2.0) == [] and fuser.last_scan["deleted"] == [1]
    # a confirmed track is deleted at its delete_after-th consecutive miss, never reused id
    fuser = TrackFuser(motion=motion_1d, confirm=(1, 1), delete_after=2)
    assert [c.confirmed for c in fuser.update(track, 0.0)] == [True]
    assert [c.misses for c in fuser.update([], 1.0)] == [1]
    assert fuser.update([], 2.0) == []
    out = fuser.update([SourceTrack("a", 1, [0.0], [[1.0]], 3.0)], 3.0)
    assert [c.id for c in out] == [2]


def test_a_partial_state_track_alone_does_not_start_a_track():
    fuser = TrackFuser(motion=motion)
    scan = [SourceTrack("cam", 5, np.zeros(2), np.eye(2), 0.0, POSITION)]
    assert fuser.update(scan, 0.0) == []
    assert fuser.last_scan["unassigned"] == [("cam", 5)]
    assert fuser.time == 0.0


# --- fusion: late and partial sources, batching -----------------------------------------------

def test_late_and_partial_sources_are_fused():
    scenario = two_targets(2, steps=6, sources=("a", "b", "c"), late=("b",), partial=("c",))
    fuser = TrackFuser("ci", motion=motion)
    previous = None
    for k, (time, reports) in enumerate(scenario.scans):
        out = fuser.update(reports, time)
        assert [c.id for c in out] == [1, 2]
        for c in out:
            assert set(c.sources) == {"a", "b", "c"}
            assert c.info["estimates"] == (3 if k == 0 else 4)
        assert fuser.last_scan["fuse_calls"] == 1
        if k == 3:
            # every source weighs in (so the comparison below sees each one's alignment)
            assert min(out[0].info["weights"][1:]) > 0.01
            # the same fusion written out: prediction, "a" now, "b" one scan old, "c" of H x
            F, Q = motion(1.0)
            c = previous[0]
            mine = {r.source: r for r in reports if scenario.origin[r.source, r.id] == 0}
            assert mine["b"].time == time - 1.0
            expected = cifilter.fuse(
                [(F @ c.x, F @ c.P @ F.T + Q), (mine["a"].x, mine["a"].P),
                 (mine["b"].x, mine["b"].P), (mine["c"].x, mine["c"].P)],
                "ci", H=[None, None, None, POSITION], times=[time, time, time - 1.0, time],
                at=time, motion=motion)
            np.testing.assert_allclose(out[0].x, expected.x, rtol=1e-8, atol=1e-10)
            np.testing.assert_allclose(out[0].P, expected.P, rtol=1e-8)
        previous = out


def test_a_late_partial_source_is_fused_through_h_f_inverse():
    # a position-only track one scan old estimates H F^-1 x(t) with P + H F^-1 Q F^-T H^T
    scenario = two_targets(4, steps=5, sources=("a", "c"), late=("c",), partial=("c",))
    fuser = TrackFuser("ci", motion=motion)
    for k, (time, reports) in enumerate(scenario.scans):
        previous = fuser.tracks
        out = fuser.update(reports, time)
        assert all(set(c.sources) == {"a", "c"} for c in out)
        if k == 3:
            assert out[1].info["weights"][2] > 0.1  # the late partial track weighs in
            F, Q = motion(1.0)
            G = POSITION @ np.linalg.inv(F)
            c = previous[1]
            mine = {r.source: r for r in reports if scenario.origin[r.source, r.id] == 1}
            expected = cifilter.fuse(
                [(F @ c.x, F @ c.P @ F.T + Q), (mine["a"].x, mine["a"].P),
                 (mine["c"].x, mine["c"].P + G @ Q @ G.T)], "ci", H=[None, None, G])
            np.testing.assert_allclose(out[1].x, expected.x, rtol=1e-8, atol=1e-10)
            np.testing.assert_allclose(out[1].P, expected.P, rtol=1e-8)


def test_one_fuse_call_per_signature():
    # six targets far apart, two sources: one group of six tracks, then one source misses
    # two targets: two groups (prediction + 2 sources, prediction + 1 source)
    P = np.diag([1.0, 0.1, 1.0, 0.1])
    starts = [np.array([0.0, 1.0, 100.0 * j, 0.0]) for j in range(6)]
    fuser = TrackFuser("ci", motion=motion)
    for k in range(4):
        F, _ = motion(float(k))
        scan = []
        for j, x in enumerate(starts):
            scan.append(SourceTrack("a", j, F @ x, P, float(k)))
            if not (k == 3 and j < 2):
                scan.append(SourceTrack("b", 10 + j, F @ x + 0.2, 2 * P, float(k)))
        out = fuser.update(scan, float(k))
        assert len(out) == 6
        if k == 0:
            assert fuser.last_scan["groups"] == [(2, 6)]
        elif k < 3:
            assert fuser.last_scan["groups"] == [(3, 6)]
        else:
            assert sorted(fuser.last_scan["groups"]) == [(2, 2), (3, 4)]
        assert fuser.last_scan["fuse_calls"] == len(fuser.last_scan["groups"])
    # batched equals one fusion per track
    for c in out[2:]:
        assert c.info["estimates"] == 3


def test_batched_fusion_equals_fusion_track_by_track():
    scenario = two_targets(5, steps=4)
    fuser = TrackFuser("ci", motion=motion)
    for time, reports in scenario.scans[:-1]:
        fuser.update(reports, time)
    before = fuser.tracks
    time, reports = scenario.scans[-1]
    out = fuser.update(reports, time)
    F, Q = motion(1.0)
    for c_old, c_new in zip(before, out):
        mine = [r for r in reports if (r.source, r.id) in c_new.sources.items()]
        mine.sort(key=lambda r: r.source)
        single = cifilter.fuse([(F @ c_old.x, F @ c_old.P @ F.T + Q)]
                               + [(r.x, r.P) for r in mine], "ci")
        np.testing.assert_allclose(c_new.x, single.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(c_new.P, single.P, rtol=1e-9)


# --- conservative central tracks and the gain over a single source (Monte Carlo) --------------

def _monte_carlo(method, runs=50, steps=8):
    nees = np.zeros((steps, 2 * runs))
    central, single = [], {"a": [], "b": []}
    for run_index in range(runs):
        scenario = two_targets(1000 + run_index, steps=steps)
        _, outputs, _ = run(scenario, method)
        for k, tracks in enumerate(outputs):
            for c in tracks:
                j = target_of(c, scenario.origin)
                e = c.x - scenario.truth[k, j]
                nees[k, 2 * run_index + j] = e @ np.linalg.solve(c.P, e)
                central.append(np.sum(e[[0, 2]] ** 2))
            for r in scenario.scans[k][1]:
                e = r.x - scenario.truth[k, scenario.origin[r.source, r.id]]
                single[r.source].append(np.sum(e[[0, 2]] ** 2))
    rmse = np.sqrt(np.mean(central))
    best_single = min(np.sqrt(np.mean(v)) for v in single.values())
    return nees.mean(axis=1), rmse, best_single


def test_ci_central_tracks_are_conservative_and_beat_the_best_source():
    anees, rmse, best_single = _monte_carlo("ci")
    samples = 2 * 50
    bound = chi2.ppf(0.975, 4 * samples) / samples  # two-sided 95% band's upper end
    assert np.all(anees <= bound), anees
    assert rmse < best_single


def test_naive_central_tracks_break_the_same_bound():
    # the sources' errors are correlated (common process noise): independence is
    # overconfident, which the test above would catch
    anees, _, _ = _monte_carlo("naive", runs=50, steps=8)
    samples = 2 * 50
    bound = chi2.ppf(0.975, 4 * samples) / samples
    assert np.any(anees[1:] > bound), anees


# --- bad input leaves the fuser unchanged ------------------------------------------------------

def _bad_scans(reports, time):
    good = reports[0]
    P = np.array(good.P, dtype=float)
    asym = P.copy()
    asym[0, 1] += 0.5
    return {
        "duplicate": ([*reports, good], time, ValueError, "appears twice in the scan"),
        "nan": ([*reports[1:], SourceTrack(good.source, good.id, np.full(4, np.nan), P, time)],
                time, ValueError, "x contains non-finite"),
        "asymmetric": ([*reports[1:], SourceTrack(good.source, good.id, good.x, asym, time)],
                       time, ValueError, "P is not symmetric"),
        "not PD": ([*reports[1:], SourceTrack(good.source, good.id, good.x,
                                               np.diag([1.0, -1.0, 1.0, 1.0]), time)],
                   time, ValueError, "P is not positive definite"),
        "size": ([*reports, SourceTrack("cam", 1, np.zeros(2), np.eye(2), time)], time,
                 ValueError, "has a state of size 2 but the central state has size 4"),
        "bad H": ([*reports, SourceTrack("cam", 1, np.zeros(2), np.eye(2), time,
                                         np.eye(2, 3))], time, ValueError, "H has shape"),
        "future": ([*reports[1:], SourceTrack(good.source, good.id, good.x, P, time + 1.0)],
                   time, ValueError, "later than the scan time"),
        "earlier scan": (reports, time - 5.0, ValueError, "earlier than the fuser's time"),
        "not a track": ([*reports, (good.x, P)], time, TypeError, "must be a SourceTrack"),
    }


@pytest.mark.parametrize("case", ["duplicate", "nan", "asymmetric", "not PD", "size", "bad H",
                                  "future", "earlier scan", "not a track"])
def test_bad_input_is_named_and_leaves_the_fuser_unchanged(case):
    scenario = two_targets(7, steps=6, false=("a", 2, 1))
    fuser = TrackFuser("ci", motion=motion)
    reference = TrackFuser("ci", motion=motion)
    for time, reports in scenario.scans[:4]:
        fuser.update(reports, time)
        reference.update(reports, time)
    time, reports = scenario.scans[4]
    scan, scan_time, error, match = _bad_scans(reports, time)[case]
    before = snapshot(fuser)
    with pytest.raises(error, match=match) as raised:
        fuser.update(scan, scan_time)
    if case not in ("earlier scan", "not a track"):
        assert "source " in str(raised.value) and " track " in str(raised.value)
    assert_same_state(before, snapshot(fuser))
    # and it goes on exactly as a fuser that never saw the bad scan
    for time, reports in scenario.scans[4:]:
        mine, theirs = fuser.update(reports, time), reference.update(reports, time)
        assert [(c.id, dict(c.sources)) for c in mine] == [(c.id, dict(c.sources))
                                                            for c in theirs]
        for a, b in zip(mine, theirs):
            np.testing.assert_array_equal(a.x, b.x)
            np.testing.assert_array_equal(a.P, b.P)


def test_a_failing_motion_leaves_the_fuser_unchanged():
    calls = []

    def fragile(dt):
        calls.append(dt)
        if len(calls) > 1:
            raise ValueError("no model for this step")
        return motion(dt)

    scenario = two_targets(8, steps=3)
    fuser = TrackFuser("ci", motion=fragile)
    fuser.update(*scenario.scans[0][::-1])
    fuser.update(*scenario.scans[1][::-1])
    before = snapshot(fuser)
    with pytest.raises(ValueError, match="no model for this step"):
        fuser.update(*scenario.scans[2][::-1])
    assert_same_state(before, snapshot(fuser))


def test_a_fusion_that_fails_leaves_the_fuser_unchanged():
    # "ei" takes no H=: the front door refuses the partial-state track at fusion time,
    # after the association; nothing of that scan is kept
    scenario = two_targets(6, steps=3, sources=("a", "b", "c"), partial=("c",))
    fuser = TrackFuser("ei", motion=motion)
    first = [r for r in scenario.scans[0][1] if r.source != "c"]
    fuser.update(first, 0.0)
    before = snapshot(fuser)
    with pytest.raises(ValueError, match="does not accept H="):
        fuser.update(scenario.scans[1][1], scenario.scans[1][0])
    assert_same_state(before, snapshot(fuser))


def test_inputs_are_not_modified():
    scenario = two_targets(9, steps=4, sources=("a", "b", "c"), late=("b",), partial=("c",))
    copies = [[(r.x.copy(), r.P.copy(), None if r.H is None else r.H.copy()) for r in reports]
              for _, reports in scenario.scans]
    run(scenario)
    for (_, reports), saved in zip(scenario.scans, copies):
        for r, (x, P, H) in zip(reports, saved):
            np.testing.assert_array_equal(r.x, x)
            np.testing.assert_array_equal(r.P, P)
            if H is not None:
                np.testing.assert_array_equal(r.H, H)


def test_tracks_time_and_reset():
    scenario = two_targets(10, steps=3)
    fuser, outputs, _ = run(scenario)
    assert fuser.time == scenario.scans[-1][0]
    assert [c.id for c in fuser.tracks] == [c.id for c in outputs[-1]] == [1, 2]
    fuser.tracks.clear()  # a copy: the fuser keeps its tracks
    assert len(fuser.tracks) == 2
    fuser.reset()
    assert fuser.tracks == [] and fuser.time is None and fuser.last_scan == {}
    out = fuser.update(*scenario.scans[0][::-1])
    assert [c.id for c in out] == [1, 2]  # ids start again after a reset


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(method="nope"), ValueError, "nope"),
    (dict(motion=3), TypeError, "motion must be callable"),
    (dict(gate=1.0), ValueError, "gate must be a probability in"),
    (dict(gate="high"), TypeError, "gate must be a probability"),
    (dict(confirm=(3, 2)), ValueError, "M <= N"),
    (dict(confirm=3), TypeError, "confirm must be a pair"),
    (dict(confirm_sources=0), ValueError, "confirm_sources must be at least 1"),
    (dict(delete_after=1.5), TypeError, "delete_after must be an integer"),
    (dict(dim=0), ValueError, "dim must be at least 1"),
    (dict(association="mahalanobis"), ValueError, "association must be"),
    (dict(fuse_prediction="yes"), TypeError, "fuse_prediction must be a bool"),
])
def test_bad_options(kwargs, error, match):
    options = dict(method="ci", motion=motion)
    options.update(kwargs)
    method = options.pop("method")
    with pytest.raises(error, match=match):
        TrackFuser(method, **options)
