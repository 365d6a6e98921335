"""Known-correlation fusion: the BLUE yardstick and naive fusion."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import assert_psd, covariance_sets, fused_error_covariance, joint_covariances

from cifilter import covariance_intersection, fuse, naive_fusion, optimal_fusion


def block_diag(*blocks):
    n = sum(b.shape[0] for b in blocks)
    out, i = np.zeros((n, n)), 0
    for b in blocks:
        out[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    return out


def random_spd(n, seed):
    A = np.random.default_rng(seed).standard_normal((n, n))
    return A @ A.T + 0.1 * np.eye(n)


def test_zero_cross_covariance_equals_naive():
    Ps = [random_spd(3, s) for s in range(3)]
    xs = [np.random.default_rng(s).standard_normal(3) for s in range(3)]
    opt = optimal_fusion(xs, block_diag(*Ps))
    naive = naive_fusion(xs, Ps)
    np.testing.assert_allclose(opt.x, naive.x, rtol=1e-10)
    np.testing.assert_allclose(opt.P, naive.P, rtol=1e-10)
    np.testing.assert_allclose(opt.gains, naive.gains, rtol=1e-9, atol=1e-12)


def test_two_estimates_match_weng_djuric_2012_eqs_4_to_6():
    P11, P22 = random_spd(2, 1), random_spd(2, 2)
    P12 = 0.3 * np.linalg.cholesky(P11) @ np.linalg.cholesky(P22).T
    joint = np.block([[P11, P12], [P12.T, P22]])
    x1, x2 = np.array([1.0, -1.0]), np.array([0.5, 2.0])
    r = optimal_fusion([x1, x2], joint)
    S_inv = np.linalg.inv(P11 - P12 - P12.T + P22)
    W1, W2 = (P22 - P12.T) @ S_inv, (P11 - P12) @ S_inv  # eqs. (4), (5)
    np.testing.assert_allclose(r.gains[0], W1, rtol=1e-10)
    np.testing.assert_allclose(r.gains[1], W2, rtol=1e-10)
    np.testing.assert_allclose(r.x, W1 @ x1 + W2 @ x2, rtol=1e-10)  # eq. (6)


def test_scalar_case_by_hand():
    c = 0.5 * np.sqrt(2.0)  # correlation 0.5 between variances 1 and 2
    r = optimal_fusion([np.array([0.0]), np.array([1.0])], [[1.0, c], [c, 2.0]])
    # P = (P11 P22 - P12^2) / (P11 + P22 - 2 P12), x = (P22 - P12) / (...) x1 + ...
    denominator = 3.0 - 2 * c
    assert r.P[0, 0] == pytest.approx((2.0 - c**2) / denominator, rel=1e-12)
    assert r.x[0] == pytest.approx((1.0 - c) / denominator, rel=1e-12)


@given(covariance_sets(2, 2).flatmap(lambda Ps: st.tuples(st.just(Ps), joint_covariances(Ps))))
def test_optimal_is_never_worse_than_ci_gains(Ps_joint):
    """The BLUE error covariance is below that of any other unbiased linear fusion."""
    Ps, joint = Ps_joint
    joint = joint + 1e-6 * np.eye(4)  # strictly positive definite for the BLUE
    Ps = [joint[:2, :2], joint[2:, 2:]]
    best = optimal_fusion([np.zeros(2)] * 2, joint)
    ci = covariance_intersection([np.zeros(2)] * 2, Ps)
    assert_psd(fused_error_covariance(ci.gains, joint) - best.P, tol=1e-7,
               what="CI error covariance - optimal")
    np.testing.assert_allclose(best.P, fused_error_covariance(best.gains, joint),
                               rtol=1e-6, atol=1e-9)


def test_gains_sum_to_identity_and_batches_match_items():
    g = np.random.default_rng(4)
    joints = []
    for _ in range(6):
        A = g.standard_normal((6, 6))
        joints.append(A @ A.T + 0.5 * np.eye(6))
    joints = np.stack(joints)
    xs = g.standard_normal((6, 3, 2))
    r = optimal_fusion(xs, joints)
    np.testing.assert_allclose(r.gains.sum(axis=-3), np.broadcast_to(np.eye(2), (6, 2, 2)),
                               atol=1e-10)
    for i in range(6):
        single = optimal_fusion(list(xs[i]), joints[i])
        np.testing.assert_allclose(r.x[i], single.x, rtol=1e-10)
        np.testing.assert_allclose(r.P[i], single.P, rtol=1e-10)


def test_column_vectors_and_layout_inference():
    joint = np.eye(4)
    r = optimal_fusion([np.ones((2, 1)), np.zeros((2, 1))], joint)
    assert r.x.shape == (2, 1)
    r = optimal_fusion(np.ones((2, 2, 1)), joint)
    assert r.x.shape == (2, 1)
    np.testing.assert_allclose(r.x[:, 0], [1.0, 1.0])


@pytest.mark.parametrize("xs, joint, message", [
    ([np.zeros(2)] * 2, np.eye(5), "N\\*n"),
    (np.zeros((2, 2)), np.eye(5), "does not match"),
    ([np.zeros(2)] * 2, np.ones((4, 4)), "not positive definite"),
    ([np.zeros(2)] * 2, np.eye(4)[:3], "shape"),
    ([np.zeros(2)] * 2, np.full((4, 4), np.nan), "non-finite"),
])
def test_bad_joint_is_named(xs, joint, message):
    with pytest.raises(ValueError, match=message):
        optimal_fusion(xs, joint)


def test_fuse_checks_that_joint_matches_the_estimates():
    joint = np.eye(4)
    with pytest.raises(ValueError, match="diagonal blocks of joint"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(2), 2 * np.eye(2))], "optimal", joint=joint)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 4, 4\)"):
        fuse([(np.zeros(2), np.eye(2))] * 2, "optimal", joint=np.eye(6))
    r = fuse([(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))], "optimal", joint=joint)
    np.testing.assert_allclose(r.x, [0.5, 0.5])


def test_naive_fusion_by_hand():
    r = naive_fusion([np.array([0.0]), np.array([3.0])], [np.eye(1), 2 * np.eye(1)])
    assert r.P[0, 0] == pytest.approx(2 / 3)
    assert r.x[0] == pytest.approx(1.0)
    assert r.omega is None and r.method == "naive"
