"""Sampling Covariance Intersection (:mod:`cifilter.rules.sampling_ci`, ``"sci"``).

What it claims: ``P = rho P_0`` with the naive fusion ``P_0`` and ``1 <= r_min <= rho <= r_max
<= N`` (between the naive fusion and CI with equal weights); the sampled extremes converge to
the exact ones (closed form for two estimates) from inside; reproducible draws; no guarantee
(a joint its gains' error exceeds ``P`` for), except ``rho = N`` where it is CI with equal
weights; conventions and bad input.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets
from worst_case import assert_bound_holds, worst_case_variance

from cifilter import (
    KalmanFilter,
    covariance_intersection,
    fuse,
    get_method,
    naive_fusion,
    sampling_ci,
)

EPS = np.finfo(float).eps


def exact_extremes(Pa, Pb):
    """``r = 1 + min(mu, 1/mu)`` with ``mu = q_b / q_a`` ranging over the generalised
    eigenvalues of (Pb^-1, Pa^-1): the exact ``r_min`` and ``r_max`` of two estimates."""
    Ia, Ib = np.linalg.inv(Pa), np.linalg.inv(Pb)
    mu = np.linalg.eigvals(np.linalg.solve(Ia, Ib)).real
    lo, hi = mu.min(), mu.max()
    f = lambda m: 1.0 + min(m, 1.0 / m)  # noqa: E731
    r_max = 2.0 if lo <= 1.0 <= hi else max(f(lo), f(hi))
    return min(f(lo), f(hi)), r_max


def test_nrl_example_covariances():
    """The NRL library's example covariances: r reaches 2 along the diagonal (exactly),
    and 1.01 along the axes."""
    xs = [np.array([1.0, -2.0]), np.array([-2.0, -1.0])]
    Ps = [np.diag([1.0, 100.0]), np.diag([100.0, 1.0])]
    assert exact_extremes(*Ps) == pytest.approx((1.01, 2.0))
    r = sampling_ci(xs, Ps, samples=20000, u=0.0, rng=3)
    assert 2.0 - 1e-3 < r.info["r_max"] <= 2.0
    assert 1.01 <= r.info["r_min"] < 1.01 + 1e-3
    naive = naive_fusion(xs, Ps)
    np.testing.assert_allclose(r.x, naive.x, rtol=1e-12)
    np.testing.assert_allclose(r.P, r.info["rho"] * naive.P, rtol=1e-12)
    np.testing.assert_allclose(r.weights, 1.0 / r.info["rho"], rtol=1e-14)


@pytest.mark.parametrize("seed", range(3))
def test_sampled_extremes_converge_to_the_exact_ones_from_inside(seed):
    g = np.random.default_rng(seed)
    A = g.standard_normal((2, 2, 2))
    Ps = list(A @ A.swapaxes(-1, -2) + 0.1 * np.eye(2))
    r_min, r_max = exact_extremes(*Ps)
    r = sampling_ci([np.zeros(2)] * 2, Ps, samples=40000, rng=seed)
    assert r_min - 1e-12 <= r.info["r_min"] <= r_min + 2e-3
    assert r_max - 2e-3 <= r.info["r_max"] <= r_max + 1e-12


@settings(max_examples=30)
@given(st.integers(2, 4), st.integers(1, 4), st.floats(0.0, 1.0), ill_conditioned_sets(4, 4))
def test_between_naive_and_equal_weight_ci_ill_conditioned(count, n, u, Ps):
    Ps = [P[:n, :n] for P in Ps[:count]]
    xs = [np.full(n, float(i)) * np.sqrt(np.diag(P)) for i, P in enumerate(Ps)]
    r = sampling_ci(xs, Ps, samples=50, u=u, rng=1)
    rho, lo, hi = float(r.info["rho"]), float(r.info["r_min"]), float(r.info["r_max"])
    assert 1.0 <= lo <= rho <= hi <= count
    assert rho == pytest.approx(u * lo + (1 - u) * hi, rel=1e-14)
    assert np.array_equal(r.P, r.P.T) and np.isfinite(r.P).all()
    np.linalg.cholesky(r.P)
    naive = naive_fusion(xs, Ps)
    norm = np.linalg.norm(r.P, 2)
    np.testing.assert_allclose(r.P, rho * naive.P, atol=64 * n * count * EPS * norm
                               * max(np.linalg.cond(P) for P in Ps) ** 0.5)
    gap = np.linalg.eigvalsh(r.P - naive.P).min()
    assert gap >= -64 * n * count * EPS * norm * max(np.linalg.cond(P) for P in Ps) ** 0.5


def test_same_seed_same_result_and_deterministic_default():
    xs = [np.zeros(3), np.ones(3), -np.ones(3)]
    g = np.random.default_rng(0)
    A = g.standard_normal((3, 3, 3))
    Ps = list(A @ A.swapaxes(-1, -2) + 0.1 * np.eye(3))
    a, b = sampling_ci(xs, Ps, rng=5), sampling_ci(xs, Ps, rng=5)
    assert np.array_equal(a.P, b.P) and np.array_equal(a.x, b.x)
    assert np.array_equal(sampling_ci(xs, Ps).P, sampling_ci(xs, Ps, rng=0).P)
    assert np.array_equal(sampling_ci(xs, Ps, rng=np.random.default_rng(5)).P, a.P)
    assert not np.array_equal(sampling_ci(xs, Ps, rng=6).P, a.P)
    via = fuse(list(zip(xs, Ps)), method="sci", rng=5)
    assert np.array_equal(via.P, a.P)
    assert a.info["samples"] == 200  # the default 100 (N - 1)


def test_permutation_invariance_with_the_same_draws():
    g = np.random.default_rng(8)
    A = g.standard_normal((3, 2, 2))
    Ps = A @ A.swapaxes(-1, -2) + 0.1 * np.eye(2)
    xs = g.standard_normal((3, 2))
    r = sampling_ci(xs, Ps, rng=2)
    s = sampling_ci(xs[::-1], Ps[::-1], rng=2)
    np.testing.assert_allclose(s.P, r.P, rtol=1e-10)
    np.testing.assert_allclose(s.x, r.x, rtol=1e-10, atol=1e-12)


def test_no_guarantee_and_the_case_where_it_is_ci():
    # One input much better: r <= 1.01 everywhere, P is about the better input's, but the
    # gains also take 1% of the worse one: fully correlated errors exceed P.
    Ps = [np.eye(1), 100.0 * np.eye(1)]
    r = sampling_ci([np.zeros(1)] * 2, Ps, rng=0)
    assert float(r.info["r_max"]) <= 1.01 + 1e-12
    worst = float(worst_case_variance(r.gains, Ps, np.ones(1)))
    assert worst > 1.1 * float(r.P[0, 0])
    # rho = N: CI with equal weights, a bound for every correlation
    Ps = [np.diag([1.0, 100.0]), np.diag([100.0, 1.0])]
    r = sampling_ci([np.zeros(2)] * 2, Ps, samples=20000, u=0.0, rng=3)
    forced = covariance_intersection([np.zeros(2)] * 2, Ps, omega=[0.5, 0.5])
    np.testing.assert_allclose(r.P, forced.P, rtol=2e-3)
    exact = sampling_ci([np.zeros(2)] * 2, Ps, samples=20000, u=0.0, rng=3)
    assert_bound_holds(exact.P * 2.0 / float(exact.info["rho"]), exact.gains, Ps)


def test_batch_and_columns_and_filter_and_no_mutation():
    g = np.random.default_rng(1)
    A = g.standard_normal((4, 3, 2, 2))
    Ps = A @ A.swapaxes(-1, -2) + 0.1 * np.eye(2)
    xs = g.standard_normal((4, 3, 2))
    copies = xs.copy(), Ps.copy()
    r = sampling_ci(xs, Ps, samples=30, rng=0)
    assert r.P.shape == (4, 2, 2) and r.weights.shape == (4, 3) and r.info["rho"].shape == (4,)
    assert np.array_equal(xs, copies[0]) and np.array_equal(Ps, copies[1])
    naive = naive_fusion(xs, Ps)
    np.testing.assert_allclose(r.P, r.info["rho"][:, None, None] * naive.P, rtol=1e-10)
    col = sampling_ci([xs[0, i][:, None] for i in range(3)], list(Ps[0]), rng=0)
    assert col.x.shape == (2, 1)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P = xs[0, 0][:, None].copy(), Ps[0, 0].copy()
    kf.fuse((xs[0, 1], Ps[0, 1]), method="sci", rng=4)
    expected = sampling_ci([xs[0, 0], xs[0, 1]], [Ps[0, 0], Ps[0, 1]], rng=4)
    np.testing.assert_allclose(kf.P, expected.P)
    assert get_method("sci").guarantee == "none"


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(samples=0), ValueError, "samples"),
    (dict(samples=2.5), TypeError, "samples"),
    (dict(u=1.5), ValueError, "u"),
    (dict(u="half"), TypeError, "u"),
    (dict(rng="seed"), TypeError, "rng"),
])
def test_bad_options(kwargs, error, match):
    with pytest.raises(error, match=match):
        sampling_ci([np.zeros(2), np.ones(2)], [np.eye(2), np.eye(2)], **kwargs)


def test_bad_estimates():
    with pytest.raises(ValueError, match="at least 2"):
        sampling_ci([np.zeros(2)], [np.eye(2)])
    with pytest.raises(ValueError, match="not symmetric"):
        sampling_ci([np.zeros(2)] * 2, [np.eye(2), np.array([[1.0, 0.5], [0.0, 1.0]])])


def test_rho_stays_between_the_extremes_when_they_nearly_coincide():
    # one dimension: every direction gives the same ratio up to rounding (r_min and r_max
    # 4 ulp apart); u r_min + (1 - u) r_max rounded above r_max here before it was clipped
    r = sampling_ci([np.zeros(1), np.ones(1)], [np.array([[1.5]]), np.array([[1.0]])],
                    samples=50, u=2.7747622030764872e-08, rng=1)
    assert r.info["r_min"] <= r.info["rho"] <= r.info["r_max"]
