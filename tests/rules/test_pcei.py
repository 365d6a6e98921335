"""Probabilistically conservative EI (:mod:`cifilter.rules.pcei`), through its public function.

Section III case 3, the constraint at the boundary and optimality of the constrained
minimum, closed forms, properties, the conditioning contract (issue 9, item 3), the argument
forms, ``fuse`` options, batching, conventions and bad input. The solver's internals are
tested in ``test_pc_constraint.py``; the paper's reproduction (Section III cases 1-2,
Table I, Section V-B: ``cifilter.cli.reproduce.naveen``) in ``test_reproduce.py``.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from strategies import ill_conditioned_sets, means_of_their_scale
from test_ei import (
    BAD_INPUT,
    METRIC_TOL,
    assert_valid_fusion,
    check_argument_form_errors,
    check_argument_forms,
    check_batched_equals_per_item,
    check_broadcast_and_columns,
    check_inputs_are_not_mutated,
    check_issue_reproducer,
    check_near_equal_covariances_are_finite,
    check_random_pairs_at_condition_1e9,
    check_registry_and_filters,
    issue_pair,
    literal_psi,
    metric_difference,
    pairs,
    random_spd,
    resolved_pair,
    setup_problem,
    within_contract,
)

from cifilter import (
    IllConditionedError,
    ellipsoidal_intersection,
    fuse,
    pc_ellipsoidal_intersection,
)

inv = np.linalg.inv


# ----------------------------------------------------------------- Section III


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_section_three_case_three_equal_means_leave_ei_unchanged(mutual_mean):
    for Pa, Pb in (([[0.5]], [[1.0]]), (random_spd(3, seed=1), random_spd(3, seed=2))):
        x = np.arange(1.0, 1.0 + np.shape(Pa)[0])
        for options in ({"eps": 0.01, "regularizer": "covariance"}, {}):
            ei = ellipsoidal_intersection(x, Pa, x, Pb, mutual_mean=mutual_mean, **options)
            pc = pc_ellipsoidal_intersection(x, Pa, x, Pb, mutual_mean=mutual_mean, **options)
            assert pc.info["solver"] == "ei" and not pc.info["active"]
            np.testing.assert_array_equal(pc.P, ei.P)
            np.testing.assert_array_equal(pc.x, ei.x)
            np.testing.assert_array_equal(pc.info["common_P"], ei.info["common_P"])


# ----------------------------------------------------------------- PC-EI: the constraint
@pytest.mark.parametrize("seed, n, dominated", [(1, 2, False), (2, 2, True), (3, 3, False),
                                                (4, 4, False), (5, 4, True)])
def test_pc_meets_the_constraint_at_the_boundary_and_only_enlarges_c(seed, n, dominated):
    xa, Pa, xb, Pb = setup_problem(n, seed, dominated)
    for alpha in (0.05, 0.01):
        ei = ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean="as-printed")
        pc = pc_ellipsoidal_intersection(xa, Pa, xb, Pb, alpha=alpha, mutual_mean="as-printed")
        info = pc.info
        gamma = stats.chi2.ppf(1 - alpha, n)
        assert info["solver"] == "interior-point" and info["feasible"] and info["converged"]
        assert info["threshold"] == pytest.approx(gamma)
        # eq. (17) evaluated literally at the returned common covariance: on the boundary
        psi = literal_psi(xa, Pa, xb, Pb, info["common_P"], "as-printed")
        assert psi == pytest.approx(gamma, rel=1e-6)
        assert info["psi"] == pytest.approx(psi, rel=1e-6)
        # C_c = C_EI + S S^T (eq. (18)) and a smaller fused covariance than EI's
        assert np.linalg.eigvalsh(info["common_P"] - ei.info["common_P"]).min() >= -1e-12
        assert np.linalg.det(pc.P) < np.linalg.det(ei.P)
        np.testing.assert_allclose(inv(pc.P), inv(Pa) + inv(Pb) - inv(info["common_P"]),
                                   rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(pc.gains[0] @ xa + pc.gains[1] @ xb, pc.x, atol=1e-10)
        assert info["kkt_residual"] < 1e-4 and info["duality_gap"] <= 1e-9
        assert info["starts"] >= 1 and info["starts_agree"] >= 1


def objective_and_psi(xa, Pa, xb, Pb, Cc, mutual_mean="as-printed"):
    return np.linalg.slogdet(Cc)[1], literal_psi(xa, Pa, xb, Pb, Cc, mutual_mean)


@pytest.mark.parametrize("seed, n, dominated", [(11, 2, False), (12, 2, True), (13, 3, False)])
def test_pc_result_is_a_constrained_minimum(seed, n, dominated):
    """No feasible common covariance near the result has a smaller determinant.

    Random perturbations ``C_c + h M`` inside the cone ``C_c >= C_EI`` (``M`` symmetric,
    of both signs along the part added to C_EI) either increase ``log det C_c`` or break
    ``psi <= gamma``; and a direct search from the result with SciPy's SLSQP over
    ``C_c = C_EI + S S^T`` finds nothing better.
    """
    from scipy.optimize import minimize

    xa, Pa, xb, Pb = setup_problem(n, seed, dominated)
    pc = pc_ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean="as-printed")
    C_ei = ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean="as-printed").info["common_P"]
    Cc, gamma = pc.info["common_P"], pc.info["threshold"]
    best, _ = objective_and_psi(xa, Pa, xb, Pb, Cc)
    g = np.random.default_rng(seed)
    for _ in range(300):
        X = g.standard_normal((n, n))
        for h in (1e-2, 1e-4):
            trial = Cc + h * (X + X.T) * np.abs(Cc).max()
            if np.linalg.eigvalsh(trial - C_ei).min() <= 0:
                continue
            value, psi = objective_and_psi(xa, Pa, xb, Pb, trial)
            assert not (value < best - 1e-9 and psi <= gamma)
    tril = np.tril_indices(n)
    S0 = np.linalg.cholesky(Cc - C_ei + 1e-9 * np.eye(n))[tril]

    def params(S):
        L = np.zeros((n, n))
        L[tril] = S
        return C_ei + L @ L.T

    for start in (S0, S0 * 0.9, S0 + 0.1 * g.standard_normal(S0.shape)):
        res = minimize(lambda S: np.linalg.slogdet(params(S))[1], start, method="SLSQP",
                       constraints={"type": "ineq", "fun": lambda S: np.log(gamma) - np.log(
                           objective_and_psi(xa, Pa, xb, Pb, params(S))[1])},
                       options={"ftol": 1e-12, "maxiter": 300})
        if objective_and_psi(xa, Pa, xb, Pb, params(res.x))[1] <= gamma * (1 + 1e-8):
            assert res.fun >= best - 1e-7


def test_equal_covariances_have_the_closed_form_rank_one_solution():
    """For Pa = Pb the optimum is C_c = Pa + e e^T / (2 gamma - e^T Pa^-1 e), e = xa - xb."""
    P = random_spd(3, seed=21)
    xa, xb = np.array([0.5, -0.2, 0.1]), np.array([-0.4, 0.3, 0.2])
    e = xa - xb
    for mutual_mean in ("as-printed", "sijs-lazar"):
        r = pc_ellipsoidal_intersection(xa, P, xb, P, mutual_mean=mutual_mean)
        gamma = r.info["threshold"]
        expected = P + np.outer(e, e) / (2 * gamma - e @ inv(P) @ e)
        assert r.info["solver"] == "closed-form"
        np.testing.assert_allclose(r.info["common_P"], expected, rtol=1e-10)
        np.testing.assert_allclose(r.x, (xa + xb) / 2, rtol=1e-10)
        np.testing.assert_allclose(r.gains, 0.5 * np.stack([np.eye(3)] * 2), atol=1e-12)
        assert np.linalg.matrix_rank(r.info["common_P"] - P, tol=1e-10) == 1
    # the interior-point method converges to it as the covariances approach each other
    near = pc_ellipsoidal_intersection(xa, P, xb, P * (1 + 1e-5), eps=0.0,
                                       mutual_mean="as-printed")
    assert near.info["solver"] == "interior-point"
    np.testing.assert_allclose(near.info["common_P"], expected, rtol=2e-3)


def test_sijs_lazar_pc_equals_ei_unless_tied_directions_have_different_means():
    xa, Pa, xb, Pb = setup_problem(3, 31)
    ei = ellipsoidal_intersection(xa, Pa, xb, Pb)
    pc = pc_ellipsoidal_intersection(xa, Pa, xb, Pb)
    assert pc.info["solver"] == "ei" and pc.info["psi"] == 0.0
    for field in ("x", "P", "gains"):
        np.testing.assert_array_equal(getattr(pc, field), getattr(ei, field))


def test_infeasible_problems_return_ei_and_say_so():
    Pa, Pb = np.eye(2), np.diag([2.0, 0.5])
    xa, xb = np.zeros(2), np.array([8.0, 8.0])  # independent test already rejects
    for mutual_mean in ("as-printed", "sijs-lazar"):
        for Pb_ in (Pb, Pa):
            r = pc_ellipsoidal_intersection(xa, Pa, xb, Pb_, mutual_mean=mutual_mean)
            ei = ellipsoidal_intersection(xa, Pa, xb, Pb_, mutual_mean=mutual_mean)
            if r.info["active"]:
                assert not r.info["feasible"]
                np.testing.assert_array_equal(r.P, ei.P)
                np.testing.assert_array_equal(r.x, ei.x)


@pytest.mark.parametrize("n", [5, 6])
def test_pc_handles_dimensions_up_to_six(n):
    size = 6
    Pa, Pb = random_spd(n, (size,), seed=n), random_spd(n, (size,), seed=n + 50)
    g = np.random.default_rng(n)
    xa, xb = 0.3 * g.standard_normal((size, n)), 0.3 * g.standard_normal((size, n))
    r = pc_ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean="as-printed")
    info = r.info
    ok = info["feasible"]
    assert ok.sum() >= size - 1 and np.all(info["converged"][ok])
    np.testing.assert_allclose(info["psi"][ok], info["threshold"][ok], rtol=1e-6)
    assert np.all(info["kkt_residual"][ok] < 1e-4)
    ei = ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean="as-printed")
    assert np.all(np.linalg.det(r.P) <= np.linalg.det(ei.P))


@given(pairs, st.lists(st.floats(-2, 2, allow_nan=False), min_size=8, max_size=8),
       st.sampled_from(["as-printed", "sijs-lazar"]), st.sampled_from([0.05, 0.01, 0.3]))
def test_pc_properties(Ps, values, mutual_mean, alpha):
    Pa, Pb = Ps
    n = Pa.shape[0]
    xa, xb = np.array(values[:n]), np.array(values[4:4 + n])
    pc = pc_ellipsoidal_intersection(xa, Pa, xb, Pb, alpha=alpha, mutual_mean=mutual_mean)
    ei = ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean=mutual_mean)
    info = pc.info
    for value in (pc.x, pc.P, pc.gains):
        assert np.all(np.isfinite(value))
    scale = max(np.abs(Pa).max(), np.abs(Pb).max())
    assert np.linalg.eigvalsh(info["common_P"] - ei.info["common_P"]).min() >= -1e-9 * scale
    assert np.linalg.det(pc.P) <= np.linalg.det(ei.P) * (1 + 1e-9)
    np.testing.assert_allclose(pc.gains[0] @ xa + pc.gains[1] @ xb, pc.x,
                               atol=1e-7 * (1 + np.abs(pc.x).max()))
    if info["active"] and info["feasible"]:
        assert info["psi"] <= info["threshold"] * (1 + 1e-6)
    if not (info["active"] and info["feasible"]):
        np.testing.assert_array_equal(pc.P, ei.P)


# ----------------------------------------------------------------- argument forms, fuse
def test_argument_forms_agree():
    check_argument_forms(pc_ellipsoidal_intersection)
    check_argument_forms(pc_ellipsoidal_intersection, alpha=0.01, mutual_mean="as-printed")
    check_argument_forms(pc_ellipsoidal_intersection, mutual_mean="as-printed", eps=0.01,
                         regularizer="covariance", tol=1e-6, max_iter=50)


def test_argument_form_errors():
    check_argument_form_errors(pc_ellipsoidal_intersection, "alpha")


def test_fuse_passes_tol_and_max_iter():
    xa, Pa, xb, Pb = setup_problem(3, 3)
    both = [(xa, Pa), (xb, Pb)]
    options = {"mutual_mean": "as-printed"}
    default = fuse(both, method="pcei", **options)
    assert default.info["solver"] == "interior-point" and default.info["converged"]
    assert default.info["duality_gap"] <= 1e-9
    loose = fuse(both, method="pcei", tol=1e-3, **options)
    direct = pc_ellipsoidal_intersection(xa, Pa, xb, Pb, tol=1e-3, **options)
    np.testing.assert_allclose(loose.P, direct.P, rtol=1e-13)  # (forms agree to rounding)
    assert loose.info["converged"] and 1e-9 < loose.info["duality_gap"] <= 1e-3
    assert loose.info["iterations"] < default.info["iterations"]
    # too few Newton iterations: not converged, and the result is EI's (flagged)
    short = fuse(both, method="pcei", max_iter=1, **options)
    assert short.info["iterations"] == 1 and not short.info["converged"]
    ei = ellipsoidal_intersection(xa, Pa, xb, Pb, **options)
    np.testing.assert_allclose(short.P, ei.P, rtol=1e-13)
    with pytest.raises(ValueError, match="max_iter"):
        fuse(both, method="pcei", max_iter=0)
    with pytest.raises(ValueError, match="tol"):
        fuse(both, method="pcei", tol=2.0)
    with pytest.raises(TypeError, match="does not accept"):
        fuse(both, method="pcei", rho=0.5)


# ----------------------------------------------------------------- batching and conventions
@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_batched_equals_per_item(mutual_mean):
    check_batched_equals_per_item(pc_ellipsoidal_intersection, mutual_mean)


def test_batch_axes_broadcast_and_column_vectors_come_back_as_columns():
    check_broadcast_and_columns(pc_ellipsoidal_intersection)


def test_inputs_are_not_mutated():
    check_inputs_are_not_mutated(pc_ellipsoidal_intersection, mutual_mean="as-printed")
    check_inputs_are_not_mutated(pc_ellipsoidal_intersection)


def test_registry_and_filters():
    check_registry_and_filters("pcei", pc_ellipsoidal_intersection)


def test_demo_rows_run_batched():
    import io

    from cifilter.cli.demo import run_demo

    rows = run_demo(runs=2, steps=20, methods=["pcei"], out=io.StringIO())
    for row in rows[2:]:
        assert "error" not in row and np.isfinite(row["mean_nees"])


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
@pytest.mark.parametrize("relative", [1e-16, 1e-13, 1e-10, 1e-7, 1e-4])
def test_near_equal_covariances_give_finite_results(mutual_mean, relative):
    P = random_spd(2, seed=8)
    Pb = P + relative * random_spd(2, seed=9)
    check_near_equal_covariances_are_finite(pc_ellipsoidal_intersection, P, Pb,
                                            np.array([1.0, 2.0]), np.array([0.0, -1.0]),
                                            mutual_mean)


# ----------------------------------------------------------------- bad input
@pytest.mark.parametrize("args, kwargs, error, message", BAD_INPUT)
def test_bad_input_is_named(args, kwargs, error, message):
    with pytest.raises(error, match=message):
        pc_ellipsoidal_intersection(*args, **kwargs)


@pytest.mark.parametrize("kwargs, error, message", [
    ({"alpha": 0.0}, ValueError, "alpha"),
    ({"alpha": 1.0}, ValueError, "alpha"),
    ({"alpha": -0.1}, ValueError, "alpha"),
    ({"alpha": float("nan")}, ValueError, "alpha"),
    ({"alpha": "0.05"}, TypeError, "alpha"),
    ({"tol": 0.0}, ValueError, "tol"),
    ({"max_iter": 0}, ValueError, "max_iter"),
])
def test_bad_pc_options_are_named(kwargs, error, message):
    with pytest.raises(error, match=message):
        pc_ellipsoidal_intersection(np.zeros(2), np.eye(2), np.ones(2), np.eye(2), **kwargs)


# ----------------------------------------------------------------- ill-conditioned inputs
# PC-EI starts from EI's common covariance and returns EI where the constraint holds, so
# it inherited EI's indefinite covariances (issue 9, item 3).
def test_issue_reproducer_is_positive_definite_and_accurate():
    check_issue_reproducer(pc_ellipsoidal_intersection)


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_random_pairs_at_condition_1e9_are_all_positive_definite(mutual_mean):
    check_random_pairs_at_condition_1e9(pc_ellipsoidal_intersection, mutual_mean)


ill_pairs = st.integers(1, 5).flatmap(lambda n: st.booleans().flatmap(
    lambda common: ill_conditioned_sets(2, n, common_scale=common)))
unit = st.floats(-2.0, 2.0, allow_nan=False)


def pc_or_contract_error(xa, Pa, xb, Pb, **options):
    try:
        return pc_ellipsoidal_intersection(xa, Pa, xb, Pb, **options)
    except IllConditionedError:
        assert not within_contract(Pa, Pb)
        return None


def assert_honest_flags(r):
    info = r.info
    if info["active"] and info["feasible"] and info["converged"]:
        assert info["psi"] <= info["threshold"] * (1 + 1e-6)


@settings(max_examples=60)
@given(ill_pairs, st.lists(unit, min_size=10, max_size=10),
       st.sampled_from(["as-printed", "sijs-lazar"]),
       st.sampled_from([("information", 1e-8), ("covariance", 0.01)]))
def test_pc_is_positive_definite_on_ill_conditioned_pairs(Ps, values, mutual_mean,
                                                          regularization):
    Pa, Pb = Ps
    xa, xb = means_of_their_scale(values, Pa, Pb)
    regularizer, eps = regularization
    r = pc_or_contract_error(xa, Pa, xb, Pb, mutual_mean=mutual_mean,
                             regularizer=regularizer, eps=eps)
    if r is None:
        return
    assert_valid_fusion(r, Pa, Pb)
    assert_honest_flags(r)
    np.testing.assert_allclose(r.gains[0] @ xa + r.gains[1] @ xb, r.x, rtol=1e-9,
                               atol=1e-9 * (np.abs(xa).max() + np.abs(xb).max()))
    if regularizer == "information" and resolved_pair(Pa, Pb):
        # a larger common covariance than EI's: P <= P_EI <= Pa, Pb (in P's metric)
        L = np.linalg.cholesky(r.P)
        for Q in (Pa, Pb):
            X = np.linalg.solve(L, np.linalg.solve(L, Q).T)
            assert np.linalg.eigvalsh(0.5 * (X + X.T))[0] >= 1 - METRIC_TOL


@settings(max_examples=40)
@given(ill_pairs, st.lists(unit, min_size=5, max_size=5))
def test_pc_with_equal_covariances_is_positive_definite_and_symmetric(Ps, values):
    """Ties everywhere (the closed form): the common part grows along the mean difference."""
    Pa = Ps[0]
    n = Pa.shape[0]
    e = np.array(values[:n]) * np.sqrt(np.diag(Pa))
    r = pc_or_contract_error(e, Pa, -e, Pa.copy())
    if r is None:
        return
    assert_valid_fusion(r, Pa, Pa)
    swapped = pc_ellipsoidal_intersection(-e, Pa, e, Pa.copy())
    assert metric_difference(r.P, swapped.P) <= 1e-8


@settings(max_examples=25)
@given(st.integers(1, 4).flatmap(lambda n: st.lists(ill_conditioned_sets(2, n), min_size=3,
                                                     max_size=3)),
       st.sampled_from(["as-printed", "sijs-lazar"]))
def test_pc_batched_ill_conditioned_pairs_are_positive_definite(pairs_, mutual_mean):
    Pa = np.stack([p[0] for p in pairs_])
    Pb = np.stack([p[1] for p in pairs_])
    n = Pa.shape[-1]
    xa = np.sqrt(np.diagonal(Pa, axis1=-2, axis2=-1))
    xb = -np.sqrt(np.diagonal(Pb, axis1=-2, axis2=-1))
    r = pc_or_contract_error(xa, Pa, xb, Pb, mutual_mean=mutual_mean)
    if r is None:
        return
    assert r.P.shape == (3, n, n)
    assert_valid_fusion(r, Pa, Pb)


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_pc_returns_ei_where_the_constraint_holds_on_ill_conditioned_pairs(mutual_mean):
    """Equal means pass the test: PC-EI is EI exactly, also at condition number 1e11."""
    rng = np.random.default_rng(7)
    Pa = np.stack([issue_pair(rng, 3, 1e11) for _ in range(20)])
    Pb = np.stack([issue_pair(rng, 3, 1e11) for _ in range(20)])
    x = rng.standard_normal((20, 3))
    ei = ellipsoidal_intersection(x, Pa, x, Pb, mutual_mean=mutual_mean)
    pc = pc_ellipsoidal_intersection(x, Pa, x, Pb, mutual_mean=mutual_mean)
    assert np.all(pc.info["solver"] == "ei")
    np.testing.assert_array_equal(pc.P, ei.P)
    assert_valid_fusion(pc, Pa, Pb)
