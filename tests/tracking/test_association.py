"""The association distances and the gated assignment of :mod:`cifilter.tracking`.

The CI distance ``s = max_w d^T (A / w + B / (1 - w))^-1 d`` must be at most the true
normalised distance ``d^T S^-1 d`` for every admissible joint (checked at 50 digits from the
inputs), equal to it for the worst joint (built from the returned ``w``, so the maximum is
really found), and a gate on it must pass a true pair at least as often as the gate
probability (Monte Carlo at the worst correlation). Derivation:
``docs/methods/track_association.rst``.
"""

import mpmath
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2
from strategies import ill_conditioned_spd, joint_covariances, spd_matrices

from cifilter.tracking import ci_distance, gated_assignment, naive_distance

EPS = np.finfo(float).eps
DIGITS = 50


def _mp(A):
    return mpmath.matrix(np.asarray(A, dtype=float).tolist())


def true_distance(d, S):
    """``d^T S^-1 d`` at 50 digits from the float entries of ``d`` and ``S``."""
    with mpmath.workdps(DIGITS):
        dm = _mp(np.asarray(d)[:, None])
        return (dm.T * mpmath.lu_solve(_mp(S), dm))[0]


def worst_joint_distance(d, A, B, w):
    """``d^T S*^-1 d`` for the admissible joint whose cross covariance is
    ``C = -A z z^T B / (sa sb)`` with ``z = (A / w + B / (1 - w))^-1 d``, at 50 digits from
    the inputs. ``S* = A + B - C - C^T``; at the optimal ``w`` it equals the CI distance."""
    with mpmath.workdps(DIGITS):
        Am, Bm, dm = _mp(A), _mp(B), _mp(np.asarray(d)[:, None])
        wm = mpmath.mpf(float(w))
        M = Am / wm + Bm / (1 - wm)
        z = mpmath.lu_solve(M, dm)
        sa = mpmath.sqrt((z.T * Am * z)[0])
        sb = mpmath.sqrt((z.T * Bm * z)[0])
        C = -(Am * z) * (z.T * Bm) / (sa * sb)
        S = Am + Bm - C - C.T
        return (dm.T * mpmath.lu_solve(S, dm))[0]


def condition(M):
    return float(np.linalg.cond(M))


# --- hand-derived values --------------------------------------------------------------------

def test_scalar_distance_is_the_opposite_correlation_distance():
    # m = 1: f(w) = d^2 w (1 - w) / ((1 - w) a + w b), maximal at w = sqrt(a)/(sqrt(a)+sqrt(b))
    # with the value d^2 / (sqrt(a) + sqrt(b))^2 (errors of opposite sign, correlation 1)
    s, w = ci_distance(np.array([6.0]), np.array([[4.0]]), np.array([[9.0]]))
    assert s == pytest.approx(36.0 / 25.0, rel=4 * EPS)
    assert w == pytest.approx(2.0 / 5.0, rel=1e-9)


def test_commuting_covariances():
    # A = a I, B = b I: the same as m scalar problems with one w: |d|^2 / (sqrt a + sqrt b)^2
    d = np.array([1.0, -2.0, 2.0])
    s, w = ci_distance(d, 0.25 * np.eye(3), 4.0 * np.eye(3))
    assert s == pytest.approx(9.0 / 2.5**2, rel=8 * EPS)
    assert w == pytest.approx(0.5 / 2.5, rel=1e-9)


def test_diagonal_covariances_hand_derived():
    # A = diag(1, 4), B = diag(4, 1), d = (1, 1): f(w) = 2 w (1 - w) / (1 + 3 w (1 - w))...
    # by symmetry w = 1/2, f = (1/2) / (1 + 3/4) * 2 / 2 ... = 2 * 0.25 / (2.5 / 2)
    # directly: M = A/w + B/(1-w) = diag(10, 10) at w = 1/2, s = 2 / 10
    s, w = ci_distance(np.array([1.0, 1.0]), np.diag([1.0, 4.0]), np.diag([4.0, 1.0]))
    assert s == pytest.approx(0.2, rel=8 * EPS)
    assert w == pytest.approx(0.5, abs=1e-9)


def test_naive_distance_hand_derived():
    assert float(naive_distance(np.array([3.0, 4.0]), np.eye(2), np.diag([1.0, 7.0]))) \
        == pytest.approx(9.0 / 2.0 + 16.0 / 8.0, rel=4 * EPS)


def test_batched_equals_one_by_one():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(6, 3, 3))
    Y = rng.normal(size=(6, 3, 3))
    A = X @ X.transpose(0, 2, 1) + 0.1 * np.eye(3)
    B = Y @ Y.transpose(0, 2, 1) + 0.1 * np.eye(3)
    d = rng.normal(size=(6, 3))
    s, w = ci_distance(d.reshape(2, 3, 3), A.reshape(2, 3, 3, 3), B.reshape(2, 3, 3, 3))
    assert s.shape == w.shape == (2, 3)
    for i in range(6):
        si, wi = ci_distance(d[i], A[i], B[i])
        assert s.reshape(-1)[i] == si and w.reshape(-1)[i] == wi


def test_threshold_only_cuts_pairs_that_are_outside():
    rng = np.random.default_rng(5)
    d = rng.normal(size=(50, 2)) * 4.0
    A = np.broadcast_to(np.diag([1.0, 2.0]), (50, 2, 2))
    B = np.broadcast_to(np.array([[2.0, 0.5], [0.5, 1.0]]), (50, 2, 2))
    exact, _ = ci_distance(d, A, B)
    cut, _ = ci_distance(d, A, B, threshold=3.0)
    inside = exact <= 3.0
    assert inside.any() and (~inside).any()
    np.testing.assert_array_equal(cut[inside], exact[inside])
    assert np.all(cut[~inside] > 3.0) and np.all(cut[~inside] <= exact[~inside])


def test_inputs_are_not_modified():
    d, A, B = np.array([1.0, 2.0]), np.diag([1.0, 2.0]), np.array([[2.0, 0.3], [0.3, 1.0]])
    copies = [a.copy() for a in (d, A, B)]
    ci_distance(d, A, B)
    naive_distance(d, A, B)
    for a, c in zip((d, A, B), copies):
        np.testing.assert_array_equal(a, c)


@pytest.mark.parametrize("args, match", [
    ((np.ones(2), np.eye(3), np.eye(2)), "A must have shape"),
    ((np.ones(2), np.eye(2), np.eye(3)), "B must have shape"),
    ((np.array([np.nan, 1.0]), np.eye(2), np.eye(2)), "d contains non-finite"),
    ((np.ones(2), np.diag([1.0, -1.0]), np.eye(2)), "A is not positive definite"),
    ((np.ones(2), np.eye(2), np.diag([np.inf, 1.0])), "B"),
])
def test_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        ci_distance(*args)
    with pytest.raises(ValueError, match=match):
        naive_distance(*args)


def test_non_numeric_input():
    with pytest.raises(TypeError, match="d must be a numeric"):
        ci_distance(np.array(["a", "b"]), np.eye(2), np.eye(2))


# --- the bound over every correlation (50 digits, from the inputs) -----------------------------

@st.composite
def problems(draw, ill=True):
    m = draw(st.integers(1, 4))
    if ill:
        A = draw(ill_conditioned_spd(m))
        B = draw(ill_conditioned_spd(m))
    else:
        A, B = draw(spd_matrices(m)), draw(spd_matrices(m))
    unit = np.array(draw(st.lists(st.integers(-30, 30), min_size=m, max_size=m))) / 10.0
    if not np.any(unit):
        unit[0] = 1.0
    # a difference of the size of the covariances' spread along a random mix of both
    scale = np.sqrt(np.diag(A) + np.diag(B))
    return unit * scale, A, B


def _tolerance(A, B, w):
    """The rounding of a Cholesky-based quadratic form: a few ``m eps`` times the condition
    number of the factorised matrix ``(1 - w) A + w B``."""
    m = A.shape[0]
    return 16.0 * m * EPS * condition((1.0 - w) * A + w * B)


@given(problems(), st.data())
def test_distance_is_at_most_the_true_distance_for_any_admissible_joint(problem, data):
    d, A, B = problem
    joint = data.draw(joint_covariances([A, B]))
    m = A.shape[0]
    # the marginals are the joint's own blocks (its construction rounds them)
    A = 0.5 * (joint[:m, :m] + joint[:m, :m].T)
    B = 0.5 * (joint[m:, m:] + joint[m:, m:].T)
    C = joint[:m, m:]
    s, w = ci_distance(d, A, B)
    with mpmath.workdps(DIGITS):
        Jm = _mp(joint)
        S = mpmath.matrix(m, m)
        for i in range(m):
            for j in range(m):
                # Cov(v - u) = B + A - C - C^T, from the joint's entries at 50 digits
                S[i, j] = (Jm[i, j] + Jm[j, i]) / 2 + (Jm[m + i, m + j] + Jm[m + j, m + i]) / 2 \
                    - Jm[i, m + j] - Jm[j, m + i]
        dm = _mp(d[:, None])
        try:
            truth = (dm.T * mpmath.lu_solve(S, dm))[0]
        except ZeroDivisionError:  # a singular joint difference: infinite true distance
            return
    del C
    if truth <= 0:  # S singular to 50 digits along d's complement: nothing to compare
        return
    assert s <= float(truth) * (1.0 + _tolerance(A, B, float(w)))


@given(problems())
def test_distance_is_reached_by_the_worst_joint(problem):
    d, A, B = problem
    s, w = ci_distance(d, A, B)
    worst = float(worst_joint_distance(d, A, B, w))
    tol = _tolerance(A, B, float(w))
    # at most the worst admissible joint's distance (a lower bound) and equal to it (the
    # maximum over w is found): the gate is exactly as loose as the unknown correlation needs
    assert s <= worst * (1.0 + tol)
    assert s >= worst * (1.0 - 1e-6 - tol)


@given(problems(ill=False))
def test_distance_is_between_the_one_sided_bounds(problem):
    # f(w) <= w d^T A^-1 d and <= (1 - w) d^T B^-1 d, so s <= a b / (a + b); and s >= f at
    # any w, e.g. at w = 1/2
    d, A, B = problem
    s, _ = ci_distance(d, A, B)
    a = float(d @ np.linalg.solve(A, d))
    b = float(d @ np.linalg.solve(B, d))
    assert s <= a * b / (a + b) * (1 + 1e-9)
    half = float(d @ np.linalg.solve(2 * A + 2 * B, d))
    assert s >= half * (1 - 1e-12)


# --- the gate passes a true pair at least as often as its probability -----------------------

def _pass_rate(statistic, A, B, rng, samples, gate):
    """Monte Carlo: errors u ~ N(0, A), v = -B^(1/2) A^(-1/2) u (perfect opposite
    correlation, the worst case for the gate), d = v - u; the rate of d inside the gate."""
    m = A.shape[0]
    ra, rb = _sqrtm(A), _sqrtm(B)
    eps = rng.standard_normal((samples, m))
    d = -(eps @ (ra + rb).T)  # v - u with u = ra eps, v = -rb eps
    if statistic == "ci":
        s, _ = ci_distance(d, A, B)
    else:
        s = naive_distance(d, A, B)
    return float(np.mean(s <= chi2.ppf(gate, m)))


def _sqrtm(A):
    values, vectors = np.linalg.eigh(A)
    return (vectors * np.sqrt(values)) @ vectors.T


@pytest.mark.parametrize("A, B", [
    (np.eye(2), 4.0 * np.eye(2)),  # commuting: s is chi-square exactly
    (np.diag([1.0, 9.0]), np.array([[4.0, 1.5], [1.5, 1.0]])),
    (np.diag([1e-6, 1.0, 1e6]), np.array([[2.0, 0.1, 0.0], [0.1, 3.0, 0.2], [0.0, 0.2, 5.0]])),
])
def test_gate_passes_true_pairs_at_the_gate_probability_or_more(A, B):
    rng = np.random.default_rng(23)
    gate, samples = 0.9, 20000
    rate = _pass_rate("ci", A, B, rng, samples, gate)
    sigma = np.sqrt(gate * (1 - gate) / samples)
    assert rate >= gate - 4 * sigma


def test_the_naive_gate_rejects_true_pairs_under_correlation():
    # the same worst-case correlation: the independence statistic rejects far more true pairs
    # than 1 - gate (this is what the CI distance is for; it also shows the test above can fail)
    rng = np.random.default_rng(23)
    rate = _pass_rate("naive", np.eye(2), 4.0 * np.eye(2), rng, 20000, 0.9)
    assert rate < 0.8


# --- the assignment -----------------------------------------------------------------------------

def test_assignment_minimises_the_total_inside_the_gate():
    cost = np.array([[1.0, 2.0], [1.5, 4.0]])
    # (0,0)+(1,1) = 5 > (0,1)+(1,0) = 3.5
    assert gated_assignment(cost, 10.0) == [(0, 1), (1, 0)]


def test_assignment_prefers_more_pairs_inside_the_gate():
    # (0,0) alone is cheaper than (0,1)+(1,0), but leaves row 1 unassigned
    cost = np.array([[0.1, 2.0], [2.0, 50.0]])
    assert gated_assignment(cost, 3.0) == [(0, 1), (1, 0)]


def test_assignment_leaves_pairs_outside_the_gate():
    cost = np.array([[9.0, np.inf], [1.0, np.nan], [8.0, 0.5]])
    assert gated_assignment(cost, 5.0) == [(1, 0), (2, 1)]
    assert gated_assignment(np.zeros((0, 3)), 1.0) == []
    assert gated_assignment(np.full((2, 2), 7.0), 1.0) == []


def test_assignment_bad_input():
    with pytest.raises(ValueError, match="cost must be a 2-D"):
        gated_assignment(np.ones(3), 1.0)
