"""Generalised CI and the other rules with ``H=`` (issue 22, item 1).

Estimate ``i`` estimates ``H_i x``: ``P^-1 = sum_i w_i H_i^T P_i^-1 H_i``,
``K_i = w_i P H_i^T P_i^-1`` (docs/methods/partial_state.rst, eqs. (H1)-(H4)). Checked
against an independent reference (a bounded scalar search on the same criterion, from
explicit inverses), hand-derived cases, the exact worst direction from the inputs at 50
digits (tests/worst_case.py) at condition numbers to 1e12 and scales 1e-12..1e12, and the
naive, optimal and split-CI forms against their closed forms.
"""

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize, minimize_scalar
from strategies import ill_conditioned_spd, partial_state_problems, spd_matrices
from worst_case import assert_bound_holds, padded

import cifilter
from cifilter import available_methods, fuse, get_method, split_covariance_intersection

EPS = np.finfo(float).eps
POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])  # of a 2-D CV state


def random_spd(g, n, scale=1.0):
    A = g.standard_normal((n, n))
    return scale * (A @ A.T + 0.3 * np.eye(n))


def explicit_P(Ps, Hs, w):
    """(sum_i w_i H_i^T P_i^-1 H_i)^-1 from explicit inverses (the reference's way)."""
    J = sum(wi * H.T @ np.linalg.inv(P) @ H for wi, P, H in zip(w, Ps, Hs))
    return np.linalg.inv(J)


def criterion(P, kind):
    if isinstance(kind, np.ndarray):
        return np.trace(kind @ P)
    if kind == "trace":
        return np.trace(P)
    return np.linalg.slogdet(P)[1]


def reference_weight(Ps, Hs, kind):
    """The bounded scalar search (N = 2) on the same criterion, from explicit inverses."""
    found = minimize_scalar(lambda w: criterion(explicit_P(Ps, Hs, (w, 1 - w)), kind),
                            bounds=(1e-6, 1 - 1e-12), method="bounded",
                            options={"xatol": 1e-12})
    return found.x


def full_H(H, n):
    return np.eye(n) if H is None else H


# ------------------------------------------------------------------ independent reference
@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
@pytest.mark.parametrize("kind", ["trace", "det", np.diag([1.0, 10.0, 1.0, 10.0])])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_generalised_ci_equals_a_bounded_scalar_search(kind, seed):
    g = np.random.default_rng(seed)
    P1, P2 = random_spd(g, 4), random_spd(g, 2, 0.5)
    x1, x2 = g.standard_normal(4), g.standard_normal(2)
    Hs = [np.eye(4), POSITION]
    r = fuse([(x1, P1), (x2, P2)], H=[None, POSITION], criterion=kind)
    w = reference_weight([P1, P2], Hs, kind)
    assert r.info["converged"] and r.info["solver"] == "diagonalise"
    assert r.weights[0] == pytest.approx(w, abs=1e-6)
    np.testing.assert_allclose(r.P, explicit_P([P1, P2], Hs, r.weights), rtol=1e-10)
    # the criterion at the result is at most the reference's (it is the optimum)
    value = criterion(r.P, kind)
    reference = criterion(explicit_P([P1, P2], Hs, (w, 1 - w)), kind)
    assert value <= reference + 1e-12 * max(1.0, abs(reference))  # (log det: absolute)
    # the batched (simplex) path gives the same optimum
    rb = fuse([(x1[None], P1[None]), (x2[None], P2[None])], H=[None, POSITION],
              criterion=kind)
    assert rb.info["solver"] == "simplex" and rb.info["converged"].all()
    np.testing.assert_allclose(rb.P[0], r.P, rtol=1e-7)
    np.testing.assert_allclose(rb.x[0], r.x, rtol=1e-7, atol=1e-9)


def test_three_partial_estimates_equal_a_search_over_the_simplex():
    g = np.random.default_rng(5)
    Hs = [POSITION, np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]),
          np.array([[1.0, 0.5, 0.0, 0.0], [0.0, 0.0, 1.0, 0.5], [1.0, 0.0, 1.0, 0.0]])]
    Ps = [random_spd(g, H.shape[0]) for H in Hs]
    xs = [g.standard_normal(H.shape[0]) for H in Hs]
    r = fuse(list(zip(xs, Ps)), H=Hs)

    def objective(z):
        w = np.exp(z - z.max())
        return np.trace(explicit_P(Ps, Hs, w / w.sum()))

    best = minimize(objective, np.zeros(3), method="Nelder-Mead",
                    options={"xatol": 1e-10, "fatol": 1e-14, "maxfev": 4000})
    assert r.info["converged"]
    assert np.trace(r.P) <= best.fun * (1 + 1e-9)
    assert np.trace(r.P) == pytest.approx(best.fun, rel=1e-7)
    # x = P sum_i w_i H_i^T P_i^-1 x_i (eq. (H1)), from explicit inverses
    x = r.P @ sum(w * H.T @ np.linalg.solve(P, xi)
                  for w, H, P, xi in zip(r.weights, Hs, Ps, xs))
    np.testing.assert_allclose(r.x, x, rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------- hand-derived cases
@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
def test_det_optimal_weight_of_a_position_fix_by_hand():
    """P_1 = diag(a, b), the fix measures the first state with variance c < a:
    det P(w) = b / (w (w/a + (1 - w)/c)), maximal information at w = a / (2 (a - c)).
    a = 4, b = 1, c = 1: w = 2/3, P = diag(1 / (1/6 + 1/3), 1 / (2/3)) = diag(2, 1.5)."""
    H = np.array([[1.0, 0.0]])
    r = fuse([(np.array([0.0, 1.0]), np.diag([4.0, 1.0])), (np.array([3.0]), np.eye(1))],
             H=[None, H], criterion="det")
    assert r.weights[0] == pytest.approx(2.0 / 3.0, abs=1e-12)
    np.testing.assert_allclose(r.P, np.diag([2.0, 1.5]), rtol=1e-12, atol=1e-15)
    # K_2 = w_2 P H^T P_2^-1 = (1/3) [2, 0]^T; x = x_1 + K_2 (z - H x_1) = (0 + 2/3 * 3, 1)
    np.testing.assert_allclose(r.info["gains"][1], [[2.0 / 3.0], [0.0]], atol=1e-12)
    np.testing.assert_allclose(r.x, [2.0, 1.0], atol=1e-12)
    assert r.gains is None and r.info["gains"][0].shape == (2, 2)


@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
def test_a_fix_as_good_as_the_track_adds_nothing_to_the_trace_bound():
    """With P_2 equal to the first state's variance, tr P(w) = a + b / w: w = 1 exactly."""
    H = np.array([[1.0, 0.0]])
    r = fuse([(np.zeros(2), np.diag([4.0, 1.0])), (np.array([5.0]), 4.0 * np.eye(1))],
             H=[None, H])
    assert r.weights.tolist() == [1.0, 0.0]
    np.testing.assert_array_equal(r.info["gains"][1], np.zeros((2, 1)))
    np.testing.assert_allclose(r.P, np.diag([4.0, 1.0]))


def test_naive_with_H_is_the_information_form_and_optimal_the_blue():
    g = np.random.default_rng(3)
    P1, P2 = random_spd(g, 4), random_spd(g, 2)
    x1, x2 = g.standard_normal(4), g.standard_normal(2)
    naive = fuse([(x1, P1), (x2, P2)], "naive", H=[None, POSITION])
    P = explicit_P([P1, P2], [np.eye(4), POSITION], (1.0, 1.0))
    np.testing.assert_allclose(naive.P, P, rtol=1e-10)
    np.testing.assert_allclose(
        naive.x, P @ (np.linalg.solve(P1, x1) + POSITION.T @ np.linalg.solve(P2, x2)),
        rtol=1e-10)
    # optimal with a zero cross-covariance is the naive fusion
    joint = np.zeros((6, 6))
    joint[:4, :4], joint[4:, 4:] = P1, P2
    optimal = fuse([(x1, P1), (x2, P2)], "optimal", H=[None, POSITION], joint=joint)
    np.testing.assert_allclose(optimal.P, naive.P, rtol=1e-10)
    np.testing.assert_allclose(optimal.x, naive.x, rtol=1e-10)
    # and with a cross-covariance it is (E^T J^-1 E)^-1 E^T J^-1 z (eq. (H6))
    C = 0.3 * np.linalg.cholesky(P1)[:, :2] @ np.linalg.cholesky(P2).T
    joint[:4, 4:], joint[4:, :4] = C, C.T
    optimal = fuse([(x1, P1), (x2, P2)], "optimal", H=[None, POSITION], joint=joint)
    E = np.vstack([np.eye(4), POSITION])
    Ji = np.linalg.inv(joint)
    P_blue = np.linalg.inv(E.T @ Ji @ E)
    np.testing.assert_allclose(optimal.P, P_blue, rtol=1e-9)
    np.testing.assert_allclose(optimal.x, P_blue @ E.T @ Ji @ np.concatenate([x1, x2]),
                               rtol=1e-9)
    K = np.concatenate(optimal.info["gains"], axis=1)
    np.testing.assert_allclose(K @ E, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(K @ joint @ K.T, optimal.P, rtol=1e-9)


def test_split_ci_through_the_front_door_equals_its_function_with_H():
    g = np.random.default_rng(4)
    P1, P2 = random_spd(g, 4), random_spd(g, 2)
    I1, I2 = 0.5 * P1, 0.3 * P2
    x1, x2 = g.standard_normal(4), g.standard_normal(2)
    via = fuse([(x1, P1), (x2, P2)], "split-ci", H=[None, POSITION], independent=[I1, I2])
    direct = split_covariance_intersection([x1, x2], [I1, I2], [P1 - I1, P2 - I2],
                                           H=POSITION)
    same = split_covariance_intersection([x1, x2], [I1, I2], [P1 - I1, P2 - I2],
                                         H=[None, POSITION])
    for other in (direct, same):
        np.testing.assert_array_equal(via.x, other.x)
        np.testing.assert_array_equal(via.P, other.P)
    with pytest.raises(ValueError, match=r"first of the full state"):
        fuse([(x2, P2), (x1, P1)], "split-ci", H=[POSITION, None])


# ---------------------------------------------------- the exact worst direction, cond 1e12
def assert_valid(P):
    assert np.all(np.isfinite(P))
    np.testing.assert_array_equal(P, P.T)
    np.linalg.cholesky(P)


@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
@settings(max_examples=60)
@given(partial_state_problems(), st.sampled_from(["trace", "det", "weighted"]))
def test_generalised_ci_bound_holds_in_the_worst_direction(problem, kind):
    Hs, Ps, n = problem
    xs = [np.zeros(P.shape[0]) for P in Ps]
    crit = np.diag(np.arange(1.0, n + 1)) if kind == "weighted" else kind
    r = fuse(list(zip(xs, Ps)), H=Hs, criterion=crit)
    assert_valid(r.P)
    gains = r.info["gains"]
    unbiased = sum(K @ full_H(H, n) for K, H in zip(gains, Hs))
    scale = 1.0 + max(np.abs(K @ full_H(H, n)).max() for K, H in zip(gains, Hs))
    cond = max(np.linalg.cond(P) for P in Ps)
    # without a full-state estimate to absorb the remainder, sum K_i H_i = I holds to the
    # rounding of the information form, which grows with the inputs' condition number
    assert np.abs(unbiased - np.eye(n)).max() <= (1e3 * n + cond) * EPS * scale
    K_pad, P_pad = padded(gains, Ps)
    assert_bound_holds(r.P, K_pad, P_pad, tol=(64.0 * n * len(Ps) + cond) * EPS)
    gap = float(r.info["gap"])
    assert np.isfinite(gap)
    assert bool(r.info["converged"]) == (gap <= 1e-9)


def exact_condition_of_fused_information(Ps, Hs, weights, n):
    """cond(sum_i w_i H_i^T P_i^-1 H_i) at 50 digits from the inputs."""
    with mpmath.workdps(50):
        J = mpmath.zeros(n, n)
        for w, P, H in zip(weights, Ps, Hs):
            Hm = mpmath.matrix(full_H(H, n).tolist())
            J += mpmath.mpf(float(w)) * Hm.T * mpmath.inverse(mpmath.matrix(P.tolist())) * Hm
        values = mpmath.eigsy((J + J.T) / 2)[0]
        return float(max(values) / min(values)) if min(values) > 0 else np.inf


@settings(max_examples=30)
@given(partial_state_problems(), st.sampled_from(["fast", "fixed"]), st.integers(0, 2**32 - 1))
def test_generalised_ci_bound_holds_for_fast_and_given_weights(problem, rule, seed):
    """Niehsen's weights can give the only estimate of some directions a weight so small
    (1 / trace of a covariance of condition number 1e12) that the fused information is
    beyond double precision: then IllConditionedError, justified at 50 digits (the exact
    condition of the fused information is outside the contract's 1e12)."""
    Hs, Ps, n = problem
    xs = [np.zeros(P.shape[0]) for P in Ps]
    omega = (np.random.default_rng(seed).dirichlet(np.ones(len(Ps))) * 0.9
             + 0.1 / len(Ps)) if rule == "fixed" else rule
    try:
        r = fuse(list(zip(xs, Ps)), H=Hs, omega=omega)
    except cifilter.IllConditionedError:
        roots = [full_H(H, n) for H in Hs]
        weights = (omega if rule == "fixed" else
                   np.array([1.0 / np.trace(np.linalg.pinv(H.T @ np.linalg.solve(P, H)))
                             for H, P in zip(roots, Ps)]))
        # the fused information's Cholesky is refused when its computed diagonal spans
        # more than 1 / (n eps) in square (_numerics/information.py). The computed
        # information carries the rounding of the inputs' factors (up to cond(P_i) eps
        # relative), so a refusal is justified when the exact condition is outside the
        # conditioning contract (1e12): hypothesis found a computed 2.7e16 for an exact
        # 9.3e13 from a P_i of condition 4e9 given the weight 1e-10
        assert exact_condition_of_fused_information(Ps, Hs, weights, n) > 1e12
        return
    assert_valid(r.P)
    K_pad, P_pad = padded(r.info["gains"], Ps)
    cond = max(np.linalg.cond(P) for P in Ps)
    assert_bound_holds(r.P, K_pad, P_pad, tol=(64.0 * n * len(Ps) + cond) * EPS)


@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
@settings(max_examples=30)
@given(st.integers(2, 4).flatmap(lambda n: st.tuples(
    st.just(n), ill_conditioned_spd(n), st.integers(1, n),
    st.integers(0, 2**32 - 1))), st.sampled_from(["trace", "det"]))
def test_kf_pair_path_bound_holds_at_condition_numbers_to_1e12(args, kind):
    """The single-problem diagonalised path (a full-state and a partial estimate), and its
    fall-back where the diagonalisation is not trusted."""
    n, P1, m, seed = args
    g = np.random.default_rng(seed)
    H = g.standard_normal((m, n))
    scale = np.sqrt(np.abs(np.diag(P1)).max())
    P2 = (H @ P1 @ H.T) * g.uniform(0.1, 3.0) + 1e-6 * scale**2 * np.eye(m)
    r = fuse([(np.zeros(n), P1), (np.zeros(m), P2)], H=[None, H], criterion=kind)
    assert_valid(r.P)
    K_pad, P_pad = padded(r.info["gains"], [P1, P2])
    cond = max(np.linalg.cond(P1), np.linalg.cond(P2))
    assert_bound_holds(r.P, K_pad, P_pad, tol=(64.0 * n * 2 + cond) * EPS)
    K1, K2 = r.info["gains"]
    if r.weights[0] > 0.0:  # the full-state estimate absorbs the remainder
        assert np.abs(K1 + K2 @ H - np.eye(n)).max() <= 1e3 * EPS * (1 + np.abs(K2 @ H).max())
    else:  # dropped, it keeps a zero gain: K2 H = I to the information form's rounding
        assert np.all(K1 == 0.0)
        assert (np.abs(K2 @ H - np.eye(n)).max()
                <= (1e3 * n + cond) * EPS * (1 + np.abs(K2 @ H).max()))


@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
@settings(max_examples=30)
@given(st.integers(2, 4).flatmap(lambda n: st.tuples(
    st.just(n), ill_conditioned_spd(n, max_condition=1e8), st.integers(1, n),
    st.integers(0, 2**32 - 1))), st.sampled_from(["trace", "det", "weighted"]))
def test_pair_path_is_the_simplex_optimum_for_every_criterion(args, kind):
    """The diagonalised pair path (the directions beyond the rank of a partial estimate of
    m < n numbers as one term of the criterion; P from the gains, checked and reported
    without a second factorisation) reaches the optimum of the batched simplex path, and
    reports the criterion of the P it returns."""
    n, P1, m, seed = args
    g = np.random.default_rng(seed)
    H = g.standard_normal((m, n))
    # (a partial estimate better than the full one's part: mostly interior optima)
    P2 = (H @ P1 @ H.T) * g.uniform(0.05, 1.0) + 1e-6 * np.abs(np.diag(P1)).max() * np.eye(m)
    W = np.diag(np.arange(1.0, n + 1)) if kind == "weighted" else None
    crit = W if kind == "weighted" else kind
    pair = [(np.zeros(n), P1), (g.standard_normal(m), P2)]
    r = fuse(pair, H=[None, H], criterion=crit)
    assert_valid(r.P)
    if kind == "det":
        sign, log_det = np.linalg.slogdet(r.P)
        assert sign > 0 and abs(float(r.info["log_value"]) - log_det) <= 1e-9 * (
            1 + abs(log_det))
    else:
        value = np.trace(r.P if W is None else W @ r.P)
        assert float(r.info["value"]) == pytest.approx(value, rel=1e-12)
    if r.info["solver"] != "diagonalise":
        return
    assert r.info["converged"]
    rb = fuse([(x[None], P[None]) for x, P in pair], H=[None, H], criterion=crit)
    assert rb.info["solver"] == "simplex"
    if kind == "det":  # absolute in log det, as the gaps
        assert float(r.info["log_value"]) <= float(rb.info["log_value"][0]) + 1e-8
    else:
        assert float(r.info["value"]) <= float(rb.info["value"][0]) * (1 + 1e-8)


@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
def test_pair_path_hand_derived_trace_optimum():
    """Hand-derived: P_a = I (2x2), P_b = diag(1/4, 4) of H = I. In the full state's
    coordinates mu = (4, 1/4), c = (1, 1), so trace P(w) = 1/(4 - 3w) + 4/(1 + 3w) and
    f'(w) = 0 at 4 - 3w = (1 + 3w)/2: w = 7/9, P = diag(3/5, 6/5), and the gains of eq. (H8)
    K_b = (1 - w) P P_b^-1 = diag(8/15, 1/15), K_a = w P = I - K_b = diag(7/15, 14/15)."""
    pair = [(np.zeros(2), np.eye(2)), (np.ones(2), np.diag([0.25, 4.0]))]
    r = fuse(pair, H=[None, np.eye(2)], criterion="trace")
    assert r.info["solver"] == "diagonalise" and r.info["converged"]
    assert r.weights[0] == pytest.approx(7.0 / 9.0, abs=4 * EPS)
    assert r.weights[1] == pytest.approx(2.0 / 9.0, abs=4 * EPS)
    assert float(r.info["value"]) == pytest.approx(9.0 / 5.0, rel=8 * EPS)
    np.testing.assert_allclose(r.P, np.diag([3.0 / 5.0, 6.0 / 5.0]), rtol=8 * EPS,
                               atol=8 * EPS)
    Ka, Kb = r.info["gains"]
    np.testing.assert_allclose(Kb, np.diag([8.0 / 15.0, 1.0 / 15.0]), rtol=0, atol=8 * EPS)
    np.testing.assert_allclose(Ka, np.diag([7.0 / 15.0, 14.0 / 15.0]), rtol=0, atol=8 * EPS)
    np.testing.assert_allclose(r.x, [8.0 / 15.0, 1.0 / 15.0], rtol=0, atol=8 * EPS)


@pytest.mark.usefixtures("ci_backend")  # (the compiled pair under numba)
def test_front_door_H_alone_equals_its_general_path():
    """fuse(..., H=) takes a path of its own (no other front-door option); with times= of
    one time (nothing moves) the general path gives the same result bit for bit."""
    g = np.random.default_rng(11)
    P1, P2 = random_spd(g, 4), random_spd(g, 2, 0.5)
    pair = [(g.standard_normal(4), P1), (g.standard_normal(2), P2)]
    for options in ({}, {"criterion": "det"}, {"omega": "fast"}, {"omega": [0.3, 0.7]}):
        alone = fuse(pair, H=[None, POSITION], **options)
        general = fuse(pair, H=[None, POSITION], times=(0.0, 0.0), **options)
        for name in ("x", "P", "weights"):
            a, b = getattr(alone, name), getattr(general, name)
            assert (a is None and b is None) or a.tobytes() == b.tobytes()
        assert general.info["at"] == 0.0 and "at" not in alone.info
    with pytest.raises(ValueError, match="does not accept H="):
        fuse(pair, method="ei", H=[None, POSITION])


@settings(max_examples=25)
@given(st.integers(2, 4).flatmap(lambda n: st.tuples(spd_matrices(n), st.integers(1, n),
                                                     st.integers(0, 2**32 - 1))))
def test_batched_equals_per_item(args):
    P1, m, seed = args
    n = P1.shape[0]
    g = np.random.default_rng(seed)
    H = g.standard_normal((m, n))
    P2 = np.stack([random_spd(g, m) for _ in range(3)])
    x1, x2 = g.standard_normal((3, n)), g.standard_normal((3, m))
    batched = fuse([(x1, P1), (x2, P2)], H=[None, H])
    for k in range(3):
        item = fuse([(np.array([x1[k]]), P1[None]), (np.array([x2[k]]), P2[k][None])],
                    H=[None, H])
        # to rounding: numpy's matmul may sum a stack in another order than one item
        np.testing.assert_allclose(batched.P[k], item.P[0], rtol=1e-13,
                                   atol=1e-14 * np.abs(item.P).max())
        np.testing.assert_allclose(batched.x[k], item.x[0], rtol=1e-13,
                                   atol=1e-14 * np.abs(item.x).max())
        single = fuse([(x1[k], P1), (x2[k], P2[k])], H=[None, H])
        np.testing.assert_allclose(single.P, batched.P[k], rtol=1e-6,
                                   atol=1e-9 * np.abs(single.P).max())


def test_an_optimum_next_to_a_singular_face_is_certified():
    """The optimum at w_2 = 2.3e-6, next to the vertex w_2 = 1 where the fused information
    is singular (the partial estimate alone): the solver's last unchecked step landed on
    that vertex (found by hypothesis); the best point it evaluated is returned."""
    P1 = np.diag([1.0, 1.0, 1.01698608e11, 1.01698608e11])
    h = np.array([[0.34558419, 0.82161814, 0.33043708, -1.30315723]])
    problems = [(np.zeros((1, 4)), P1[None]), (np.zeros((1, 1)), np.eye(1)[None])]
    r = fuse(problems, H=[None, h])  # (a batch of one: the simplex path)
    assert r.info["solver"] == "simplex" and r.info["converged"].all()
    w = reference_weight([P1, np.eye(1)], [np.eye(4), h], "trace")
    assert r.weights[0, 1] == pytest.approx(1 - w, rel=1e-3)
    assert np.trace(r.P[0]) <= np.trace(explicit_P([P1, np.eye(1)], [np.eye(4), h],
                                                   (w, 1 - w))) * (1 + 1e-9)


def test_many_partial_estimates_use_the_interior_point_phase():
    g = np.random.default_rng(8)
    Hs = [g.standard_normal((1, 3)) for _ in range(14)]
    Ps = [random_spd(g, 1) for _ in Hs]
    r = fuse([(np.zeros(1), P) for P in Ps], H=Hs)
    assert r.info["converged"] and r.weights.shape == (14,)
    K_pad, P_pad = padded(r.info["gains"], Ps)
    assert_bound_holds(r.P, K_pad, P_pad)


# -------------------------------------------------------------------- errors and contract
def test_unobserved_directions_are_named():
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match=r"do not observe the state.*\[0\.0, 0\.0, 1\.0\]"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(2), np.eye(2))], H=[H, H])
    for method, options in (("naive", {}), ("optimal", {"joint": np.eye(4)})):
        with pytest.raises(ValueError, match=r"\[0\.0, 0\.0, 1\.0\]"):
            fuse([(np.zeros(2), np.eye(2)), (np.zeros(2), np.eye(2))], method, H=[H, H],
                 **options)
    # given weights that leave out the estimate that alone observes a direction
    with pytest.raises(ValueError, match=r"given weights.*\[0\.0, 0\.0, 1\.0\]"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))],
             H=[H, np.array([[0.0, 0.0, 1.0]])], omega=[1.0, 0.0])


def test_rules_without_H_name_the_rules_that_accept_it():
    accepting = [name for name in available_methods() if "H" in get_method(name).front_door]
    assert accepting[:5] == ["ci", "naive", "optimal", "pci", "split-ci"]
    for method in ("ei", "bayes"):
        expected = (f"method '{method}' does not accept H=; the rules that accept H are "
                    + ", ".join(repr(name) for name in accepting))
        with pytest.raises(ValueError) as raised:
            fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))], method,
                 H=[None, np.array([[1.0, 0.0]])], rho=0.5)
        assert str(raised.value) == expected


@pytest.mark.parametrize("H, error, message", [
    (np.array([[1.0, 0.0]]), ValueError, r"H must be a sequence of 2 entries"),
    ([None], ValueError, r"H has 1 entries but there are 2 estimates"),
    ("H", TypeError, r"H must be a sequence"),
    ([None, np.array([1.0, 0.0])], ValueError, r"H\[1\] must be None or a matrix"),
    ([None, np.array([[np.nan, 0.0]])], ValueError, r"H\[1\] contains non-finite"),
    ([None, np.array([[1.0, 0.0, 0.0]])], ValueError, r"H\[1\] needs 2 columns"),
    ([None, np.eye(2)], ValueError, r"H\[1\] has shape \(2, 2\).*needs 1 rows"),
    ([None, [[1 + 1j, 0.0]]], TypeError, r"H\[1\] must be real"),
    ([None, np.array([[True, False]])], TypeError, r"H\[1\] must be a numeric array"),
])
def test_bad_H_is_named(H, error, message):
    with pytest.raises(error, match=message):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))], H=H)


def test_a_full_state_estimate_of_another_dimension_needs_its_H():
    with pytest.raises(ValueError, match=r"estimates\[2\]'s P is 3x3, but the state has "
                                         r"dimension 2.*needs its H\[2\]"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1)), (np.zeros(3), np.eye(3))],
             H=[None, np.array([[1.0, 0.0]]), None])


def test_determinant_fast_rules_refuse_partial_estimates():
    with pytest.raises(ValueError, match=r"omega='det-ratio' compares the determinants"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))],
             H=[None, np.array([[1.0, 0.0]])], omega="det-ratio")


def test_fast_weights_with_H_are_niehsens_on_the_observed_part():
    """w_i proportional to 1 / tr((H_i^T P_i^-1 H_i)^+): tr(P_i) for a selection H_i."""
    P1, P2 = np.diag([1.0, 3.0]), np.array([[2.0]])
    r = fuse([(np.zeros(2), P1), (np.zeros(1), P2)], H=[None, np.array([[0.0, 1.0]])],
             omega="fast")
    np.testing.assert_allclose(r.weights, np.array([1 / 4.0, 1 / 2.0]) / 0.75)
    # H = 2 e_1: the estimate of x_1 is z / 2, of variance P_2 / 4
    r = fuse([(np.zeros(2), P1), (np.zeros(1), P2)], H=[None, np.array([[2.0, 0.0]])],
             omega="fast")
    np.testing.assert_allclose(r.weights, np.array([1 / 4.0, 2.0]) / 2.25)


def test_inputs_are_not_modified_and_the_result_is_read_only():
    g = np.random.default_rng(9)
    P1, P2 = random_spd(g, 4), random_spd(g, 2)
    x1, x2, H = g.standard_normal(4), g.standard_normal(2), POSITION.copy()
    copies = [a.copy() for a in (P1, P2, x1, x2, H)]
    for array in (P1, P2, x1, x2, H):
        array.flags.writeable = False
    r = fuse([(x1, P1), (x2, P2)], H=[None, H])
    for a, b in zip((P1, P2, x1, x2, H), copies):
        np.testing.assert_array_equal(a, b)
    assert not r.info["gains"][1].flags.writeable
    with pytest.raises(ValueError):
        r.info["gains"][1][0, 0] = 1.0


def test_horizon_with_H_is_refused():
    model = dict(F=np.eye(2), Q=np.eye(2))
    with pytest.raises(ValueError, match=r"horizon=.*does not support H="):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))],
             H=[None, np.array([[1.0, 0.0]])], horizon=2, model=model)


def test_all_none_H_is_the_ordinary_fusion():
    pair = [(np.array([1.0, 0.0]), np.diag([1.0, 4.0])), (np.zeros(2), np.diag([4.0, 1.0]))]
    a, b = fuse(pair), fuse(pair, H=[None, None])
    # (plain "ci" of two pairs takes its single-call route: the same result to rounding)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-15, atol=0)
    np.testing.assert_allclose(a.x, b.x, rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(a.omega, b.omega, rtol=1e-15, atol=0)


def test_result_x_keeps_the_style_of_the_first_estimate():
    r = fuse([(np.zeros((2, 1)), np.eye(2)), (np.zeros(1), np.eye(1))],
             H=[None, np.array([[1.0, 0.0]])])
    assert r.x.shape == (2, 1)
    assert cifilter.get_method("ci").front_door == ("H", "residual", "times")


def test_a_full_state_estimate_of_weight_zero_keeps_a_zero_gain():
    # Only the full-state estimate could take the remainder I - sum_j K_j H_j; at weight 0
    # it has no term in P, so it must keep a zero gain (the remainder is rounding
    # amplified by cond(H), which P would not cover) and the mean is sum_i K_i x_i.
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    H = Q @ np.diag([1.0, 1e-3, 1e3])  # square, invertible, condition number 1e6
    Pa, Pb = np.diag([1.0, 2.0, 3.0]), np.diag([0.5, 1.0, 4.0])
    xa, xb = np.array([1e3, -2e3, 5e2]), np.array([1.0, 2.0, 3.0])
    r = fuse([(xa, Pa), (xb, Pb)], H=[None, H], omega=[0.0, 1.0])
    Ka, Kb = r.info["gains"]
    assert np.all(Ka == 0.0)
    np.testing.assert_allclose(r.x, Kb @ xb, rtol=1e-12, atol=0)
    np.testing.assert_allclose(r.P, Kb @ Pb @ Kb.T, rtol=1e-12, atol=0)
