"""cifilter.network: graphs, scenarios, the vectorised network simulation and its studies."""

import numpy as np
import pytest

from cifilter import FusionResult, KalmanFilter, available_methods, registry
from cifilter.cli.demo import run_two_tracks, score
from cifilter.network import (
    NetworkData,
    NetworkStudy,
    Scenario,
    adjacency_matrix,
    chain,
    compare,
    fully_connected,
    get_scenario,
    naveen_taylor,
    ring,
    run_network,
    scenario_names,
    simulate_data,
    summarize,
    two_tracks,
)

DETERMINISTIC = ("ci", "naive", "optimal", "pci", "ei", "pcei")


# --- graphs and scenarios ------------------------------------------------------------

def test_adjacency_from_matrix_edges_and_a_graph_object():
    matrix = adjacency_matrix(np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]]))
    assert adjacency_matrix([(0, 1), (1, 2)]).tolist() == matrix.tolist()

    class Graph:  # what networkx offers: nodes and edges (networkx itself not needed)
        nodes = ("a", "b", "c")
        edges = (("a", "b"), ("b", "c"))

    assert adjacency_matrix(Graph()).tolist() == matrix.tolist()
    assert adjacency_matrix([(0, 1)], nodes=3).sum(axis=1).tolist() == [1, 1, 0]
    assert not adjacency_matrix(np.ones((3, 3))).diagonal().any()  # self-loops ignored
    with pytest.raises(ValueError, match="symmetric"):
        adjacency_matrix(np.array([[0, 1], [0, 0]]))
    with pytest.raises(ValueError, match="outside"):
        adjacency_matrix([(0, 5)], nodes=3)


def test_ready_scenarios():
    six = naveen_taylor()
    assert six.nodes == 6 and len(six.edges) == 7
    assert six.degrees.tolist() == [2, 3, 2, 2, 3, 2]
    assert all(np.linalg.eigvalsh(R).min() > 0 for R in six.R)
    assert chain(5).edges == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert ring(6).degrees.tolist() == [2] * 6
    assert fully_connected(4).degrees.tolist() == [3] * 4
    assert two_tracks().edges == [(0, 1)]
    for name in scenario_names():
        assert get_scenario(name).name == name
    with pytest.raises(ValueError, match="unknown scenario"):
        get_scenario("star")
    # the sensors are part of the scenario: fixed by sensor_seed (default 2), the same on
    # every construction, different for another sensor_seed
    first, again = naveen_taylor().R, naveen_taylor().R
    assert len(first) == 6 and all(np.array_equal(a, b) for a, b in zip(first, again))
    assert all(np.array_equal(a, b) for a, b in zip(first, naveen_taylor(sensor_seed=2).R))
    assert not any(np.array_equal(a, b) for a, b in zip(first, naveen_taylor(sensor_seed=3).R))
    assert len({tuple(np.ravel(R)) for R in first}) == 6  # six different sensors


def test_scenario_from_the_users_filters_and_graph():
    filters = []
    for r in (1.0, 4.0, 9.0):
        kf = KalmanFilter(dim_x=2, dim_z=1)
        kf.F = np.array([[1.0, 1.0], [0.0, 1.0]])
        kf.Q = 0.01 * np.eye(2)
        kf.H, kf.R, kf.P = np.array([[1.0, 0.0]]), np.array([[r]]), 10.0 * np.eye(2)
        filters.append(kf)
    scenario = Scenario.from_filters(filters, [(0, 1), (1, 2)])
    assert scenario.nodes == 3 and scenario.R[2][0, 0] == 9.0
    rows = compare(scenario, ["ci"], runs=5, steps=20, rng=0)
    assert [row["method"] for row in rows] == ["local", "centralised", "ci"]
    filters[1].F = np.eye(2)
    with pytest.raises(ValueError, match="share the target model"):
        Scenario.from_filters(filters, [(0, 1), (1, 2)])


# --- the simulation against hand-computed cases --------------------------------------

def _two_track_data(seed, runs, steps):
    """The two-track demo's truth and measurements, drawn in the demo's order."""
    scenario = two_tracks()
    rng = np.random.default_rng(seed)
    L_P0 = np.linalg.cholesky(scenario.P0[0])
    H = scenario.H[0]
    sigma = [np.sqrt(np.diag(R)) for R in scenario.R]
    truth = np.empty((runs, steps, 4))
    z = [np.empty((runs, steps, 2)), np.empty((runs, steps, 2))]
    initial = np.empty((runs, 2, 4))
    L_Q = np.linalg.cholesky(scenario.Q)
    for r in range(runs):
        state = np.array([0.0, 10.0, 0.0, 5.0])
        initial[r, 0] = state + L_P0 @ rng.standard_normal(4)
        initial[r, 1] = state + L_P0 @ rng.standard_normal(4)
        for k in range(steps):
            state = scenario.F @ state + L_Q @ rng.standard_normal(4)
            truth[r, k] = state
            for node in (0, 1):
                z[node][r, k] = H @ state + sigma[node] * rng.standard_normal(2)
    return scenario, NetworkData(truth, tuple(z), initial)


def test_two_nodes_without_feedback_reproduce_the_two_track_demo():
    seed, runs, steps = 3, 4, 30
    rows = {row["method"]: row for row in run_two_tracks(
        seed, runs, steps, methods=list(DETERMINISTIC), out=open("/dev/null", "w"))}
    scenario, data = _two_track_data(seed, runs, steps)
    local = run_network(scenario, data, None)
    for node, name in ((0, "local A"), (1, "local B")):
        got = score(local.x[:, :, node], local.P[:, :, node], data.truth)
        for key in ("rmse", "mean_nees", "inside", "mean_trace"):
            assert got[key] == pytest.approx(rows[name][key], rel=1e-9), (name, key)
    for method in DETERMINISTIC:
        track = run_network(scenario, data, method, feedback=False)
        got = score(track.x[:, :, 0], track.P[:, :, 0], data.truth)  # node A fuses (A, B)
        for key in ("rmse", "mean_nees", "inside", "mean_trace"):
            assert got[key] == pytest.approx(rows[method][key], rel=1e-6), (method, key)


def test_a_node_without_neighbours_is_its_local_filter():
    scenario = ring(4).with_graph([(0, 1), (1, 2)])  # node 3 is alone
    data = simulate_data(scenario, runs=3, steps=15, rng=4)
    fused = run_network(scenario, data, "ci")
    local = run_network(scenario, data, None)
    assert np.array_equal(fused.x[:, :, 3], local.x[:, :, 3])
    assert np.array_equal(fused.P[:, :, 3], local.P[:, :, 3])
    assert not np.allclose(fused.x[:, :, 0], local.x[:, :, 0])
    # ... and the local filter is filterpy's Kalman filter
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.Q, kf.H, kf.R = scenario.F, scenario.Q, scenario.H[3], scenario.R[3]
    kf.x, kf.P = data.initial[1, 3].reshape(4, 1), scenario.P0[3].copy()
    for k in range(15):
        kf.predict()
        kf.update(data.measurements[3][1, k].reshape(2, 1))
        assert np.allclose(kf.x[:, 0], local.x[1, k, 3], rtol=1e-10, atol=1e-9)
        assert np.allclose(kf.P, local.P[1, k, 3], rtol=1e-10, atol=1e-10)


def test_runs_are_vectorised_without_mixing():
    scenario = naveen_taylor()
    data = simulate_data(scenario, runs=3, steps=8, loss=0.3, rng=2)
    batch = run_network(scenario, data, "ci", sequential=True)
    for r in range(3):
        one = NetworkData(data.truth[r:r + 1], tuple(z[r:r + 1] for z in data.measurements),
                          data.initial[r:r + 1], data.delivered[r:r + 1])
        alone = run_network(scenario, one, "ci", sequential=True)
        assert np.allclose(alone.x[0], batch.x[r], rtol=1e-9, atol=1e-9)
        assert np.allclose(alone.P[0], batch.P[r], rtol=1e-9, atol=1e-9)


def test_exchange_options():
    scenario = ring(4)
    data = simulate_data(scenario, runs=2, steps=6, rng=1)
    assert run_network(scenario, data, "ci").fusions == 2 * 6 * 4
    every_other = run_network(scenario, data, "ci", period=2)
    assert every_other.fusions == 2 * 3 * 4 and every_other.exchanges == 3
    local = run_network(scenario, data, None)
    # a step without exchange is the local update of the fused state: step 1 equals local
    assert np.array_equal(every_other.x[:, 0], local.x[:, 0])
    lost = simulate_data(scenario, runs=2, steps=6, loss=1.0, rng=1)
    silent = run_network(scenario, lost, "ci")
    assert silent.fusions == 0 and np.array_equal(silent.x, run_network(scenario, lost, None).x)
    # two neighbours, one at a time: twice the fusions of two estimates
    assert run_network(scenario, data, "ci", sequential=True).fusions == 2 * 6 * 8
    delayed = run_network(scenario, data, "optimal", delay=True)
    assert np.all(np.isfinite(delayed.P))
    # with one neighbour, sequential and all-at-once fusion are the same
    pair = two_tracks()
    pair_data = simulate_data(pair, runs=2, steps=6, rng=0)
    assert np.allclose(run_network(pair, pair_data, "ci", sequential=True).x,
                       run_network(pair, pair_data, "ci").x, rtol=1e-12)


# --- the story: CI conservative everywhere, naive fusion overconfident with feedback --

@pytest.mark.parametrize("name", scenario_names())
def test_ci_is_conservative_in_every_scenario(name):
    scenario = get_scenario(name)
    rows = {row["method"]: row for row in compare(scenario, ["ci"], runs=10, steps=30,
                                                  rng=5, sequential=True)}
    assert rows["ci"]["anees"] < rows["ci"]["upper"]
    assert rows["ci"]["rmse"] < rows["local"]["rmse"]


@pytest.mark.parametrize("config", [dict(sequential=False), dict(loss=0.3),
                                    dict(delay=True), dict(period=3)])
def test_ci_is_conservative_with_every_exchange_option(config):
    rows = {row["method"]: row for row in compare(ring(5), ["ci"], runs=10, steps=30, rng=6,
                                                  **config)}
    assert rows["ci"]["anees"] < rows["ci"]["upper"]


def test_naive_fusion_is_overconfident_under_feedback_only():
    scenario = naveen_taylor()
    with_feedback = {row["method"]: row for row in compare(
        scenario, ["naive", "ci"], runs=10, steps=30, rng=7, sequential=True)}
    assert with_feedback["naive"]["verdict"] == "overconfident"
    assert with_feedback["naive"]["anees"] > 10 * with_feedback["naive"]["upper"]
    assert with_feedback["ci"]["verdict"] != "overconfident"
    without = {row["method"]: row for row in compare(
        scenario, ["naive"], runs=10, steps=30, rng=7, sequential=True, feedback=False)}
    assert without["naive"]["anees"] < with_feedback["naive"]["anees"] / 10


@pytest.mark.parametrize("config", [dict(sequential=True),
                                    dict(sequential=False, loss=0.3),
                                    dict(sequential=False, delay=True, period=2)])
def test_optimal_fusion_with_the_propagated_joint_is_consistent_under_feedback(config):
    """The joint covariance the simulation carries (common process noise, gains, losses,
    delayed messages) is the true one: the optimal fusion told it is consistent."""
    rows = {row["method"]: row for row in compare(naveen_taylor(), ["optimal"], runs=10,
                                                  steps=30, rng=8, **config)}
    assert rows["optimal"]["verdict"] == "consistent"
    assert rows["optimal"]["inside"] > 0.85
    assert rows["optimal"]["rmse"] < rows["local"]["rmse"]


# --- studies: every rule, failures reported, new rules appear ------------------------

def test_a_rule_that_cannot_run_is_reported_not_fatal():
    rows = {row["method"]: row for row in compare(naveen_taylor(), ["ei", "ci"], runs=2,
                                                  steps=4, rng=0, sequential=False)}
    assert "two estimates" in rows["ei"]["error"]
    assert "error" not in rows["ci"]


def test_a_rule_registered_later_appears_in_the_study(monkeypatch):
    def keep_own(xs, Ps):
        gains = np.zeros(Ps.shape)
        gains[..., 0, :, :] = np.eye(Ps.shape[-1])
        return FusionResult(xs[..., 0, :], Ps[..., 0, :, :], "keep-own", gains=gains)

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    registry.register_method("keep-own", keep_own, guarantee="exact")
    assert "keep-own" in available_methods()
    scenario = ring(3)
    rows = {row["method"]: row for row in summarize(
        NetworkStudy(scenario, steps=5, methods=("keep-own",))(0, 2), scenario)}
    assert rows["keep-own"]["rmse"] == pytest.approx(rows["local"]["rmse"])
    assert "keep-own" in NetworkStudy(scenario, steps=5).methods


def test_study_chunks_concatenate_and_repeat():
    from cifilter import montecarlo

    study = NetworkStudy(ring(4), ("ci",), steps=6)
    first = montecarlo.run(study, 6, chunk_size=3, seed=1)
    second = montecarlo.run(study, 6, chunk_size=3, seed=1)
    assert first["ci/nees"].shape == (6, 6, 4)
    assert np.array_equal(first["ci/nees"], second["ci/nees"])
    assert not np.array_equal(first["ci/nees"],
                              montecarlo.run(study, 6, chunk_size=3, seed=2)["ci/nees"])


@pytest.mark.slow
def test_every_rule_on_the_six_node_network_at_a_larger_size():
    """20 runs x 60 steps (the bayes rule makes it slow): CI and partial CI stay below
    the upper bound, naive and Bayesian fusion become overconfident, the optimal fusion
    with the propagated joint covariance is consistent and beats CI."""
    rows = {row["method"]: row for row in compare(naveen_taylor(), runs=20, steps=60,
                                                  rng=11, sequential=True)}
    for name in ("ci", "pci"):
        assert rows[name]["anees"] < rows[name]["upper"]
    for name in ("naive", "bayes"):
        assert rows[name]["verdict"] == "overconfident"
    assert rows["optimal"]["verdict"] == "consistent"
    assert rows["optimal"]["rmse"] < rows["ci"]["rmse"] < rows["local"]["rmse"]
