"""Covariance union (:mod:`cifilter.rules.union`, ``"cu"``).

The guarantee (``P >= P_i + (x - x_i)(x - x_i)^T`` for every input, to rounding, at
condition numbers up to 1e12), hand-derived cases, the exact pairwise unions against
independent references, the optimality of the mean against scipy, MATLAB's documented
``fusecovunion`` example (its documentation prints no numbers, so only the guarantee is
checked there), batching, permutation invariance and bad input.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from scipy.special import expit
from strategies import ill_conditioned_sets

from cifilter import IllConditionedError, KalmanFilter, covariance_union, fuse, get_method
from cifilter.rules import _union
from cifilter.rules._union import (
    SMOOTHING_STAGES,
    mean_candidates_value,
    pair_union,
    smoothed_dual_bound,
    smoothed_point,
    smoothed_trace_mean,
    trace_certificate,
    trace_dual_bound,
)

EPS = np.finfo(float).eps


def covered(x, P, xs, Ps):
    """Smallest eigenvalue of ``P - P_i - (x - x_i)(x - x_i)^T`` over the inputs relative to
    ``||P||``, and that of ``L_i^-1 P L_i^-T - I`` (``M_i = L_i L_i^T``, the shortfall in the
    input's own metric) relative to ``eps ||P|| / lambda_min(M_i)``, the rounding of ``P``
    seen in that metric."""
    worst_abs, worst_rel = np.inf, np.inf
    for xi, Pi in zip(xs, Ps):
        d = x - xi
        M = Pi + np.outer(d, d)
        worst_abs = min(worst_abs, np.linalg.eigvalsh(P - M).min() / np.linalg.norm(P, 2))
        Li = np.linalg.inv(np.linalg.cholesky(M))
        rel = np.linalg.eigvalsh(Li @ P @ Li.T).min() - 1.0
        rounding = EPS * np.linalg.norm(P, 2) / np.linalg.eigvalsh(M).min()
        worst_rel = min(worst_rel, rel / rounding)
    return worst_abs, worst_rel


def union_value(u, xs, Ps, kind):
    M = [P + np.outer(u - x, u - x) for x, P in zip(xs, Ps)]
    U = pair_union(M[0], M[1], xs[0], xs[1], kind).U
    return np.trace(U) if kind == "trace" else np.linalg.slogdet(U)[1]


def random_problem(rng, n, count=2, spread=3.0):
    A = rng.standard_normal((count, n, n))
    return rng.standard_normal((count, n)) * spread, A @ A.swapaxes(-1, -2) + 0.1 * np.eye(n)


# ----------------------------------------------------------------- hand-derived cases
def test_scalar_union_is_centred_between_equal_tracks():
    r = covariance_union([np.array([0.0]), np.array([2.0])], [np.eye(1), np.eye(1)])
    assert r.x.tolist() == [1.0] and r.P.tolist() == [[2.0]]
    assert r.method == "cu" and r.weights is None and r.gains is None


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_scalar_union_keeps_a_track_that_covers_the_other(criterion):
    # p = 4 at 1 covers p = 1 at 0: 1 + (1 - 0)^2 = 2 <= 4, so the union is the wide track
    r = covariance_union([np.array([0.0]), np.array([1.0])], [np.eye(1), 4 * np.eye(1)],
                         criterion=criterion)
    np.testing.assert_allclose(r.x, [1.0], atol=1e-12)
    np.testing.assert_allclose(r.P, [[4.0]], rtol=1e-12)


def test_scalar_union_at_the_crossing():
    # max(1 + u^2, 2 + (u - 3)^2): the vertices lie in the other's region, optimum where
    # they cross: 1 + u^2 = 2 + (u - 3)^2  ->  u = 10 / 6, U = 1 + (10/6)^2
    r = covariance_union([np.array([0.0]), np.array([3.0])], [np.eye(1), 2 * np.eye(1)])
    np.testing.assert_allclose(r.x, [10 / 6], rtol=1e-9)
    np.testing.assert_allclose(r.P, [[1 + (10 / 6) ** 2]], rtol=1e-9)
    assert bool(r.info["converged"])


def test_fixed_mean_det_and_trace_closed_forms():
    xs, Ps = [np.zeros(2), np.ones(2)], [np.eye(2), np.eye(2)]
    for criterion in ("trace", "det"):  # M_2 = I + 1 1^T >= M_1 = I: the union is M_2
        r = covariance_union(xs, Ps, criterion=criterion, mean=np.zeros(2))
        np.testing.assert_allclose(r.P, [[2.0, 1.0], [1.0, 2.0]], rtol=1e-12)
        assert r.info["rule"] == "fixed"
    # two crossing ellipses at the same mean: det gives T max(1, d) T^T, trace A + (B - A)_+
    A, B = np.array([[2.0, 1.0], [1.0, 2.0]]), np.diag([4.0, 1.0])
    det = covariance_union([np.zeros(2)] * 2, [A, B], criterion="det", mean=np.zeros(2)).P
    tr = covariance_union([np.zeros(2)] * 2, [A, B], criterion="trace", mean=np.zeros(2)).P
    lam, V = np.linalg.eigh(B - A)
    np.testing.assert_allclose(tr, A + (V * np.maximum(lam, 0)) @ V.T, rtol=1e-12)
    Li = np.linalg.inv(np.linalg.cholesky(A))
    d, W = np.linalg.eigh(Li @ B @ Li.T)
    T = np.linalg.cholesky(A) @ W
    np.testing.assert_allclose(det, (T * np.maximum(d, 1.0)) @ T.T, rtol=1e-12)


def test_equal_estimates_are_returned():
    P = np.array([[2.0, 0.3], [0.3, 1.0]])
    for criterion in ("trace", "det"):
        r = covariance_union([np.ones(2)] * 2, [P, P], criterion=criterion)
        np.testing.assert_allclose(r.x, np.ones(2), atol=1e-12)
        np.testing.assert_allclose(r.P, P, rtol=1e-12)


# ----------------------------------------------------------------- exactness of the union
@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("seed", range(2))
def test_pairwise_union_is_the_smallest_bound(criterion, seed):
    """Against an independent reference: min f(U) over symmetric 2x2 U >= A, B (SLSQP)."""
    rng = np.random.default_rng(seed)
    _, (A, B) = random_problem(rng, 2)
    U = pair_union(A, B, np.zeros(2), np.zeros(2), criterion).U

    def f(p):
        V = np.array([[p[0], p[1]], [p[1], p[2]]])
        return np.trace(V) if criterion == "trace" else np.linalg.slogdet(V)[1]

    def smallest(p, M):
        return np.linalg.eigvalsh(np.array([[p[0], p[1]], [p[1], p[2]]]) - M).min()

    def psd(p, M):  # a 2 x 2 matrix is PSD iff its diagonal and determinant are >= 0
        D = np.array([[p[0], p[1]], [p[1], p[2]]]) - M
        return [D[0, 0], D[1, 1], D[0, 0] * D[1, 1] - D[0, 1] ** 2]

    start = A + B
    reference = minimize(f, [start[0, 0], start[0, 1], start[1, 1]], method="SLSQP",
                         constraints=[{"type": "ineq", "fun": psd, "args": (M,)}
                                      for M in (A, B)],
                         options={"ftol": 1e-14, "maxiter": 500})
    # the reference is feasible to SLSQP's tolerance (a determinant constraint of order
    # 1e-8 lets an eigenvalue reach -1e-7), so it may undercut the optimum by that much
    assert min(smallest(reference.x, A), smallest(reference.x, B)) > -1e-6
    assert f([U[0, 0], U[0, 1], U[1, 1]]) <= reference.fun + 1e-6 * abs(reference.fun)
    assert np.linalg.eigvalsh(U - A).min() > -1e-12 and np.linalg.eigvalsh(U - B).min() > -1e-12


# ----------------------------------------------------------------- optimality of the mean
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_mean_is_optimal_against_scipy(criterion):
    """Nelder-Mead from three starts on the exact union's criterion: where the rule reports
    convergence its value matches the best reference; the trace gap bounds the excess."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        n = int(rng.integers(1, 4))
        xs, Ps = random_problem(rng, n)
        r = covariance_union(xs, Ps, criterion=criterion)
        value = np.trace(r.P) if criterion == "trace" else np.linalg.slogdet(r.P)[1]
        best = min(
            minimize(union_value, start, args=(xs, Ps, criterion), method="Nelder-Mead",
                     options={"xatol": 1e-11, "fatol": 1e-14, "maxiter": 5000}).fun
            for start in (xs[0], xs[1], xs.mean(0)))
        scale = abs(best) if criterion == "trace" else 1.0
        if r.info["converged"]:  # a reported optimum is one (to the reference's accuracy)
            assert abs(value - best) <= 1e-7 * scale
        else:  # an unconverged mean (several kinks meet at the optimum) is close
            assert value - best <= 1e-3 * scale
        if criterion == "trace":  # the certified gap is a true bound of the excess
            assert value - best <= (r.info["gap"] + 1e-9) * value


def test_trace_gap_certifies_excess_at_a_fixed_start():
    """The dual bound is a lower bound of the optimum at any point (not only the optimum)."""
    from cifilter.rules._union import trace_dual_bound

    rng = np.random.default_rng(3)
    xs, Ps = random_problem(rng, 3)
    best = covariance_union(xs, Ps).info["value"]
    for u in (xs[0], xs[1], rng.standard_normal(3)):
        M = [P + np.outer(u - x, u - x) for x, P in zip(xs, Ps)]
        pair = pair_union(M[0], M[1], xs[0], xs[1], "trace")
        assert trace_dual_bound(pair, Ps[0], Ps[1]) <= best * (1 + 1e-12)


# ----------------------------------------------------------------- the guarantee
@settings(max_examples=30)
@given(st.integers(2, 3), st.integers(1, 4), st.sampled_from(["trace", "det"]), st.data())
def test_union_covers_every_input_ill_conditioned(count, n, criterion, data):
    Ps = data.draw(ill_conditioned_sets(count, n))
    values = data.draw(st.lists(st.floats(-3, 3), min_size=count * n, max_size=count * n))
    xs = [np.array(values[i * n:(i + 1) * n]) * np.sqrt(np.diag(Ps[i])) for i in range(count)]
    try:
        r = covariance_union(xs, Ps, criterion=criterion)
    except IllConditionedError:  # allowed only beyond the contract
        assert max(np.linalg.cond(P) for P in Ps) > 1e11
        return
    assert np.array_equal(r.P, r.P.T) and np.isfinite(r.P).all()
    np.linalg.cholesky(r.P)
    worst_abs, worst_rel = covered(r.x, r.P, xs, Ps)
    assert worst_abs >= -64 * n * count * EPS
    assert worst_rel >= -64 * n * count


def test_matlab_fusecovunion_example():
    """MATLAB's documented example (three 3-D tracks). The documentation shows only a plot,
    no numbers, so the numbers cannot be compared; the guarantee is checked."""
    x = np.array([[1.0, 2.0, 0.0], [2.0, 2.0, 0.0], [2.0, 3.0, 0.0]])
    p = np.array([[[10, 5, 0], [5, 10, 0], [0, 0, 1]], [[10, -5, 0], [-5, 10, 0], [0, 0, 1]],
                  [[12, 9, 0], [9, 12, 0], [0, 0, 1]]], dtype=float)
    for criterion in ("trace", "det"):
        r = covariance_union(x, p, criterion=criterion)
        assert r.info["rule"] == "candidates" and not r.info["optimal_covariance"]
        worst_abs, _ = covered(r.x, r.P, x, p)
        assert worst_abs >= -1e-14
        assert r.x[2] == 0.0 and r.P[2, 2] == pytest.approx(1.0)  # the decoupled third axis


def test_three_estimates_bound_is_at_least_each_pairwise_union():
    rng = np.random.default_rng(11)
    xs, Ps = random_problem(rng, 2, count=3)
    r = covariance_union(xs, Ps)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        Mi, Mj = (Ps[k] + np.outer(r.x - xs[k], r.x - xs[k]) for k in (i, j))
        smallest = pair_union(Mi, Mj, r.x, r.x, "trace").U
        assert np.trace(r.P) >= np.trace(smallest) * (1 - 1e-12)


# ----------------------------------------------------------------- conventions
def test_batch_matches_single_problems_and_permutation():
    rng = np.random.default_rng(5)
    xs = rng.standard_normal((6, 2, 3))
    A = rng.standard_normal((6, 2, 3, 3))
    Ps = A @ A.swapaxes(-1, -2) + 0.1 * np.eye(3)
    for criterion in ("trace", "det"):
        batch = covariance_union(xs, Ps, criterion=criterion)
        swapped = covariance_union(xs[:, ::-1], Ps[:, ::-1], criterion=criterion)
        for k in range(6):
            one = covariance_union(list(xs[k]), list(Ps[k]), criterion=criterion)
            # the single-problem whitening calls LAPACK directly: the iterations round
            # differently and stop within their tolerance (1e-6 standard deviations)
            np.testing.assert_allclose(batch.x[k], one.x, rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(batch.P[k], one.P, rtol=1e-6, atol=1e-6)
            if batch.info["converged"][k] and swapped.info["converged"][k]:
                assert swapped.info["value"][k] == pytest.approx(batch.info["value"][k],
                                                                 rel=1e-8)


def test_column_vectors_registry_filter_and_no_mutation():
    xa, xb = np.array([[1.0], [0.0]]), np.array([[0.0], [1.0]])
    Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    copies = [a.copy() for a in (xa, xb, Pa, Pb)]
    r = covariance_union([xa, xb], [Pa, Pb])
    assert r.x.shape == (2, 1)
    for a, b in zip((xa, xb, Pa, Pb), copies):
        assert np.array_equal(a, b)
    via = fuse([(xa, Pa), (xb, Pb)], method="cu")
    np.testing.assert_array_equal(via.x, r.x)
    np.testing.assert_array_equal(via.P, r.P)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P = xa.copy(), Pa.copy()
    kf.fuse((xb, Pb), method="cu", criterion="det")
    assert kf.P[0, 0] >= 4.0 - 1e-12 and kf.P[1, 1] >= 4.0 - 1e-12
    record = get_method("cu")
    assert record.guarantee == "bound" and record.horizon is None


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(criterion="volume"), ValueError, "criterion"),
    (dict(criterion=np.eye(2)), ValueError, "criterion"),
    (dict(mean=np.zeros(3)), ValueError, "mean"),
    (dict(mean=np.array([np.nan, 0.0])), ValueError, "mean"),
    (dict(mean="origin"), TypeError, "mean"),
])
def test_bad_options(kwargs, error, match):
    with pytest.raises(error, match=match):
        covariance_union([np.zeros(2), np.ones(2)], [np.eye(2), np.eye(2)], **kwargs)


def test_bad_estimates():
    with pytest.raises(ValueError, match="at least 2"):
        covariance_union([np.zeros(2)], [np.eye(2)])
    with pytest.raises(ValueError, match="positive definite"):
        covariance_union([np.zeros(2)] * 2, [np.eye(2), -np.eye(2)])


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_degenerate_problems_converge_without_error(criterion):
    """Equal covariances (exactly zero eigenvalues of M_2 - M_1 besides the rank-two offset
    part), equal estimates, and a batch mixing them with regular problems."""
    e1 = np.array([1.0, 0.0, 0.0])
    xs = np.array([[np.zeros(3), e1], [np.zeros(3), np.zeros(3)], [np.zeros(3), 3 * e1]])
    Ps = np.array([[np.eye(3), np.eye(3)], [np.eye(3), np.eye(3)],
                   [np.eye(3), np.diag([1.0, 2.0, 3.0])]])
    r = covariance_union(xs, Ps, criterion=criterion)
    assert r.info["converged"].all()
    for k in range(3):
        worst_abs, _ = covered(r.x[k], r.P[k], xs[k], Ps[k])
        assert worst_abs >= -1e-14
    np.testing.assert_allclose(r.x[0], e1 / 2, atol=1e-9)  # symmetric: halfway


def _rank_two_differences(count, seed):
    """Pairs whose covariances differ by a rank-two matrix, as in a network that fuses with
    covariance union and feeds the result back: the trace optimum then often sits on two
    kinks at once, where the per-direction iteration converges only linearly."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(count, 4, 4))
    P1 = A @ A.swapaxes(-1, -2) + np.eye(4)
    v = rng.normal(size=(count, 4, 2))
    P2 = (P1 + 3.0 * v[..., :, 0, None] * v[..., None, :, 0]
          - 0.2 * v[..., :, 1, None] * v[..., None, :, 1])
    keep = np.linalg.eigvalsh(P2)[:, 0] > 0.1
    x1 = rng.normal(size=(count, 4))
    x2 = x1 + 0.5 * rng.normal(size=(count, 4))
    return np.stack([x1, x2], 1)[keep], np.stack([P1, P2], 1)[keep]


def _union_trace(u, xs, Ps):
    M = Ps + (u - xs)[:, :, None] * (u - xs)[:, None, :]
    c = np.linalg.eigvalsh(M[1] - M[0])
    return np.trace(M[0]) + c[c > 0].sum()


def test_rank_two_differences_are_certified_by_the_smoothed_continuation():
    xs, Ps = _rank_two_differences(120, seed=5)
    r = covariance_union(xs, Ps)
    smoothed, gap = np.asarray(r.info["smoothed"]), np.asarray(r.info["gap"])
    assert smoothed.sum() >= 20  # the continuation is exercised
    assert np.all(r.info["converged"]) and np.all(gap <= 1e-9)
    value = np.trace(r.P, axis1=-2, axis2=-1)
    # the certificate is honest: nothing finds a smaller union than value (1 - gap)
    for i in np.flatnonzero(smoothed)[:6]:
        best = minimize(_union_trace, r.x[i], args=(xs[i], Ps[i]), method="Nelder-Mead",
                        options=dict(xatol=1e-12, fatol=1e-14, maxiter=20000)).fun
        assert best >= value[i] * (1 - gap[i]) - 1e-12 * value[i]


def test_smoothed_dual_bound_is_a_lower_bound_and_tight_at_the_smoothed_optimum():
    xs, Ps = _rank_two_differences(40, seed=7)
    minimum = np.trace(covariance_union(xs, Ps).P, axis1=-2, axis2=-1)
    rng = np.random.default_rng(0)
    for mu in (1.0, 1e-3, 1e-8):  # any mean and any smoothing give a valid bound
        e = rng.normal(size=xs[:, 0].shape)
        lower = smoothed_dual_bound(Ps, xs, e, np.full(len(e), mu))
        assert np.all(lower <= minimum * (1 + 1e-12))
    # at the end of the continuation the bound is within 0.28 n mu of the value
    u, lower, steps = smoothed_trace_mean(Ps, xs, xs.mean(axis=1), minimum, tol=0.0)
    M = Ps + (u[:, None, :] - xs)[..., :, None] * (u[:, None, :] - xs)[..., None, :]
    c = np.linalg.eigvalsh(M[:, 1] - M[:, 0])
    value = np.trace(M[:, 0], axis1=-2, axis2=-1) + np.maximum(c, 0).sum(-1)
    assert np.all(steps <= 10 * SMOOTHING_STAGES.size)
    assert np.all(value - lower <= 0.28 * 4 * SMOOTHING_STAGES[-1] * minimum + 1e-12 * value)
    assert np.all(lower <= minimum * (1 + 1e-12))


def _smoothed_reference(P, x, e, mu):
    """``|e|^2 + sum_k mu log(1 + exp(c_k / mu))`` for one problem, written out from ``M_i``
    (independent of :func:`smoothed_point`)."""
    M = P + (x[0] + e - x)[:, :, None] * (x[0] + e - x)[:, None, :]
    c = np.linalg.eigvalsh(M[1] - M[0])
    return e @ e + mu * np.logaddexp(0.0, c / mu).sum()


def _point(P, x, e, mu):
    d = x[1] - x[0]
    C = P[1] - P[0] + np.outer(e - d, e - d) - np.outer(e, e)
    c, V = np.linalg.eigh(C)
    return smoothed_point(np.trace(P[0])[None], e[None], c[None], V[None], d[None],
                          np.array([mu])), c, V


def test_smoothed_point_bound_equals_the_matrix_form_and_its_gap_splits():
    """The dual bound written in the eigenbasis equals ``q(Z)`` formed with matrices, and the
    gap to the value is the smoothing's part plus the residual ``|e - Z d|^2``."""
    xs, Ps = _rank_two_differences(30, seed=11)
    rng = np.random.default_rng(3)
    for P, x in zip(Ps, xs):
        for mu in (1.0, 1e-2, 1e-6):
            e = rng.normal(size=4)
            point, c, V = _point(P, x, e, mu)
            s = expit(c / mu)
            Z = (V * s) @ V.T
            d = x[1] - x[0]
            q = np.trace(P[0]) + np.trace(Z @ (P[1] - P[0])) + d @ Z @ d - (Z @ d) @ (Z @ d)
            scale = point.value[0]
            assert point.lower[0] == pytest.approx(q, abs=1e-13 * scale)
            split = (np.maximum(c, 0) - s * c).sum() + np.sum((e - Z @ d) ** 2)
            assert point.value[0] - point.lower[0] == pytest.approx(split, abs=1e-13 * scale)
            assert point.residual[0] == pytest.approx(np.sum((e - Z @ d) ** 2),
                                                      abs=1e-13 * scale)


def _gradient_fd(P, x, e, mu, h=1e-4):
    """Central differences of :func:`_smoothed_reference` in ``e``."""
    return np.array([(_smoothed_reference(P, x, e + h * unit, mu)
                      - _smoothed_reference(P, x, e - h * unit, mu)) / (2 * h)
                     for unit in np.eye(len(e))])


def test_smoothed_newton_step_and_tangent_match_finite_differences():
    """The Newton step ``-H^-1 g`` and the path tangent ``-H^-1 dg/dmu`` of the smoothed
    criterion against central differences of an independent implementation."""
    xs, Ps = _rank_two_differences(12, seed=13)
    rng = np.random.default_rng(4)
    mu, h = 0.5, 1e-4
    for P, x in zip(Ps, xs):
        e = 0.3 * rng.normal(size=4)
        g = _gradient_fd(P, x, e, mu)
        H = np.array([(_gradient_fd(P, x, e + h * unit, mu)
                       - _gradient_fd(P, x, e - h * unit, mu)) / (2 * h)
                      for unit in np.eye(4)])
        g_mu = (_gradient_fd(P, x, e, mu + h) - _gradient_fd(P, x, e, mu - h)) / (2 * h)
        point, _, _ = _point(P, x, e, mu)
        step, tangent = -np.linalg.solve(H, g), -np.linalg.solve(H, g_mu)
        np.testing.assert_allclose(point.step[0], step, rtol=1e-4,
                                   atol=1e-6 * np.linalg.norm(step))
        np.testing.assert_allclose(point.tangent[0], tangent, rtol=1e-4,
                                   atol=1e-6 * np.linalg.norm(tangent))
        assert point.residual[0] == pytest.approx(g @ g / 4, rel=1e-6)


def test_trace_certificate_is_the_union_trace_and_the_dual_bound_of_its_eigenbasis():
    """One eigen-decomposition of ``M_2 - M_1`` gives the criterion (the trace of the union
    formed with matrices) and :func:`trace_dual_bound` of the pair union at the same mean,
    and the bound is below the certified minimum."""
    xs, Ps = _rank_two_differences(40, seed=17)
    rng = np.random.default_rng(5)
    u = xs.mean(axis=1) + rng.normal(size=xs[:, 0].shape)
    value, lower, (c, V) = trace_certificate(Ps, xs, u)
    M = Ps + (u[:, None, :] - xs)[..., :, None] * (u[:, None, :] - xs)[..., None, :]
    pair = pair_union(M[:, 0], M[:, 1], xs[:, 0], xs[:, 1], "trace")
    scale = np.trace(pair.U, axis1=-2, axis2=-1)
    np.testing.assert_allclose(value, [_union_trace(u[i], xs[i], Ps[i]) for i in range(len(u))],
                               rtol=1e-13)
    np.testing.assert_allclose(value, scale, rtol=1e-13)
    assert np.all(np.abs(lower - trace_dual_bound(pair, Ps[:, 0], Ps[:, 1])) <= 1e-12 * scale)
    assert np.all(np.abs(c - np.linalg.eigvalsh(M[:, 1] - M[:, 0])) <= 1e-13 * scale[:, None])
    # (c, V) is the decomposition at u that trace_newton_steps reuses
    assert np.all(np.abs((V * c[:, None, :]) @ V.swapaxes(-1, -2) - (M[:, 1] - M[:, 0]))
                  <= 1e-13 * scale[:, None, None])
    minimum = np.trace(covariance_union(xs, Ps).P, axis1=-2, axis2=-1)
    assert np.all(lower <= minimum * (1 + 1e-12))


def test_kink_polish_certifies_the_continuation_early(monkeypatch):
    """The Newton steps of the kink's KKT system from the smoothed minimisers certify
    problems stages before the continuation alone would: fewer Newton steps in total on
    random pairs (most optima on one kink), every problem still certified to 1e-9 with the
    same criterion to that precision; where the optima sit on two kinks (the rank-two
    differences) no polish certifies and it is tried once (at most 2 more steps a problem)."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((200, 2, 4, 4))
    random_pairs = rng.standard_normal((200, 2, 4)), A @ A.swapaxes(-1, -2) + 0.1 * np.eye(4)

    def solve(xs, Ps):
        r = covariance_union(xs, Ps)
        assert np.all(r.info["converged"]) and np.all(np.asarray(r.info["gap"]) <= 1e-9)
        return np.asarray(r.info["iterations"]), np.trace(r.P, axis1=-2, axis2=-1)

    two_kinks = _rank_two_differences(120, seed=19)
    steps, value = solve(*random_pairs)
    steps_two, value_two = solve(*two_kinks)
    monkeypatch.setattr(_union, "POLISH_BELOW", 0.0)  # the continuation alone
    steps_alone, value_alone = solve(*random_pairs)
    steps_two_alone, value_two_alone = solve(*two_kinks)
    assert steps.sum() < 0.9 * steps_alone.sum()
    np.testing.assert_allclose(value, value_alone, rtol=2e-9)
    assert np.all(steps_two <= steps_two_alone + _union.POLISH_STEPS)
    np.testing.assert_allclose(value_two, value_two_alone, rtol=2e-9)


def test_candidate_values_of_two_estimates_are_the_traces_of_their_unions():
    """The candidates' trace criterion of two estimates, from the eigenvalues alone, is the
    trace of the pairwise union formed with matrices, in either order (batch (3, 5), four
    candidates each)."""
    rng = np.random.default_rng(23)
    A = rng.normal(size=(3, 5, 2, 4, 4))
    Ps = A @ A.swapaxes(-1, -2) + 0.1 * np.eye(4)
    xs = rng.normal(size=(3, 5, 2, 4))
    candidates = rng.normal(size=(3, 5, 4, 4))
    values = mean_candidates_value(Ps, xs, candidates, "trace", np.zeros((3, 5, 2), dtype=int))
    assert values.shape == (3, 5, 4)
    for index in np.ndindex(3, 5, 4):
        u = candidates[index]
        x, P = xs[index[:2]], Ps[index[:2]]
        M = P + (u - x)[:, :, None] * (u - x)[:, None, :]
        for a, b in ((0, 1), (1, 0)):
            reference = np.trace(pair_union(M[a], M[b], x[a], x[b], "trace").U)
            assert values[index] == pytest.approx(reference, rel=1e-13)
