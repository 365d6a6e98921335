"""The bound's propagation (:mod:`cifilter.horizon.model`): ``propagate_bound`` and
``steady_state_covariance``.

Ajgl et al. (2014): the static example's eqs. (27)-(28) and the dynamical example's eq. (35);
for a fixed omega the recursive bound equals the batch estimator's (Sec. III) and holds for
every admissible correlation; filterpy's recursion, per-step models, the Lyapunov limit,
overflow and conditioning, and bad input (of every function of :mod:`cifilter.horizon`).
"""


import filterpy.kalman as fk
import numpy as np
import pytest
from helpers import (
    F_DYN,
    F_UNSTABLE,
    FILTERS,
    H_A,
    H_B,
    Q_DYN,
    R_A,
    R_B,
    RA_STATIC,
    RB_STATIC,
    ci_bound,
    local_bounds_at_zero,
    random_system,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import (
    assert_psd,
    fused_error_covariance,
    ill_conditioned_spd,
    joint_covariances,
    models,
    systems,
)

from cifilter import covariance_intersection
from cifilter.horizon import (
    horizon_study,
    horizon_weights,
    optimal_omega,
    propagate_bound,
    steady_state_covariance,
)


# ----------------------------------------------------------------- static example (IV.A)
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


# ----------------------------------------------------------------- dynamical example (IV.B)
def test_eq_35_steady_state_matrices():
    PA = steady_state_covariance(F_DYN, Q_DYN, H_A, R_A)
    PB = steady_state_covariance(F_DYN, Q_DYN, H_B, R_B)
    np.testing.assert_allclose(PA, [[0.6076, 0.5772], [0.5772, 1.5483]], atol=5e-5)
    np.testing.assert_allclose(PB, [[2.1216, 1.1806], [1.1806, 1.2427]], atol=5e-5)
    for P, (H, R) in ((PA, FILTERS["A"]), (PB, FILTERS["B"])):
        np.testing.assert_allclose(propagate_bound(P, F_DYN, Q_DYN, H, R, 1), P, atol=1e-12)


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


# ----------------------------------------------------------------- steady_state_covariance
def test_steady_state_without_measurements_is_the_lyapunov_solution():
    P = steady_state_covariance(F_DYN, Q_DYN, None, None)
    np.testing.assert_allclose(F_DYN @ P @ F_DYN.T + Q_DYN, P, rtol=1e-10)
    with pytest.raises(ValueError, match="stable F"):
        steady_state_covariance(np.eye(2), Q_DYN, None, None)
    batched = steady_state_covariance(np.stack([F_DYN, 0.5 * np.eye(2)]), Q_DYN, H_A, R_A)
    np.testing.assert_allclose(batched[0], steady_state_covariance(F_DYN, Q_DYN, H_A, R_A))


# ----------------------------------------------------------------- bad input
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


# ----------------------------------------------------------------- overflow and conditioning
def test_issue_9_propagate_bound_at_horizon_3000_raises_instead_of_nan():
    PA, _ = local_bounds_at_zero()
    with pytest.raises(ValueError, match=r"horizon 3000 overflows float64.*1e478"):
        propagate_bound(PA, F_UNSTABLE, np.eye(2), None, None, 3000)
    with pytest.raises(ValueError, match="horizon 1928 of 3000"):  # the first that overflows
        propagate_bound(PA, F_UNSTABLE, np.eye(2), None, None, 3000, history=True)
    with pytest.raises(ValueError, match="horizon 3000"):
        horizon_study(PA, PA, F_UNSTABLE, np.eye(2), None, None, [0, 3000], limit=False)


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


def test_steady_state_covariance_is_finite_and_positive_definite_or_raises():
    F = np.diag([1.0 - 1e-9, 0.5])
    P = steady_state_covariance(F, np.eye(2), None, None)
    assert np.isfinite(P).all()
    np.linalg.cholesky(P)
    with pytest.raises(ValueError):
        steady_state_covariance(F_UNSTABLE, np.eye(2), None, None)
