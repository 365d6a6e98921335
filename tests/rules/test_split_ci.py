"""Split Covariance Intersection: the Kalman and CI special cases, the bound in the exact
worst direction for independent independent parts and arbitrarily correlated dependent
parts, optimality of omega, partial estimates (H), sequential N, conventions."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar
from strategies import ill_conditioned_sets
from worst_case import assert_bound_holds

from cifilter import (
    IllConditionedError,
    KalmanFilter,
    covariance_intersection,
    fuse,
    get_method,
    naive_fusion,
    split_covariance_intersection,
)

rng = np.random.default_rng(20261202)


def random_spd(n, seed, scale=1.0):
    g = np.random.default_rng(seed)
    A = g.standard_normal((n, n))
    return scale * (A @ A.T + 0.1 * np.eye(n))


def parts(n, seed):
    return ([random_spd(n, seed), random_spd(n, seed + 1, 0.5)],
            [random_spd(n, seed + 2), random_spd(n, seed + 3, 2.0)])


def criterion_of(w, Pi, Pd, criterion, H=None):
    H = np.eye(Pi[0].shape[0]) if H is None else H
    X1 = Pd[0] / w + Pi[0]
    X2 = Pd[1] / (1 - w) + Pi[1]
    P = np.linalg.inv(np.linalg.inv(X1) + H.T @ np.linalg.inv(X2) @ H)
    return np.log(np.linalg.det(P)) if criterion == "det" else np.trace(P)


# ----------------------------------------------------------------- special cases
@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_zero_independent_parts_give_covariance_intersection(criterion):
    _, Pd = parts(3, 1)
    xs = [rng.standard_normal(3) for _ in range(2)]
    zero = np.zeros((3, 3))
    r = split_covariance_intersection(xs, [zero, zero], Pd, criterion=criterion)
    ci = covariance_intersection(xs, Pd, criterion=criterion)
    assert r.weights[0] == pytest.approx(ci.weights[0], abs=1e-9)
    np.testing.assert_allclose(r.P, ci.P, rtol=1e-9)
    np.testing.assert_allclose(r.x, ci.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.info["P_independent"], zero, atol=1e-15)


def test_zero_dependent_parts_give_the_kalman_update():
    Pi, _ = parts(3, 5)
    xs = [rng.standard_normal(3) for _ in range(2)]
    zero = np.zeros((3, 3))
    r = split_covariance_intersection(xs, Pi, [zero, zero])
    naive = naive_fusion(xs, Pi)
    np.testing.assert_allclose(r.P, naive.P, rtol=1e-12)
    np.testing.assert_allclose(r.x, naive.x, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(r.info["P_dependent"], zero, atol=1e-15)
    assert r.weights[0] == 0.5 and r.info["converged"]  # the criterion is flat in omega


def test_partial_estimate_with_zero_dependent_parts_is_the_kalman_filter_update():
    """H observes the position of a (position, velocity) state: the Kalman update."""
    P1 = random_spd(2, 9)
    R = np.array([[0.5]])
    H = np.array([[1.0, 0.0]])
    x1, z = np.array([1.0, -1.0]), np.array([2.0])
    r = split_covariance_intersection([x1, z], [P1, R], [np.zeros((2, 2)), np.zeros((1, 1))],
                                      H=H)
    K = P1 @ H.T @ np.linalg.inv(H @ P1 @ H.T + R)
    np.testing.assert_allclose(r.x, x1 + K @ (z - H @ x1), rtol=1e-12)
    np.testing.assert_allclose(r.P, (np.eye(2) - K @ H) @ P1, rtol=1e-12)
    assert r.gains is None and r.info["gains"][1].shape == (2, 1)


# ----------------------------------------------------------------- the bound
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_bound_in_the_worst_direction(seed, criterion):
    """The fused error is sum_k K_k (i_k + d_k): its independent part has covariance
    P_ind = sum_k K_k P_k_ind K_k^T exactly, and P_dep dominates the dependent part for
    every correlation of the d_k, checked in the exact worst direction."""
    Pi, Pd = parts(2 + seed % 2, 10 * seed)
    n = Pi[0].shape[0]
    r = split_covariance_intersection([np.zeros(n)] * 2, Pi, Pd, criterion=criterion)
    P_ind = sum(K @ P @ K.T for K, P in zip(r.gains, Pi))
    np.testing.assert_allclose(r.info["P_independent"], P_ind, rtol=1e-10,
                               atol=1e-13 * np.abs(P_ind).max())
    assert_bound_holds(r.info["P_dependent"], r.gains, Pd, rho=1.0)
    np.testing.assert_array_equal(r.P, 0.5 * ((r.info["P_independent"] + r.info["P_dependent"])
                                              + (r.info["P_independent"]
                                                 + r.info["P_dependent"]).T))


def test_bound_with_a_partial_estimate():
    P1i, P1d = random_spd(3, 21), random_spd(3, 22)
    P2i, P2d = random_spd(2, 23), random_spd(2, 24)
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])
    r = split_covariance_intersection([np.zeros(3), np.zeros(2)], [P1i, P2i], [P1d, P2d], H=H)
    K1, K2 = r.info["gains"]
    np.testing.assert_allclose(K1 + K2 @ H, np.eye(3), atol=1e-12)
    D1, D2 = np.linalg.cholesky(P1d), np.linalg.cholesky(P2d)
    P_ind = K1 @ P1i @ K1.T + K2 @ P2i @ K2.T
    directions = np.vstack([np.linalg.eigh(r.P)[1].T, rng.standard_normal((300, 3))])
    for v in directions:
        worst = v @ P_ind @ v + (np.linalg.norm(D1.T @ K1.T @ v)
                                 + np.linalg.norm(D2.T @ K2.T @ v)) ** 2
        assert worst <= v @ r.P @ v * (1 + 1e-12)


def test_not_a_bound_when_independent_parts_are_correlated():
    """The guarantee needs truly independent parts: with the independent parts fully
    correlated in the worst direction, the error can exceed P."""
    Pi = [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])]
    Pd = [0.1 * np.eye(2), 0.1 * np.eye(2)]
    r = split_covariance_intersection([np.zeros(2)] * 2, Pi, Pd)
    with pytest.raises(AssertionError):
        assert_bound_holds(r.P, r.gains, [a + b for a, b in zip(Pi, Pd)], rho=1.0)


# ----------------------------------------------------------------- optimality
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_omega_is_optimal(seed, criterion):
    Pi, Pd = parts(3, 40 + 5 * seed)
    r = split_covariance_intersection([np.zeros(3)] * 2, Pi, Pd, criterion=criterion)
    grid = np.linspace(1e-4, 1 - 1e-4, 2001)
    k = int(np.argmin([criterion_of(w, Pi, Pd, criterion) for w in grid]))
    best = minimize_scalar(lambda w: criterion_of(w, Pi, Pd, criterion),
                           bounds=(grid[max(k - 1, 0)], grid[min(k + 1, 2000)]),
                           method="bounded", options={"xatol": 1e-12})
    assert r.info["converged"]
    assert r.weights[0] == pytest.approx(best.x, abs=1e-6)
    mine = criterion_of(r.weights[0], Pi, Pd, criterion)
    assert mine <= best.fun + 1e-10 * abs(best.fun)


# ----------------------------------------------------------------- N estimates
def test_sequential_three_estimates_is_a_bound_and_depends_on_the_order():
    Pi = [random_spd(2, 60 + k) for k in range(3)]
    Pd = [random_spd(2, 70 + k, 0.5) for k in range(3)]
    xs = [rng.standard_normal(2) for _ in range(3)]
    r = split_covariance_intersection(xs, Pi, Pd)
    assert r.weights is None and r.info["omegas"].shape == (2,)
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(2), atol=1e-12)
    np.testing.assert_allclose(np.einsum("kij,kj->i", r.gains, np.array(xs)), r.x, atol=1e-12)
    P_ind = sum(K @ P @ K.T for K, P in zip(r.gains, Pi))
    np.testing.assert_allclose(r.info["P_independent"], P_ind, rtol=1e-10)
    assert_bound_holds(r.info["P_dependent"], r.gains, Pd, rho=1.0)
    other = split_covariance_intersection(xs[::-1], Pi[::-1], Pd[::-1])
    assert not np.allclose(other.P, r.P, rtol=1e-6)


# ----------------------------------------------------------------- conditioning
@settings(max_examples=20)
@given(ill_conditioned_sets(4, 3), st.sampled_from(["det", "trace"]))
def test_conditioning_contract(Ps, criterion):
    Pi, Pd = Ps[:2], Ps[2:]
    try:
        r = split_covariance_intersection([np.zeros(3)] * 2, Pi, Pd, criterion=criterion)
    except IllConditionedError:
        assert max(np.linalg.cond(P) for P in Ps) > 1e8
        return
    assert np.all(np.isfinite(r.P)) and np.array_equal(r.P, r.P.T)
    np.linalg.cholesky(r.P)
    if r.info["converged"]:
        assert r.info["gap"] <= 1e-9


# ----------------------------------------------------------------- conventions
def test_batched_equals_one_at_a_time():
    Pi = np.stack([parts(3, 100 + 4 * k)[0] for k in range(5)])
    Pd = np.stack([parts(3, 100 + 4 * k)[1] for k in range(5)])
    xs = rng.standard_normal((5, 2, 3))
    batch = split_covariance_intersection(xs, Pi, Pd)
    for k in range(5):
        one = split_covariance_intersection(list(xs[k][..., None]), list(Pi[k]), list(Pd[k]))
        assert one.x.shape == (3, 1)
        np.testing.assert_allclose(batch.P[k], one.P, rtol=1e-10)
        np.testing.assert_allclose(batch.x[k], one.x[:, 0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(batch.info["P_dependent"][k], one.info["P_dependent"],
                                   rtol=1e-10)


def test_front_door_and_filters():
    Pi, Pd = parts(2, 120)
    Ps = [a + b for a, b in zip(Pi, Pd)]
    xs = [np.zeros(2), np.ones(2)]
    r = fuse(list(zip(xs, Ps)), method="split-ci", independent=Pi)
    direct = split_covariance_intersection(xs, Pi, Pd)
    np.testing.assert_allclose(r.P, direct.P, rtol=1e-12)
    # without independent parts: CI with the determinant criterion
    r = fuse(list(zip(xs, Ps)), method="split-ci")
    ci = covariance_intersection(xs, Ps, criterion="det")
    np.testing.assert_allclose(r.P, ci.P, rtol=1e-9)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.P = Ps[0].copy()
    kf.fuse((np.ones(2), Ps[1]), method="split-ci", independent=Pi)
    np.testing.assert_allclose(kf.P, direct.P, rtol=1e-12)
    assert get_method("split-ci").guarantee == "bound"


def test_errors_and_inputs_unchanged():
    Pi, Pd = parts(2, 130)
    xs = [np.zeros(2), np.ones(2)]
    copies = [p.copy() for p in Pi + Pd]
    split_covariance_intersection(xs, Pi, Pd)
    for p, c in zip(Pi + Pd, copies):
        np.testing.assert_array_equal(p, c)
    with pytest.raises(ValueError, match="Ps_dependent"):
        split_covariance_intersection(xs, Pi, [Pd[0], -Pd[1]])
    with pytest.raises(ValueError, match=r"Ps_independent \+ Ps_dependent"):
        split_covariance_intersection(xs, [np.zeros((2, 2))] * 2, [np.zeros((2, 2))] * 2)
    with pytest.raises(ValueError, match="H"):
        split_covariance_intersection(xs, Pi, Pd, H=np.eye(3))
    with pytest.raises(ValueError, match="two"):
        split_covariance_intersection(xs + [xs[0]], Pi + [Pi[0]], Pd + [Pd[0]], H=np.eye(2))
    with pytest.raises(ValueError, match="dependent parts"):
        fuse(list(zip(xs, Pi)), method="split-ci", independent=[a + b for a, b in zip(Pi, Pd)])
    with pytest.raises(ValueError, match="criterion"):
        split_covariance_intersection(xs, Pi, Pd, criterion="volume")


# ----------------------------------------------------------------- the certificate at high kappa
def _mp_split_criterion(w, parts, criterion):
    """The split-CI criterion at omega ``w`` from the inputs in 40-digit arithmetic
    (``P^-1 = w V_1^-1 + (1 - w) V_2^-1``, ``V_1 = P1_dep + w P1_ind``, ``V_2 = P2_dep
    + (1 - w) P2_ind``)."""
    import mpmath as mp

    (Pi1, Pd1), (Pi2, Pd2) = parts
    P = mp.inverse(w * mp.inverse(Pd1 + w * Pi1) + (1 - w) * mp.inverse(Pd2 + (1 - w) * Pi2))
    return mp.log(mp.det(P)) if criterion == "det" else sum(P[i, i] for i in range(P.rows))


def _mp_split_optimum(parts, criterion):
    """The minimum over omega by a 40-digit golden-section search (the criterion is convex)
    and at the ends."""
    import mpmath as mp

    def f(w):
        return _mp_split_criterion(w, parts, criterion)

    a, b = mp.mpf(0), mp.mpf(1)
    ratio = (mp.sqrt(5) - 1) / 2
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(110):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = f(d)
    tiny = mp.mpf(10) ** -30
    return min(fc, fd, f(tiny), f(1 - tiny))


def _mixed_scale_spd(g, n, condition):
    Q, _ = np.linalg.qr(g.standard_normal((n, n)))
    exponents = np.concatenate([[0.0, 1.0], g.uniform(0.0, 1.0, n - 2)]) * np.log10(condition)
    P = (Q * 10.0 ** (exponents + g.uniform(-12.0, 12.0))) @ Q.T
    return 0.5 * (P + P.T)


@pytest.mark.parametrize("condition", [1e9, 1e10, 1e11, 1e12])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_converged_is_never_reported_for_a_wrong_optimum_up_to_kappa_1e12(condition, criterion):
    """Issue 21, item 10: four parts of condition number ``condition``, each of its own scale
    in 1e-12..1e12 (n = 3). Against the optimum found in 40 digits from the inputs:
    ``converged=True`` means an excess of at most 1e-9 (relative for the trace, in log det);
    and on these fixed draws every returned omega, converged or not, is optimal to 1e-9
    (the figures of docs/methods/split_ci.rst, "Measured limits": the certificate, not the
    weight, is what loses accuracy at high condition numbers; here the worst unconverged
    excess is 8.1e-10 at kappa 1e12, det, and one converged gap of 2.0e-13 has a true
    excess of 7.8e-11, so the gap itself is not asserted to bound the excess)."""
    import mpmath as mp

    mp.mp.dps = 40
    g = np.random.default_rng(int(np.log10(condition)) * 10 + (criterion == "det"))
    unconverged = 0
    for _ in range(3):
        Ps = [_mixed_scale_spd(g, 3, condition) for _ in range(4)]
        r = split_covariance_intersection([np.zeros(3)] * 2, Ps[:2], Ps[2:],
                                          criterion=criterion)
        parts = tuple((mp.matrix(a.tolist()), mp.matrix(b.tolist()))
                      for a, b in zip(Ps[:2], Ps[2:]))
        w = float(r.weights[0])
        w_mp = mp.mpf(w) if 0.0 < w < 1.0 else (mp.mpf(10) ** -30 if w == 0.0
                                                  else 1 - mp.mpf(10) ** -30)
        mine = _mp_split_criterion(w_mp, parts, criterion)
        best = min(_mp_split_optimum(parts, criterion), mine)
        excess = float(mine - best) if criterion == "det" else float((mine - best) / abs(best))
        if r.info["converged"]:
            assert excess <= 1e-9
            assert r.info["gap"] <= 1e-9
        else:
            unconverged += 1
        assert excess <= 1e-9
    assert unconverged <= 3
