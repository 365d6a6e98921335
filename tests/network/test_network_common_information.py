"""The "common-information" network scenario: its true joint covariance satisfies Noack et
al.'s common-information model, and Inverse CI is a bound there.

The joint covariance of the two nodes is propagated here independently of
``cifilter.network.simulate`` (a recursion on covariances only: every rule compared here
has gains that depend on the covariances, not on the data), and the reported covariances
of that recursion are checked against the simulation's.
"""

import numpy as np
import pytest

from cifilter import fuse
from cifilter.network import compare, get_scenario, run_network, simulate_data
from cifilter.network.graph import common_information

STEPS = 25


def _update_maps(scenario, P):
    """Kalman update of each node's reported P: (I - K H) and K R K^T per node."""
    out = []
    for i, (H, R) in enumerate(zip(scenario.H, scenario.R)):
        S = H @ P[i] @ H.T + R
        K = np.linalg.solve(S, H @ P[i]).T
        A = np.eye(scenario.dim) - K @ H
        out.append((A, K @ R @ K.T))
    return out


def _joint_history(scenario, method, feedback, steps=STEPS):
    """Reported covariances and true joint error covariance of the two nodes' estimates
    just before each exchange (the inputs of the fusion), and the fused reported ones."""
    n = scenario.dim
    F, Q = scenario.F, scenario.Q
    P = [scenario.P0[0].copy(), scenario.P0[1].copy()]
    joint = np.zeros((2 * n, 2 * n))
    joint[:n, :n], joint[n:, n:] = P
    big_F = np.kron(np.eye(2), F)
    history = []
    for _ in range(steps):
        P = [F @ p @ F.T + Q for p in P]
        joint = big_F @ joint @ big_F.T + np.kron(np.ones((2, 2)), Q)
        maps = _update_maps(scenario, P)
        A = np.zeros((2 * n, 2 * n))
        noise = np.zeros((2 * n, 2 * n))
        for i, (Ai, KRK) in enumerate(maps):
            A[i * n:(i + 1) * n, i * n:(i + 1) * n] = Ai
            noise[i * n:(i + 1) * n, i * n:(i + 1) * n] = KRK
            P[i] = Ai @ P[i] @ Ai.T + KRK
        joint = A @ joint @ A.T + noise
        zero = np.zeros(n)
        fused = []
        M = np.zeros((2 * n, 2 * n))
        for i, j in ((0, 1), (1, 0)):
            result = fuse([(zero, P[i]), (zero, P[j])], method=method)
            fused.append(np.asarray(result.P))
            M[i * n:(i + 1) * n, i * n:(i + 1) * n] = result.gains[0]
            M[i * n:(i + 1) * n, j * n:(j + 1) * n] = result.gains[1]
        history.append((P[0].copy(), P[1].copy(), joint.copy(), fused))
        if feedback:
            P = fused
            joint = M @ joint @ M.T
            joint = 0.5 * (joint + joint.T)
    return history


def _model_violation(Pa, Pb, Sab):
    """How far ``C = Pa^-1 Sab Pb^-1`` is from ``C = C^T``, ``0 <= C <= Pa^-1, Pb^-1``
    (relative; 0 inside the model)."""
    C = np.linalg.solve(Pa, np.linalg.solve(Pb, Sab.T).T)
    Ya, Yb = np.linalg.inv(Pa), np.linalg.inv(Pb)
    scale = max(np.abs(Ya).max(), np.abs(Yb).max())
    asymmetry = np.abs(C - C.T).max() / scale
    Cs = 0.5 * (C + C.T)
    lowest = min(np.linalg.eigvalsh(Cs)[0], np.linalg.eigvalsh(Ya - Cs)[0],
                 np.linalg.eigvalsh(Yb - Cs)[0])
    return max(asymmetry, -lowest / scale)


def _dominated(bound, true):
    """Smallest eigenvalue of bound - true relative to the bound's size (>= 0: dominated)."""
    return np.linalg.eigvalsh(bound - true)[0] / np.abs(bound).max()


def test_registered_and_two_nodes_without_process_noise():
    scenario = get_scenario("common-information")
    assert scenario.nodes == 2 and scenario.edges == [(0, 1)]
    assert not scenario.Q.any()
    assert common_information(q=0.5).Q.any()


@pytest.mark.parametrize("q", [0.0, 0.5])
def test_joint_satisfies_the_common_information_model_with_feedback(q):
    # ICI's own trajectory: before every exchange Pab = Pa C Pb with C symmetric and
    # 0 <= C <= Pa^-1, Pb^-1, and the true joint is dominated by the model's joint with the
    # reported Pa, Pb (the fused estimate both nodes start from is shared information).
    history = _joint_history(common_information(q=q), "ici", feedback=True)
    n = 4
    for step, (Pa, Pb, joint, _) in enumerate(history):
        assert _model_violation(Pa, Pb, joint[:n, n:]) < 1e-9, step
        assert _dominated(Pa, joint[:n, :n]) > -1e-9
        assert _dominated(Pb, joint[n:, n:]) > -1e-9
    # the correlation is not zero: after the first exchange the common part is large
    Pa, Pb, joint, _ = history[-1]
    C = np.linalg.solve(Pa, np.linalg.solve(Pb, joint[:n, n:].T).T)
    assert np.linalg.eigvalsh(0.5 * (C + C.T))[-1] > 0.1 * np.linalg.eigvalsh(
        np.linalg.inv(Pa))[-1]


def test_without_feedback_common_process_noise_is_outside_the_model():
    # local filters with common process noise: C = Pa^-1 Pab Pb^-1 is not symmetric while
    # the filters converge (measured: it approaches the model at their steady state)
    history = _joint_history(common_information(q=0.5), "ici", feedback=False)
    violations = [_model_violation(Pa, Pb, joint[:4, 4:]) for Pa, Pb, joint, _ in history]
    assert max(violations) > 1e-3
    # without process noise the local estimates are independent (C = 0, inside)
    joint = _joint_history(common_information(), "ici", feedback=False)[-1][2]
    assert np.abs(joint[:4, 4:]).max() == 0.0


def test_recursion_matches_the_simulation():
    scenario = common_information()
    data = simulate_data(scenario, runs=2, steps=STEPS, rng=0)
    track = run_network(scenario, data, "ici")
    history = _joint_history(scenario, "ici", feedback=True)
    for k, (_, _, _, fused) in enumerate(history):
        np.testing.assert_allclose(track.P[0, k, 0], fused[0], rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(track.P[1, k, 1], fused[1], rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("method", ["ici", "ci", "split-ci"])
def test_bound_rules_dominate_the_true_fused_error(method):
    # exact check on the covariances (no Monte Carlo): every fused P bounds its true error
    n = 4
    history = _joint_history(common_information(), method, feedback=True)
    for Pa, Pb, joint, _ in history:
        zero = np.zeros(n)
        result = fuse([(zero, Pa), (zero, Pb)], method=method)
        G = np.concatenate(result.gains, axis=-1)
        true = G @ joint @ G.T
        assert _dominated(np.asarray(result.P), true) > -1e-9


def test_ici_is_the_tightest_bound_rule_not_given_the_truth():
    # deterministic: these rules' covariances do not depend on the data
    traces = {}
    for method in ("ici", "ci", "split-ci"):
        history = _joint_history(common_information(), method, feedback=True)
        traces[method] = np.array([np.trace(h[3][0]) for h in history])
    assert (traces["ici"] < traces["ci"]).all()
    assert (traces["ici"] < traces["split-ci"]).all()


def test_monte_carlo_verdicts():
    scenario = get_scenario("common-information")
    rows = {row["method"]: row for row in compare(
        scenario, ["ici", "ci", "naive", "cross"], runs=40, steps=30, rng=1)}
    assert rows["ici"]["anees"] < rows["ici"]["upper"]
    assert rows["ci"]["anees"] < rows["ci"]["upper"]
    assert rows["ici"]["mean_trace"] < rows["ci"]["mean_trace"]
    # data incest: the shared estimate is counted twice at every exchange
    assert rows["naive"]["verdict"] == "overconfident"
    assert rows["cross"]["verdict"] == "overconfident"


# ------------------------------------------------- the simulation's own joint covariance
def _excess_probe(monkeypatch, method):
    """Register ``"<method>-probe"``: the rule itself, but its truth hook receives the
    simulation's true joint covariance of the estimates it fuses, and every fusion records
    the largest eigenvalue of ``P^-1/2 E P^-1/2`` (``E``: the true covariance of the fused
    error ``sum_s K_s e_s``; above 1: overconfident in some direction)."""
    from cifilter import registry

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    joints, excess = [], []

    def hook(joint, rng, count=2):
        joints.append(joint)
        return {}

    def probed(xs, Ps):
        result = fuse([(xs[..., s, :], Ps[..., s, :, :]) for s in range(Ps.shape[-3])],
                      method=method)
        joint = joints.pop()
        G = np.concatenate(list(np.moveaxis(result.gains, -3, 0)), axis=-1)
        true = G @ joint @ np.swapaxes(G, -1, -2)
        L = np.linalg.cholesky(result.P)
        W = np.linalg.solve(L, np.swapaxes(np.linalg.solve(L, true), -1, -2))
        excess.append(np.linalg.eigvalsh(0.5 * (W + np.swapaxes(W, -1, -2)))[..., -1].max())
        return result

    registry.register_method(f"{method}-probe", probed, guarantee="bound", truth_options=hook,
                            replace=True)
    return f"{method}-probe", excess


def _largest_excess(monkeypatch, scenario, method, steps=30, **config):
    name, excess = _excess_probe(monkeypatch, method)
    data = simulate_data(scenario, runs=1, steps=steps, rng=0)
    run_network(scenario, data, name, sequential=True, **config)
    return max(excess)


@pytest.mark.parametrize("method", ["ici", "ci"])
def test_bound_holds_at_every_fusion_of_the_common_information_scenario(monkeypatch, method):
    # with the simulation's own joint covariance, in the worst direction of every fusion
    assert _largest_excess(monkeypatch, common_information(), method) <= 1 + 1e-9


def test_ci_bound_holds_on_the_six_node_network(monkeypatch):
    # CI needs no model: its bound holds at every fusion of the other scenario too
    assert _largest_excess(monkeypatch, get_scenario("naveen-taylor"), "ci", steps=15) \
        <= 1 + 1e-9


def test_the_probe_can_fail(monkeypatch):
    # naive fusion counts the shared estimate twice: overconfident in the worst direction
    assert _largest_excess(monkeypatch, common_information(), "naive", steps=10) > 2.0
