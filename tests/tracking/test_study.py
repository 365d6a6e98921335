"""cifilter.tracking.study: running a fusion node over the multi-target scenario and scoring
its central tracks (hand-derived scores, the scenario's verdicts, bad input)."""

import numpy as np
import pytest

from cifilter.network import TargetData, multi_target, simulate_targets
from cifilter.tracking import (
    CentralTrack,
    TrackingRun,
    compare_tracking,
    format_tracking,
    run_tracking,
    score_sources,
    score_tracking,
)


def _central(track_id, position, *, confirmed=True, P=None, velocity=(0.0, 0.0)):
    x = np.array([position[0], velocity[0], position[1], velocity[1]])
    return CentralTrack(id=track_id, x=x, P=np.eye(4) if P is None else P, time=0.0,
                        confirmed=confirmed, sources={}, hits=1, misses=0, born=0.0)


def _data(truth, alive):
    truth = np.asarray(truth, float)
    steps = truth.shape[0]
    return TargetData(multi_target(), np.where(alive[..., None], truth, np.nan),
                      np.asarray(alive), np.arange(float(steps)), [()] * steps,
                      [()] * steps)


def _run(scans, method="ci"):
    return TrackingRun(method, tuple(tuple(s) for s in scans), np.arange(float(len(scans))),
                       np.full(len(scans), 0.002), {})


def test_scores_by_hand():
    # two targets; state [x, vx, y, vy]
    truth = np.zeros((3, 2, 4))
    truth[:, 0] = [0.0, 0.0, 0.0, 0.0]
    truth[:, 1] = [100.0, 0.0, 0.0, 0.0]
    alive = np.array([[True, True], [True, True], [True, False]])
    scans = [
        # scan 0: target 0 found 5 m off (3, 4) by track 1; target 1 missed; track 2 false;
        # track 3 is tentative (not scored)
        [_central(1, (3.0, 4.0)), _central(2, (500.0, 0.0)),
         _central(3, (100.0, 0.0), confirmed=False)],
        # scan 1: target 0 found exactly by track 1, target 1 found 1 m off by track 4
        [_central(1, (0.0, 0.0)), _central(4, (101.0, 0.0))],
        # scan 2: track 1 gone; target 0 found 2 m off by track 4: one ID switch;
        # target 1 is no longer alive
        [_central(4, (0.0, 2.0))],
    ]
    score = score_tracking(_run(scans), _data(truth, alive), c=10.0)
    # GOSPA^2 per scan: 25 + 50 (missed) + 50 (false); 0 + 1; 4
    assert score.gospa == pytest.approx((np.sqrt(125.0) + 1.0 + 2.0) / 3, rel=1e-15)
    assert score.localisation == pytest.approx((25.0 + 1.0 + 4.0) / 3)
    assert score.missed == pytest.approx(50.0 / 3) and score.false == pytest.approx(50.0 / 3)
    # four matched pairs, P = I: NEES = squared errors 25, 0, 1, 4
    assert score.matches == 4
    assert score.anees == pytest.approx(30.0 / 4)
    assert score.rmse == pytest.approx(np.sqrt(30.0 / 4))
    assert score.id_switches == 1
    assert score.false_tracks == pytest.approx(1 / 3)
    assert score.missed_targets == pytest.approx(1 / 3)
    assert score.ms_per_scan == pytest.approx(2.0)
    assert score.verdict == "overconfident" and score.scans == 3
    # skip leaves out the first scan
    later = score_tracking(_run(scans), _data(truth, alive), c=10.0, skip=1)
    assert later.scans == 2 and later.matches == 3 and later.id_switches == 1


def test_a_gate_narrower_than_c_matches_fewer():
    truth = np.zeros((1, 1, 4))
    scans = [[_central(1, (6.0, 0.0))]]
    wide = score_tracking(_run(scans), _data(truth, np.array([[True]])), c=10.0)
    narrow = score_tracking(_run(scans), _data(truth, np.array([[True]])), c=10.0, gate=5.0)
    assert wide.matches == 1 and narrow.matches == 0
    assert wide.gospa == narrow.gospa == 6.0          # GOSPA does not depend on the gate
    assert narrow.false_tracks == 1.0 and narrow.missed_targets == 1.0
    assert np.isnan(narrow.anees) and narrow.verdict == "-"


def test_crossing_targets_keep_their_tracks_in_the_score():
    # at scan 1 the targets are 0.1 m apart and each track is nearer the *other* target:
    # a fresh optimal assignment would swap them (two ID switches); the score keeps last
    # scan's pairs while they stay within the gate (CLEAR MOT)
    truth = np.zeros((3, 2, 4))
    truth[:, 0, [0, 2]] = [[-4.0, 0.0], [0.0, 0.05], [4.0, 0.0]]
    truth[:, 1, [0, 2]] = [[-4.0, 4.0], [0.0, -0.05], [4.0, -4.0]]
    alive = np.ones((3, 2), dtype=bool)
    scans = [[_central(7, truth[k, 0, [0, 2]] + 0.1), _central(9, truth[k, 1, [0, 2]] - 0.1)]
             for k in range(3)]
    scans[1] = [_central(9, (0.0, 0.1)), _central(7, (0.0, -0.1))]
    score = score_tracking(_run(scans), _data(truth, alive), c=3.0)
    assert score.id_switches == 0 and score.matches == 6
    # the errors are those of the kept pairs: 0.15 m at scan 1
    expected = np.sqrt((4 * 2 * 0.1**2 + 2 * 0.15**2) / 6)
    assert score.rmse == pytest.approx(expected, rel=1e-12)


def test_ci_on_the_scenario_conservative_and_better_than_every_source():
    data = [simulate_targets(multi_target(), rng=seed) for seed in (0, 1)]
    runs = [run_tracking(d, "ci") for d in data]
    assert all(len(r.tracks) == d.steps for r, d in zip(runs, data))
    assert np.all(runs[0].seconds > 0)
    ci = score_tracking(runs, data, skip=5)
    best_source = min(row["rmse"] for row in score_sources(data, skip=5))
    assert ci.anees < ci.upper and ci.verdict != "overconfident"
    assert ci.rmse < best_source
    assert ci.id_switches == 0                        # through the crossing
    naive = score_tracking([run_tracking(d, "naive") for d in data], data, skip=5)
    assert naive.verdict == "overconfident"          # data incest of correlated tracks
    assert naive.anees > 1.5 * ci.anees


def test_score_sources_are_consistent_local_tracks():
    rows = score_sources([simulate_targets(multi_target(), rng=s) for s in (0, 1, 2)])
    assert [r["method"] for r in rows] == ["source radar-1", "source radar-2",
                                           "source camera"]
    for row in rows:
        assert row["matches"] > 300
        assert 3.0 < row["anees"] < 5.0
        assert 2.0 < row["rmse"] < 40.0


def test_partial_and_late_sources_are_fused_or_refused_by_name():
    data = simulate_targets(multi_target(), rng=1, partial=["camera"], lateness=1)
    rows = compare_tracking(data, ["ci", "ici"])
    ci, ici = rows
    assert "error" not in ci and ci["matches"] > 100
    assert "error" in ici and "ici" in ici["error"]
    table = format_tracking(rows)
    assert "cannot run" in table.splitlines()[4]


def test_compare_and_format():
    data = simulate_targets(multi_target(steps=40), rng=3)
    rows = compare_tracking(data, ["ci", "pci"], delete_after=2)
    assert [r["method"] for r in rows] == ["ci", "pci rho=0.5"]
    assert rows[0]["guarantee"] == "bound"
    lines = format_tracking(rows + score_sources(data)).splitlines()
    assert len(lines) == 3 + 2 + 3
    assert lines[3].split()[0] == "ci" and lines[5].split()[:2] == ["source", "radar-1"]
    own = compare_tracking(data, ["pci"], options={"pci": {"rho": 0.2}})
    assert own[0]["method"] == "pci rho=0.2"


def test_same_data_same_scores():
    data = simulate_targets(multi_target(steps=40), rng=4)
    one = score_tracking(run_tracking(data, "ci"), data).as_row()
    two = score_tracking(run_tracking(data, "ci"), data).as_row()
    for key in one:
        if key != "ms_per_scan":
            assert one[key] == two[key] or (one[key] != one[key] and two[key] != two[key])


def test_bad_input():
    data = simulate_targets(multi_target(steps=40), rng=0)
    run = run_tracking(data, "naive")
    with pytest.raises(TypeError, match="TargetData"):
        run_tracking("data", "ci")
    with pytest.raises(ValueError, match="unknown"):
        run_tracking(data, "no-such-rule")
    with pytest.raises(ValueError, match="as many runs"):
        score_tracking([run, run], data)
    with pytest.raises(ValueError, match="skip"):
        score_tracking(run, data, skip=40)
    with pytest.raises(ValueError, match="c must"):
        score_tracking(run, data, c=0.0)
    with pytest.raises(ValueError, match="gate"):
        score_tracking(run, data, gate=-1.0)
    short = simulate_targets(multi_target(steps=32), rng=0)
    with pytest.raises(ValueError, match="scans"):
        score_tracking(run, short)
