"""Issue 22, item 5: tracks that arrive late and out of order (``simulate_data(lateness=)``,
``run_network(late=)``) and nodes that send part of their track (``run_network(
partial_nodes=, partial=)``), against the synchronous simulation and an independent
per-run reference that predicts late tracks by hand."""

import dataclasses

import numpy as np
import pytest

import cifilter
from cifilter import KalmanFilter, montecarlo
from cifilter.network import (
    NetworkStudy,
    compare,
    constant_velocity_model,
    naveen_taylor,
    ring,
    run_network,
    simulate_data,
    two_tracks,
)

POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _same(a, b):
    assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    assert a.fusions == b.fusions and a.exchanges == b.exchanges


# --- nothing late, nothing partial: the synchronous simulation, bitwise -----------------

def test_no_lateness_draws_nothing_and_changes_no_draw():
    scenario = naveen_taylor()
    plain = simulate_data(scenario, 3, 7, loss=0.2, rng=3)
    for lateness in (0, (1.0,), [1.0]):
        same = simulate_data(scenario, 3, 7, loss=0.2, lateness=lateness, rng=3)
        assert same.lateness is None
        assert np.array_equal(same.truth, plain.truth)
        assert np.array_equal(same.initial, plain.initial)
        assert np.array_equal(same.delivered, plain.delivered)
        assert all(np.array_equal(a, b) for a, b in zip(same.measurements, plain.measurements))
    # the lateness is drawn last: every other draw is that of a call without it
    late = simulate_data(scenario, 3, 7, loss=0.2, lateness=3, rng=3)
    assert np.array_equal(late.truth, plain.truth)
    assert np.array_equal(late.delivered, plain.delivered)
    assert late.lateness.shape == (3, 7, 6, 6) and late.lateness.max() == 3


@pytest.mark.parametrize("method", ["ci", "naive", "optimal", "pci"])
@pytest.mark.parametrize("config", [dict(), dict(sequential=True),
                                    dict(period=2, feedback=False)])
def test_zero_lateness_and_no_partial_nodes_reproduce_the_simulation_bitwise(method, config):
    scenario = naveen_taylor()
    data = simulate_data(scenario, 3, 8, loss=0.3, rng=4)
    synchronous = run_network(scenario, data, method, rng=1, **config)
    zeros = dataclasses.replace(data, lateness=np.zeros((3, 8, 6, 6), dtype=int))
    for late in ("align", "ignore", "drop"):
        for partial_nodes in (None, (), {}):
            _same(run_network(scenario, zeros, method, rng=1, late=late,
                              partial_nodes=partial_nodes, **config), synchronous)


@pytest.mark.parametrize("method", ["ci", "optimal"])
@pytest.mark.parametrize("sequential", [False, True])
def test_dropping_late_tracks_is_losing_them(method, sequential):
    """late="drop" is the synchronous network whose late messages are lost (the optimal
    fusion too: its joint covariance is propagated when nothing late is fused)."""
    scenario = ring(5)
    data = simulate_data(scenario, 3, 10, loss=0.2, lateness=2, rng=5)
    lost = dataclasses.replace(data, delivered=data.delivered & (data.lateness == 0),
                               lateness=None)
    _same(run_network(scenario, data, method, late="drop", sequential=sequential, rng=2),
          run_network(scenario, lost, method, sequential=sequential, rng=2))
    # and dropping the partial tracks is losing every message of the partial nodes
    data = simulate_data(scenario, 3, 10, loss=0.2, rng=5)
    lost = data.delivered.copy()
    lost[:, :, :, [1, 3]] = False
    _same(run_network(scenario, data, method, partial_nodes=[1, 3], partial="drop",
                      sequential=sequential, rng=2),
          run_network(scenario, dataclasses.replace(data, delivered=lost), method,
                      sequential=sequential, rng=2))


# --- an independent reference: one run, one node at a time, late tracks predicted by hand

def _predicted(x, P, F, Q, steps):
    """A track brought ``steps`` steps forward by the model, written out."""
    for _ in range(steps):
        x, P = F @ x, F @ P @ F.T + Q
    return x, P


def _reference(scenario, data, method, *, late, partial_nodes=(), sequential=False,
               feedback=True, period=1):
    """The network written naively with cifilter.KalmanFilter objects and cifilter.fuse:
    every node keeps the tracks it sent; a late track is predicted explicitly (late=
    "align") or fused as it is ("ignore"); a partial track is fused with H=."""
    runs, steps, nodes, n = data.runs, data.steps, scenario.nodes, scenario.dim
    S = np.eye(n)[list(scenario.position_indices)]
    out_x, out_P = np.empty((runs, steps, nodes, n)), np.empty((runs, steps, nodes, n, n))
    fusions = 0
    for r in range(runs):
        filters = []
        for i in range(nodes):
            kf = KalmanFilter(dim_x=n, dim_z=scenario.H[i].shape[0])
            kf.F, kf.Q, kf.H, kf.R = scenario.F, scenario.Q, scenario.H[i], scenario.R[i]
            kf.x, kf.P = data.initial[r, i].reshape(-1, 1).copy(), scenario.P0[i].copy()
            filters.append(kf)
        sent = {}
        for k in range(steps):
            for i, kf in enumerate(filters):
                kf.predict()
                kf.update(data.measurements[i][r, k].reshape(-1, 1))
            if (k + 1) % period == 0:
                for j, kf in enumerate(filters):
                    sent[k, j] = (kf.x[:, 0].copy(), kf.P.copy())
            fused = []
            for i, kf in enumerate(filters):
                arrivals = []
                for j in np.flatnonzero(scenario.adjacency[i]):
                    for d in range(4):
                        s = k - d
                        if (s, j) not in sent or data.lateness[r, s, i, j] != d:
                            continue
                        if data.delivered is not None and not data.delivered[r, s, i, j]:
                            continue
                        if d and late == "drop":
                            continue
                        arrivals.append((j in partial_nodes, d, j))
                own = (kf.x[:, 0].copy(), kf.P.copy())
                messages, H = [], []
                # one at a time: the senders' order, newest first; all at once: full
                # tracks, then partial ones, each by lateness and sender (the simulation's
                # order, which changes the sum of the fusion only in rounding)
                for partial, d, j in sorted(arrivals, key=(lambda a: (a[2], a[1])) if
                                            sequential else None):
                    x_j, P_j = sent[k - d, j]
                    if late == "align":
                        x_j, P_j = _predicted(x_j, P_j, scenario.F, scenario.Q, d)
                    if partial:
                        x_j, P_j = S @ x_j, S @ P_j @ S.T
                    messages.append((x_j, P_j))
                    H.append(S if partial else None)
                if not messages:
                    fused.append(own)
                    continue
                fusions += len(messages) if sequential else 1
                if sequential:
                    for message, h in zip(messages, H):
                        result = cifilter.fuse([own, message], method,
                                               **({"H": [None, h]} if h is not None else {}))
                        own = (result.x, result.P)
                else:
                    options = {"H": [None, *H]} if any(h is not None for h in H) else {}
                    result = cifilter.fuse([own, *messages], method, **options)
                    own = (result.x, result.P)
                fused.append(own)
            for i, (x_i, P_i) in enumerate(fused):
                out_x[r, k, i], out_P[r, k, i] = x_i, P_i
                if feedback:
                    filters[i].x, filters[i].P = x_i.reshape(-1, 1).copy(), P_i.copy()
    return out_x, out_P, fusions


def _close(track, reference):
    x, P, fusions = reference
    assert track.fusions == fusions
    scale = max(1.0, float(np.abs(x).max()))
    assert np.allclose(track.x, x, rtol=1e-8, atol=1e-8 * scale)
    assert np.allclose(track.P, P, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("late", ["align", "ignore", "drop"])
@pytest.mark.parametrize("config", [dict(), dict(sequential=True),
                                    dict(feedback=False, period=2)])
def test_late_tracks_out_of_order_against_the_reference(late, config):
    """Every late track fused through the time alignment equals its explicit prediction
    followed by the rule; several tracks of one sender, and tracks older than one fused
    before, arrive at once (checked to occur in these data)."""
    scenario = ring(4)
    data = simulate_data(scenario, 2, 9, loss=0.1, lateness=3, rng=7)
    arrival = (np.arange(9)[None, :, None, None] + data.lateness)[..., scenario.adjacency]
    assert (arrival[:, :-1] > arrival[:, 1:]).any()   # a track after a newer one of its link
    assert (arrival[:, :-1] == arrival[:, 1:]).any()  # two tracks of one link at once
    track = run_network(scenario, data, "ci", late=late, **config)
    _close(track, _reference(scenario, data, "ci", late=late, **config))
    assert track.exchanges == 9 // config.get("period", 1)  # the steps at which nodes send


@pytest.mark.parametrize("config", [dict(), dict(sequential=True), dict(feedback=False)])
def test_partial_tracks_against_the_reference(config):
    scenario = ring(4)
    data = simulate_data(scenario, 2, 9, loss=0.1, rng=8)
    data = dataclasses.replace(data, lateness=np.zeros((2, 9, 4, 4), dtype=int))
    for method in ("ci", "naive"):
        track = run_network(scenario, data, method, partial_nodes=[1, 2], **config)
        _close(track, _reference(scenario, data, method, late="align",
                                 partial_nodes=(1, 2), **config))
    # late partial tracks fused as they are (late="ignore"), late full tracks aligned
    late = simulate_data(scenario, 2, 9, lateness=2, rng=9)
    track = run_network(scenario, late, "ci", late="ignore", partial_nodes=[1], **config)
    _close(track, _reference(scenario, late, "ci", late="ignore", partial_nodes=(1,),
                             **config))


def test_a_late_track_through_the_alignment_equals_prediction_then_fusion_by_hand():
    """Two nodes without feedback: node 0's fused estimate at step 5 is its local track
    fused with node 1's tracks of steps 2 and 4, each predicted to step 5 by hand."""
    scenario = two_tracks()
    data = simulate_data(scenario, 1, 6, rng=0)
    lateness = np.full((1, 6, 2, 2), 6)  # nothing arrives within the 6 steps ...
    lateness[0, 2, 0, 1] = 3             # ... but these two tracks of node 1, at step 5
    lateness[0, 4, 0, 1] = 1
    data = dataclasses.replace(data, lateness=lateness)
    local = run_network(scenario, data, None)
    F, Q = constant_velocity_model(1.0, 0.5)  # two_tracks' model
    own = (local.x[0, 5, 0], local.P[0, 5, 0])
    old = [(local.x[0, s, 1], local.P[0, s, 1], 5 - s) for s in (4, 2)]  # lateness 1, 3
    for sequential in (False, True):
        track = run_network(scenario, data, "ci", feedback=False, sequential=sequential)
        predicted = [_predicted(x, P, F, Q, d) for x, P, d in old]
        if sequential:
            expected = own
            for message in predicted:
                r = cifilter.fuse([expected, message], "ci")
                expected = (r.x, r.P)
        else:
            r = cifilter.fuse([own, *predicted], "ci")
            expected = (r.x, r.P)
        assert np.allclose(track.x[0, 5, 0], expected[0], rtol=1e-10, atol=1e-9)
        assert np.allclose(track.P[0, 5, 0], expected[1], rtol=1e-10, atol=1e-10)
        # steps 0 to 4: nothing arrived, node 0 is its local filter
        assert np.array_equal(track.x[0, :5, 0], local.x[0, :5, 0])
        # ignoring the delay fuses the old tracks as they are: another (wrong) answer
        ignored = run_network(scenario, data, "ci", feedback=False, late="ignore",
                              sequential=sequential)
        assert not np.allclose(ignored.x[0, 5, 0], track.x[0, 5, 0])
    # the time alignment gives the late track the weight its predicted covariance earns:
    # here (1 step late, node 1's sensor better along x) a positive one
    r = cifilter.fuse([own, (local.x[0, 4, 1], local.P[0, 4, 1])], "ci", times=[5.0, 4.0],
                      motion=scenario.motion)
    assert r.weights[1] > 0.0


def test_a_partial_track_is_fused_through_H():
    scenario = two_tracks()
    data = simulate_data(scenario, 3, 6, rng=1)
    local = run_network(scenario, data, None)
    x_only = np.array([[1.0, 0.0, 0.0, 0.0]])
    for partial_nodes, S in (([1], POSITION), ({1: x_only}, x_only)):
        track = run_network(scenario, data, "ci", feedback=False, partial_nodes=partial_nodes)
        message = (local.x[:, :, 1] @ S.T, S @ local.P[:, :, 1] @ S.T)
        expected = cifilter.fuse([(local.x[:, :, 0], local.P[:, :, 0]), message],
                                 "ci", H=[None, S])
        assert np.allclose(track.x[:, :, 0], expected.x, rtol=1e-10, atol=1e-9)
        assert np.allclose(track.P[:, :, 0], expected.P, rtol=1e-10, atol=1e-10)
        # node 1 keeps its full filter and fuses node 0's full track
        full = cifilter.fuse([(local.x[:, :, 1], local.P[:, :, 1]),
                              (local.x[:, :, 0], local.P[:, :, 0])], "ci")
        assert np.allclose(track.x[:, :, 1], full.x, rtol=1e-10, atol=1e-9)
    dropped = run_network(scenario, data, "ci", feedback=False, partial_nodes=[1],
                          partial="drop")
    assert np.array_equal(dropped.x[:, :, 0], local.x[:, :, 0])


@pytest.mark.parametrize("method", ["ci", "optimal"])
@pytest.mark.parametrize("sequential", [False, True])
def test_a_partial_track_of_all_of_the_state_is_a_full_track(method, sequential):
    """A node that sends ``S x`` with ``S`` invertible sends all it knows: through H= (and,
    for the optimal fusion, the propagated joint covariance of the partial tracks, rows
    ``S e_j``) the network is the synchronous one, to rounding."""
    scenario = ring(4)
    data = simulate_data(scenario, 3, 10, loss=0.2, rng=2)
    full = run_network(scenario, data, method, sequential=sequential)
    shuffle = np.eye(4)[[2, 0, 3, 1]] * np.array([[2.0], [0.5], [1.0], [3.0]])
    for S in (np.eye(4), shuffle):
        track = run_network(scenario, data, method, sequential=sequential,
                            partial_nodes={1: S, 2: S})
        assert np.allclose(track.x, full.x, rtol=1e-8, atol=1e-8)
        assert np.allclose(track.P, full.P, rtol=1e-8, atol=1e-9)


def test_the_optimal_fusion_of_partial_tracks_with_the_propagated_joint_is_consistent():
    """The joint covariance the simulation carries through partial tracks is the true one:
    the optimal fusion told it is consistent (and, knowing the correlations, better than
    CI), while CI stays below the band."""
    rows = {row["method"]: row for row in compare(
        ring(4), ["ci", "optimal"], runs=10, steps=30, rng=8, partial_nodes=(1, 3))}
    assert rows["optimal"]["verdict"] == "consistent"
    assert rows["optimal"]["rmse"] < rows["ci"]["rmse"] < rows["local"]["rmse"]
    assert rows["ci"]["anees"] < rows["ci"]["upper"]


# --- randomness -------------------------------------------------------------------------

def test_same_seed_same_result_and_the_lateness_distribution():
    scenario = ring(4)
    first = simulate_data(scenario, 3, 10, lateness=3, rng=5)
    again = simulate_data(scenario, 3, 10, lateness=3, rng=np.random.default_rng(5))
    assert np.array_equal(first.lateness, again.lateness)
    assert not np.array_equal(first.lateness,
                              simulate_data(scenario, 3, 10, lateness=3, rng=6).lateness)
    a = run_network(scenario, first, "ci", partial_nodes=[2], late="ignore")
    b = run_network(scenario, again, "ci", partial_nodes=[2], late="ignore")
    _same(a, b)
    study = NetworkStudy(scenario, ("ci",), steps=6, lateness=(0.5, 0.3, 0.2),
                         partial_nodes=(1,), partial="fuse", late="ignore")
    one = montecarlo.run(study, 4, chunk_size=2, seed=3)
    two = montecarlo.run(study, 4, chunk_size=2, seed=3)
    assert np.array_equal(one["ci/nees"], two["ci/nees"])
    assert not np.array_equal(one["ci/nees"],
                              montecarlo.run(study, 4, chunk_size=2, seed=4)["ci/nees"])
    # the draws follow the probabilities given (360000 draws: 5 standard errors < 0.004)
    draws = simulate_data(scenario, 100, 100, lateness=(0.7, 0.2, 0.0, 0.1), rng=0).lateness
    shares = np.bincount(draws.ravel(), minlength=4) / draws.size
    assert np.allclose(shares, [0.7, 0.2, 0.0, 0.1], atol=0.004)
    uniform = simulate_data(scenario, 100, 100, lateness=2, rng=0).lateness
    assert np.allclose(np.bincount(uniform.ravel()) / uniform.size, 1 / 3, atol=0.004)


# --- bad options --------------------------------------------------------------------------

def test_bad_options_give_clear_errors():
    scenario = ring(4)
    data = simulate_data(scenario, 2, 5, rng=0)
    late = simulate_data(scenario, 2, 5, lateness=3, rng=0)
    for value, error, match in ((-1, ValueError, "lateness must be >= 0"),
                                ((0.5, 0.6), ValueError, "sum to 1"),
                                ((1.2, -0.2), ValueError, "finite and >= 0"),
                                ((), ValueError, "non-empty"),
                                ("3", TypeError, "lateness must be an integer"),
                                (1.5, TypeError, "lateness must be an integer"),
                                (True, TypeError, "lateness must be an integer")):
        with pytest.raises(error, match=match):
            simulate_data(scenario, 2, 5, lateness=value, rng=0)
    for options, error, match in (
            (dict(late="later"), ValueError, "late must be one of 'align', 'ignore', 'drop'"),
            (dict(late=1), TypeError, "late must be one of"),
            (dict(partial="keep"), ValueError, "partial must be one of 'fuse', 'drop'"),
            (dict(partial_nodes=[4]), ValueError, "node 4, outside 0..3"),
            (dict(partial_nodes=[1, 1]), ValueError, "node 1 twice"),
            (dict(partial_nodes=[1.0]), TypeError, "by their index"),
            (dict(partial_nodes="1"), TypeError, "sequence of node indices"),
            (dict(partial_nodes=3), TypeError, "sequence of node indices"),
            (dict(partial_nodes={1: np.ones((2, 3))}), ValueError, r"shape \(m, 4\)"),
            (dict(partial_nodes={1: [[1, 0, 0, 0], [2, 0, 0, 0]]}), ValueError,
             "linearly independent"),
            (dict(partial_nodes={1: [[np.nan, 0, 0, 0]]}), ValueError, "finite")):
        with pytest.raises(error, match=match):
            run_network(scenario, data, "ci", **options)
    with pytest.raises(ValueError, match="give one or the other"):
        run_network(scenario, late, "ci", delay=True)
    with pytest.raises(ValueError, match=r"'optimal'.*late='drop'"):
        run_network(scenario, late, "optimal")
    with pytest.raises(ValueError, match=r"'pci'.*late='drop'"):
        run_network(scenario, late, "pci", late="ignore")
    with pytest.raises(ValueError, match="cannot bring them to the current time"):
        run_network(scenario, late, "ci", partial_nodes=[1])
    with pytest.raises(ValueError, match=r"does not accept times=.*'ci'"):
        run_network(scenario, late, "naive")  # the front door's refusal
    with pytest.raises(ValueError, match=r"does not accept H=.*'ci'"):
        run_network(scenario, data, "ei", partial_nodes=[1], sequential=True)
    for lateness, error, match in ((np.zeros((2, 5, 4)), ValueError, "must have shape"),
                                   (np.zeros((2, 5, 4, 4)), TypeError, "integers"),
                                   (-np.ones((2, 5, 4, 4), dtype=int), ValueError, ">= 0")):
        with pytest.raises(error, match=match):
            run_network(scenario, dataclasses.replace(data, lateness=lateness), "ci")
    # a study refuses bad options when it is made, before any work
    with pytest.raises(ValueError, match="late must be one of"):
        NetworkStudy(scenario, ("ci",), late="soon")
    with pytest.raises(ValueError, match="sum to 1"):
        NetworkStudy(scenario, ("ci",), lateness=(0.2, 0.2))
    with pytest.raises(ValueError, match="give one or the other"):
        NetworkStudy(scenario, ("ci",), lateness=2, delay=True)
    # the model over several steps
    with pytest.raises(ValueError, match="whole number of steps"):
        scenario.motion(1.5)
    with pytest.raises(ValueError, match="dt must lie in"):
        scenario.motion(-1)
    with pytest.raises(TypeError, match="dt must be a real number"):
        scenario.motion("1")


def test_the_scenarios_motion_is_its_model_over_several_steps():
    scenario = ring(4)  # dt 1, q 0.5
    F0, Q0 = scenario.motion(0)
    assert np.array_equal(F0, np.eye(4)) and not Q0.any()
    for steps in (1, 2, 3):
        F, Q = scenario.motion(float(steps))
        F_cv, Q_cv = constant_velocity_model(float(steps), 0.5)
        assert np.allclose(F, F_cv, rtol=1e-14, atol=0)
        assert np.allclose(Q, Q_cv, rtol=1e-13, atol=0)
        assert np.array_equal(Q, Q.T)


# --- the verdicts: ignoring the delay is overconfident, the alignment with CI is not ------

def test_ignoring_the_delay_is_overconfident_where_aligning_with_ci_is_not():
    """Ring of four, tracks 0-3 steps late, 5 runs x 20 steps. Over seeds 0-99 the verdicts
    never flipped: CI with the alignment had a pooled ANEES of at most 0.76 times the
    upper end of its band (dropping the late tracks 0.86), CI ignoring the delay at least
    5.56 times it, with at least 2.26 times the aligned RMSE."""
    rows = {late: {row["method"]: row for row in compare(
        ring(4), ["ci"], runs=5, steps=20, rng=0, lateness=3, late=late)}["ci"]
        for late in ("align", "ignore", "drop")}
    assert rows["align"]["anees"] < rows["align"]["upper"]
    assert rows["align"]["verdict"] != "overconfident"
    assert rows["ignore"]["verdict"] == "overconfident"
    assert rows["ignore"]["anees"] > 5 * rows["ignore"]["upper"]
    assert rows["ignore"]["rmse"] > 2 * rows["align"]["rmse"]
    assert rows["drop"]["verdict"] != "overconfident"


def test_fusing_partial_tracks_beats_dropping_them_and_stays_conservative():
    """Ring of four whose nodes 1 and 3 send only their position, 5 runs x 20 steps: CI
    through H= has a smaller position RMSE than CI without the partial tracks and is not
    overconfident. Over seeds 0-99 neither flipped: CI through H= had a pooled ANEES of at
    most 0.481 times the upper end of its band and at most 0.611 times the RMSE of
    dropping the partial tracks; dropping them stayed at most 0.79 times its upper end."""
    rows = {partial: {row["method"]: row for row in compare(
        ring(4), ["ci"], runs=5, steps=20, rng=0, partial_nodes=(1, 3),
        partial=partial)}["ci"] for partial in ("fuse", "drop")}
    assert rows["fuse"]["anees"] < rows["fuse"]["upper"]
    assert rows["fuse"]["rmse"] < rows["drop"]["rmse"]
    assert rows["drop"]["verdict"] != "overconfident"


def test_the_pci_truth_hook_splits_the_joint_of_partial_tracks_by_their_sizes():
    """The 'pci' truth hook's rho for a full and a partial track comes from blocks of the
    tracks' own sizes (4 and 2), not from equal halves of the joint."""
    rng = np.random.default_rng(4)
    A = rng.standard_normal((6, 6))
    joint = A @ A.T + 6.0 * np.eye(6)
    record = cifilter.get_method("pci")
    rho = record.options_given_truth(joint, None, count=2, sizes=[4, 2])["rho"]
    # eq. (8): the largest singular value of X^-1 P_ab Y^-T with P_a = X X^T, P_b = Y Y^T
    X, Y = np.linalg.cholesky(joint[:4, :4]), np.linalg.cholesky(joint[4:, 4:])
    expected = np.linalg.svd(np.linalg.solve(X, np.linalg.solve(Y, joint[:4, 4:].T).T),
                             compute_uv=False).max()
    assert np.isclose(np.max(rho), expected, rtol=1e-10)
    # a hook that uses the joint whole is not given the sizes
    optimal = cifilter.get_method("optimal").options_given_truth(joint, None, count=2,
                                                                  sizes=[4, 2])
    assert optimal["joint"] is joint or np.array_equal(optimal["joint"], joint)


@pytest.mark.parametrize("sequential", [False, True])
def test_pci_fuses_partial_tracks_with_the_rho_of_their_joint(sequential):
    scenario = ring(4)
    data = simulate_data(scenario, 4, 12, rng=3)
    track = run_network(scenario, data, "pci", sequential=sequential, partial_nodes=[1])
    assert np.all(np.isfinite(track.P))
    reference = run_network(scenario, data, "ci", sequential=sequential, partial_nodes=[1])
    # with the true (smallest admissible) rho the bound is at most CI's (rho = 1) bound
    # for the same inputs at the first fusion of every node
    first = np.trace(track.P[:, 0], axis1=-2, axis2=-1)
    assert np.all(first <= np.trace(reference.P[:, 0], axis1=-2, axis2=-1) * (1 + 1e-9))
