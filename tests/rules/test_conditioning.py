"""The conditioning contract of the conservative rules (CI and partial-correlation CI).

For inputs whose condition numbers are at most 1e12, at any scale in 1e-12..1e12, the
fused ``P`` is finite, exactly symmetric and positive definite, the gains sum to the
identity, and ``P`` dominates the error covariance of the returned gains for every
admissible joint covariance: checked against the inputs at 50 digits in every direction
(tests/worst_case.py), not only at random joints. Partial CI meets the suite's default
tolerance ``64 n N eps ||P||``; CI is checked at the tolerance its contract states,
``cond * eps`` more (docs/conventions.rst: its bound is assembled from Cholesky factors,
whose rounding its large gains amplify). Optimal weights are checked against a 50-digit
reference. Each item of issue 9 that concerns these rules has a regression test here.
"""

import mpmath
import numpy as np
import pytest
from helpers import fused_bound_tolerance
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets
from worst_case import assert_bound_holds, assert_unbiased, worst_violation

from cifilter import ci_weights, covariance_intersection, fuse, partial_ci
from cifilter._numerics.criteria import GAP_FLOOR_SAFETY

criteria = st.sampled_from(["trace", "det"])
EPS = np.finfo(float).eps


def assert_valid_covariance(P):
    assert np.all(np.isfinite(P))
    np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    np.linalg.cholesky(P)  # raises if not positive definite


def zeros_like_means(Ps):
    return [np.zeros(P.shape[-1]) for P in Ps]


def ci_tolerance(Ps):
    """CI's contract: ``64 n N eps`` plus ``cond * eps`` relative to ``||P||``."""
    return fused_bound_tolerance(np.asarray(Ps))


# ----------------------------------------------------------------- conservativeness
@pytest.mark.usefixtures("ci_backend")
@settings(max_examples=60)
@given(st.integers(2, 5).flatmap(lambda count: st.integers(1, 4).flatmap(
    lambda n: st.tuples(ill_conditioned_sets(count, n), st.booleans()))), criteria)
def test_ci_bound_holds_in_the_worst_direction(sets, criterion):
    Ps, _ = sets
    r = covariance_intersection(zeros_like_means(Ps), Ps, criterion=criterion)
    assert_valid_covariance(r.P)
    assert_unbiased(r.gains)
    assert_bound_holds(r.P, r.gains, Ps, tol=ci_tolerance(Ps))
    assert_converged_or_honest(r.info, Ps, P=r.P)


def floor_bound(Ps, P):
    """The size a rounding floor may have: ``64 n^3 eps (cond(P) + max_i cond(P_i))``, the
    conditions of the fused covariance and of the inputs (docs/conventions.rst: the floor is
    of order ``kappa eps``; measured at most a few hundred ``eps kappa``)."""
    n = P.shape[-1]
    kappa = np.linalg.cond(P) + max(np.linalg.cond(Pi) for Pi in Ps)
    return 64.0 * n**3 * EPS * kappa


def assert_converged_or_honest(info, Ps, tol=1e-9, P=None):
    """Converged means optimal to the precision the inputs allow (docs/conventions.rst):
    a certified gap, rounding included, of at most ``max(1e-9, 2 gap_floor)``, with a
    floor of order ``kappa eps`` (:func:`floor_bound`; rules without a floor: 0), and every
    set whose condition numbers are at most 1e8 converges. Beyond that a set that is also
    nearly tied may stop at the iteration limit: it must then say so, with a finite
    certified gap above what converged allows. The gap is never 0.0 where there is a
    rounding floor (it bounds the true excess)."""
    gap = float(info["gap"])
    floor = float(info.get("gap_floor", 0.0))
    assert np.isfinite(gap) and gap >= 0.0
    assert np.isfinite(floor) and floor >= 0.0
    if floor > 0.0:
        assert gap > 0.0
    if P is not None and "gap_floor" in info:
        assert floor <= floor_bound(Ps, P), (floor, floor_bound(Ps, P))
    allowed = max(tol, GAP_FLOOR_SAFETY * floor)
    if info["converged"]:
        assert gap <= allowed
    else:
        assert gap > min(tol, allowed)
        assert max(np.linalg.cond(P) for P in Ps) > 1e8, gap


@pytest.mark.usefixtures("ci_backend")
@settings(max_examples=40)
@given(st.integers(2, 5).flatmap(lambda count: st.tuples(
    ill_conditioned_sets(count, 3, common_scale=False),
    st.sampled_from(["fast", "improved-fast", "det-ratio", "fixed"]),
    st.integers(0, 2**32 - 1))))
def test_ci_bound_holds_for_fast_and_given_weights_at_any_scales(args):
    Ps, rule, seed = args
    omega = np.random.default_rng(seed).dirichlet(np.ones(len(Ps))) if rule == "fixed" else rule
    r = covariance_intersection(zeros_like_means(Ps), Ps, omega=omega)
    assert_valid_covariance(r.P)
    assert_unbiased(r.gains)
    assert_bound_holds(r.P, r.gains, Ps, tol=ci_tolerance(Ps))


@settings(max_examples=60)
@given(st.integers(2, 5).flatmap(lambda count: st.tuples(
    st.booleans().flatmap(lambda common: ill_conditioned_sets(count, 3, common_scale=common)),
    st.floats(0.0, 1.0))))
def test_partial_ci_bound_holds_in_the_worst_direction(args):
    Ps, rho = args
    r = partial_ci(zeros_like_means(Ps), Ps, rho)
    assert_valid_covariance(r.P)
    assert_unbiased(r.gains)
    # for two estimates the bound used is sqrt(rho_1 rho_2) = rho; the default tolerance
    # 64 n N eps ||P|| (issue 21, item 2: it was exceeded by up to 1.6e5 times that)
    assert_bound_holds(r.P, r.gains, Ps, rho=rho)
    assert_converged_or_honest(r.info, Ps, tol=1e-10)


def _spd_at_scale(rng, n, cond, scale):
    """A rotated log-spaced spectrum from ``scale`` to ``scale * cond``."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    P = Q @ np.diag(scale * np.logspace(0, np.log10(cond), n)) @ Q.T
    return (P + P.T) / 2


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.9])
def test_issue_21_item_2_partial_ci_meets_the_tolerance_against_the_inputs(rho):
    """Condition numbers 1e9, every covariance at its own scale in 1e-6..1e6, N = 2..4.

    With P assembled from the Cholesky factors, 41 of 60 such sets (rho = 0) exceeded
    64 n N eps ||P|| against the true P_i, by up to 1.6e5 times that (20 to 31 of 60 at
    rho = 0.001..0.9); here every one is within it.
    """
    for seed in range(12):
        rng = np.random.default_rng(seed)
        count, n = 2 + seed % 3, 3 + (seed // 3) % 2
        Ps = [_spd_at_scale(rng, n, 1e9, 10 ** rng.uniform(-6, 6)) for _ in range(count)]
        r = partial_ci(zeros_like_means(Ps), Ps, rho)
        assert_valid_covariance(r.P)
        assert_bound_holds(r.P, r.gains, Ps, rho=rho, what=f"P (seed {seed})")


def test_worst_direction_check_detects_a_bound_that_is_too_small():
    """The check can fail, in a direction that is not an eigenvector of P.

    Example 2 of Wu, Cai & Fu: P = 1.6 I, K_1 = diag(0.8, 0.2), K_2 = diag(0.2, 0.8). Along
    e_1 the worst error variance is (0.8 * 1 + 0.2 * 2)^2 = 1.44, so 0.88 P (1.408) is no
    bound. Along v = (1, 1) / sqrt(2), s_1^2 = (0.64 * 1 + 0.04 * 4) / 2 = 0.4 = s_2^2 and
    the worst variance is (2 sqrt(0.4))^2 = 1.6 = v^T P v: CI's bound is tight there, so
    0.91 P (which the check of the Cholesky factors passed: it only looked at e_1, e_2
    and where its ascent went from them) and even (1 - 1e-9) P are not bounds.
    """
    Ps = [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])]
    r = covariance_intersection(zeros_like_means(Ps), Ps)
    with pytest.raises(AssertionError, match="not a bound"):
        assert_bound_holds(0.88 * r.P, r.gains, Ps)
    for factor in (0.91, 1.0 - 1e-9):
        excess, v = worst_violation(factor * r.P, r.gains, Ps)
        assert excess == pytest.approx((1.0 - factor) * 1.6 - 256 * EPS * 1.6, abs=64 * EPS)
        assert abs(v[0]) == pytest.approx(abs(v[1]), rel=1e-6)  # (1, +-1) / sqrt(2)
        with pytest.raises(AssertionError, match="not a bound"):
            assert_bound_holds(factor * r.P, r.gains, Ps)
    assert_bound_holds(r.P, r.gains, Ps)
    # and the naive fusion's covariance is not a bound under arbitrary correlation
    naive = fuse([(np.zeros(2), P) for P in Ps], method="naive")
    with pytest.raises(AssertionError, match="not a bound"):
        assert_bound_holds(naive.P, naive.gains, Ps)
    assert_bound_holds(naive.P, naive.gains, Ps, rho=0.0)


def test_worst_direction_check_with_a_correlation_bound_is_exact():
    """rho = 1/2 on Example 2's inputs: delta = (1/2, 1/2), w_i = 2/3, P = 1.2 I and the
    gains are CI's. Along (1, 1) / sqrt(2), worst = (1 - rho) 0.8 + rho 1.6 = 1.2: tight,
    so 0.999 P fails there (a witness), while P is certified by t = delta."""
    Ps = [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])]
    r = partial_ci(zeros_like_means(Ps), Ps, 0.5)
    np.testing.assert_allclose(r.P, 1.2 * np.eye(2), rtol=1e-15)
    assert_bound_holds(r.P, r.gains, Ps, rho=0.5)
    excess, v = worst_violation(0.999 * r.P, r.gains, Ps, rho=0.5)
    assert excess == pytest.approx(0.0012 - 256 * EPS * 1.2, abs=64 * EPS)
    assert abs(v[0]) == pytest.approx(abs(v[1]), rel=1e-6)  # (1, +-1) / sqrt(2)
    # rho = 0: the check is one eigenvalue; P - 1e-12 I fails by exactly 1e-12 (P = 0.8 I)
    naive = partial_ci(zeros_like_means(Ps), Ps, 0.0)
    excess, _ = worst_violation(naive.P - 1e-12 * np.eye(2), naive.gains, Ps, rho=0.0)
    assert excess == pytest.approx(1e-12 - 256 * EPS * 0.8, abs=64 * EPS)


# ----------------------------------------------------------------- optimality
def _rounding_level(Ps):
    """``kappa eps``: the contract's accuracy, kappa the largest input condition number."""
    return max(np.linalg.cond(P) for P in Ps) * np.finfo(float).eps


def _mp_gap(Ps, weights, criterion, rho=None):
    """Relative (trace) or log-det (det) certified gap at ``weights``, in 50 digits.

    For partial CI (``rho`` given) ``weights`` are ``delta`` and the trace criterion's
    gradient goes through eq. (24).
    """
    with mpmath.workdps(50):
        informations = [mpmath.matrix(P.tolist()) ** -1 for P in Ps]
        if rho is None:
            w = [mpmath.mpf(float(v)) for v in weights]
            first = [mpmath.mpf(1)] * len(Ps)
        else:
            delta = [mpmath.mpf(float(v)) for v in weights]
            rho_ = mpmath.mpf(float(rho))
            w = [d / (rho_ + (1 - rho_) * d) if rho_ > 0 else mpmath.mpf(1) for d in delta]
            first = [rho_ / (rho_ + (1 - rho_) * d) ** 2 if rho_ > 0 else mpmath.mpf(0)
                     for d in delta]
            weights = delta
        J = sum((wi * I for wi, I in zip(w[1:], informations[1:])), w[0] * informations[0])
        P = J ** -1
        n = P.rows
        trace = lambda M: sum(M[i, i] for i in range(n))  # noqa: E731
        if criterion == "det":
            g = [trace(P * I) for I in informations]
            scale = 1
        else:
            g = [f * trace(P * I * P) for f, I in zip(first, informations)]
            scale = trace(P)
        along = sum(mpmath.mpf(float(v)) * gi for v, gi in zip(weights, g))
        return float((max(g) - along) / scale)


@pytest.mark.usefixtures("ci_backend")
@settings(max_examples=25)
@given(st.integers(2, 4).flatmap(lambda count: ill_conditioned_sets(count, 3, 1e10)), criteria)
def test_ci_weights_are_optimal_against_a_50_digit_reference(Ps, criterion):
    omega, info = ci_weights(Ps, criterion)
    assert_converged_or_honest(info, Ps)
    # the reported gap includes the rounding of the gradients it is computed from, so it
    # bounds the 50-digit Frank-Wolfe gap at the returned weights (itself a bound of the
    # true excess): the optimum is never wrong by more than it says
    assert _mp_gap(Ps, omega, criterion) <= info["gap"]


@settings(max_examples=20)
@given(st.integers(2, 4).flatmap(lambda count: ill_conditioned_sets(count, 3, 1e10)),
       st.floats(0.05, 1.0))
def test_partial_ci_delta_is_optimal_against_a_50_digit_reference(Ps, rho):
    r = partial_ci(zeros_like_means(Ps), Ps, rho)
    assert_converged_or_honest(r.info, Ps, tol=1e-10)
    assert (_mp_gap(Ps, r.info["delta"], "trace", rho)
            <= max(r.info["gap"], 1e-10) + 1e-8 + _rounding_level(Ps))


# ----------------------------------------------------------------- permutation
@pytest.mark.usefixtures("ci_backend")
@settings(max_examples=40)
@given(st.integers(2, 4).flatmap(lambda count: st.tuples(
    ill_conditioned_sets(count, 3), st.permutations(range(count)))), criteria)
def test_ci_is_permutation_invariant_for_ill_conditioned_inputs(args, criterion):
    Ps, order = args
    r = covariance_intersection(zeros_like_means(Ps), Ps, criterion=criterion)
    q = covariance_intersection(zeros_like_means(Ps), [Ps[i] for i in order],
                                criterion=criterion)
    # the criterion is the same (the optimum is unique in value, not always in weights)
    value = "log_value" if criterion == "det" else "value"
    assert q.info[value] == pytest.approx(r.info[value], rel=1e-8, abs=1e-8)


# ----------------------------------------------------------------- issue 9 regressions
def _spd(rng, n, cond):
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    P = (Q * np.logspace(0, np.log10(cond), n)) @ Q.T
    return (P + P.T) / 2


@pytest.mark.usefixtures("ci_backend")
def test_item_1_two_estimate_ci_is_conservative_at_condition_1e8():
    rng = np.random.default_rng(29)
    P1, P2 = _spd(rng, 3, 1e8), _spd(rng, 3, 1e8)
    r = covariance_intersection([np.zeros(3)] * 2, [P1, P2])
    v = np.array([0.33579355619, 0.84489766623, 0.41640199473])  # the reported direction
    s = [np.linalg.norm(np.linalg.cholesky(P).T @ K.T @ v) for K, P in zip(r.gains, [P1, P2])]
    assert v @ r.P @ v >= sum(s) ** 2 * (1 - 1e-9)  # was 0.337 against 1.008
    assert_bound_holds(r.P, r.gains, [P1, P2], tol=ci_tolerance([P1, P2]))


@pytest.mark.usefixtures("ci_backend")
@pytest.mark.parametrize("cond", [1e7, 1e8, 1e9, 1e10, 1e11, 1e12])
def test_item_1_conservative_and_positive_definite_over_the_condition_range(cond):
    rng = np.random.default_rng(int(np.log10(cond)))
    for _ in range(20):
        Ps = [_spd(rng, 4, cond), _spd(rng, 4, cond)]
        r = covariance_intersection([np.zeros(4)] * 2, Ps)
        assert_valid_covariance(r.P)
        assert_bound_holds(r.P, r.gains, Ps, tol=ci_tolerance(Ps))


@pytest.mark.usefixtures("ci_backend")
def test_item_2_det_optimum_at_condition_1e10_is_not_a_wrong_vertex():
    rng = np.random.default_rng(0)
    Ps = [_spd(rng, 4, 1e10), _spd(rng, 4, 1e10)]
    r = covariance_intersection([np.zeros(4)] * 2, Ps, criterion="det")
    half = covariance_intersection([np.zeros(4)] * 2, Ps, criterion="det", omega=0.5)
    assert r.info["converged"]
    assert r.info["log_value"] <= half.info["log_value"] + 1e-12  # was 2.6e11 times larger
    assert _mp_gap(Ps, r.omega, "det") <= 1e-8 + _rounding_level(Ps)


@pytest.mark.usefixtures("ci_backend")
def test_item_2_graded_case_finds_the_vertex():
    P1 = np.array([[1e18, 1e8], [1e8, 1.0]])
    r = covariance_intersection([[1.0, 0.0], [0.0, 1.0]], [P1, np.diag([4.0, 1.0])])
    np.testing.assert_array_equal(r.omega, [0.0, 1.0])  # was trace 1.4e14
    assert np.trace(r.P) == pytest.approx(5.0, rel=1e-12) and r.info["converged"]


@pytest.mark.usefixtures("ci_backend")
def test_item_6_nearly_tied_inputs_converge_at_once():
    Ps = [np.eye(2), np.eye(2), (1 + 1e-5) * np.eye(2)]
    for criterion in ("trace", "det"):
        r = covariance_intersection([np.zeros(2)] * 3, Ps, criterion=criterion)
        assert r.info["converged"] and r.info["iterations"] <= 5  # was 200, unconverged
        # every split of the weight between the two identical estimates is optimal: the
        # solver's is set by rounding in its Hessian (1.3e-6 apart with the Gram form of
        # trace_curvature, 2.8e-7 with the pairwise form it replaced)
        assert r.omega[2] == 0.0 and r.omega[0] == pytest.approx(r.omega[1], abs=1e-5)
    # one such problem in a batch does not hold the others back
    rng = np.random.default_rng(1)
    batch = np.array([[_spd(rng, 2, 10.0) for _ in range(3)] for _ in range(50)] + [Ps])
    r = covariance_intersection(np.zeros(batch.shape[:-1]), batch)
    assert r.info["converged"].all() and r.info["iterations"].max() <= 10


@pytest.mark.parametrize("count", [2, 3, 4])
def test_item_7_partial_ci_default_converges_and_ignores_the_batch(count):
    rng = np.random.default_rng(count)
    Ps = np.array([[_spd(rng, 3, 10 ** rng.uniform(0, 3)) for _ in range(count)]
                   for _ in range(60)])
    rho = rng.uniform(0.0, 1.0, size=(60, 1))
    xs = np.zeros(Ps.shape[:-1])
    r = partial_ci(xs, Ps, rho)
    assert r.info["solver"] == "newton"
    assert r.info["converged"].all() and (r.info["gap"] <= 1e-10).all()
    alone = [int(partial_ci(xs[k], Ps[k], rho[k]).info["iterations"]) for k in range(60)]
    np.testing.assert_array_equal(r.info["iterations"], alone)  # no batch composition effect


def test_item_7_the_paper_algorithm_stays_available():
    Ps = [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])]
    r = partial_ci([np.zeros(2)] * 2, Ps, 0.5, solver="alternating")
    assert r.info["solver"] == "alternating" and np.trace(r.P) == pytest.approx(2.4)


@pytest.mark.usefixtures("ci_backend")
def test_item_11_det_value_reports_its_logarithm_at_huge_scales():
    # omega = 1/2: P = 1.6 c I and det P = 2.56 c^2, log det P = log 2.56 + 2 log c
    for c in (1e150, 1e200):
        Ps = [c * np.diag([1.0, 4.0]), c * np.diag([4.0, 1.0])]
        r = covariance_intersection([np.zeros(2)] * 2, Ps, criterion="det")
        expected = np.log(2.56) + 2 * np.log(c)
        assert r.info["log_value"] == pytest.approx(expected, rel=1e-14)
        if c < 1e154:
            assert r.info["value"] == pytest.approx(2.56 * c * c, rel=1e-13)
        else:
            assert r.info["value"] == np.inf
