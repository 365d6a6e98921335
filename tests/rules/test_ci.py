"""Covariance Intersection: paper values, optimality, fast rules, conventions, properties."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.optimize import minimize, minimize_scalar
from strategies import (
    assert_psd,
    covariance_sets,
    fused_error_covariance,
    joint_covariances,
    spd_matrices,
)

from cifilter import ci_weights, covariance_intersection

# every test runs on each backend (numpy, and the compiled kernels when numba is installed)
pytestmark = pytest.mark.usefixtures("ci_backend")

rng = np.random.default_rng(20261123)


def random_spd(n, size=(), seed=None):
    g = np.random.default_rng(seed) if seed is not None else rng
    A = g.standard_normal(size + (n, n))
    return A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)


# ----------------------------------------------------------------- paper values
def test_wu_example_2_trace_optimal_ci():
    """Wu, Cai & Fu (2018), Example 2: omega = 0.5, trace 3.2, K1 = diag(0.8, 0.2)."""
    P1, P2 = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    r = covariance_intersection([np.zeros(2), np.zeros(2)], [P1, P2])
    assert r.omega[0] == pytest.approx(0.5, abs=1e-12)
    assert np.trace(r.P) == pytest.approx(3.2, abs=1e-12)
    np.testing.assert_allclose(r.gains[0], np.diag([0.8, 0.2]), atol=1e-12)
    np.testing.assert_allclose(r.gains[1], np.diag([0.2, 0.8]), atol=1e-12)
    # the bound printed in the example: diag(1/(w + 0.25(1-w)), 1/(0.25 w + 1 - w))
    np.testing.assert_allclose(r.P, np.diag([1.6, 1.6]), atol=1e-12)


def test_ajgl_eq_34_det_and_trace_optimal_omega():
    """Ajgl et al. (2014), eq. (34): det-optimal omega 0.6, trace-optimal about 0.4124."""
    PA, PB = np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])
    det = covariance_intersection([np.zeros(2)] * 2, [PA, PB], criterion="det")
    trace = covariance_intersection([np.zeros(2)] * 2, [PA, PB], criterion="trace")
    assert det.omega[0] == pytest.approx(0.6, abs=1e-10)
    assert trace.omega[0] == pytest.approx(0.4124, abs=1e-4)
    for r in (det, trace):
        w = r.omega[0]
        np.testing.assert_allclose(r.P, np.diag([10 / (1 + 10 * w), 30 / (13 - 10 * w)]),
                                   rtol=1e-12)
    # hand derivation of the trace optimum: d/dw [10/(1+10w) + 30/(13-10w)] = 0
    # <=> (13 - 10w)^2 = 3 (1 + 10w)^2 <=> w = (13 - sqrt(3)) / (10 (1 + sqrt(3)))
    assert trace.omega[0] == pytest.approx((13 - np.sqrt(3)) / (10 * (1 + np.sqrt(3))),
                                           abs=1e-12)


# ----------------------------------------------------------------- optimality
def _trace_bound(w, P1, P2):
    return np.trace(np.linalg.inv(w * np.linalg.inv(P1) + (1 - w) * np.linalg.inv(P2)))


@pytest.mark.parametrize("seed", range(8))
def test_two_estimate_optimum_matches_bounded_scalar_search(seed):
    P1, P2 = random_spd(3, seed=seed), random_spd(3, seed=seed + 100)
    r = covariance_intersection([np.zeros(3)] * 2, [P1, P2])
    reference = minimize_scalar(_trace_bound, bounds=(0, 1), args=(P1, P2), method="bounded",
                                options={"xatol": 1e-12})
    assert np.trace(r.P) <= reference.fun + 1e-10
    assert r.omega[0] == pytest.approx(reference.x, abs=1e-5)
    assert r.info["converged"]


@pytest.mark.parametrize("criterion", ["trace", "det", "weighted"])
@pytest.mark.parametrize("count", [3, 4])
def test_n_estimate_optimum_matches_general_solver(criterion, count):
    g = np.random.default_rng(count)
    Ps = [random_spd(3, seed=int(g.integers(1 << 30))) for _ in range(count)]
    W = np.diag([1.0, 0.0, 2.0])
    crit = W if criterion == "weighted" else criterion
    r = covariance_intersection([np.zeros(3)] * count, Ps, criterion=crit)
    info = [np.linalg.inv(P) for P in Ps]

    def value(w):
        P = np.linalg.inv(sum(wi * I for wi, I in zip(w, info)))
        if criterion == "det":
            return np.linalg.slogdet(P)[1]
        return np.trace(P) if criterion == "trace" else np.trace(W @ P)

    best = min(
        (minimize(value, w0, method="SLSQP", bounds=[(0, 1)] * count,
                  constraints={"type": "eq", "fun": lambda w: w.sum() - 1},
                  options={"ftol": 1e-14, "maxiter": 500})
         for w0 in np.eye(count) * 0.8 + 0.2 / count),
        key=lambda res: res.fun,
    )
    ours = np.linalg.slogdet(r.P)[1] if criterion == "det" else r.info["value"]
    assert ours <= best.fun + 1e-9
    assert r.info["converged"]
    assert r.info["solver"] == "simplex"


def test_boundary_optimum_is_exact_for_two_estimates():
    P1 = np.diag([1.0, 2.0])
    P2 = np.diag([3.0, 5.0])  # P2 > P1: the optimum ignores P2 entirely
    for criterion in ("trace", "det"):
        r = covariance_intersection([np.zeros(2)] * 2, [P1, P2], criterion=criterion)
        assert r.omega[0] == 1.0 and r.omega[1] == 0.0
        reverse = covariance_intersection([np.zeros(2)] * 2, [P2, P1], criterion=criterion)
        assert reverse.omega[0] == 0.0 and reverse.omega[1] == 1.0
        np.testing.assert_allclose(r.P, P1, rtol=1e-12)


def test_boundary_optimum_is_exact_for_three_estimates():
    P1, P2 = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    P3 = np.diag([5.0, 5.0])  # dominated by both others
    r = covariance_intersection([np.zeros(2)] * 3, [P1, P2, P3])
    assert r.omega[2] == 0.0
    np.testing.assert_allclose(r.omega, [0.5, 0.5, 0.0], atol=1e-10)
    assert np.trace(r.P) == pytest.approx(3.2, abs=1e-10)


def test_equal_covariances_give_half_and_the_same_covariance():
    P = random_spd(3, seed=5)
    r = covariance_intersection([np.zeros(3), np.ones(3)], [P, P])
    assert r.omega[0] == 0.5
    np.testing.assert_allclose(r.P, P, rtol=1e-10)
    np.testing.assert_allclose(r.x, 0.5 * np.ones(3), rtol=1e-10)


@pytest.mark.parametrize("criterion", ["trace", "det", np.diag([2.0, 1.0, 0.5])])
def test_diagonalisation_and_simplex_solvers_agree(criterion):
    Ps = np.stack([random_spd(3, size=(40,), seed=1), random_spd(3, size=(40,), seed=2)], axis=1)
    w_fast, info_fast = ci_weights(Ps, criterion, method="diagonalise")
    w_slow, info_slow = ci_weights(Ps, criterion, method="simplex")
    np.testing.assert_allclose(w_fast, w_slow, atol=1e-8)
    assert info_fast["converged"].all() and info_slow["converged"].all()
    assert info_fast["iterations"].max() < 30


def test_weight_matrix_criterion_minimises_weighted_trace():
    P1, P2 = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    W = np.diag([1.0, 0.0])  # only the first component matters: trust estimate 1 fully
    r = covariance_intersection([np.zeros(2)] * 2, [P1, P2], criterion=W)
    assert r.omega[0] == 1.0
    identity = covariance_intersection([np.zeros(2)] * 2, [P1, P2], criterion=np.eye(2))
    assert identity.omega[0] == pytest.approx(0.5, abs=1e-12)


# ----------------------------------------------------------------- fast rules
def test_fast_rule_is_niehsen_inverse_trace_weights():
    Ps = [np.diag([1.0, 1.0]), np.diag([3.0, 1.0]), np.diag([2.0, 2.0])]
    r = covariance_intersection([np.zeros(2)] * 3, Ps, omega="fast")
    inverse_traces = np.array([1 / 2, 1 / 4, 1 / 4])
    np.testing.assert_allclose(r.omega, inverse_traces / inverse_traces.sum())
    assert r.info["rule"] == "fast"


def test_det_ratio_rule_is_weng_djuric_eq_7():
    P1, P2 = random_spd(2, seed=3), random_spd(2, seed=4)
    r = covariance_intersection([np.zeros(2)] * 2, [P1, P2], omega="det-ratio")
    d1, d2 = np.linalg.det(P1), np.linalg.det(P2)
    assert r.omega[0] == pytest.approx(d2 / (d1 + d2), rel=1e-12)


def test_det_ratio_rule_survives_huge_determinants():
    Ps = [1e200 ** (1 / 4) * np.eye(4), 2e200 ** (1 / 4) * np.eye(4)]
    r = covariance_intersection([np.zeros(4)] * 2, Ps, omega="det-ratio")
    np.testing.assert_allclose(r.omega, [2 / 3, 1 / 3], rtol=1e-10)


def test_improved_fast_rule_two_estimates_closed_form():
    P1, P2 = random_spd(3, seed=6), random_spd(3, seed=7)
    I1, I2 = np.linalg.inv(P1), np.linalg.inv(P2)
    d, d1, d2 = np.linalg.det(I1 + I2), np.linalg.det(I1), np.linalg.det(I2)
    r = covariance_intersection([np.zeros(3)] * 2, [P1, P2], omega="improved-fast")
    assert r.omega[0] == pytest.approx((d - d2 + d1) / (2 * d), rel=1e-10)


def test_improved_fast_rule_n_estimates_formula():
    Ps = [random_spd(2, seed=s) for s in (8, 9, 10)]
    info = [np.linalg.inv(P) for P in Ps]
    total = sum(info)
    det = np.linalg.det
    numerators = [det(total) - det(total - I) + det(I) for I in info]
    denominator = 3 * det(total) + sum(det(I) - det(total - I) for I in info)
    r = covariance_intersection([np.zeros(2)] * 3, Ps, omega="improved-fast")
    np.testing.assert_allclose(r.omega, np.array(numerators) / denominator, rtol=1e-10)


@given(st.integers(2, 4).flatmap(lambda count: covariance_sets(count, 2)),
       st.sampled_from(["fast", "improved-fast", "det-ratio"]))
def test_fast_rules_give_weights_on_the_simplex(Ps, rule):
    w = covariance_intersection([np.zeros(2)] * len(Ps), Ps, omega=rule).omega
    assert np.all(w > 0) and w.sum() == pytest.approx(1.0, abs=1e-12)


# ----------------------------------------------------------------- fixed weights
def test_fixed_scalar_and_array_weights():
    P1, P2 = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    r = covariance_intersection([np.zeros(2)] * 2, [P1, P2], omega=0.25)
    np.testing.assert_allclose(r.omega, [0.25, 0.75])
    expected = np.linalg.inv(0.25 * np.linalg.inv(P1) + 0.75 * np.linalg.inv(P2))
    np.testing.assert_allclose(r.P, expected, rtol=1e-12)
    assert r.info["rule"] == "fixed"
    r3 = covariance_intersection([np.zeros(2)] * 3, [P1, P2, np.eye(2)], omega=[0.2, 0.3, 0.5])
    np.testing.assert_allclose(r3.omega, [0.2, 0.3, 0.5])


@pytest.mark.parametrize("omega, message", [
    (1.5, "simplex"),
    (-0.1, "simplex"),
    ([0.5, 0.6], "simplex"),
    ([0.5, 0.25, 0.25], r"shape \(\.\.\., 2\)"),
    ([np.nan, 1.0], "non-finite"),
    ("fastest", "fast"),
])
def test_bad_weights_are_rejected(omega, message):
    with pytest.raises(ValueError, match=message):
        covariance_intersection([np.zeros(2)] * 2, [np.eye(2)] * 2, omega=omega)


def test_scalar_weight_needs_two_estimates():
    with pytest.raises(ValueError, match="two estimates"):
        covariance_intersection([np.zeros(2)] * 3, [np.eye(2)] * 3, omega=0.3)


# ----------------------------------------------------------------- conventions
def test_column_vectors_come_back_as_columns():
    x1, x2 = np.array([[1.0], [2.0]]), np.array([[3.0], [4.0]])
    r = covariance_intersection([x1, x2], [np.eye(2), 2 * np.eye(2)])
    assert r.x.shape == (2, 1)
    flat = covariance_intersection([x1.ravel(), x2.ravel()], [np.eye(2), 2 * np.eye(2)])
    np.testing.assert_array_equal(r.x[:, 0], flat.x)


def test_first_input_decides_the_style():
    r = covariance_intersection([np.zeros(2), np.ones((2, 1))], [np.eye(2)] * 2)
    assert r.x.shape == (2,)
    r = covariance_intersection([np.zeros((2, 1)), np.ones(2)], [np.eye(2)] * 2)
    assert r.x.shape == (2, 1)


def test_one_dimensional_state():
    r = covariance_intersection([np.array([0.0]), np.array([1.0])], [[[1.0]], [[2.0]]])
    assert r.omega[0] == 1.0  # with n = 1 the smaller variance wins outright
    assert r.x.shape == (1,) and r.P.shape == (1, 1)


@pytest.mark.parametrize("count", [2, 3])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_batched_equals_per_item(count, criterion):
    batch = (4, 5)
    Ps = np.stack([random_spd(3, size=batch, seed=10 + i) for i in range(count)], axis=-3)
    xs = np.random.default_rng(1).standard_normal(batch + (count, 3))
    r = covariance_intersection(xs, Ps, criterion=criterion)
    assert r.x.shape == batch + (3,) and r.P.shape == batch + (3, 3)
    assert r.gains.shape == batch + (count, 3, 3) and r.omega.shape == batch + (count,)
    for index in np.ndindex(*batch):
        single = covariance_intersection(xs[index], Ps[index], criterion=criterion)
        np.testing.assert_allclose(r.x[index], single.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r.P[index], single.P, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r.omega[index], single.omega, atol=1e-9)


def test_batch_axes_of_means_and_covariances_broadcast():
    Ps = np.stack([random_spd(2, seed=1), random_spd(2, seed=2)])
    xs = np.random.default_rng(2).standard_normal((7, 2, 2))
    r = covariance_intersection(xs, Ps)
    assert r.x.shape == (7, 2) and r.P.shape == (7, 2, 2)
    np.testing.assert_allclose(r.x[3], covariance_intersection(xs[3], Ps).x)


def test_inputs_are_not_mutated():
    xs = [np.array([1.0, 2.0]), np.array([[3.0], [4.0]])]
    Ps = np.stack([random_spd(2, seed=1), random_spd(2, seed=2)])
    Ps[0, 0, 1] += 1e-12  # slightly asymmetric, within tolerance: symmetrised internally
    copies = ([x.copy() for x in xs], Ps.copy())
    covariance_intersection(xs, Ps)
    for before, after in zip(copies[0], xs):
        np.testing.assert_array_equal(before, after)
    np.testing.assert_array_equal(copies[1], Ps)


def test_result_is_symmetric_and_gains_sum_to_identity():
    r = covariance_intersection([np.zeros(3)] * 3, [random_spd(3, seed=s) for s in range(3)])
    np.testing.assert_array_equal(r.P, r.P.T)
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3), atol=1e-12)


@pytest.mark.parametrize("xs, Ps, error, message", [
    ([np.zeros(2)], [np.eye(2)], ValueError, "at least 2"),
    ([np.zeros(2)] * 2, [np.eye(2), np.eye(3)], ValueError, "shape"),
    ([np.zeros(3)] * 2, [np.eye(2)] * 2, ValueError, r"\(\.\.\., 2\)"),
    ([np.zeros(2)] * 2, [np.eye(2), [[1.0, 0.5], [0.0, 1.0]]], ValueError, "not symmetric"),
    ([np.zeros(2)] * 2, [np.eye(2), -np.eye(2)], ValueError, "not positive definite"),
    ([np.zeros(2)] * 2, [np.eye(2), [[np.nan, 0], [0, 1]]], ValueError, "non-finite"),
    ([np.array([np.inf, 0.0]), np.zeros(2)], [np.eye(2)] * 2, ValueError, "non-finite"),
    ([np.zeros(2)] * 2, [np.eye(2), "eye"], TypeError, "numeric"),
    ([np.zeros(2)] * 3, [np.eye(2)] * 2, ValueError, "3 estimates"),
    ([np.zeros(2)] * 2, np.eye(2), ValueError, "shape"),
])
def test_bad_input_is_named(xs, Ps, error, message):
    with pytest.raises(error, match=message):
        covariance_intersection(xs, Ps)


def test_non_positive_definite_member_of_a_batch_is_located():
    Ps = np.stack([np.eye(2)] * 2)[None].repeat(3, axis=0)
    Ps[2, 1] = np.diag([1.0, -1.0])
    with pytest.raises(ValueError, match=r"Ps\[2, 1\] is not positive definite"):
        covariance_intersection(np.zeros((3, 2, 2)), Ps)


@pytest.mark.parametrize("criterion, message", [
    ("volume", "criterion"),
    (np.diag([1.0, -1.0]), "positive semidefinite"),
    (np.zeros((2, 2)), "zero"),
    (np.eye(3), "2x2"),
    (np.array([[1.0, 1.0], [0.0, 1.0]]), "symmetric"),
])
def test_bad_criterion_is_rejected(criterion, message):
    with pytest.raises(ValueError, match=message):
        covariance_intersection([np.zeros(2)] * 2, [np.eye(2)] * 2, criterion=criterion)


# ----------------------------------------------------------------- properties
@given(covariance_sets(2, 3).flatmap(lambda Ps: st.tuples(st.just(Ps), joint_covariances(Ps))),
       st.one_of(st.none(), st.floats(0, 1), st.sampled_from(["fast", "improved-fast"])))
def test_ci_bound_dominates_true_error_covariance_two_estimates(Ps_joint, omega):
    """P_CI - K J K^T is PSD for every admissible joint covariance J (any omega)."""
    Ps, joint = Ps_joint
    r = covariance_intersection([np.zeros(3)] * 2, Ps, omega=omega)
    assert_psd(r.P - fused_error_covariance(r.gains, joint), what="P_CI - true covariance")


@given(covariance_sets(3, 2).flatmap(lambda Ps: st.tuples(st.just(Ps), joint_covariances(Ps))),
       st.sampled_from(["trace", "det"]))
def test_ci_bound_dominates_true_error_covariance_three_estimates(Ps_joint, criterion):
    Ps, joint = Ps_joint
    r = covariance_intersection([np.zeros(2)] * 3, Ps, criterion=criterion)
    assert_psd(r.P - fused_error_covariance(r.gains, joint), what="P_CI - true covariance")


@given(st.integers(2, 4).flatmap(lambda count: covariance_sets(count, 3)), st.randoms())
def test_outputs_are_spd_and_permutation_invariant(Ps, random):
    count = len(Ps)
    xs = [np.arange(3.0) * (i + 1) for i in range(count)]
    r = covariance_intersection(xs, Ps)
    np.testing.assert_array_equal(r.P, r.P.T)
    assert np.linalg.eigvalsh(r.P)[0] > 0
    order = list(range(count))
    random.shuffle(order)
    p = covariance_intersection([xs[i] for i in order], [Ps[i] for i in order])
    assert np.trace(p.P) == pytest.approx(np.trace(r.P), rel=1e-9)
    # The permuted weights are optimal for the original order too. (They need not agree
    # to many digits: for nearly equal covariances the criterion is nearly flat in omega.)
    unpermuted = np.empty(count)
    unpermuted[order] = p.omega
    again = covariance_intersection(xs, Ps, omega=unpermuted)
    assert np.trace(again.P) == pytest.approx(np.trace(r.P), rel=1e-9)
    # With the weights fixed, permuting the inputs permutes nothing else.
    fixed = covariance_intersection([xs[i] for i in order], [Ps[i] for i in order],
                                    omega=r.omega[order])
    np.testing.assert_allclose(fixed.x, r.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fixed.P, r.P, rtol=1e-10, atol=1e-12)


@given(spd_matrices(2), spd_matrices(2))
def test_trace_optimum_is_not_above_either_input(P1, P2):
    r = covariance_intersection([np.zeros(2)] * 2, [P1, P2])
    assert np.trace(r.P) <= min(np.trace(P1), np.trace(P2)) * (1 + 1e-12)
