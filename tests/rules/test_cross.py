"""Assumed-correlation ("cross") fusion: Bar-Shalom-Campo when the assumption is the truth,
hand-derived values, MATLAB's documented fusexcov example, what the lack of a guarantee
means, conditioning and conventions."""

import numpy as np
import pytest
from hypothesis import given, settings
from scipy.linalg import sqrtm
from strategies import ill_conditioned_sets

from cifilter import (
    IllConditionedError,
    KalmanFilter,
    cross_covariance_fusion,
    fuse,
    get_method,
    naive_fusion,
    optimal_fusion,
)

rng = np.random.default_rng(20261203)


def random_spd(n, seed):
    g = np.random.default_rng(seed)
    A = g.standard_normal((n, n))
    return A @ A.T + 0.1 * np.eye(n)


def assumed_joint(Ps, rho):
    S = [np.real(sqrtm(P)) for P in Ps]
    return np.block([[Ps[i] if i == j else rho * S[i] @ S[j] for j in range(len(Ps))]
                     for i in range(len(Ps))])


@pytest.mark.parametrize("count", [2, 3, 4])
@pytest.mark.parametrize("rho", [0.0, 0.4, 0.9])
def test_is_bar_shalom_campo_when_the_assumption_is_true(count, rho):
    Ps = [random_spd(3, 10 * count + k) for k in range(count)]
    xs = [rng.standard_normal(3) for _ in range(count)]
    r = cross_covariance_fusion(xs, Ps, rho)
    best = optimal_fusion(xs, assumed_joint(Ps, rho))
    np.testing.assert_allclose(r.P, best.P, rtol=1e-10)
    np.testing.assert_allclose(r.x, best.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3), atol=1e-12)
    # P is the covariance of the returned gains under the assumed joint
    K = np.concatenate(list(r.gains), axis=-1)
    np.testing.assert_allclose(r.P, K @ assumed_joint(Ps, rho) @ K.T, rtol=1e-10)


def test_two_estimate_formula_of_bar_shalom_and_campo():
    """x = xa + (Pa - Pab)(Pa + Pb - Pab - Pba)^-1 (xb - xa), P = Pa - (Pa - Pab)(...)^-1
    (Pa - Pba), with Pab = rho Pa^1/2 Pb^1/2."""
    Pa, Pb = random_spd(2, 1), random_spd(2, 2)
    xa, xb = np.array([1.0, 0.0]), np.array([0.0, 2.0])
    Pab = 0.4 * np.real(sqrtm(Pa)) @ np.real(sqrtm(Pb))
    D = np.linalg.inv(Pa + Pb - Pab - Pab.T)
    r = cross_covariance_fusion([xa, xb], [Pa, Pb])
    np.testing.assert_allclose(r.x, xa + (Pa - Pab) @ D @ (xb - xa), rtol=1e-12)
    np.testing.assert_allclose(r.P, Pa - (Pa - Pab) @ D @ (Pa - Pab).T, rtol=1e-12)
    assert r.info["rho"] == 0.4 and r.weights is None


def test_scalar_hand_values_and_rho_zero_is_naive():
    r = cross_covariance_fusion([np.zeros(1), np.ones(1)], [np.eye(1), 4 * np.eye(1)], 0.4)
    # Pab = 0.8: x = 0 + (1 - 0.8) / (1 + 4 - 1.6) * 1, P = 1 - 0.2^2 / 3.4
    assert r.x[0] == pytest.approx(0.2 / 3.4, rel=1e-14)
    assert r.P[0, 0] == pytest.approx(1 - 0.04 / 3.4, rel=1e-14)
    Ps = [random_spd(3, 3), random_spd(3, 4)]
    xs = [rng.standard_normal(3) for _ in range(2)]
    np.testing.assert_allclose(cross_covariance_fusion(xs, Ps, 0.0).P, naive_fusion(xs, Ps).P,
                               rtol=1e-11)


def test_matlab_fusexcov_documented_example_runs():
    """MATLAB's fusexcov page fuses these three tracks (default factor 0.4) but prints no
    numbers (only a plot), so there are no published values to compare with: we check
    that the same input gives the best linear fusion for our assumed joint, symmetric
    positive definite, with the decoupled third component fused as scalars."""
    x = np.array([[1.0, 2.0, 0.0], [2.0, 2.0, 0.0], [2.0, 3.0, 0.0]])
    p = np.array([[[10, 5, 0], [5, 10, 0], [0, 0, 1]], [[10, -5, 0], [-5, 10, 0], [0, 0, 1]],
                  [[12, 9, 0], [9, 12, 0], [0, 0, 1]]], dtype=float)
    r = cross_covariance_fusion(x, p)
    best = optimal_fusion(list(x), assumed_joint(list(p), 0.4))
    np.testing.assert_allclose(r.P, best.P, rtol=1e-10)
    np.linalg.cholesky(r.P)
    # third component: three unit variances, correlation 0.4: (1 + 2 rho) / 3
    assert r.P[2, 2] == pytest.approx((1 + 2 * 0.4) / 3, rel=1e-12)


def test_no_guarantee_even_below_the_assumed_correlation():
    """sigma_a = 1, sigma_b = 2, assumed rho = 0.9: the gain of b is negative, and the true
    error variance with *independent* errors exceeds P (overconfident), while with the
    assumed correlation P is exact and with equal variances a smaller correlation is
    covered."""
    Pa, Pb = np.eye(1), 4 * np.eye(1)
    r = cross_covariance_fusion([np.zeros(1)] * 2, [Pa, Pb], 0.9)
    ka, kb = r.gains[0, 0, 0], r.gains[1, 0, 0]
    assert kb < 0
    independent = ka**2 * 1 + kb**2 * 4
    assert independent > 3 * r.P[0, 0]
    assumed = independent + 2 * ka * kb * 0.9 * 2
    assert assumed == pytest.approx(r.P[0, 0], rel=1e-12)
    r = cross_covariance_fusion([np.zeros(1)] * 2, [Pa, Pa], 0.4)
    for true_rho in (0.0, 0.2, 0.4):
        ka, kb = r.gains[:, 0, 0]
        assert ka**2 + kb**2 + 2 * ka * kb * true_rho <= r.P[0, 0] * (1 + 1e-12)


@settings(max_examples=30)
@given(ill_conditioned_sets(2, 3))
def test_conditioning_contract(Ps):
    try:
        r = cross_covariance_fusion([np.zeros(3)] * 2, Ps)
    except IllConditionedError:
        return
    assert np.all(np.isfinite(r.P)) and np.array_equal(r.P, r.P.T)
    np.linalg.cholesky(r.P)


def test_batched_equals_one_at_a_time():
    Ps = np.stack([[random_spd(2, 50 + 3 * k + j) for j in range(3)] for k in range(4)])
    xs = rng.standard_normal((4, 3, 2))
    batch = cross_covariance_fusion(xs, Ps, 0.3)
    for k in range(4):
        one = cross_covariance_fusion(list(xs[k][..., None]), list(Ps[k]), 0.3)
        assert one.x.shape == (2, 1)
        np.testing.assert_allclose(batch.P[k], one.P, rtol=1e-12)
        np.testing.assert_allclose(batch.x[k], one.x[:, 0], rtol=1e-12, atol=1e-14)


def test_front_door_filter_and_errors():
    Pa, Pb = random_spd(2, 60), random_spd(2, 61)
    r = fuse([(np.zeros(2), Pa), (np.ones(2), Pb)], method="cross", rho=0.5)
    np.testing.assert_array_equal(
        r.P, cross_covariance_fusion([np.zeros(2), np.ones(2)], [Pa, Pb], 0.5).P)
    assert get_method("cross").guarantee == "none"
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.P = Pa.copy()
    kf.fuse((np.ones(2), Pb), method="cross")
    assert kf.x.shape == (2, 1)
    copies = (Pa.copy(), Pb.copy())
    for bad in (1.0, -0.1, 2.0):
        with pytest.raises(ValueError, match="rho"):
            cross_covariance_fusion([np.zeros(2)] * 2, [Pa, Pb], bad)
    with pytest.raises(TypeError, match="rho"):
        cross_covariance_fusion([np.zeros(2)] * 2, [Pa, Pb], "0.4")
    # equal estimates with rho next to 1: the differences have covariance (1 - rho^2) S^2,
    # factored without cancellation; the fusion returns the common estimate
    r = cross_covariance_fusion([np.zeros(2)] * 2, [Pa, Pa], 1.0 - 1e-15)
    np.testing.assert_allclose(r.P, Pa, rtol=1e-9)
    np.testing.assert_array_equal(Pa, copies[0])
    np.testing.assert_array_equal(Pb, copies[1])
