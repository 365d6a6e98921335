"""Horizon-aware partial-correlation CI: the ``rho=`` option of cifilter.horizon and
``kf.fuse(method="pci", horizon=)``. Limits rho = 1 (CI) and rho = 0 (naive), horizon 0
(partial CI's optimum), derivatives, convexity, global optimality, conservativeness,
batching, bad input and the filters."""

import copy

import numpy as np
import pytest
from helpers import (
    F_DYN,
    F_UNSTABLE,
    H_A,
    H_B,
    Q_DYN,
    R_A,
    R_B,
    assert_propagation_agrees,
    criterion_value,
    dynamic_filter,
    fused_bound_tolerance,
    horizon_call_or_ill_conditioned,
    local_bounds_at_zero,
    random_system,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from strategies import (
    assert_psd,
    fused_error_covariance,
    ill_conditioned_sets,
    models,
    sets_with_joint,
)
from worst_case import assert_bound_holds

from cifilter import KalmanFilter, naive_fusion, partial_ci
from cifilter.horizon import horizon_study, horizon_weights, optimal_omega, propagate_bound
from cifilter.horizon._model import as_model, horizon_terms
from cifilter.horizon._pci import delta_problem

CRITERIA = ["det", "trace", "weighted"]


def as_criterion(name, n):
    return np.diag(np.arange(1.0, n + 1.0) ** 2) if name == "weighted" else name


def system_with(count, seed, n=3, p=2):
    """A random model and ``count`` covariances."""
    F, Q, H, R, PA, PB = random_system(seed, n=n, p=p)
    g = np.random.default_rng(1000 + seed)
    extra = []
    for _ in range(count - 2):
        D = g.standard_normal((n, n))
        extra.append(D @ D.T + 0.1 * np.eye(n))
    return F, Q, H, R, np.stack([PA, PB] + extra)


def partial_weights(delta, rho):
    """Eq. (24), written independently of the package."""
    delta, rho = np.broadcast_arrays(np.asarray(delta, float), np.asarray(rho, float))
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1.0 / (rho / delta + 1.0 - rho)
    return np.where(rho == 0, 1.0, np.where(delta == 0, 0.0, w))


def propagated(Ps, delta, rho, F, Q, H, R, horizon):
    """The bound P_kappa(delta): partial CI's fused bound (33) through the Riccati recursion."""
    w = partial_weights(delta, rho)
    fused = np.linalg.inv(np.einsum("...k,kij->...ij", w, np.linalg.inv(Ps)))
    return propagate_bound(fused, F, Q, H, R, horizon)


def simplex_grid(count, steps):
    if count == 2:
        d = np.linspace(0.0, 1.0, steps + 1)
        return np.stack([d, 1 - d], axis=-1)
    return np.array([(i, j, steps - i - j) for i in range(steps + 1)
                     for j in range(steps + 1 - i)]) / steps


# ----------------------------------------------------------------- the limits
@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("horizon", [0, 1, 4, 1000])
def test_rho_1_is_the_ci_horizon_choice_for_two_estimates(criterion, horizon):
    """rho = 1 gives w = delta: the CI problem, here solved by the simplex Newton method
    and compared with the diagonalising interval solver of the CI path."""
    PA, PB = local_bounds_at_zero()
    for H, R in ((H_A, R_A), (H_B, R_B)):
        crit = as_criterion(criterion, 2)
        ci = optimal_omega(PA, PB, F_DYN, Q_DYN, H, R, horizon, crit)
        pci = optimal_omega(PA, PB, F_DYN, Q_DYN, H, R, horizon, crit, rho=1.0)
        assert float(pci.omega) == pytest.approx(float(ci.omega), abs=1e-9)
        assert float(pci.value) == pytest.approx(float(ci.value), rel=1e-12)
        assert float(pci.info["omega_recursive"]) == pytest.approx(
            float(ci.info["omega_recursive"]), abs=1e-9)
        np.testing.assert_allclose(pci.info["weights"], [pci.omega, 1 - pci.omega],
                                   atol=1e-15)


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("seed", range(3))
def test_rho_1_is_the_ci_horizon_choice_for_three_estimates(criterion, seed):
    F, Q, H, R, Ps = system_with(3, seed)
    crit = as_criterion(criterion, 3)
    ci = horizon_weights(Ps, F, Q, H, R, 3, crit)
    pci = horizon_weights(Ps, F, Q, H, R, 3, crit, rho=[1.0, 1.0, 1.0])
    assert pci.value == pytest.approx(ci.value, rel=1e-10)
    np.testing.assert_allclose(pci.omega, ci.omega, atol=1e-6)
    np.testing.assert_allclose(pci.P, ci.P, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize("count", [2, 3])
@pytest.mark.parametrize("criterion", CRITERIA)
def test_rho_0_is_the_naive_bound_propagated(count, criterion):
    F, Q, H, R, Ps = system_with(count, 5)
    crit = as_criterion(criterion, 3)
    naive = naive_fusion(np.zeros((count, 3)), Ps).P
    expected = propagate_bound(naive, F, Q, H, R, 4)
    r = horizon_weights(Ps, F, Q, H, R, 4, crit, rho=0.0)
    np.testing.assert_allclose(r.P, expected, rtol=1e-10)
    np.testing.assert_array_equal(r.info["weights"], 1.0)
    assert r.info["value_recursive"] == pytest.approx(r.value, rel=1e-12)
    assert r.info["converged"] and r.info["gap"] == 0.0  # flat: every delta is optimal
    np.testing.assert_allclose(r.omega, 1.0 / count)  # and the start is kept


def test_inputs_with_rho_0_get_no_delta_when_others_are_correlated():
    """rho_i = 0 means w_i = 1 for every delta_i: the optimum gives its delta to the
    correlated inputs (delta_i = 0 exactly), which is the best use of the simplex."""
    F, Q, H, R, Ps = system_with(3, 2)
    for criterion in ("det", "trace"):
        r = horizon_weights(Ps, F, Q, H, R, 2, criterion, rho=[0.0, 0.5, 0.7])
        assert r.omega[0] == 0.0
        assert r.info["weights"][0] == 1.0


@pytest.mark.parametrize("count", [2, 3])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("rho", [0.2, 0.6, 0.95])
def test_horizon_zero_trace_is_partial_ci(count, seed, rho):
    """At kappa = 0 the trace criterion is Tr P(delta) of eq. (35): partial CI's optimum."""
    F, Q, H, R, Ps = system_with(count, seed)
    r = horizon_weights(Ps, F, Q, H, R, 0, "trace", rho=rho)
    reference = partial_ci(np.zeros((count, 3)), Ps, rho, solver="newton")
    assert reference.info["converged"]
    assert r.value == pytest.approx(np.trace(reference.P), rel=1e-8)
    np.testing.assert_allclose(r.omega, reference.info["delta"], atol=1e-5)
    np.testing.assert_allclose(r.P, reference.P, rtol=1e-6, atol=1e-9)


def test_per_estimate_bounds_of_a_pair_use_the_geometric_mean_as_partial_ci_does():
    PA, PB = local_bounds_at_zero()
    r = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 0, "trace", rho=[0.25, 0.64])
    same = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 0, "trace", rho=0.4)
    assert float(r.omega) == float(same.omega)
    np.testing.assert_allclose(r.info["rho"], [0.4, 0.4])
    reference = partial_ci(np.zeros((2, 2)), [PA, PB], [0.25, 0.64], solver="newton")
    assert float(r.value) == pytest.approx(np.trace(reference.P), rel=1e-10)


# (filter, criterion): (CI omega, pCI delta_1) at kappa = 0, 1, 3, 10 and the limit
DOCS_WEIGHTS = {
    ("A", "det"): ([0.6, 0.1925, 0.0458, 0.0418, 0.0418],
                   [0.5511, 0.3548, 0.2692, 0.2666, 0.2666]),
    ("A", "trace"): ([0.4124, 0.0, 0.0080, 0.0417, 0.0418],
                     [0.4327, 0.2151, 0.2478, 0.2666, 0.2666]),
    ("B", "det"): ([0.6, 0.7635, 0.8402, 0.8532, 0.8532],
                   [0.5511, 0.6050, 0.6489, 0.6572, 0.6572]),
    ("B", "trace"): ([0.4124, 0.7791, 0.9890, 0.8573, 0.8532],
                     [0.4327, 0.6393, 0.7306, 0.6594, 0.6572]),
}
# (filter, criterion, kappa): (CI batch, CI recursive, pCI batch, pCI recursive, naive)
DOCS_VALUES = {
    ("A", "det", 0): (6.1224, 6.1224, 3.4908, 3.4908, 1.5625),
    ("A", "det", 3): (1.8191, 2.4030, 1.6251, 1.7683, 1.2293),
    ("B", "det", 3): (2.9159, 3.0368, 2.5600, 2.5839, 1.9902),
    ("A", "trace", 1): (3.9101, 4.5447, 3.6778, 3.8224, 3.0009),
    ("B", "trace", 2): (3.8843, 4.4452, 3.7234, 3.8913, 3.3616),
}


@pytest.mark.parametrize("key", sorted(DOCS_WEIGHTS))
def test_the_documented_example_on_the_papers_dynamical_system(key):
    """The tables of docs/methods/horizon.rst (rho = 0.5 against CI, fusion at k = 0)."""
    name, criterion = key
    H, R = (H_A, R_A) if name == "A" else (H_B, R_B)
    PA, PB = local_bounds_at_zero()
    studies = [horizon_study(PA, PB, F_DYN, Q_DYN, H, R, [0, 1, 2, 3, 10], criterion, rho=rho)
               for rho in (None, 0.5, 0.0)]
    for study, expected in zip(studies, DOCS_WEIGHTS[key]):
        got = np.append(study.omega[[0, 1, 3, 4]], study.omega_limit)
        np.testing.assert_allclose(got, expected, atol=5e-5)
    for (filt, crit, kappa), values in DOCS_VALUES.items():
        if (filt, crit) != key:
            continue
        index = [0, 1, 2, 3, 10].index(kappa)
        got = [studies[0].batch[index], studies[0].recursive[index], studies[1].batch[index],
               studies[1].recursive[index], studies[2].batch[index]]
        np.testing.assert_allclose(got, values, atol=5e-5)
        assert studies[2].recursive[index] == pytest.approx(studies[2].batch[index])


# ----------------------------------------------------------------- derivatives, convexity
def criterion_of(P, criterion):
    """log det for "det" (the solver's criterion), else the (weighted) trace."""
    if criterion == "det":
        return np.linalg.slogdet(P)[1]
    return criterion_value(P, as_criterion(criterion, P.shape[-1]))


@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("horizon", [0, 3])
@pytest.mark.parametrize("count", [2, 3])
def test_gradient_and_hessian_agree_with_finite_differences(criterion, horizon, count):
    F, Q, H, R, Ps = system_with(count, 7)
    terms = horizon_terms(as_model(F, Q, H, R, None, 3), horizon, 3)
    weight = {"det": None, "trace": np.eye(3)}.get(criterion, as_criterion(criterion, 3))
    rho = np.array([0.3, 0.8, 0.55][:count])
    objective, derivatives, factor = delta_problem(np.linalg.inv(Ps), terms, rho, weight)

    g = np.random.default_rng(count + horizon)
    step = 1e-6
    for delta in g.dirichlet(np.ones(count), 3):
        grad, hess = derivatives(delta)
        for i in range(count):
            e = np.zeros(count)
            e[i] = step
            numeric = (objective(delta + e) - objective(delta - e)) / (2 * step)
            assert grad[i] == pytest.approx(numeric, rel=1e-6, abs=1e-9 * abs(grad).max())
            column = (derivatives(delta + e)[0] - derivatives(delta - e)[0]) / (2 * step)
            np.testing.assert_allclose(hess[:, i], column, rtol=1e-5,
                                       atol=1e-8 * np.abs(hess).max())
        # the objective is the criterion up to a constant and the positive factor
        other = g.dirichlet(np.ones(count))
        change = factor * (objective(other) - objective(delta))
        exact = [criterion_of(propagated(Ps, d, rho, F, Q, H, R, horizon), criterion)
                 for d in (delta, other)]
        assert change == pytest.approx(exact[1] - exact[0], rel=1e-8, abs=1e-13)


def test_the_det_objective_keeps_its_accuracy_where_log_det_rounds_away():
    """At kappa = 400 the delta-dependent part of log det P_kappa is below rounding; the
    objective (log det Z - log det Z_0) / exp(2 s) still resolves it, and the optimum
    equals the limit of the horizon study."""
    PA, PB = local_bounds_at_zero()
    far = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 1000, "det", rho=0.5)
    study = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 5, "det", rho=0.5)
    assert np.isfinite(study.omega_limit)
    assert float(far.omega) == pytest.approx(float(study.omega_limit), abs=1e-10)
    assert far.info["value_recursive"] == pytest.approx(far.value, rel=1e-14)
    assert far.info["converged"]


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("count", [2, 3])
def test_criteria_are_convex_in_delta_on_random_systems(seed, count):
    """Second differences along random chords of the simplex are non-negative (log det and
    weighted traces), with random rho in (0, 1] including tiny and unit bounds."""
    F, Q, H, R, Ps = system_with(count, 20 + seed)
    g = np.random.default_rng(seed)
    rho = g.choice([1e-3, 0.1, 0.5, 0.9, 1.0], count)
    t = np.linspace(0.0, 1.0, 41)
    for horizon in (1, 4):
        for _ in range(3):
            a, b = g.dirichlet(np.ones(count), 2)
            chord = (1 - t)[:, None] * a + t[:, None] * b
            P = propagated(Ps, chord, rho, F, Q, H, R, horizon)
            for values in (np.linalg.slogdet(P)[1], np.trace(P, axis1=-2, axis2=-1),
                           criterion_value(P, np.diag([1.0, 0.0, 5.0]))):
                second = values[:-2] - 2 * values[1:-1] + values[2:]
                assert second.min() >= -1e-10 * np.abs(values).max()


# ----------------------------------------------------------------- global optimality
@pytest.mark.parametrize("count, steps", [(2, 2000), (3, 80)])
@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("rho", [0.5, "mixed"])
def test_optimum_is_never_above_a_dense_simplex_grid(count, steps, criterion, rho):
    F, Q, H, R, Ps = system_with(count, 11)
    rho = [0.3, 0.9, 0.0][:count] if rho == "mixed" else rho
    # a pair's bounds act through sqrt(rho_1 rho_2) (Definition 2 for two vectors)
    used = np.sqrt(np.prod(rho)) if count == 2 and np.ndim(rho) else rho
    crit = as_criterion(criterion, 3)
    grid = simplex_grid(count, steps)
    for horizon in (1, 3):
        r = horizon_weights(Ps, F, Q, H, R, horizon, crit, rho=rho)
        assert r.info["converged"] and r.info["gap"] <= 1e-9
        values = criterion_value(propagated(Ps, grid, used, F, Q, H, R, horizon), crit)
        assert r.value <= values.min() * (1 + 1e-9)
        np.testing.assert_allclose(r.P, propagated(Ps, r.omega, used, F, Q, H, R, horizon),
                                   rtol=1e-8)


@pytest.mark.parametrize("seed", range(3))
def test_batch_is_never_above_recursive(seed):
    F, Q, H, R, Ps = system_with(2, seed)
    for criterion in ("det", "trace"):
        for rho in (0.2, [0.4, 0.9]):
            s = horizon_study(Ps[0], Ps[1], F, Q, H, R, 8, criterion, rho=rho, limit=False)
            assert np.all(s.batch <= s.recursive * (1 + 1e-12))
            assert s.batch[0] == pytest.approx(s.recursive[0], rel=1e-12)
            assert s.omega[0] == pytest.approx(float(s.omega_recursive), abs=1e-12)
            # a study's horizon is the single-horizon problem
            one = optimal_omega(Ps[0], Ps[1], F, Q, H, R, 5, criterion, rho=rho)
            assert float(one.omega) == pytest.approx(s.omega[5], abs=1e-10)
            assert float(one.info["value_recursive"]) == pytest.approx(s.recursive[5],
                                                                       rel=1e-12)


def test_tiny_positive_bounds_are_floored_for_the_solver_and_certified():
    """0 < rho_i < 1e-8 is raised to 1e-8 for the Newton iterations; the result is still a
    valid bound for the true rho, its certified gap bounds the excess, and it is close to
    the rho_i = 0 optimum."""
    F, Q, H, R, Ps = system_with(3, 1)
    for criterion in ("det", "trace"):
        r = horizon_weights(Ps, F, Q, H, R, 3, criterion, rho=[1e-14, 0.5, 0.9])
        zero = horizon_weights(Ps, F, Q, H, R, 3, criterion, rho=[0.0, 0.5, 0.9])
        assert 0 <= r.value / zero.value - 1 < 1e-4
        np.testing.assert_allclose(r.P, propagated(Ps, r.omega, [1e-14, 0.5, 0.9], F, Q, H,
                                                   R, 3), rtol=1e-8)
        # the certificate bounds the excess over the true optimum, found here by SLSQP
        def f(d, criterion=criterion):
            return criterion_value(propagated(Ps, np.clip(d, 0, 1), [1e-14, 0.5, 0.9],
                                              F, Q, H, R, 3), criterion)
        best = minimize(f, r.omega, method="SLSQP", bounds=[(0, 1)] * 3,
                        constraints={"type": "eq", "fun": lambda d: d.sum() - 1},
                        options={"ftol": 1e-15}).fun
        assert 0 < r.info["gap"] < 1e-3
        assert r.value - min(best, r.value) <= r.info["gap"] * r.value * (1 + 1e-6)


# ----------------------------------------------------------------- conservativeness
def filter_on_and_compare(bound, actual, F, Q, H, R, horizon, expected):
    """The filter runs ``horizon`` steps on the bound; the true error covariance follows with
    the same gains. The bound must be the predicted one and dominate the true one."""
    for _ in range(horizon):
        M = F @ bound @ F.T + Q
        K = M @ H.T @ np.linalg.inv(H @ M @ H.T + R)
        A = np.eye(len(M)) - K @ H
        bound = A @ M @ A.T + K @ R @ K.T
        actual = A @ (F @ actual @ F.T + Q) @ A.T + K @ R @ K.T
    np.testing.assert_allclose(bound, expected, rtol=1e-7, atol=1e-9)
    assert_psd(bound - actual, tol=1e-7, what="propagated bound - actual")


@given(sets_with_joint(2, 2, per_estimate=True), st.integers(0, 30), st.integers(0, 4),
       st.sampled_from(["det", "trace"]))
def test_propagated_bound_dominates_the_true_error_covariance(args, seed, horizon,
                                                             criterion):
    """For a joint covariance within the bound (Definition 2), fusing with the horizon
    delta and filtering on: the propagated bound dominates the true error covariance."""
    Ps, rho, joint = args
    F, Q, H, R, _, _ = random_system(seed, n=2, p=1)
    choice = optimal_omega(Ps[0], Ps[1], F, Q, H, R, horizon, criterion, rho=rho)
    fused = partial_ci(np.zeros((2, 2)), Ps, rho, delta=float(choice.omega))
    actual = fused_error_covariance(fused.gains, joint)
    assert_psd(fused.P - actual, tol=1e-7, what="fused bound - actual")
    filter_on_and_compare(fused.P, actual, F, Q, H, R, horizon, choice.P)


@given(sets_with_joint(3, 2, per_estimate=True), st.integers(0, 30), st.integers(1, 3))
def test_propagated_bound_dominates_the_true_error_covariance_three_estimates(args, seed,
                                                                            horizon):
    Ps, rho, joint = args
    F, Q, H, R, _, _ = random_system(seed, n=2, p=1)
    choice = horizon_weights(Ps, F, Q, H, R, horizon, "trace", rho=rho)
    fused = partial_ci(np.zeros((3, 2)), Ps, rho, delta=choice.omega)
    filter_on_and_compare(fused.P, fused_error_covariance(fused.gains, joint), F, Q, H, R,
                          horizon, choice.P)


# ----------------------------------------------------------------- batching, conventions
def test_batched_equals_per_item():
    systems = [system_with(2, seed) for seed in range(4)]
    F, Q, H, R, Ps = (np.stack(parts) for parts in zip(*systems))
    rho = np.array([[0.1, 0.1], [0.5, 0.9], [1.0, 1.0], [0.0, 0.3]])
    for criterion in ("det", "trace"):
        batched = horizon_weights(Ps, F, Q, H, R, 3, criterion, rho=rho)
        study = horizon_study(Ps[:, 0], Ps[:, 1], F, Q, H, R, 3, criterion, rho=rho,
                              limit=False)
        assert batched.omega.shape == (4, 2) and study.omega.shape == (4, 4)
        # every problem stops by its own test, far from the iteration limit (200)
        assert np.all(batched.info["converged"]) and batched.info["iterations"].max() < 20
        for i, (Fi, Qi, Hi, Ri, Psi) in enumerate(systems):
            single = horizon_weights(Psi, Fi, Qi, Hi, Ri, 3, criterion, rho=rho[i])
            np.testing.assert_allclose(batched.omega[i], single.omega, atol=1e-12)
            np.testing.assert_allclose(batched.P[i], single.P, rtol=1e-12)
            one = horizon_study(Psi[0], Psi[1], Fi, Qi, Hi, Ri, 3, criterion, rho=rho[i],
                                limit=False)
            np.testing.assert_allclose(study.omega[i], one.omega, atol=1e-12)
            np.testing.assert_allclose(study.recursive[i], one.recursive, rtol=1e-12)
            np.testing.assert_allclose(study.rho[i], one.rho)
    # one rho per problem (last axis 1) and a scalar broadcast alike
    per_problem = horizon_weights(Ps, F, Q, H, R, 2, rho=rho[:, :1])
    assert per_problem.omega[1] == pytest.approx(
        horizon_weights(Ps[1], F[1], Q[1], H[1], R[1], 2, rho=0.5).omega, abs=1e-12)
    # a batch of bounds for one set of estimates and one model
    many = optimal_omega(Ps[0, 0], Ps[0, 1], F[0], Q[0], H[0], R[0], 2, rho=[[0.2], [0.7]])
    assert many.omega.shape == (2,)
    assert many.omega[1] == pytest.approx(
        float(optimal_omega(Ps[0, 0], Ps[0, 1], F[0], Q[0], H[0], R[0], 2, rho=0.7).omega),
        abs=1e-12)


def test_inputs_are_not_mutated():
    F, Q, H, R, Ps = system_with(3, 8)
    rho = np.array([0.2, 0.5, 0.9])
    arrays = [F, Q, H, R, Ps, rho]
    copies = [a.copy() for a in arrays]
    horizon_weights(Ps, F, Q, H, R, 3, "det", rho=rho)
    horizon_study(Ps[0], Ps[1], F, Q, H, R, 3, rho=rho[:2], limit=False)
    partial_ci(np.zeros((3, 3)), Ps, rho, delta=np.array([0.2, 0.3, 0.5]))
    for a, b in zip(arrays, copies):
        np.testing.assert_array_equal(a, b)


def test_results_record_rho_and_the_weights():
    PA, PB = local_bounds_at_zero()
    r = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 5, "det", rho=0.5)
    delta = np.array([float(r.omega), 1 - float(r.omega)])
    np.testing.assert_allclose(r.info["weights"], partial_weights(delta, 0.5), rtol=1e-14)
    np.testing.assert_array_equal(r.info["rho"], [0.5, 0.5])
    s = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 2, rho=0.5)
    np.testing.assert_array_equal(s.rho, [0.5, 0.5])
    assert horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 2).rho is None
    import matplotlib.pyplot as plt

    fig = s.plot()
    assert "delta" in fig.axes[0].get_ylabel()
    plt.close(fig)


@pytest.mark.parametrize("call, error, match", [
    (lambda: horizon_weights([np.eye(2)] * 3, np.eye(2), 1.0, None, None, 1, rho=1.5),
     ValueError, r"rho must lie in \[0, 1\]"),
    (lambda: horizon_weights([np.eye(2)] * 3, np.eye(2), 1.0, None, None, 1, rho=[0.1, 0.2]),
     ValueError, "rho must be a scalar or have shape"),
    (lambda: horizon_weights([np.eye(2)] * 3, np.eye(2), 1.0, None, None, 1, rho="high"),
     TypeError, "rho must be a numeric array"),
    (lambda: horizon_weights([np.eye(2)] * 3, np.eye(2), 1.0, None, None, 1, rho=np.nan),
     ValueError, "rho contains non-finite"),
    (lambda: optimal_omega(np.eye(2), np.eye(2), np.eye(2), 1.0, None, None, 1,
                           rho=-0.1), ValueError, r"rho must lie in \[0, 1\]"),
    (lambda: optimal_omega(np.stack([np.eye(2)] * 3), np.eye(2), np.eye(2), 1.0, None, None,
                           1, rho=np.full((2, 2), 0.5)), ValueError, "does not broadcast"),
    (lambda: horizon_study(np.eye(2), np.eye(2), np.eye(2), 1.0, None, None, 2,
                           rho=[0.1, 0.2, 0.3]), ValueError, "rho must be a scalar"),
])
def test_bad_rho_is_rejected(call, error, match):
    with pytest.raises(error, match=match):
        call()


# ----------------------------------------------------------------- filters
@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_filter_fuse_pci_with_horizon(criterion):
    PA, PB = local_bounds_at_zero()
    kf = dynamic_filter("A")
    kf.x, kf.P = np.array([[1.0], [2.0]]), PA.copy()
    other = (np.array([0.0, 1.0]), PB.copy())
    other_copy = copy.deepcopy(other)
    result = kf.fuse(other, method="pci", rho=0.5, horizon=10, criterion=criterion)
    expected = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 10, criterion, rho=0.5)
    delta = [float(expected.omega), 1 - float(expected.omega)]
    plain = partial_ci([np.array([1.0, 2.0]), other[0]], [PA, PB], 0.5, delta=delta)
    assert result.method == "pci" and kf.last_fusion is result
    np.testing.assert_allclose(result.info["delta"], delta, atol=1e-15)
    np.testing.assert_allclose(result.weights, plain.weights, rtol=1e-14)
    np.testing.assert_allclose(kf.x[:, 0], plain.x, rtol=1e-12)
    np.testing.assert_allclose(kf.P, plain.P, rtol=1e-12)
    np.testing.assert_array_equal(kf.P_post, kf.P)
    info, chosen = result.info, result.info["horizon"]
    assert info["rule"] == "horizon" and chosen["steps"] == 10
    assert chosen["criterion"] == criterion and info["converged"]
    assert info["converged"] == chosen["converged"] and info["gap"] == chosen["gap"]
    assert chosen["value"] == pytest.approx(float(expected.value), rel=1e-12)
    assert chosen["value_recursive"] >= chosen["value"]
    assert float(chosen["weights_recursive"][0]) == pytest.approx(
        float(expected.info["omega_recursive"]), abs=1e-15)
    # the fused bound carried 10 steps is the horizon value
    assert criterion_value(propagate_bound(kf.P, F_DYN, Q_DYN, H_A, R_A, 10),
                           criterion) == pytest.approx(chosen["value"], rel=1e-10)
    np.testing.assert_array_equal(other[0], other_copy[0])
    np.testing.assert_array_equal(other[1], other_copy[1])


def test_filter_fuse_pci_horizon_zero_is_partial_ci_and_model_overrides():
    PA, PB = local_bounds_at_zero()
    kf, plain = dynamic_filter("A"), dynamic_filter("A")
    kf.P, plain.P = PA.copy(), PA.copy()
    r0 = kf.fuse((np.zeros(2), PB), method="pci", rho=0.5, horizon=0)
    rp = plain.fuse((np.zeros(2), PB), method="pci", rho=0.5)
    np.testing.assert_array_equal(r0.info["delta"], rp.info["delta"])
    np.testing.assert_array_equal(r0.P, rp.P)
    kf.P = PA.copy()
    model = dict(F=F_DYN, Q=Q_DYN, H=H_B, R=R_B)
    r = kf.fuse((np.zeros(2), PB), method="pci", rho=0.5, horizon=30, model=model,
                criterion="det")
    as_b = optimal_omega(PA, PB, F_DYN, Q_DYN, H_B, R_B, 30, "det", rho=0.5)
    assert r.info["delta"][0] == pytest.approx(float(as_b.omega), abs=1e-12)


def test_filter_fuse_pci_with_horizon_and_several_estimates():
    kf = dynamic_filter("A")
    kf.P = np.diag([1.0, 2.0])
    others = [(np.zeros(2), np.diag([2.0, 1.0])), (np.ones(2), np.diag([1.5, 1.5]))]
    r = kf.fuse(others, method="pci", rho=[0.2, 0.6, 0.9], horizon=4)
    expected = horizon_weights([np.diag([1.0, 2.0]), np.diag([2.0, 1.0]),
                                np.diag([1.5, 1.5])], F_DYN, Q_DYN, H_A, R_A, 4,
                               rho=[0.2, 0.6, 0.9])
    np.testing.assert_allclose(r.info["delta"], expected.omega, atol=1e-12)
    np.testing.assert_allclose(r.weights, expected.info["weights"], atol=1e-12)


def test_filter_without_model_needs_a_model_for_pci_horizon():
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.H = None  # no measurement matrix
    with pytest.raises(ValueError, match="no matrix H"):
        kf.fuse((np.zeros(2), np.eye(2)), method="pci", rho=0.5, horizon=3)
    assert kf.last_fusion is None


# ----------------------------------------------------------------- overflow and conditioning
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_unstable_model_overflow_raises_and_representable_horizons_are_finite(criterion):
    """Issue 9, item 4, with rho: no NaN optimum; horizon 5000 (bound about 1e795) raises."""
    PA, PB = local_bounds_at_zero()
    with pytest.raises(ValueError, match="horizon 5000"):
        optimal_omega(PA, PB, F_UNSTABLE, np.eye(2), None, None, 5000, criterion, rho=0.5)
    r = optimal_omega(PA, PB, F_UNSTABLE, np.eye(2), None, None, 1000, criterion, rho=0.5)
    assert r.info["converged"] and np.isfinite(r.P).all() and np.isfinite(r.value)
    np.linalg.cholesky(r.P)
    grid = np.linspace(0.0, 1.0, 401)
    values = [np.linalg.slogdet(P)[1] if criterion == "det" else np.log(np.trace(P))
              for P in propagated(np.stack([PA, PB]), np.stack([grid, 1 - grid], -1), 0.5,
                                  F_UNSTABLE, np.eye(2), None, None, 1000)]
    best = np.linalg.slogdet(r.P)[1] if criterion == "det" else np.log(np.trace(r.P))
    assert best <= min(values) + 1e-12 * abs(best)


@settings(max_examples=30)
@given(st.integers(2, 5), st.integers(2, 3), st.sampled_from(["trace", "det"]),
       st.sampled_from([0, 1, 5, 40]), st.floats(0.0, 1.0), st.data())
def test_horizon_delta_of_ill_conditioned_estimates_is_on_the_simplex_and_conservative(
        count, n, criterion, horizon, rho, data):
    Ps = np.asarray(data.draw(ill_conditioned_sets(count, n)))
    F, Q, H, R = data.draw(models(n))
    r = horizon_call_or_ill_conditioned(
        lambda: horizon_weights(Ps, F, Q, H, R, horizon, criterion, rho=rho), Ps, F, Q, H, R,
        horizon, rho)
    if r is None:
        return
    delta = r.omega
    assert np.isfinite(delta).all() and np.all(delta >= 0.0)
    assert delta.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.isfinite(r.value) and r.value > 0 and np.isfinite(r.P).all()
    np.linalg.cholesky(r.P)
    fused = partial_ci(np.zeros((count, n)), Ps, rho, delta=delta)
    assert_bound_holds(fused.P, fused.gains, Ps, rho=rho, tol=fused_bound_tolerance(Ps))
    assert_propagation_agrees(r.P, fused.P, Ps, F, Q, H, R, horizon)
