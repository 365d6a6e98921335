"""Known-correlation fusion: the BLUE yardstick and naive fusion."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import (
    assert_psd,
    covariance_sets,
    fused_error_covariance,
    ill_conditioned_spd,
    joint_covariances,
)

from cifilter import KalmanFilter, covariance_intersection, fuse, naive_fusion, optimal_fusion
from cifilter._numerics.linalg import IllConditionedError

# every test runs on each backend (numpy, and the compiled kernels when numba is installed)
pytestmark = pytest.mark.usefixtures("ci_backend")


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
    ([np.zeros(2)] * 2, np.ones((4, 4)), "fusion undefined|leaves the fusion undefined"),
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


# ----------------------------------------------------------------- singular (PSD) joints
def gain_matrix(result):
    """[K_1 ... K_N], n x N*n."""
    return np.concatenate(list(result.gains), axis=-1)


def blue_formula(xs, joint):
    """Eqs. (18)-(20) with explicit inverses (reference only)."""
    count, n = len(xs), xs[0].shape[0]
    E = np.tile(np.eye(n), (count, 1))
    J_inv = np.linalg.inv(joint)
    P = np.linalg.inv(E.T @ J_inv @ E)
    return P @ E.T @ J_inv @ np.concatenate(xs), P


def exchange_and_fuse(seed=5, n=3):
    """Two filters with a known joint covariance exchange estimates and both fuse optimally.

    Returns the filters and the joint covariance of their new errors, which is singular:
    both hold the same estimate, e_a = K_a e and e_b = K_b e with K_a = K_b up to order.
    """
    g = np.random.default_rng(seed)
    A = g.standard_normal((2 * n, 2 * n))
    joint = A @ A.T + 0.1 * np.eye(2 * n)
    a, b = KalmanFilter(dim_x=n, dim_z=1), KalmanFilter(dim_x=n, dim_z=1)
    a.x, b.x = g.standard_normal((n, 1)), g.standard_normal((n, 1))
    a.P, b.P = joint[:n, :n].copy(), joint[n:, n:].copy()
    sent_a, sent_b = (a.x.copy(), a.P.copy()), (b.x.copy(), b.P.copy())
    swapped = np.block([[joint[n:, n:], joint[n:, :n]], [joint[:n, n:], joint[:n, :n]]])
    ra = a.fuse(sent_b, method="optimal", joint=joint)
    rb = b.fuse(sent_a, method="optimal", joint=swapped)
    K_a = gain_matrix(ra)  # over (e_a, e_b)
    K_b = np.concatenate([rb.gains[1], rb.gains[0]], axis=-1)  # b's gains, reordered
    cross = K_a @ joint @ K_b.T
    new_joint = np.block([[a.P, cross], [cross.T, b.P]])
    return a, b, new_joint


def test_two_way_exchange_leaves_a_singular_joint():
    a, b, joint = exchange_and_fuse()
    np.testing.assert_allclose(a.x, b.x, rtol=1e-10, atol=1e-12)
    eigenvalues = np.linalg.eigvalsh(joint)
    assert abs(eigenvalues[0]) < 1e-13 * eigenvalues[-1]  # singular up to rounding


def test_after_a_two_way_exchange_optimal_fusion_fuses_again():
    a, b, joint = exchange_and_fuse()
    x_before, P_before = a.x.copy(), a.P.copy()
    r = a.fuse(b, method="optimal", joint=joint)  # old code: "not positive definite"
    assert r.info["joint"] == "singular"
    assert np.all(np.isfinite(r.x)) and np.all(np.isfinite(r.P))
    np.testing.assert_array_equal(r.P, r.P.T)
    np.linalg.cholesky(r.P)  # positive definite
    # Nothing new was learnt: the same estimate and covariance.
    np.testing.assert_allclose(r.x, x_before, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.P, P_before, rtol=1e-10, atol=1e-12)
    # The fused error covariance is K J K^T for the gains returned.
    K = gain_matrix(r)
    np.testing.assert_allclose(K @ joint @ K.T, r.P, rtol=1e-12, atol=1e-14 * np.trace(joint))
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3), atol=1e-12)
    # The non-singular formula on a slightly regularised nearby joint agrees.
    delta = 1e-9 * np.trace(joint) / 6
    x_reg, P_reg = blue_formula([x_before[:, 0], b.x[:, 0]], joint + delta * np.eye(6))
    np.testing.assert_allclose(r.P, P_reg, rtol=1e-6, atol=1e-6 * np.abs(r.P).max())
    np.testing.assert_allclose(r.x[:, 0], x_reg, rtol=1e-6, atol=1e-6)


def test_after_an_exchange_and_a_common_prediction_the_joint_is_still_singular_and_fuses():
    a, b, joint = exchange_and_fuse(seed=9, n=2)
    F, Q = np.array([[1.0, 1.0], [0.0, 1.0]]), np.diag([0.1, 0.2])
    for kf in (a, b):
        kf.F, kf.Q = F, Q
        kf.predict()
    FF = np.kron(np.eye(2), F)
    joint = FF @ joint @ FF.T + np.kron(np.ones((2, 2)), Q)  # common process noise
    r = optimal_fusion([a.x, b.x], joint)
    assert r.info["joint"] == "singular"
    np.testing.assert_allclose(r.P, a.P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.x, a.x, rtol=1e-10, atol=1e-12)


@given(covariance_sets(2, 2).flatmap(lambda Ps: st.tuples(st.just(Ps), joint_covariances(Ps))),
       st.floats(0.0, 1.0))
def test_fusing_with_a_copy_of_an_estimate_returns_it(Ps_joint, mix):
    """Three estimates, the third a linear combination of the first two: J is singular."""
    _, joint = Ps_joint
    joint = joint + 0.05 * np.eye(4)
    T = np.block([[np.eye(4)], [mix * np.eye(2), (1 - mix) * np.eye(2)]])  # x_3 = m x_1 + ...
    big = T @ joint @ T.T
    xs = [np.array([1.0, -1.0]), np.array([0.5, 2.0])]
    xs.append(mix * xs[0] + (1 - mix) * xs[1])
    r = optimal_fusion(xs, 0.5 * (big + big.T))
    two = optimal_fusion(xs[:2], joint)
    scale = np.abs(two.P).max()
    np.testing.assert_allclose(r.P, two.P, rtol=1e-7, atol=1e-9 * scale)
    np.testing.assert_allclose(r.x, two.x, rtol=1e-7, atol=1e-7 * (1 + np.abs(two.x).max()))
    K = gain_matrix(r)
    np.testing.assert_allclose(K @ big @ K.T, r.P, rtol=1e-7, atol=1e-9 * scale)


def test_regular_joints_keep_the_exact_formula():
    g = np.random.default_rng(11)
    A = g.standard_normal((6, 6))
    joint = A @ A.T + 0.5 * np.eye(6)
    xs = list(g.standard_normal((3, 2)))
    r = optimal_fusion(xs, joint)
    x_ref, P_ref = blue_formula(xs, joint)
    assert r.info["joint"] == "regular"
    np.testing.assert_allclose(r.P, P_ref, rtol=1e-12)
    np.testing.assert_allclose(r.x, x_ref, rtol=1e-12, atol=1e-14)


@given(ill_conditioned_spd(4))
def test_conditioning_contract_for_optimal_fusion(joint):
    """cond(joint) <= 1e12: finite, symmetric, PD output, or IllConditionedError."""
    try:
        r = optimal_fusion([np.ones(2), -np.ones(2)], joint)
    except IllConditionedError:
        return
    assert np.all(np.isfinite(r.x)) and np.all(np.isfinite(r.P))
    np.testing.assert_array_equal(r.P, r.P.T)
    np.linalg.cholesky(r.P)


@pytest.mark.parametrize("xs, joint, error, message", [
    (np.zeros((3, 2, 2)), np.broadcast_to(np.eye(4), (4, 4, 4)), ValueError,
     r"batch shapes of xs \(3,\) and joint \(4,\) do not broadcast"),
    ([np.zeros(2)] * 2, -np.eye(4), ValueError,
     r"joint is not positive semidefinite \(smallest eigenvalue -1"),
    ([np.zeros(2)] * 2, np.zeros((4, 4)), ValueError, "joint has a zero diagonal"),
    ([np.zeros(2)] * 2, np.eye(4) + 0j, TypeError, "joint must be real"),
    ([np.zeros(2)] * 2, np.eye(4, dtype=bool), TypeError, "joint must be a numeric array"),
    ([np.zeros(2)] * 2, np.ones(4), ValueError, r"joint must have shape \(\.\.\., N\*n"),
    ([np.zeros(2) + 1j, np.zeros(2)], np.eye(4), TypeError, r"xs\[0\] must be real"),
])
def test_bad_optimal_inputs_are_named(xs, joint, error, message):
    with pytest.raises(error, match=message):
        optimal_fusion(xs, joint)


def test_fuse_optimal_names_batch_mismatch_and_missing_joint():
    batch = [(np.zeros((3, 2)), np.eye(2)), (np.zeros((3, 2)), np.eye(2))]
    with pytest.raises(ValueError, match=r"batch shapes of the estimates \(3,\) and joint "
                                         r"\(4,\) do not broadcast"):
        fuse(batch, "optimal", joint=np.broadcast_to(np.eye(4), (4, 4, 4)))
    with pytest.raises(TypeError, match=r"'optimal' needs the option\(s\) 'joint'"):
        fuse(batch, "optimal")
    with pytest.raises(ValueError, match="joint contains non-finite"):
        fuse(batch, "optimal", joint=np.full((4, 4), np.nan))
