"""The batched convex minimisers of cifilter._numerics.optimize, on problems with known answers."""

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.optimize import minimize

from cifilter._numerics.optimize import (
    INTERIOR_MIN_COUNT,
    minimize_convex_interval,
    minimize_convex_segment,
    minimize_convex_simplex,
)

EPS = np.finfo(float).eps


# ------------------------------------------------------------------ interval [0, 1]
class Recorder:
    """Wrap ``derivatives(w, index)`` and remember every call (for the per-item contract)."""

    def __init__(self, function):
        self.function = function
        self.calls = []

    def __call__(self, w, index):
        assert w.shape == index.shape
        self.calls.append((w.copy(), index.copy()))
        return self.function(w, index)


def quadratic_derivatives(curvature, centre):
    """f = curvature/2 (w - centre)^2 per problem."""
    curvature, centre = np.asarray(curvature, float), np.asarray(centre, float)

    def derivatives(w, index):
        return curvature[index] * (w - centre[index]), curvature[index] * np.ones_like(w)

    return derivatives


def test_interval_interior_minimum_of_a_smooth_convex_function():
    # f = e^w + e^(2 (1 - w)): f' = e^w - 2 e^(2 - 2w) = 0 at w = (2 + ln 2) / 3
    def derivatives(w, index):
        return np.exp(w) - 2.0 * np.exp(2.0 - 2.0 * w), np.exp(w) + 4.0 * np.exp(2.0 - 2.0 * w)

    w, iterations, converged = minimize_convex_interval(derivatives, 1, scale=np.ones(1))
    assert converged[0] and 1 <= iterations[0] <= 10
    assert w[0] == pytest.approx((2.0 + np.log(2.0)) / 3.0, abs=1e-13)


@pytest.mark.parametrize("centre", [-3.0, -1e-300, 0.0])
def test_interval_minimum_at_zero_is_exactly_zero_without_iterations(centre):
    recorder = Recorder(quadratic_derivatives([2.0], [centre]))
    w, iterations, converged = minimize_convex_interval(recorder, 1, scale=np.ones(1))
    assert w[0] == 0.0 and iterations[0] == 0 and converged[0]
    assert len(recorder.calls) == 2  # f'(0) and f'(1) only


@pytest.mark.parametrize("centre", [1.0, 1.0 + 1e-15, 7.0])
def test_interval_minimum_at_one_is_exactly_one_without_iterations(centre):
    recorder = Recorder(quadratic_derivatives([2.0], [centre]))
    w, iterations, converged = minimize_convex_interval(recorder, 1, scale=np.ones(1))
    assert w[0] == 1.0 and iterations[0] == 0 and converged[0]
    assert len(recorder.calls) == 2


@pytest.mark.parametrize("slope", [0.0, 1e-14, -1e-14])
def test_interval_flat_function_returns_one_half(slope):
    def derivatives(w, index):
        return np.full_like(w, slope), np.zeros_like(w)

    w, iterations, converged = minimize_convex_interval(derivatives, 1, scale=np.ones(1))
    assert w[0] == 0.5 and iterations[0] == 0 and converged[0]


def test_interval_flatness_is_relative_to_scale():
    # The same slopes are not flat for a function of magnitude 1e-20: the signs decide.
    def derivatives(w, index):
        return np.where(w < 0.25, -1e-14, 1e-14) + 0.0 * w, np.zeros_like(w)

    w, _, converged = minimize_convex_interval(derivatives, 1, scale=np.ones(1))
    assert w[0] == 0.5 and converged[0]  # flat at scale 1
    w, _, converged = minimize_convex_interval(derivatives, 1, scale=np.array([1e-20]))
    assert converged[0] and abs(w[0] - 0.25) < 1e-12  # bisection to the sign change


@pytest.mark.parametrize("curvature", [1e-250, 1e-100, 1.0, 1e100, 1e250])
def test_interval_is_invariant_to_the_scale_of_the_function(curvature):
    centre = 0.123456789
    derivatives = quadratic_derivatives([curvature], [centre])
    w, iterations, converged = minimize_convex_interval(
        derivatives, 1, scale=np.array([curvature]))
    assert converged[0] and iterations[0] <= 3
    assert w[0] == pytest.approx(centre, abs=1e-15)


def test_interval_very_ill_scaled_curvature_is_bracketed_not_lost():
    # f' = tanh(k (w - c)): f'' is huge near c and vanishes elsewhere, so Newton steps from
    # the flanks leave [0, 1]: the bracket must take over. Every point evaluated is in [0, 1].
    k = np.array([1e3, 1e6, 1e9, 3.0])
    c = np.array([0.9, 0.01, 0.6180339887, 0.7])

    def derivatives(w, index):
        t = np.tanh(k[index] * (w - c[index]))
        return t, k[index] * (1.0 - t * t)

    recorder = Recorder(derivatives)
    w, iterations, converged = minimize_convex_interval(recorder, 4, scale=np.ones(4))
    assert converged.all() and (iterations < 100).all()
    np.testing.assert_allclose(w, c, rtol=0, atol=2e-13)
    for points, _ in recorder.calls:
        assert ((points >= 0.0) & (points <= 1.0)).all()


def test_interval_degenerate_root_with_vanishing_curvature():
    # f = (w - c)^4 / 4: f'' = 0 at the root, Newton converges linearly (factor 2/3).
    c = 0.3

    def derivatives(w, index):
        return (w - c) ** 3, 3.0 * (w - c) ** 2

    w, iterations, converged = minimize_convex_interval(derivatives, 1, scale=np.ones(1))
    assert converged[0] and 20 < iterations[0] < 100
    assert abs(w[0] - c) < 1e-6  # f is flat to rounding within (eps)^(1/4) of c
    # ... and the function value there is at the rounding level of f
    assert (w[0] - c) ** 4 / 4 < 1e-20


def test_interval_batch_of_mixed_problems_stops_each_individually():
    # 0: minimum at 0, 1: at 1, 2: flat, 3: quadratic (Newton exact in one step, then
    # confirmed), 4: quartic (slow), 5: quadratic with its root exactly at 1/2.
    def derivatives(w, index):
        g = np.empty_like(w)
        h = np.empty_like(w)
        for j, (i, wi) in enumerate(zip(index, w)):
            g[j], h[j] = {
                0: (1.0 + wi, 1.0),
                1: (wi - 2.0, 1.0),
                2: (0.0, 0.0),
                3: (4.0 * (wi - 0.2), 4.0),
                4: ((wi - 0.8) ** 3, 3.0 * (wi - 0.8) ** 2),
                5: (wi - 0.5, 1.0),
            }[int(i)]
        return g, h

    recorder = Recorder(derivatives)
    w, iterations, converged = minimize_convex_interval(recorder, 6, scale=np.ones(6))
    assert converged.all()
    assert w[0] == 0.0 and w[1] == 1.0 and w[2] == 0.5 and w[5] == 0.5
    assert w[3] == pytest.approx(0.2, abs=1e-15)
    assert abs(w[4] - 0.8) < 1e-6
    np.testing.assert_array_equal(iterations[[0, 1, 2, 5]], [0, 0, 0, 1])
    assert iterations[3] == 2 and iterations[4] > 20
    # After the two end-point evaluations only unfinished problems are evaluated, once per
    # iteration: problem k appears in exactly iterations[k] calls.
    later = np.concatenate([index for _, index in recorder.calls[2:]])
    np.testing.assert_array_equal(np.bincount(later, minlength=6), iterations)
    assert len(recorder.calls) == 2 + iterations.max()


@pytest.mark.parametrize("max_iter", [0, 1, 5])
def test_interval_iteration_limit_reports_not_converged(max_iter):
    def derivatives(w, index):
        slow = (w - 0.8) ** 3, 3.0 * (w - 0.8) ** 2
        return np.where(index == 0, slow[0], 1.0), np.where(index == 0, slow[1], 0.0)

    w, iterations, converged = minimize_convex_interval(
        derivatives, 2, scale=np.ones(2), max_iter=max_iter)
    np.testing.assert_array_equal(iterations, [max_iter, 0])
    np.testing.assert_array_equal(converged, [False, True])
    assert w[1] == 0.0 and 0.0 < w[0] < 1.0
    if max_iter == 0:
        assert w[0] == 0.5


def test_interval_xtol_controls_the_precision():
    def derivatives(w, index):
        return (w - 0.3) ** 3, 3.0 * (w - 0.3) ** 2

    coarse, it_coarse, ok_coarse = minimize_convex_interval(
        derivatives, 1, scale=np.ones(1), xtol=1e-3)
    fine, it_fine, ok_fine = minimize_convex_interval(derivatives, 1, scale=np.ones(1))
    assert ok_coarse[0] and ok_fine[0] and it_coarse[0] < it_fine[0]
    assert 1e-6 < abs(coarse[0] - 0.3) < 1e-2 and abs(fine[0] - 0.3) < 1e-6


# ------------------------------------------------------------------ the simplex
def quadratic(A, c, offset=1.0):
    """f(w) = offset + (w - c)^T A (w - c) / 2 over batches (A: (..., N, N), c: (..., N))."""
    A, c = np.asarray(A, float), np.asarray(c, float)

    def objective(w, index=None):
        Ai, ci = (A, c) if index is None else (A[index], c[index])
        r = w - ci
        return offset + 0.5 * np.einsum("...i,...ij,...j->...", r, Ai, r)

    def evaluate(w, index=None):
        Ai, ci = (A, c) if index is None else (A[index], c[index])
        r = w - ci
        g = np.einsum("...ij,...j->...i", Ai, r)
        return offset + 0.5 * np.einsum("...i,...i->...", r, g), g, Ai.copy()

    return evaluate, objective


def frank_wolfe_gap(w, g):
    return np.einsum("...i,...i->...", w, g) - g.min(axis=-1)


def exact_quadratic_minimum(A, c, offset=1.0):
    """Brute force over the supports: the minimum of the quadratic on the simplex."""
    count = len(c)
    best = np.inf
    for size in range(1, count + 1):
        for support in itertools.combinations(range(count), size):
            S = list(support)
            kkt = np.zeros((size + 1, size + 1))
            kkt[:size, :size] = A[np.ix_(S, S)]
            kkt[:size, size] = kkt[size, :size] = 1.0
            rhs = np.concatenate([A[S] @ c, [1.0]])
            solution = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
            w = np.zeros(count)
            w[S] = solution[:size]
            if (w >= -1e-12).all():
                w = np.clip(w, 0.0, None)
                w /= w.sum()
                best = min(best, offset + 0.5 * (w - c) @ A @ (w - c))
    return best


def random_spd(rng, count, condition=10.0):
    Q, _ = np.linalg.qr(rng.standard_normal((count, count)))
    return (Q * np.geomspace(1.0, condition, count)) @ Q.T


def euclidean_projection(c):
    """Projection of c onto the simplex (sort-based), the minimiser for A = I."""
    u = np.sort(c)[::-1]
    cumulative = np.cumsum(u) - 1.0
    k = np.flatnonzero(u - cumulative / np.arange(1, len(c) + 1) > 0)[-1]
    return np.maximum(c - cumulative[k] / (k + 1), 0.0)


@pytest.mark.parametrize("count", [2, 3, 4, 5, 6])
def test_simplex_interior_optimum_of_a_quadratic(count):
    rng = np.random.default_rng(count)
    A = random_spd(rng, count, condition=100.0)
    c = rng.dirichlet(np.full(count, 5.0))
    evaluate, objective = quadratic(A, c)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, ())
    assert converged and w.shape == (count,) and 1 <= iterations <= 10
    np.testing.assert_allclose(w, c, rtol=0, atol=1e-10)
    assert w.sum() == pytest.approx(1.0, abs=4 * EPS)


@pytest.mark.parametrize("c, expected", [
    ([0.8, 0.6, -0.5], [0.6, 0.4, 0.0]),  # on an edge
    ([0.5, 0.5, 0.5, -1.0], [1 / 3, 1 / 3, 1 / 3, 0.0]),  # on a facet
    ([2.0, 0.0, 0.0], [1.0, 0.0, 0.0]),  # at a vertex
    ([-1.0, 5.0, 0.0, 1.0, 0.5], [0.0, 1.0, 0.0, 0.0, 0.0]),
])
def test_simplex_optimum_on_a_face_has_exact_zeros(c, expected):
    count = len(c)
    evaluate, objective = quadratic(np.eye(count), c)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, ())
    assert converged and iterations <= 10
    zero = np.asarray(expected) == 0.0
    assert (w[zero] == 0.0).all(), w  # exactly zero, not approached
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-12)


def test_simplex_kkt_conditions_hold_at_the_result():
    rng = np.random.default_rng(11)
    for _ in range(20):
        count = int(rng.integers(2, 7))
        A = random_spd(rng, count, condition=1e4)
        c = rng.standard_normal(count)
        evaluate, objective = quadratic(A, c)
        w, _, converged = minimize_convex_simplex(evaluate, objective, count, ())
        assert converged
        _, g, _ = evaluate(w)
        mu = g[w > 0].mean()
        scale = np.abs(g).max() + 1.0
        np.testing.assert_allclose(g[w > 0], mu, rtol=0, atol=1e-9 * scale)
        assert (g[w == 0] >= mu - 1e-9 * scale).all()
        # 1e-12, plus the rounding of the reference, itself computed in floating point (an
        # absolute 1e-12 alone is below a unit in the last place of values near 500)
        best = exact_quadratic_minimum(A, c)
        assert best >= objective(w) - 1e-12 - 64 * np.finfo(float).eps * abs(best)


def test_simplex_ties_keep_equal_weights():
    # f depends on w_1 + w_2 only (two equal inputs): the Hessian is singular along
    # e_1 - e_2, and the tie is shared fairly (the uniform start is kept along it).
    def evaluate(w):
        s = w[..., 0] + w[..., 1]
        f = 1.0 + (s - 0.7) ** 2 + (w[..., 2] - 0.3) ** 2
        g = np.stack([2 * (s - 0.7), 2 * (s - 0.7), 2 * (w[..., 2] - 0.3)], axis=-1)
        H = np.array([[2.0, 2.0, 0.0], [2.0, 2.0, 0.0], [0.0, 0.0, 2.0]])
        return f, g, np.broadcast_to(H, w.shape + (3,)).copy()

    def objective(w):
        return evaluate(w)[0]

    for gtol in (0.0, 1e-12):
        w, _, converged = minimize_convex_simplex(evaluate, objective, 3, (), gtol=gtol)
        assert converged
        assert w[0] == w[1]
        np.testing.assert_allclose(w, [0.35, 0.35, 0.3], rtol=0, atol=1e-12)


@pytest.mark.parametrize("count", [2, 3, 5])
def test_simplex_identical_inputs_give_uniform_weights(count):
    # f(w) constant on the simplex (linear in sum w): every direction is flat.
    def evaluate(w):
        f = 2.0 + 0.0 * w.sum(axis=-1)
        return f, np.ones(w.shape), np.zeros(w.shape + (count,))

    def objective(w):
        return 2.0 + 0.0 * w.sum(axis=-1)

    for gtol in (0.0, 1e-10):
        w, _, converged = minimize_convex_simplex(evaluate, objective, count, (4,), gtol=gtol)
        assert converged.all()
        np.testing.assert_array_equal(w, np.full((4, count), 1.0 / count))


def test_simplex_batch_equals_the_problems_solved_one_by_one():
    rng = np.random.default_rng(5)
    shape, count = (2, 3), 4
    A = np.stack([random_spd(rng, count, 1e3) for _ in range(6)]).reshape(shape + (4, 4))
    c = rng.standard_normal(shape + (count,))
    c[0, 0] = 0.25  # the uniform start is optimal: no iteration
    evaluate, objective = quadratic(A, c)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, shape)
    assert w.shape == shape + (count,) and iterations.shape == shape == converged.shape
    assert converged.all() and iterations[0, 0] == 0 and iterations.max() > 0
    for index in np.ndindex(*shape):
        e1, o1 = quadratic(A[index], c[index])
        w1, _, ok1 = minimize_convex_simplex(e1, o1, count, ())
        assert ok1
        np.testing.assert_allclose(w[index], w1, rtol=0, atol=1e-12)
        assert objective(w)[index] <= exact_quadratic_minimum(A[index], c[index]) + 1e-12


def test_simplex_iteration_limit_reports_not_converged():
    rng = np.random.default_rng(3)
    A = random_spd(rng, 4, 1e3)
    c = np.array([2.0, -1.0, 0.5, -0.3])
    evaluate, objective = quadratic(A, c)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, 4, (), max_iter=0)
    assert not converged and iterations == 0
    np.testing.assert_array_equal(w, np.full(4, 0.25))
    _, full_iterations, ok = minimize_convex_simplex(evaluate, objective, 4, ())
    assert ok and full_iterations >= 2
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, 4, (), max_iter=1)
    assert not converged and iterations == 1
    assert w.sum() == pytest.approx(1.0) and (w >= 0).all()


def test_simplex_gtol_certifies_the_start_without_iterations():
    # f = 1000 + |w - c|^2 / 2 at the uniform start: gap = |c - u|^2-ish, far below 1e-3 |f|
    # but not below 1e-3 in absolute terms.
    c = np.array([0.2, 0.3, 0.5])
    evaluate, objective = quadratic(np.eye(3), c, offset=1000.0)
    w, iterations, converged = minimize_convex_simplex(
        evaluate, objective, 3, (), gtol=1e-3, max_iter=50)
    assert converged and iterations == 0
    np.testing.assert_array_equal(w, np.full(3, 1 / 3))
    _, g, _ = evaluate(w)
    assert 1e-3 < frank_wolfe_gap(w, g) <= 1e-3 * 1000.0
    w, iterations, converged = minimize_convex_simplex(
        evaluate, objective, 3, (), gtol=1e-3, absolute_gap=True, max_iter=50)
    assert converged and iterations >= 1
    f, g, _ = evaluate(w)
    assert frank_wolfe_gap(w, g) <= 1e-3
    assert f - exact_quadratic_minimum(np.eye(3), c, offset=1000.0) <= 1e-3


def test_simplex_absolute_gap_handles_objectives_near_zero():
    # log-determinant-like objectives can be zero at the optimum: a relative gap test
    # would demand an exact zero, the absolute one certifies.
    c = np.array([0.1, 0.6, 0.3])
    evaluate, objective = quadratic(4.0 * np.eye(3), c, offset=0.0)
    w, _, converged = minimize_convex_simplex(
        evaluate, objective, 3, (), gtol=1e-12, absolute_gap=True)
    assert converged
    _, g, _ = evaluate(w)
    assert 0.0 <= frank_wolfe_gap(w, g) <= 1e-12
    np.testing.assert_allclose(w, c, rtol=0, atol=1e-12)


def test_simplex_subset_evaluates_only_unfinished_rows():
    rng = np.random.default_rng(9)
    size, count = 5, 3
    A = np.stack([random_spd(rng, count, 10 ** k) for k in range(size)])
    c = rng.standard_normal((size, count))
    c[2] = 1.0 / count  # optimal at the start
    evaluate, objective = quadratic(A, c)
    seen = {"evaluate": [], "objective": []}

    def evaluate_rows(w, index):
        assert w.shape == (len(index), count)
        seen["evaluate"].append(index.copy())
        return evaluate(w, index)

    def objective_rows(w, index):
        seen["objective"].append(index.copy())
        return objective(w, index)

    for gtol in (0.0, 1e-12):
        seen["evaluate"].clear()
        w, iterations, converged = minimize_convex_simplex(
            evaluate_rows, objective_rows, count, (size,), subset=True, gtol=gtol)
        full, full_iterations, full_converged = minimize_convex_simplex(
            evaluate, objective, count, (size,), gtol=gtol)
        assert converged.all() and full_converged.all()
        np.testing.assert_allclose(w, full, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(iterations, full_iterations)
        assert iterations[2] == 0
        np.testing.assert_array_equal(seen["evaluate"][0], np.arange(size))
        later = np.concatenate(seen["evaluate"][1:])
        assert 2 not in later and len(later) < size * (len(seen["evaluate"]) - 1)
        # a problem is evaluated once per iteration it takes (plus the final check)
        counts = np.bincount(np.concatenate(seen["evaluate"]), minlength=size)
        assert (counts <= iterations + 1).all()


# ------------------------------------------------------------------ certified gap, property
def ci_diagonal_trace(a):
    """f(w) = sum_k 1 / (sum_i w_i a_ik): the trace of CI of diagonal covariances (a: N x n
    information values). Convex on the simplex."""

    def objective(w):
        return (1.0 / (w @ a)).sum(axis=-1)

    def evaluate(w):
        s = w @ a
        g = -(a / s**2).sum(axis=-1)
        H = 2.0 * np.einsum("ik,jk,k->ij", a, a, 1.0 / s**3)
        return objective(w), g, H

    return evaluate, objective


def simplex_reference(objective, count, starts):
    """A fine reference minimum (SLSQP from several starts and every vertex)."""
    best = min(objective(np.eye(count)[i]) for i in range(count))
    for start in starts:
        result = minimize(objective, start, method="SLSQP", bounds=[(0.0, 1.0)] * count,
                          constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1.0}],
                          options={"ftol": 1e-15, "maxiter": 500})
        w = np.clip(result.x, 0.0, None)
        best = min(best, objective(w / w.sum()))
    return best


@given(st.integers(2, 5).flatmap(lambda count: st.tuples(
    arrays(float, (count, 3), elements=st.floats(-6.0, 6.0)),
    st.sampled_from([1e-8, 1e-10, 1e-12]),
)))
def test_simplex_certified_gap_is_honest_on_ci_traces(args):
    log_information, gtol = args
    count = log_information.shape[0]
    a = 10.0 ** log_information  # information of every estimate and axis, 1e-6..1e6
    evaluate, objective = ci_diagonal_trace(a)
    w, _, converged = minimize_convex_simplex(evaluate, objective, count, (), gtol=gtol)
    assert w.shape == (count,) and (w >= 0).all() and w.sum() == pytest.approx(1.0, abs=1e-15)
    f, g, _ = evaluate(w)
    gap = frank_wolfe_gap(w, g)
    reference = simplex_reference(objective, count, [np.full(count, 1 / count), w])
    # the Frank-Wolfe gap bounds the excess over the minimum (convexity) ...
    assert f - reference <= gap + 1e-13 * f
    # ... and a converged problem is certified to gtol (relative to |f|)
    if converged:
        assert gap <= gtol * abs(f)
        assert f - reference <= gtol * f + 1e-13 * f


@given(st.integers(2, 5).flatmap(lambda count: st.tuples(
    arrays(float, (count, count), elements=st.floats(-3.0, 3.0)),
    arrays(float, (count,), elements=st.floats(-2.0, 2.0)),
    st.floats(0.0, 6.0),
)))
def test_simplex_quadratics_reach_the_exact_minimum(args):
    Z, c, log_condition = args
    count = len(c)
    Q, _ = np.linalg.qr(Z + 1e-3 * np.eye(count))
    A = (Q * np.geomspace(1.0, 10.0**log_condition, count)) @ Q.T
    A = 0.5 * (A + A.T)
    evaluate, objective = quadratic(A, c)
    best = exact_quadratic_minimum(A, c)

    def rounding(w):  # of evaluating f: n eps |r|^T |A| |r| (cancellation for large cond A)
        r = np.abs(w - c)
        return 4.0 * count * EPS * (r @ np.abs(A) @ r)

    w, _, converged = minimize_convex_simplex(evaluate, objective, count, ())
    assert converged
    assert objective(w) - best <= 1e-12 * best + rounding(w)
    # With a gap test the tolerance must lie above the rounding of the gradient (about
    # cond(A) eps |A (w - c)|, up to 1e-9 here; f >= 1).
    w, _, converged = minimize_convex_simplex(evaluate, objective, count, (), gtol=1e-8)
    assert converged
    _, g, _ = evaluate(w)
    assert frank_wolfe_gap(w, g) <= 1e-8 * objective(w)
    assert objective(w) - best <= 1e-8 * objective(w) + rounding(w)


def test_euclidean_projection_reference_is_right():
    np.testing.assert_allclose(euclidean_projection(np.array([0.8, 0.6, -0.5])), [0.6, 0.4, 0])
    rng = np.random.default_rng(1)
    for _ in range(5):
        c = 2.0 * rng.standard_normal(4)
        evaluate, objective = quadratic(np.eye(4), c)
        w, _, ok = minimize_convex_simplex(evaluate, objective, 4, ())
        assert ok
        np.testing.assert_allclose(w, euclidean_projection(c), rtol=0, atol=1e-12)
        assert objective(w) == pytest.approx(exact_quadratic_minimum(np.eye(4), c), abs=1e-13)


@pytest.mark.parametrize("gtol", [0.0, 1e-10])
def test_simplex_released_weight_with_a_negative_newton_step_does_not_stall(gtol):
    L = np.array([[95.6, 0.0, 0.0, 0.0, 0.0],
                  [159.9, 97.1, 0.0, 0.0, 0.0],
                  [-283.3, -46.6, 29.6, 0.0, 0.0],
                  [-119.1, 46.3, 9.8, 5.7, 0.0],
                  [284.6, 91.6, 4.7, 4.0, 3.1]])
    A, c = L @ L.T, np.array([-0.1, -0.4, -2.9, 1.9, -2.6])  # cond(A) = 2.2e5
    evaluate, objective = quadratic(A, c)
    best = exact_quadratic_minimum(A, c)
    w, _, converged = minimize_convex_simplex(evaluate, objective, 5, (), gtol=gtol)
    # (before: w = [0, 0, 0.662, 0.338, 0], unconverged, f - min f = 532, gap 4864: three
    # weights released at once, the face step made one negative and blocked at length 0)
    assert converged
    assert objective(w) - best <= 1e-9 * best


def test_simplex_solver_stops_when_the_decrement_is_below_rounding():
    """A face solved to working precision stops, although the Newton step exceeds xtol.

    The objective is flat to rounding (every trial point looks 1e-14 worse: noise), the
    Newton step is 1e-6 but its decrement -g.d is 1e-20: no line search can confirm it.
    """
    def evaluate(w):
        g = np.stack([np.full(w.shape[:-1], 1e-14), np.full(w.shape[:-1], -1e-14)], axis=-1)
        H = np.broadcast_to(1e-8 * np.eye(2), w.shape + (2,)).copy()
        return np.ones(w.shape[:-1]), g, H

    def objective(w):
        return np.ones(w.shape[:-1]) + 1e-14

    w, iterations, converged = minimize_convex_simplex(evaluate, objective, 2, (3,))
    assert converged.all() and iterations.max() <= 1
    np.testing.assert_allclose(w.sum(axis=-1), 1.0)


def test_segment_minimiser_equals_the_simplex_of_two_and_one_problem_its_batch():
    """Quadratics of two weights: the segment method reaches each exact minimum (interior or
    an end), and one problem alone gives what it gives in a batch."""
    A = np.array([[[2.0, 0.5], [0.5, 1.0]], [[1.0, 0.0], [0.0, 1.0]], [[3.0, 1.0], [1.0, 2.0]]])
    c = np.array([[0.3, 0.2], [5.0, -5.0], [-4.0, 6.0]])  # interior, at (1, 0), at (0, 1)
    evaluate, objective = quadratic(A, c)

    def rows(w, index):
        return evaluate(w, index)

    scale = objective(np.full((3, 2), 0.5))
    w, iterations, converged = minimize_convex_segment(rows, 3, scale=scale)
    assert converged.all()
    for k in range(3):
        assert objective(w[k], k) == pytest.approx(exact_quadratic_minimum(A[k], c[k]),
                                                   rel=1e-12)
        alone, steps, _ = minimize_convex_segment(
            lambda v, index, k=k: evaluate(v, np.array([k])), 1, scale=scale[k:k + 1])
        np.testing.assert_allclose(alone[0], w[k], rtol=0, atol=1e-12)
        assert steps[0] == iterations[k]
    np.testing.assert_array_equal(w[1], [1.0, 0.0])
    np.testing.assert_array_equal(w[2], [0.0, 1.0])


# ------------------------------------------------------------------ many weights (issue 21, item 4)
def exact_ci_trace_gap(w, a, digits=50):
    """The Frank-Wolfe gap of ``ci_diagonal_trace(a)`` at the float weights ``w`` in
    ``digits``-digit arithmetic, relative to the exact objective: a certified bound on the
    relative excess of ``f(w)`` over the exact minimum, free of the solver's rounding."""
    import mpmath

    with mpmath.workdps(digits):
        weights = [mpmath.mpf(float(v)) for v in w]
        columns = [[mpmath.mpf(float(v)) for v in a[:, k]] for k in range(a.shape[1])]
        s = [mpmath.fsum(wi * ak for wi, ak in zip(weights, column)) for column in columns]
        f = mpmath.fsum(1 / sk for sk in s)
        g = [-mpmath.fsum(column[i] / sk**2 for column, sk in zip(columns, s))
             for i in range(len(weights))]
        gap = mpmath.fsum(wi * gi for wi, gi in zip(weights, g)) - min(g)
        return float(gap / f)


def many_ci_traces(count, seed, spread=2.0):
    """``ci_diagonal_trace`` of ``count`` random diagonal 3x3 estimates (information values
    within ``10**+-spread``): the optimum uses a few of them (an exact face)."""
    rng = np.random.default_rng(seed)
    return 10.0 ** rng.uniform(-spread, spread, (count, 3))


@pytest.mark.parametrize("count", [30, 300])
def test_simplex_many_weights_converge_in_a_bounded_number_of_iterations(count):
    # The active-set method alone fixed one weight per iteration from the uniform start:
    # about `count` iterations (before: 300 weights did not converge in 200). The interior
    # phase moves every weight at once; its count does not grow with N.
    a = many_ci_traces(count, seed=count)
    evaluate, objective = ci_diagonal_trace(a)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, (),
                                                       gtol=1e-10)
    assert converged and iterations <= 30, (converged, iterations)
    assert (w >= 0).all() and w.sum() == pytest.approx(1.0, abs=4 * count * EPS)
    support = w > 0
    assert 1 <= support.sum() <= 10  # an exact face: the others are exactly zero
    # certified by the gap of the float gradient, and by the exact one (50 digits)
    f, g, _ = evaluate(w)
    assert frank_wolfe_gap(w, g) <= 1e-10 * f
    assert exact_ci_trace_gap(w, a) <= 1e-10
    # the KKT conditions: one level on the support, none below it elsewhere
    level = g[support].mean()
    assert np.abs(g[support] - level).max() <= 1e-9 * abs(level)
    assert (g[~support] >= level - 1e-9 * abs(level)).all()


def test_simplex_many_weights_agree_with_slsqp():
    count = 40
    a = many_ci_traces(count, seed=7)
    evaluate, objective = ci_diagonal_trace(a)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, (),
                                                       gtol=1e-12)
    assert converged and iterations <= 30
    reference = simplex_reference(objective, count, [np.full(count, 1 / count)])
    f = objective(w)
    assert f <= reference * (1 + 1e-12)  # no worse than SLSQP's best ...
    assert f >= reference * (1 - 1e-9)  # ... which is within its tolerance of it
    assert exact_ci_trace_gap(w, a) <= 1e-12


@pytest.mark.parametrize("count", [INTERIOR_MIN_COUNT, INTERIOR_MIN_COUNT + 2])
@pytest.mark.parametrize("gtol", [0.0, 1e-10])
def test_simplex_interior_phase_reaches_the_exact_minimum_of_quadratics(count, gtol):
    # brute force over the 2^count supports
    rng = np.random.default_rng(count)
    for _ in range(2):
        A = random_spd(rng, count, condition=1e4)
        c = 0.5 * rng.standard_normal(count)
        evaluate, objective = quadratic(A, c)
        w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, (),
                                                           gtol=gtol)
        assert converged and iterations <= 30
        best = exact_quadratic_minimum(A, c)
        assert objective(w) - best <= 1e-12 * best + 64 * EPS * best


@pytest.mark.parametrize("count", [INTERIOR_MIN_COUNT, 40])
def test_simplex_interior_phase_gives_a_face_with_exact_zeros(count):
    # the Euclidean projection onto the simplex: a face known in closed form
    c = np.linspace(-1.0, 1.0, count)
    evaluate, objective = quadratic(np.eye(count), c)
    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, ())
    expected = euclidean_projection(c)
    assert converged and iterations <= 30
    np.testing.assert_array_equal(w == 0.0, expected == 0.0)
    np.testing.assert_allclose(w, expected, rtol=0, atol=1e-12)


def test_simplex_interior_phase_shares_ties_to_rounding():
    # equal inputs (rows 0 and 1, 2 and 3 of the information) have equal weights to rounding
    a = many_ci_traces(20, seed=3, spread=0.5)
    a[1], a[3] = a[0], a[2]
    evaluate, objective = ci_diagonal_trace(a)
    w, _, converged = minimize_convex_simplex(evaluate, objective, 20, (), gtol=1e-12)
    assert converged
    assert abs(w[0] - w[1]) <= 1e-12 and abs(w[2] - w[3]) <= 1e-12


def test_simplex_interior_phase_batch_equals_the_problems_one_by_one():
    count, size = INTERIOR_MIN_COUNT + 2, 4
    a = np.stack([many_ci_traces(count, seed=20 + k) for k in range(size)])

    def evaluate(w, index):
        out = [ci_diagonal_trace(a[k])[0](wk) for k, wk in zip(index, w)]
        return tuple(np.stack(parts) for parts in zip(*out))

    def objective(w, index):
        return np.array([ci_diagonal_trace(a[k])[1](wk) for k, wk in zip(index, w)])

    w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, (size,),
                                                       gtol=1e-12, subset=True)
    assert converged.all()
    for k in range(size):
        e1, o1 = ci_diagonal_trace(a[k])
        w1, iterations1, ok = minimize_convex_simplex(e1, o1, count, (), gtol=1e-12)
        assert ok and iterations1 == iterations[k]
        np.testing.assert_allclose(w[k], w1, rtol=0, atol=1e-12)


def test_simplex_interior_phase_respects_the_iteration_limit():
    a = many_ci_traces(50, seed=1)
    evaluate, objective = ci_diagonal_trace(a)
    for limit in (1, 3):
        w, iterations, converged = minimize_convex_simplex(evaluate, objective, 50, (),
                                                           gtol=1e-12, max_iter=limit)
        assert not converged and iterations == limit
        assert (w >= 0).all() and w.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("count", [INTERIOR_MIN_COUNT, 20])
def test_simplex_interior_phase_keeps_identical_inputs_uniform(count):
    def evaluate(w):
        return 2.0 + 0.0 * w.sum(axis=-1), np.ones(w.shape), np.zeros(w.shape + (count,))

    def objective(w):
        return 2.0 + 0.0 * w.sum(axis=-1)

    for gtol in (0.0, 1e-10):
        w, iterations, converged = minimize_convex_simplex(evaluate, objective, count, (3,),
                                                           gtol=gtol)
        assert converged.all() and (iterations == 0).all()
        np.testing.assert_array_equal(w, np.full((3, count), 1.0 / count))


def steep_ci_trace(a, rho):
    """``ci_diagonal_trace(a)`` of the weights ``w_i = d_i / (rho + (1 - rho) d_i)`` of
    partial CI (eq. (24) of Wu, Cai & Fu), minimised over ``d``: convex (a convex decreasing
    function of concave weights) and steep next to the boundary for small ``rho`` (a ``d_i``
    of 1e-8 already gives ``w_i`` near 1/2)."""

    def weights(d):
        den = rho + (1.0 - rho) * d
        return d / den, rho / den**2, -2.0 * rho * (1.0 - rho) / den**3

    def objective(d):
        return (1.0 / (weights(d)[0] @ a)).sum(axis=-1)

    def evaluate(d):
        w, first, second = weights(d)
        s = w @ a
        g = -(a / s**2).sum(axis=-1)
        H = first[:, None] * first[None, :] * 2.0 * np.einsum("ik,jk,k->ij", a, a, 1.0 / s**3)
        H = H + np.diag(g * second)
        return objective(d), g * first, 0.5 * (H + H.T)

    return evaluate, objective


@pytest.mark.parametrize("seed", range(6))
def test_simplex_interior_phase_keeps_the_weights_a_steep_optimum_needs(seed):
    # Optimal d_i of order rho look negligible to the crossover's threshold; a face that
    # drops them is worse than the interior iterate by far more than its gap, and is
    # refused. (Before that check, 14 of 20 such problems stopped unconverged at 200
    # iterations, the face lacking weights the optimum needs.)
    rng = np.random.default_rng(seed)
    count = INTERIOR_MIN_COUNT + 3
    a = 10.0 ** rng.uniform(-3.0, 3.0, (count, 2))
    evaluate, objective = steep_ci_trace(a, 1e-8)
    d, iterations, converged = minimize_convex_simplex(evaluate, objective, count, (),
                                                       gtol=1e-10)
    assert converged and iterations <= 30
    f, g, _ = evaluate(d)
    assert frank_wolfe_gap(d, g) <= 1e-10 * f
