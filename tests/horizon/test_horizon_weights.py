"""The horizon-aware weights (:mod:`cifilter.horizon.weights`): ``optimal_omega``,
``horizon_weights`` and their ``HorizonOmega`` results.

Ajgl et al. (2014): the static example's omega (eq. 24 and one future measurement) and the
dynamical example at k = 0 (eq. 34); global optimality against dense grids, convexity in
omega, horizon 0 is ordinary CI, N estimates, batching, conventions, overflow and
conditioning. The partial-correlation option ``rho=`` is tested in ``test_horizon_pci.py``.
"""


import numpy as np
import pytest
from helpers import (
    F_DYN,
    F_UNSTABLE,
    FILTERS,
    H_A,
    Q_DYN,
    R_A,
    RA_STATIC,
    RB_STATIC,
    assert_propagation_agrees,
    ci_bound,
    criterion_value,
    fused_bound_tolerance,
    horizon_call_or_ill_conditioned,
    local_bounds_at_zero,
    random_system,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets, models, systems
from worst_case import assert_bound_holds

from cifilter import ci_weights, covariance_intersection
from cifilter.horizon import (
    horizon_study,
    horizon_weights,
    optimal_omega,
    propagate_bound,
    steady_state_covariance,
)


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
        # paper: "about 0.41"; hand derivation in tests/rules/test_ci.py
        assert float(trace.omega) == pytest.approx((13 - np.sqrt(3)) / (10 * (1 + np.sqrt(3))),
                                                   abs=1e-12)


# ----------------------------------------------------------------- global optimality
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


# ----------------------------------------------------------------- batching, conventions
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


# ----------------------------------------------------------------- overflow and conditioning
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


def test_gamma_overflow_with_noise_free_unstable_observed_mode_is_named():
    """Q = 0 and an unstable observed F: the filter started at P = 0 never gains, so the
    information Gamma about the initial state grows like 2^(2 k) and overflows."""
    F = np.diag([2.0, 0.9])
    with pytest.raises(ValueError, match="Gamma overflowed at step"):
        optimal_omega(np.eye(2), 2 * np.eye(2), F, np.zeros((2, 2)), np.eye(2), np.eye(2), 1200)
    r = optimal_omega(np.eye(2), 2 * np.eye(2), F, np.zeros((2, 2)), np.eye(2), np.eye(2), 300)
    assert np.isfinite(r.P).all() and r.info["converged"]


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
