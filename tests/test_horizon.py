"""Horizon-aware CI (Ajgl et al. 2014): paper values, batch vs recursive, global optimality,
N estimates, the filters' ``fuse(horizon=)``, conventions and bad input."""

import copy

import filterpy.kalman as fk
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import (
    assert_psd,
    fused_error_covariance,
    ill_conditioned_sets,
    ill_conditioned_spd,
    joint_covariances,
    spd_matrices,
)
from worst_case import assert_bound_holds

from cifilter import (
    ExtendedKalmanFilter,
    KalmanFilter,
    ci_weights,
    covariance_intersection,
    partial_ci,
)
from cifilter._linalg import IllConditionedError
from cifilter.horizon import (
    horizon_study,
    horizon_weights,
    optimal_omega,
    propagate_bound,
    steady_state_covariance,
)

# The dynamical example, eqs. (29)-(30).
F_DYN = 0.95 * np.eye(2)
Q_DYN = np.array([[1.0, 0.95], [0.95, 1.0]])
H_A, R_A = np.array([[1.0, 0.0]]), 1.0
H_B, R_B = np.array([[0.0, 1.0]]), 3.0
FILTERS = {"A": (H_A, R_A), "B": (H_B, R_B)}
# The static example, eqs. (22)-(23).
RA_STATIC, RB_STATIC = np.diag([1.0, 2.0]), np.diag([2.0, 1.0])


def local_bounds_at_zero():
    """MMSE estimates at k = 0 from P_0 = 10 I and one local measurement (eqs. 29-30)."""
    P0_inv = np.eye(2) / 10.0
    PA = np.linalg.inv(P0_inv + H_A.T @ H_A / R_A)
    PB = np.linalg.inv(P0_inv + H_B.T @ H_B / R_B)
    return PA, PB


def ci_bound(PA, PB, omega):
    return np.linalg.inv(omega * np.linalg.inv(PA) + (1 - omega) * np.linalg.inv(PB))


def criterion_value(P, criterion):
    if isinstance(criterion, np.ndarray):
        return np.einsum("ij,...ji->...", criterion, P)
    if criterion == "det":
        return np.linalg.det(P)
    if criterion == "trace":
        return np.trace(P, axis1=-2, axis2=-1)
    return np.einsum("ij,...ji->...", criterion, P)


def random_system(seed, n=3, p=2):
    g = np.random.default_rng(seed)
    A = g.standard_normal((n, n))
    F = A / max(1.0, 0.8 * np.abs(np.linalg.eigvals(A)).max()) * g.choice([0.7, 1.0, 1.2])
    B = g.standard_normal((n, n))
    Q = g.choice([0.01, 1.0]) * B @ B.T + 1e-3 * np.eye(n)
    H = g.standard_normal((p, n))
    C = g.standard_normal((p, p))
    R = g.choice([0.1, 1.0, 10.0]) * C @ C.T + 0.1 * np.eye(p)
    Ps = []
    for _ in range(2):
        D = g.standard_normal((n, n)) * g.choice([0.3, 1.0, 3.0])
        Ps.append(D @ D.T + 0.05 * np.eye(n))
    return F, Q, H, R, Ps[0], Ps[1]


# ----------------------------------------------------------------- static example (IV.A)
def test_static_eq_24_without_future_data_omega_is_one_half():
    for omega in (0.0, 0.25, 0.5, 1.0):
        r = covariance_intersection([np.zeros(2)] * 2, [RA_STATIC, RB_STATIC], omega=omega)
        np.testing.assert_allclose(r.P, np.diag([2 / (1 + omega), 2 / (2 - omega)]), atol=1e-14)
        np.testing.assert_allclose(r.gains[0], np.diag([2 * omega / (1 + omega),
                                                        omega / (2 - omega)]), atol=1e-14)
    for criterion in ("det", "trace"):
        r = optimal_omega(RA_STATIC, RB_STATIC, np.eye(2), 0.0, np.eye(2), RA_STATIC, 0,
                          criterion)
        assert float(r.omega) == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("omega", [0.0, 0.2, 0.5, 0.9, 1.0])
def test_static_eqs_27_28_one_future_measurement_of_filter_A(omega):
    fused = covariance_intersection([np.zeros(2)] * 2, [RA_STATIC, RB_STATIC], omega=omega)
    P1 = propagate_bound(fused.P, np.eye(2), 0.0, np.eye(2), RA_STATIC, 1)
    np.testing.assert_allclose(P1, np.diag([2 / (3 + omega), 2 / (3 - omega)]), atol=1e-14)
    # eq. (27): the weights of Z_0^A, Z_0^B and Z_1^A in the batch estimator equal those of
    # the recursive estimator with the same omega (CI, then a Kalman update, eq. 31)
    K1 = fused.P @ np.linalg.inv(fused.P + RA_STATIC)
    weights = np.hstack([(np.eye(2) - K1) @ fused.gains[0], (np.eye(2) - K1) @ fused.gains[1],
                         K1])
    w = omega
    expected = np.array([
        [2 * w / (3 + w), 0, (1 - w) / (3 + w), 0, 2 / (3 + w), 0],
        [0, w / (3 - w), 0, 2 * (1 - w) / (3 - w), 0, 1 / (3 - w)],
    ])
    np.testing.assert_allclose(weights, expected, atol=1e-14)


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_static_future_measurement_gives_omega_0_in_A_and_1_in_B(criterion):
    args = (RA_STATIC, RB_STATIC, np.eye(2), 0.0, np.eye(2))
    in_A = optimal_omega(*args, RA_STATIC, 1, criterion)
    in_B = optimal_omega(*args, RB_STATIC, 1, criterion)
    # f'(0) = 0 exactly for both criteria (f is even in omega around 0), so rounding
    # may leave omega a few ulps inside the interval
    assert float(in_A.omega) == pytest.approx(0.0, abs=1e-12)
    assert float(in_B.omega) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(in_A.P, np.diag([2 / 3, 2 / 3]), atol=1e-12)
    assert float(in_A.info["omega_recursive"]) == pytest.approx(0.5, abs=1e-12)
    assert in_A.value < in_A.info["value_recursive"]


# ----------------------------------------------------------------- dynamical example (IV.B)
def test_local_bounds_at_zero_give_eq_34():
    PA, PB = local_bounds_at_zero()
    np.testing.assert_allclose(PA, np.diag([10 / 11, 10.0]), rtol=1e-14)
    np.testing.assert_allclose(PB, np.diag([10.0, 30 / 13]), rtol=1e-14)
    for omega in (0.1, 0.6):
        np.testing.assert_allclose(ci_bound(PA, PB, omega),
                                   np.diag([10 / (1 + 10 * omega), 30 / (13 - 10 * omega)]),
                                   rtol=1e-13)


def test_fusion_at_zero_det_0_6_and_trace_0_41():
    PA, PB = local_bounds_at_zero()
    for H, R in FILTERS.values():
        det = optimal_omega(PA, PB, F_DYN, Q_DYN, H, R, 0, "det")
        trace = optimal_omega(PA, PB, F_DYN, Q_DYN, H, R, 0, "trace")
        assert float(det.omega) == pytest.approx(0.6, abs=1e-12)
        # paper: "about 0.41"; hand derivation in tests/test_ci.py
        assert float(trace.omega) == pytest.approx((13 - np.sqrt(3)) / (10 * (1 + np.sqrt(3))),
                                                   abs=1e-12)


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_fig_3_omega_approaches_0_04_in_A_and_0_85_in_B(criterion):
    PA, PB = local_bounds_at_zero()
    limits = {}
    for name, (H, R) in FILTERS.items():
        s = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 40, criterion)
        limits[name] = float(s.omega_limit)
        assert s.omega[0] == pytest.approx(0.6 if criterion == "det" else 0.41244, abs=1e-5)
        assert s.omega[-1] == pytest.approx(s.omega_limit, abs=1e-6)
    # the paper: omega ~ 0.04 (A) and ~ 0.85 (B); computed 0.04177 and 0.85317
    assert limits["A"] == pytest.approx(0.04, abs=0.005)
    assert limits["B"] == pytest.approx(0.85, abs=0.005)


def test_fig_3_limits_are_the_same_for_det_and_trace():
    PA, PB = local_bounds_at_zero()
    for H, R in FILTERS.values():
        det = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 5, "det").omega_limit
        trace = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 5, "trace").omega_limit
        assert float(det) == pytest.approx(float(trace), abs=1e-8)


def test_fig_3_shape_det_in_A_falls_monotonically_and_B_rises():
    PA, PB = local_bounds_at_zero()
    a = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 30, "det").omega
    b = horizon_study(PA, PB, F_DYN, Q_DYN, H_B, R_B, 30, "det").omega
    assert np.all(np.diff(a) <= 1e-12) and a[-1] < 0.05
    assert np.all(np.diff(b) >= -1e-12) and b[-1] > 0.85


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_fig_4_batch_below_recursive_and_both_reach_the_steady_state(criterion):
    PA, PB = local_bounds_at_zero()
    for H, R in FILTERS.values():
        s = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 200, criterion)
        assert s.batch[0] == pytest.approx(s.recursive[0], rel=1e-13)
        assert np.all(s.batch <= s.recursive * (1 + 1e-12))
        assert np.any(s.batch[1:] < s.recursive[1:] * (1 - 1e-3))  # a real gain somewhere
        gap = s.recursive - s.batch
        assert gap[-1] < 1e-6 * s.steady_value  # the influence of omega vanishes
        assert s.batch[-1] == pytest.approx(s.steady_value, rel=1e-6)
        np.testing.assert_allclose(s.P_batch[-1], s.steady_P, atol=1e-6)


def test_eq_35_steady_state_matrices():
    PA = steady_state_covariance(F_DYN, Q_DYN, H_A, R_A)
    PB = steady_state_covariance(F_DYN, Q_DYN, H_B, R_B)
    np.testing.assert_allclose(PA, [[0.6076, 0.5772], [0.5772, 1.5483]], atol=5e-5)
    np.testing.assert_allclose(PB, [[2.1216, 1.1806], [1.1806, 1.2427]], atol=5e-5)
    for P, (H, R) in ((PA, FILTERS["A"]), (PB, FILTERS["B"])):
        np.testing.assert_allclose(propagate_bound(P, F_DYN, Q_DYN, H, R, 1), P, atol=1e-12)


def test_steady_state_fusion_omegas_and_fig_6_limits():
    PA = steady_state_covariance(F_DYN, Q_DYN, H_A, R_A)
    PB = steady_state_covariance(F_DYN, Q_DYN, H_B, R_B)
    det = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 0, "det")
    trace = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 0, "trace")
    assert float(det.omega) == pytest.approx(0.88, abs=0.005)  # computed 0.8841
    assert float(trace.omega) == pytest.approx(0.69, abs=0.006)  # computed 0.6949
    for criterion in ("det", "trace"):
        a = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 5, criterion).omega_limit
        b = horizon_study(PA, PB, F_DYN, Q_DYN, H_B, R_B, 5, criterion).omega_limit
        assert float(a) == pytest.approx(0.14, abs=0.005)  # computed 0.1370
        assert float(b) == pytest.approx(0.69, abs=0.005)  # computed 0.6927


# ----------------------------------------------------------------- Sec. III: batch vs recursive
def explicit_batch_bound(PA, PB, omega, F, Q, H, R, horizon):
    """Generalised least squares on [x_0, w_0, ..., w_{kappa-1}] with the bound (13).

    The best linear unbiased estimator of x_kappa from the two estimates (covariances
    P_A / omega, P_B / (1 - omega)), the process noises (prior covariance Q) and the
    measurements z_j = H x_j + v_j; returns its error covariance L J^-1 L^T.
    """
    n = F.shape[0]
    dim = n * (1 + horizon)
    rows, covariances = [], []

    def state(j):  # x_j = F^j x_0 + sum_{i<j} F^{j-1-i} w_i, as a row block over theta
        M = np.zeros((n, dim))
        M[:, :n] = np.linalg.matrix_power(F, j)
        for i in range(j):
            M[:, n * (1 + i):n * (2 + i)] = np.linalg.matrix_power(F, j - 1 - i)
        return M

    rows += [state(0), state(0)]
    covariances += [PA / omega, PB / (1 - omega)]
    for i in range(horizon):
        M = np.zeros((n, dim))
        M[:, n * (1 + i):n * (2 + i)] = np.eye(n)
        rows.append(M)
        covariances.append(Q)
    for j in range(1, horizon + 1):
        rows.append(H @ state(j))
        covariances.append(R)
    A = np.vstack(rows)
    sizes = [c.shape[0] for c in covariances]
    Sigma_inv = np.zeros((sum(sizes), sum(sizes)))
    offset = 0
    for c in covariances:
        Sigma_inv[offset:offset + c.shape[0], offset:offset + c.shape[0]] = np.linalg.inv(c)
        offset += c.shape[0]
    J = A.T @ Sigma_inv @ A
    L = state(horizon)
    return L @ np.linalg.solve(J, L.T)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("horizon", [1, 3])
def test_for_fixed_omega_batch_and_recursive_bounds_coincide(seed, horizon):
    F, Q, H, R, PA, PB = random_system(seed)
    for omega in (0.1, 0.5, 0.85):
        recursive = propagate_bound(ci_bound(PA, PB, omega), F, Q, H, R, horizon)
        batch = explicit_batch_bound(PA, PB, omega, F, Q, H, R, horizon)
        np.testing.assert_allclose(recursive, batch, rtol=1e-8, atol=1e-10)


@st.composite
def systems(draw, n=2):
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    F = g.standard_normal((n, n)) * draw(st.sampled_from([0.3, 1.0]))
    Q = draw(spd_matrices(n, min_eigenvalue=0.01, max_eigenvalue=5.0))
    H = g.standard_normal((draw(st.integers(1, n)), n))
    R = np.eye(H.shape[0]) * draw(st.sampled_from([0.1, 1.0, 10.0]))
    PA, PB = draw(spd_matrices(n)), draw(spd_matrices(n))
    return F, Q, H, R, PA, PB


@given(systems(), st.sampled_from(["det", "trace", "weighted"]))
def test_batch_optimum_never_above_recursive_at_any_horizon(system, criterion):
    F, Q, H, R, PA, PB = system
    crit = np.diag([2.0, 0.5]) if criterion == "weighted" else criterion
    s = horizon_study(PA, PB, F, Q, H, R, 6, crit, limit=False)
    assert np.all(s.batch <= s.recursive * (1 + 1e-9) + 1e-300)
    assert s.batch[0] == pytest.approx(s.recursive[0], rel=1e-9)
    # the recursive bound is the fixed-omega propagation (eqs. 31-33)
    fixed = ci_bound(PA, PB, float(s.omega_recursive))
    history = propagate_bound(fixed, F, Q, H, R, 6, history=True)
    np.testing.assert_allclose(s.P_recursive, history, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(s.recursive, criterion_value(history, crit), rtol=1e-7)


@given(systems(), st.sampled_from(["det", "trace", "weighted"]), st.integers(1, 5))
def test_optimal_omega_is_global_against_a_dense_grid(system, criterion, horizon):
    F, Q, H, R, PA, PB = system
    crit = np.diag([1.0, 3.0]) if criterion == "weighted" else criterion
    r = optimal_omega(PA, PB, F, Q, H, R, horizon, crit)
    grid = np.linspace(0.0, 1.0, 2001)
    values = criterion_value(propagate_bound(ci_bound(PA, PB, grid[:, None, None]), F, Q, H, R,
                                             horizon), crit)
    assert r.value <= values.min() * (1 + 1e-10)
    assert r.info["converged"]
    np.testing.assert_allclose(r.P, propagate_bound(ci_bound(PA, PB, float(r.omega)), F, Q, H,
                                                    R, horizon), rtol=1e-8, atol=1e-10)
    assert r.value == pytest.approx(criterion_value(r.P, crit), rel=1e-12)


@given(systems(), st.sampled_from(["det", "trace"]), st.integers(1, 6))
def test_criterion_is_convex_in_omega(system, criterion, horizon):
    """The issue expected non-convexity for kappa >= 1; the module docstring proves
    convexity. Second differences on a fine grid must be non-negative."""
    F, Q, H, R, PA, PB = system
    grid = np.linspace(0.0, 1.0, 401)
    P = propagate_bound(ci_bound(PA, PB, grid[:, None, None]), F, Q, H, R, horizon)
    values = np.log(np.linalg.det(P)) if criterion == "det" else np.trace(P, axis1=1, axis2=2)
    second = np.diff(values, 2)
    assert second.min() >= -1e-9 * np.abs(values).max()


@settings(max_examples=30)
@given(systems(), st.integers(1, 4), st.floats(0.0, 1.0), st.data())
def test_propagated_bound_holds_for_every_admissible_correlation(system, horizon, omega, data):
    F, Q, H, R, PA, PB = system
    joint = data.draw(joint_covariances([PA, PB]))
    fused = covariance_intersection([np.zeros(2)] * 2, [PA, PB], omega=omega)
    bound, actual = fused.P, fused_error_covariance(fused.gains, joint)
    for _ in range(horizon):  # the filter runs on the bound; the true error follows
        M = F @ bound @ F.T + Q
        K = M @ H.T @ np.linalg.inv(H @ M @ H.T + R)
        A = np.eye(2) - K @ H
        bound = A @ M @ A.T + K @ R @ K.T
        actual = A @ (F @ actual @ F.T + Q) @ A.T + K @ R @ K.T
    np.testing.assert_allclose(bound, propagate_bound(fused.P, F, Q, H, R, horizon), rtol=1e-7,
                               atol=1e-9)
    assert_psd(bound - actual, tol=1e-7, what="bound - actual MSE")


@pytest.mark.parametrize("seed", range(5))
def test_horizon_zero_is_ordinary_ci(seed):
    F, Q, H, R, PA, PB = random_system(seed)
    for criterion in ("det", "trace"):
        r = optimal_omega(PA, PB, F, Q, H, R, 0, criterion)
        omega, _ = ci_weights([PA, PB], criterion)
        assert float(r.omega) == pytest.approx(omega[0], abs=1e-10)
        np.testing.assert_allclose(r.P, ci_bound(PA, PB, omega[0]), rtol=1e-9)


def test_omega_is_well_defined_at_horizons_beyond_rounding():
    """The omega-dependent part decays like rho^(2 kappa); carried on a log scale, the
    optimum at kappa = 1000 equals the limit although the criterion values agree to
    machine precision there."""
    PA, PB = local_bounds_at_zero()
    far = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 1000, "det")
    study = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 5, "det")
    assert float(far.omega) == pytest.approx(float(study.omega_limit), abs=1e-10)
    assert far.info["value_recursive"] == pytest.approx(far.value, rel=1e-14)


# ----------------------------------------------------------------- N estimates
@pytest.mark.parametrize("criterion", ["det", "trace", "weighted"])
def test_three_estimates_against_a_simplex_grid(criterion):
    F, Q, H, R, PA, PB = random_system(11, n=2, p=1)
    PC = np.array([[1.0, 0.3], [0.3, 0.5]])
    crit = np.diag([1.0, 4.0]) if criterion == "weighted" else criterion
    r = horizon_weights([PA, PB, PC], F, Q, H, R, 3, crit)
    assert r.omega.shape == (3,) and r.omega.sum() == pytest.approx(1.0)
    assert r.info["converged"]
    steps = 80
    grid = np.array([(i, j, steps - i - j) for i in range(steps + 1)
                     for j in range(steps + 1 - i)]) / steps
    Ps = np.stack([PA, PB, PC])
    info = np.einsum("gk,kij->gij", grid, np.linalg.inv(Ps))
    values = criterion_value(propagate_bound(np.linalg.inv(info), F, Q, H, R, 3), crit)
    assert r.value <= values.min() * (1 + 1e-9)
    fused = np.linalg.inv(np.einsum("k,kij->ij", r.omega, np.linalg.inv(Ps)))
    np.testing.assert_allclose(r.P, propagate_bound(fused, F, Q, H, R, 3), rtol=1e-8)


def test_three_estimates_det_converges_where_the_bound_has_det_one():
    """log det P_kappa near 0 must not hide the rounding level from the solver's stopping
    test (the problems used to run to the iteration limit, flagged unconverged)."""
    for seed in (2, 7, 13):
        F, Q, H, R, PA, PB = random_system(seed)
        PC = np.array([[1.0, 0.3, 0.0], [0.3, 0.5, 0.1], [0.0, 0.1, 2.0]])
        Ps = np.stack([PA, PB, PC])
        for horizon in (1, 3, 10):
            scale = np.linalg.det(horizon_weights(Ps, F, Q, H, R, horizon, "det").P) ** (1 / 3)
            r = horizon_weights(Ps / scale, F, Q / scale, H, R / scale, horizon, "det")
            assert np.linalg.det(r.P) == pytest.approx(1.0, abs=1e-6)
            assert r.info["converged"] and r.info["iterations"] < 50


def test_n_weights_with_two_estimates_equal_optimal_omega():
    F, Q, H, R, PA, PB = random_system(4)
    for criterion in ("det", "trace"):
        pair = optimal_omega(PA, PB, F, Q, H, R, 2, criterion)
        general = horizon_weights([PA, PB], F, Q, H, R, 2, criterion)
        assert general.omega[0] == pytest.approx(float(pair.omega), abs=1e-12)


# ----------------------------------------------------------------- propagate_bound
def test_propagate_bound_matches_filterpy():
    F, Q, H, R, P, _ = random_system(2)
    kf = fk.KalmanFilter(dim_x=3, dim_z=2)
    kf.F, kf.Q, kf.H, kf.R, kf.P = F, Q, H, R, P.copy()
    history = propagate_bound(P, F, Q, H, R, 4, history=True)
    for step in range(4):
        kf.predict()
        kf.update(np.zeros((2, 1)))
        np.testing.assert_allclose(history[step + 1], kf.P, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(history[0], P)


def test_propagate_bound_per_step_models_and_prediction_only():
    F, Q, H, R, P, _ = random_system(5)
    G = np.array([[1.0], [0.5], [0.0]])
    only = propagate_bound(P, F, 2.0, None, None, 2, G=G)
    noise = 2.0 * G @ G.T
    np.testing.assert_allclose(only, F @ (F @ P @ F.T + noise) @ F.T + noise, rtol=1e-12)
    H2 = np.array([[1.0, 0.0, 0.0]])
    steps = propagate_bound(P, F, Q, [H, None, H2], [R, None, 0.5], 3)
    expected = propagate_bound(P, F, Q, H, R, 1)
    expected = propagate_bound(expected, F, Q, None, None, 1)
    expected = propagate_bound(expected, F, Q, H2, 0.5 * np.eye(1), 1)
    np.testing.assert_allclose(steps, expected, rtol=1e-12)
    # a nested list is one matrix, not a sequence of steps
    np.testing.assert_allclose(propagate_bound(P, F, Q, [[1.0, 0.0, 0.0]], 0.5, 2),
                               propagate_bound(P, F, Q, H2, [[0.5]], 2), rtol=1e-13)


def test_batched_equals_per_item():
    systems_ = [random_system(seed) for seed in range(4)]
    F, Q, H, R, PA, PB = (np.stack(parts) for parts in zip(*systems_))
    for criterion in ("det", "trace"):
        batched = optimal_omega(PA, PB, F, Q, H, R, 3, criterion)
        study = horizon_study(PA, PB, F, Q, H, R, 3, criterion)
        for i, system in enumerate(systems_):
            single = optimal_omega(system[4], system[5], *system[:4], 3, criterion)
            assert batched.omega[i] == pytest.approx(float(single.omega), abs=1e-12)
            np.testing.assert_allclose(batched.P[i], single.P, rtol=1e-12)
            one = horizon_study(system[4], system[5], *system[:4], 3, criterion)
            np.testing.assert_allclose(study.omega[i], one.omega, atol=1e-12)
            np.testing.assert_allclose(study.recursive[i], one.recursive, rtol=1e-12)
    # one model, a batch of estimate pairs
    pairs = optimal_omega(PA, PB[0], F[0], Q[0], H[0], R[0], 2)
    assert pairs.omega.shape == (4,)
    assert pairs.omega[0] == pytest.approx(float(optimal_omega(PA[0], PB[0], F[0], Q[0], H[0],
                                                               R[0], 2).omega), abs=1e-12)


def test_inputs_are_not_mutated():
    F, Q, H, R, PA, PB = random_system(8)
    arrays = [F, Q, H, R, PA, PB]
    copies = [a.copy() for a in arrays]
    optimal_omega(PA, PB, F, Q, H, R, 3, "det")
    horizon_study(PA, PB, F, Q, H, R, 3)
    propagate_bound(PA, F, Q, H, R, 3)
    steady_state_covariance(F / 2, Q, H, R)
    for a, b in zip(arrays, copies):
        np.testing.assert_array_equal(a, b)


def test_steady_state_without_measurements_is_the_lyapunov_solution():
    P = steady_state_covariance(F_DYN, Q_DYN, None, None)
    np.testing.assert_allclose(F_DYN @ P @ F_DYN.T + Q_DYN, P, rtol=1e-10)
    with pytest.raises(ValueError, match="stable F"):
        steady_state_covariance(np.eye(2), Q_DYN, None, None)
    batched = steady_state_covariance(np.stack([F_DYN, 0.5 * np.eye(2)]), Q_DYN, H_A, R_A)
    np.testing.assert_allclose(batched[0], steady_state_covariance(F_DYN, Q_DYN, H_A, R_A))


def test_study_result_fields_and_plot():
    import matplotlib.pyplot as plt

    PA, PB = local_bounds_at_zero()
    s = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, [0, 2, 7], "det")
    assert s.horizons.tolist() == [0, 2, 7]
    assert s.omega.shape == s.batch.shape == s.recursive.shape == (3,)
    assert s.P_batch.shape == (3, 2, 2)
    fig = s.plot(label="A")
    assert len(fig.axes) == 2
    plt.close(fig)
    batched = horizon_study(np.stack([PA, PB]), PB, F_DYN, Q_DYN, H_A, R_A, 2)
    assert batched.omega.shape == (2, 3)
    with pytest.raises(ValueError, match="batched"):
        batched.plot()


@pytest.mark.parametrize("call, error, match", [
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), np.eye(2), np.eye(2), -1),
     ValueError, "horizon must be >= 0"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), np.eye(2), np.eye(2), 1.5),
     TypeError, "horizon must be an integer"),
    (lambda: propagate_bound(np.eye(2), np.eye(3), np.eye(2), None, None, 1),
     ValueError, "F must have shape"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), -np.eye(2), None, None, 1),
     ValueError, "Q must be positive semidefinite"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), np.eye(2), None, 1),
     ValueError, "R is None but H is not"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), np.ones((1, 3)), 1.0, 1),
     ValueError, "H must have shape"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), np.eye(2), -np.eye(2), 1),
     ValueError, "R is not positive definite"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), [np.eye(2)], [np.eye(2)], 2),
     ValueError, "one per step"),
    (lambda: propagate_bound(np.eye(2), np.eye(2), np.eye(2), [np.eye(2)], np.eye(2), 1),
     ValueError, "R must be a sequence"),
    (lambda: propagate_bound(np.diag([1.0, -1.0]), np.eye(2), 1.0, None, None, 1),
     ValueError, "P is not positive definite"),
    (lambda: propagate_bound("P", np.eye(2), 1.0, None, None, 1), TypeError, "P must be"),
    (lambda: optimal_omega(np.eye(2), np.eye(3), np.eye(2), 1.0, None, None, 1),
     ValueError, "PB is 3x3"),
    (lambda: optimal_omega(np.eye(2), np.eye(2), np.eye(2), 1.0, None, None, 1, "max"),
     ValueError, "criterion must be"),
    (lambda: optimal_omega(np.eye(2), np.eye(2), np.full((2, 2), np.nan), 1.0, None, None, 1),
     ValueError, "F contains non-finite"),
    (lambda: horizon_study(np.eye(2), np.eye(2), np.eye(2), 1.0, None, None, [1, -2]),
     ValueError, "horizons must be >= 0"),
    (lambda: horizon_study(np.eye(2), np.eye(2), np.eye(2), 1.0, None, None, []),
     ValueError, "horizons must be"),
    (lambda: horizon_weights([np.eye(2)], np.eye(2), 1.0, None, None, 1),
     ValueError, "at least 2 estimates"),
    (lambda: steady_state_covariance(np.eye(2), np.eye(2), [np.eye(2)], [np.eye(2)]),
     ValueError, "not a sequence"),
])
def test_bad_input_is_rejected(call, error, match):
    with pytest.raises(error, match=match):
        call()


# ----------------------------------------------------------------- filters: fuse(horizon=)
def dynamic_filter(name):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.Q = F_DYN.copy(), Q_DYN.copy()
    kf.H, kf.R = (H_A.copy(), np.eye(1) * R_A) if name == "A" else (H_B.copy(), np.eye(1) * R_B)
    return kf


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_filter_fuse_with_horizon_uses_its_own_model(criterion):
    PA, PB = local_bounds_at_zero()
    kf = dynamic_filter("A")
    kf.x, kf.P = np.array([[1.0], [2.0]]), PA.copy()
    other = (np.array([0.0, 1.0]), PB.copy())
    other_copy = copy.deepcopy(other)
    result = kf.fuse(other, horizon=10, criterion=criterion)
    expected = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 10, criterion)
    assert result.omega[0] == pytest.approx(float(expected.omega), abs=1e-12)
    assert kf.last_fusion is result
    chosen = result.info["horizon"]
    assert result.info["rule"] == "horizon" and chosen["steps"] == 10
    assert chosen["criterion"] == criterion
    assert chosen["value"] == pytest.approx(float(expected.value), rel=1e-12)
    assert chosen["value_recursive"] >= chosen["value"]
    assert result.info["converged"] == chosen["converged"] and result.info["gap"] == chosen["gap"]
    plain = covariance_intersection([np.array([1.0, 2.0]), other[0]], [PA, PB],
                                    omega=float(expected.omega))
    np.testing.assert_allclose(kf.x[:, 0], plain.x, rtol=1e-12)
    np.testing.assert_allclose(kf.P, plain.P, rtol=1e-12)
    np.testing.assert_array_equal(kf.P_post, kf.P)
    np.testing.assert_array_equal(other[0], other_copy[0])
    np.testing.assert_array_equal(other[1], other_copy[1])


def test_filter_fuse_horizon_zero_equals_plain_ci_and_model_overrides():
    PA, PB = local_bounds_at_zero()
    kf, plain = dynamic_filter("A"), dynamic_filter("A")
    kf.P, plain.P = PA.copy(), PA.copy()
    r0 = kf.fuse((np.zeros(2), PB), horizon=0, criterion="det")
    rp = plain.fuse((np.zeros(2), PB), criterion="det")
    np.testing.assert_array_equal(r0.omega, rp.omega)
    # filter A fusing as if it were filter B (the model) picks B's omega
    kf.P = PA.copy()
    model = dict(F=F_DYN, Q=Q_DYN, H=H_B, R=R_B)
    r = kf.fuse((np.zeros(2), PB), horizon=30, model=model, criterion="det")
    assert r.omega[0] == pytest.approx(0.853, abs=1e-3)
    kf.P = PA.copy()
    r_obj = kf.fuse((np.zeros(2), PB), horizon=30, model=dynamic_filter("B"), criterion="det")
    assert r_obj.omega[0] == pytest.approx(r.omega[0], abs=1e-12)
    kf.P = PA.copy()
    with pytest.warns(DeprecationWarning, match="model="):
        r_old = kf.fuse((np.zeros(2), PB), horizon=30, future=model, criterion="det")
    np.testing.assert_array_equal(r_old.omega, r.omega)


def test_filter_fuse_with_horizon_and_several_estimates():
    kf = dynamic_filter("A")
    kf.P = np.diag([1.0, 2.0])
    others = [(np.zeros(2), np.diag([2.0, 1.0])), (np.ones(2), np.diag([1.5, 1.5]))]
    r = kf.fuse(others, horizon=4)
    expected = horizon_weights([np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.diag([1.5, 1.5])],
                               F_DYN, Q_DYN, H_A, R_A, 4)
    np.testing.assert_allclose(r.omega, expected.omega, atol=1e-10)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(horizon=2, method="naive"), ValueError, "does not support horizon="),
    (dict(horizon=2, omega=0.3), ValueError, "give one"),
    (dict(model=dict(F=F_DYN, Q=Q_DYN)), ValueError, "give horizon="),
    (dict(horizon=2, model=dict(F=F_DYN)), ValueError, "at least F and Q"),
    (dict(horizon=2, model=dict(F=F_DYN, Q=Q_DYN, X=1)), ValueError, "unknown entries"),
    (dict(horizon=-1), ValueError, "horizon must be >= 0"),
    (dict(horizon=2, model=dict(F=np.eye(3), Q=Q_DYN)), ValueError, "F must have shape"),
    (dict(horizon=2, criterion="max"), ValueError, "criterion"),
    # partial-correlation CI (tests/test_horizon_pci.py)
    (dict(method="pci", horizon=2), ValueError, "needs a correlation coefficient bound"),
    (dict(method="pci", rho=0.5, delta=[0.5, 0.5], horizon=2), ValueError, "give one"),
    (dict(method="pci", rho=0.5, horizon=2, tol=1e-3), TypeError, "accepts the option"),
    (dict(method="pci", rho=1.5, horizon=2), ValueError, "rho must lie"),
    (dict(method="pci", rho=[0.1, 0.2, 0.3], horizon=2), ValueError, "rho must be a scalar"),
    (dict(method="pci", rho=0.5, horizon=2, criterion="max"), ValueError, "criterion"),
    (dict(method="pci", rho=0.5, horizon=-1), ValueError, "horizon must be >= 0"),
    (dict(method="pci", rho=0.5, model=dict(F=F_DYN, Q=Q_DYN)), ValueError, "give horizon="),
    (dict(method="naive", horizon=2), ValueError, "'ci', 'pci'"),
])
def test_filter_fuse_with_horizon_is_atomic_on_bad_input(kwargs, error, match):
    kf = dynamic_filter("A")
    kf.x, kf.P = np.array([[1.0], [2.0]]), np.diag([1.0, 2.0])
    before = copy.deepcopy(kf.__dict__)
    with pytest.raises(error, match=match):
        kf.fuse((np.zeros(2), np.eye(2)), **kwargs)
    np.testing.assert_array_equal(kf.x, before["x"])
    np.testing.assert_array_equal(kf.P, before["P"])
    assert kf.last_fusion is None


def test_extended_filter_needs_a_model():
    ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    ekf.P = np.diag([1.0, 2.0])
    with pytest.raises(ValueError, match="no matrix H"):
        ekf.fuse((np.zeros(2), np.eye(2)), horizon=3)
    assert ekf.last_fusion is None
    r = ekf.fuse((np.zeros(2), np.eye(2)), horizon=3,
                 model=dict(F=ekf.F, Q=ekf.Q, H=np.array([[1.0, 0.0]]), R=ekf.R))
    assert r.info["horizon"]["steps"] == 3 and ekf.last_fusion is r


# ----------------------------------------------------------------- reproduction command
def test_reproduce_ajgl_prints_the_papers_numbers_and_writes_figs_3_to_8(tmp_path, capsys):
    from cifilter.cli import main

    assert main(["reproduce", "ajgl", "--horizons", "15", "--plot", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for text in ("0.6000", "0.4124", "0.0418", "0.8532", "0.8841", "0.6949", "0.1370",
                 "0.6927", "[0.6076 0.5772; 0.5772 1.5483]", "[2.1216 1.1806; 1.1806 1.2427]"):
        assert text in out
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"fig{i}.png" for i in range(3, 9)]


# ----------------------------------------------------------------- overflow and conditioning
# Issue 9, item 4: an unstable model without measurements; the bound grows like 1.2^(2 k).
F_UNSTABLE = np.array([[1.2, 1.0], [0.0, 1.1]])


def _log_criterion(P, criterion):
    """log of the criterion (log det from slogdet, so that det may exceed float64)."""
    if criterion == "det":
        sign, logdet = np.linalg.slogdet(P)
        assert np.all(sign > 0)
        return logdet
    return np.log(np.trace(P, axis1=-2, axis2=-1))


def _reference_omega(PA, PB, F, Q, H, R, horizon, criterion):
    """High-accuracy reference: bounded Brent on the log criterion of propagate_bound."""
    from scipy.optimize import minimize_scalar

    def f(omega):
        P = propagate_bound(ci_bound(PA, PB, omega), F, Q, H, R, horizon)
        return _log_criterion(P, criterion)

    result = minimize_scalar(f, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-12})
    return result.x, f


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_issue_9_horizon_5000_overflow_raises_instead_of_nan(criterion):
    """Was: NaN value and P with converged=True (trace); 'not positive definite (smallest
    eigenvalue nan)' (det). The bound at horizon 5000 is about 1e795: not representable."""
    PA, PB = local_bounds_at_zero()
    with pytest.raises(ValueError, match="horizon 5000"):
        optimal_omega(PA, PB, F_UNSTABLE, np.eye(2), None, None, 5000, criterion)


def test_issue_9_propagate_bound_at_horizon_3000_raises_instead_of_nan():
    PA, _ = local_bounds_at_zero()
    with pytest.raises(ValueError, match=r"horizon 3000 overflows float64.*1e478"):
        propagate_bound(PA, F_UNSTABLE, np.eye(2), None, None, 3000)
    with pytest.raises(ValueError, match="horizon 1928 of 3000"):  # the first that overflows
        propagate_bound(PA, F_UNSTABLE, np.eye(2), None, None, 3000, history=True)
    with pytest.raises(ValueError, match="horizon 3000"):
        horizon_study(PA, PA, F_UNSTABLE, np.eye(2), None, None, [0, 3000], limit=False)


@pytest.mark.parametrize("horizon", [100, 1000, 1900])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_growing_but_representable_bound_keeps_the_right_omega(horizon, criterion):
    """Where the bound is still representable the optimum is computed (not NaN) and matches
    a bounded-Brent reference; det P beyond float64 (horizon 1900) raises, quoting omega."""
    PA, PB = local_bounds_at_zero()
    args = (PA, PB, F_UNSTABLE, np.eye(2), None, None, horizon)
    reference, f = _reference_omega(*args, criterion)
    if criterion == "det" and horizon == 1900:
        with pytest.raises(ValueError, match=r"det of the propagated bound at horizon 1900, "
                                             r"where the optimal weights \[0.101472"):
            optimal_omega(*args, criterion)
        return
    r = optimal_omega(*args, criterion)
    assert r.info["converged"]
    assert np.isfinite(r.P).all() and np.isfinite(r.value)
    np.linalg.cholesky(r.P)
    # the reference's own rounding (flat log criterion) limits it to about 1e-7 in omega
    assert float(r.omega) == pytest.approx(reference, abs=1e-6)
    assert f(float(r.omega)) <= f(reference) + 1e-13 * abs(f(reference))
    np.testing.assert_allclose(r.P, propagate_bound(ci_bound(PA, PB, float(r.omega)),
                                                    F_UNSTABLE, np.eye(2), None, None,
                                                    horizon), rtol=1e-9)
    # the limit of omega for large horizons (dominant mode of F)
    limit = horizon_study(PA, PB, F_UNSTABLE, np.eye(2), None, None, [0], criterion).omega_limit
    if horizon >= 1000:
        assert float(r.omega) == pytest.approx(float(limit), abs=1e-9)


def test_study_of_an_unstable_model_has_a_finite_limit_and_values():
    PA, PB = local_bounds_at_zero()
    s = horizon_study(PA, PB, F_UNSTABLE, np.eye(2), None, None, [0, 10, 300, 1000], "det")
    assert np.isfinite(s.batch).all() and np.isfinite(s.recursive).all()
    assert np.all(s.batch <= s.recursive * (1 + 1e-12))
    assert float(s.omega_limit) == pytest.approx(0.1014724336, abs=1e-9)
    assert s.steady_P is None


def test_gamma_overflow_with_noise_free_unstable_observed_mode_is_named():
    """Q = 0 and an unstable observed F: the filter started at P = 0 never gains, so the
    information Gamma about the initial state grows like 2^(2 k) and overflows."""
    F = np.diag([2.0, 0.9])
    with pytest.raises(ValueError, match="Gamma overflowed at step"):
        optimal_omega(np.eye(2), 2 * np.eye(2), F, np.zeros((2, 2)), np.eye(2), np.eye(2), 1200)
    r = optimal_omega(np.eye(2), 2 * np.eye(2), F, np.zeros((2, 2)), np.eye(2), np.eye(2), 300)
    assert np.isfinite(r.P).all() and r.info["converged"]


@st.composite
def models(draw, n, measured=None):
    """(F, Q, H, R) with a spectral radius from 0.3 to 1.25 (stable and unstable)."""
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    A = g.standard_normal((n, n))
    radius = draw(st.sampled_from([0.3, 0.9, 1.0, 1.05, 1.25]))
    F = A * radius / np.abs(np.linalg.eigvals(A)).max()
    Q = draw(ill_conditioned_spd(n, max_condition=1e6, scales=(1e-6, 1e2)))
    if measured is None:
        measured = draw(st.booleans())
    if not measured:
        return F, Q, None, None
    H = g.standard_normal((draw(st.integers(1, n)), n))
    R = draw(ill_conditioned_spd(H.shape[0], max_condition=1e6, scales=(1e-6, 1e2)))
    return F, Q, H, R


def fused_bound_tolerance(Ps):
    """Rounding of a CI bound formed in information form: the default ``64 n N eps`` of
    :func:`worst_case.worst_violation` plus ``eps * max cond(P_i)`` (the information-form
    inverse of ``cifilter.covariance_intersection``'s fixed-omega path loses that much,
    relative to ``||P||``, for nearly equal inputs of condition number 1e11)."""
    Ps = np.asarray(Ps)
    count, n = Ps.shape[-3], Ps.shape[-1]
    return (64.0 * n * count + np.linalg.cond(Ps).max()) * np.finfo(float).eps


def assert_propagation_agrees(P, fused_P, Ps, F, Q, H, R, horizon):
    """``P`` (the horizon solver's bound) equals ``propagate_bound(fused_P, ...)``.

    The fused P's own rounding, and the propagation's: two routes to a bound whose condition
    number is cond(P) agree to about cond(P) eps relative to its norm (P = 1e12 I against
    R = 1 gives cond ~ 1e11 from well-conditioned inputs). The reference route (Joseph
    updates of F P F^T + Q) also loses eps ||prior|| absolutely: a prior of norm 3e9 (an
    estimate ignored along a measured direction) updated to a bound of norm 20 is accurate
    to only 1e-7 relative, while the solver's information form of the superposition
    formula stays exact (checked at 60 digits).
    """
    history = [fused_P]
    for _ in range(horizon):  # the reference, step by step: it has a contract of its own
        step_prior = F @ history[-1] @ F.T + Q
        try:
            history.append(propagate_bound(history[-1], F, Q, H, R, 1))
        except ValueError:  # IllConditionedError included
            # No reference: a prior beyond the conditioning contract, or one whose update
            # cancels more than float64 holds (its rounding eps ||prior|| is not small
            # against the bound the solver found; propagate_bound's covariance form)
            assert (np.linalg.cond(step_prior) > 1e12
                    or 64 * np.finfo(float).eps * np.abs(step_prior).max()
                    > 1e-3 * np.abs(P).max())
            return
    history = np.array(history)
    prior = np.abs(F @ history[:-1] @ F.T + Q).max() if horizon else 0.0
    eps = np.finfo(float).eps
    tol = max(1e-7, fused_bound_tolerance(Ps), 64 * eps * np.linalg.cond(P),
              64 * eps * prior / np.abs(P).max())
    np.testing.assert_allclose(P, history[-1], rtol=tol, atol=tol * np.abs(P).max())


def horizon_call_or_ill_conditioned(call, Ps, F, Q, H, R, horizon, rho=1.0):
    """``call()``, or None if it raises IllConditionedError naming the horizon for a problem
    whose propagated bound, at a vertex or the centre of the simplex, is beyond the
    contract's condition number 1e12 (the optimiser evaluates the criterion there)."""
    try:
        return call()
    except IllConditionedError as exc:
        assert f"horizon {horizon}" in str(exc)
        count, n = len(Ps), Ps[0].shape[-1]
        conditions = []
        for delta in np.vstack([np.eye(count), np.full(count, 1.0 / count)]):
            fused = partial_ci(np.zeros((count, n)), Ps, rho, delta=delta)
            try:
                conditions.append(np.linalg.cond(propagate_bound(fused.P, F, Q, H, R, horizon)))
            except IllConditionedError:
                conditions.append(np.inf)
        assert max(conditions) > 1e12, str(exc)
        return None


@settings(max_examples=40)
@given(st.integers(2, 5), st.integers(2, 3), st.sampled_from(["trace", "det"]),
       st.sampled_from([0, 1, 5, 40]), st.data())
def test_horizon_weights_of_ill_conditioned_estimates_are_on_the_simplex_and_conservative(
        count, n, criterion, horizon, data):
    Ps = data.draw(ill_conditioned_sets(count, n))
    F, Q, H, R = data.draw(models(n))
    r = horizon_call_or_ill_conditioned(
        lambda: horizon_weights(Ps, F, Q, H, R, horizon, criterion), Ps, F, Q, H, R, horizon)
    if r is None:
        return
    w = r.omega
    assert np.isfinite(w).all() and np.all(w >= 0.0)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.isfinite(r.value) and r.value > 0
    assert np.isfinite(r.P).all()
    np.testing.assert_array_equal(r.P, r.P.T)
    np.linalg.cholesky(r.P)
    fused = covariance_intersection([np.zeros(n)] * count, Ps, omega=w)
    assert_bound_holds(fused.P, fused.gains, np.asarray(Ps), tol=fused_bound_tolerance(Ps))
    assert_propagation_agrees(r.P, fused.P, Ps, F, Q, H, R, horizon)


@settings(max_examples=15)
@given(st.integers(2, 3), st.sampled_from([0, 50, 500, 3000, 10_000]), st.data())
def test_propagated_bound_is_finite_and_positive_definite_or_a_clear_error(n, horizon, data):
    P = data.draw(ill_conditioned_spd(n))
    F, Q, H, R = data.draw(models(n))
    try:
        out = propagate_bound(P, F, Q, H, R, horizon)
    except ValueError as exc:
        assert f"horizon {horizon}" in str(exc)
        assert np.abs(np.linalg.eigvals(F)).max() > 1.0  # only an unstable model overflows
        return
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(out, out.T)
    np.linalg.cholesky(out)


@pytest.mark.parametrize("scale", [1e-12, 1e12])
@pytest.mark.parametrize("radius, measured", [(0.9, False), (1.2, True), (1.2, False)])
def test_horizon_10_000_with_ill_conditioned_start(scale, radius, measured):
    """Horizon 1e4 from a bound of condition number 1e12: finite and positive definite for
    stable (or stabilised) models; a ValueError naming the horizon for an unstable one."""
    c, s_ = np.cos(0.3), np.sin(0.3)
    F = radius * np.array([[c, -s_], [s_, c]])
    U = np.array([[c, s_], [-s_, c]])
    P = scale * U @ np.diag([1.0, 1e-12]) @ U.T
    H, R = (np.array([[1.0, 0.0]]), 0.5) if measured else (None, None)
    args = (P, F, 1e-3 * np.eye(2), H, R, 10_000)
    if radius > 1.0 and not measured:
        with pytest.raises(ValueError, match="horizon 10000 overflows"):
            propagate_bound(*args)
        with pytest.raises(ValueError, match="horizon 10000"):
            optimal_omega(P, 2 * P, *args[1:], "trace")
        return
    out = propagate_bound(*args)
    assert np.isfinite(out).all()
    np.linalg.cholesky(out)
    r = optimal_omega(P, 2 * P + scale * 1e-3 * np.eye(2), *args[1:], "det")
    assert r.info["converged"] and np.isfinite(r.value) and np.isfinite(r.P).all()
    np.linalg.cholesky(r.P)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_optimal_omega_of_ill_conditioned_pairs_matches_bounded_brent(seed, criterion):
    g = np.random.default_rng(seed)
    n = 3
    PA, PB = (q @ np.diag(10.0 ** g.uniform(-6, 6, n)) @ q.T
              for q in (np.linalg.qr(g.standard_normal((n, n)))[0] for _ in range(2)))
    PA, PB = (0.5 * (P + P.T) for P in (PA, PB))
    F = g.standard_normal((n, n))
    F = F * [0.9, 1.1][seed % 2] / np.abs(np.linalg.eigvals(F)).max()
    Q, H, R = 1e-2 * np.eye(n), g.standard_normal((1, n)), np.eye(1)
    for horizon in (0, 3, 30):
        r = optimal_omega(PA, PB, F, Q, H, R, horizon, criterion)
        reference, f = _reference_omega(PA, PB, F, Q, H, R, horizon, criterion)
        assert r.info["converged"]
        # The optimum's criterion is not above the reference's beyond the rounding noise of
        # the reference objective itself (measured next to the reference: for inputs of
        # condition number 1e12 it reaches a few 1e-11 relative at horizon 0) and 1e-12
        # relative (the solver's derivatives come from a Cholesky factor of the bound, of
        # condition number up to 1e12: omega is then good to about 1e-6).
        at_reference = f(reference)
        noise = max(abs(f(min(max(reference + d, 0.0), 1.0)) - at_reference)
                    for d in np.linspace(-5e-11, 5e-11, 11))
        assert f(float(r.omega)) <= at_reference + 2.0 * noise + 1e-12 * abs(at_reference)


def test_steady_state_covariance_is_finite_and_positive_definite_or_raises():
    F = np.diag([1.0 - 1e-9, 0.5])
    P = steady_state_covariance(F, np.eye(2), None, None)
    assert np.isfinite(P).all()
    np.linalg.cholesky(P)
    with pytest.raises(ValueError):
        steady_state_covariance(F_UNSTABLE, np.eye(2), None, None)


def test_bound_of_an_estimate_ignored_along_a_measured_direction_is_exact():
    """The hypothesis landing of issue 10: omega = (0, 1) ignores P_1 and leaves a prior of
    norm 3e9 along a direction the next measurement fixes. The solver's bound is exact
    (60-digit reference 20.40308530206274); the Joseph route loses about 1e-7."""
    Ps = [63.2455532 * np.eye(2), np.diag([3.16227766e09, 3.16227766e01])]
    F = np.array([[-1.73141426, -0.46411801], [4.41950682, 1.75095628]])
    H = np.array([[-1.64139729, -0.00520326]])
    r = horizon_weights(Ps, F, np.eye(2), H, np.eye(1), 1, "trace")
    assert r.P[1, 1] == pytest.approx(20.40308530206274, rel=1e-14)
    fused = covariance_intersection([np.zeros(2)] * 2, Ps, omega=r.omega)
    assert_propagation_agrees(r.P, fused.P, Ps, F, np.eye(2), H, np.eye(1), 1)
