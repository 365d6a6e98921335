"""Information-form fusion with scalar weights (cifilter._numerics.information)."""

import numpy as np
import pytest
from helpers import fused_bound_tolerance
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from strategies import covariance_sets, ill_conditioned_sets
from worst_case import assert_bound_holds, assert_unbiased

from cifilter._numerics.information import (
    checked_cholesky,
    diagonal_spread_squared,
    information_factors,
    information_matrices,
    log_det_curvature,
    lower_inverse_stack,
    reference_estimates,
    squared_norms,
    trace_curvature,
    weighted_fusion,
)
from cifilter._numerics.linalg import IllConditionedError

rng = np.random.default_rng(4)


def spd(shape, n):
    A = rng.standard_normal(shape + (n, n))
    return A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(n)


def fuse(xs, Ps, weights):
    L = np.linalg.cholesky(Ps)
    return weighted_fusion(np.asarray(xs, float), L, np.asarray(weights, float))


@pytest.mark.parametrize("shape", [(), (4,), (2, 3)])
@pytest.mark.parametrize("count, n", [(2, 1), (3, 2), (4, 3)])
def test_weighted_fusion_is_the_information_fusion_on_well_conditioned_input(shape, count, n):
    Ps = spd(shape + (count,), n)
    xs = rng.standard_normal(shape + (count, n))
    w = rng.dirichlet(np.ones(count), size=shape)
    result = fuse(xs, Ps, w)
    information = np.einsum("...k,...kij->...ij", w, np.linalg.inv(Ps))
    P_expected = np.linalg.inv(information)
    np.testing.assert_allclose(result.P, P_expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(result.P, np.swapaxes(result.P, -1, -2))
    gains = w[..., :, None, None] * (P_expected[..., None, :, :] @ np.linalg.inv(Ps))
    np.testing.assert_allclose(result.gains, gains, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.x, np.einsum("...kij,...kj->...i", gains, xs),
                               rtol=1e-9, atol=1e-12)
    residual = np.abs(result.gains.sum(axis=-3) - np.eye(n)).max()
    assert residual <= 64 * n * np.finfo(float).eps * (1 + np.abs(result.gains).max())
    # the factors are those of P^-1 at the weights
    np.testing.assert_allclose(result.factors.R @ np.swapaxes(result.factors.R, -1, -2),
                               information, rtol=1e-10, atol=1e-12)


def test_zero_weights_give_exactly_zero_gains_and_no_term():
    Ps = spd((3,), 2)
    xs = rng.standard_normal((3, 2))
    result = fuse(xs, Ps, [0.6, 0.0, 0.4])
    assert (result.gains[1] == 0.0).all()
    alone = fuse(xs[[0, 2]], Ps[[0, 2]], [0.6, 0.4])
    np.testing.assert_allclose(result.P, alone.P, rtol=1e-13, atol=0)
    np.testing.assert_allclose(result.x, alone.x, rtol=1e-13, atol=1e-15)
    one = fuse(xs, Ps, [0.0, 1.0, 0.0])  # a vertex: the estimate itself, exactly
    np.testing.assert_array_equal(one.gains[1], np.eye(2))
    assert (one.gains[[0, 2]] == 0.0).all()
    np.testing.assert_array_equal(one.x, xs[1])
    np.testing.assert_allclose(one.P, Ps[1], rtol=1e-14)


def test_precomputed_inverse_factors_and_factors_give_the_same_result():
    Ps = spd((5, 3), 3)
    xs = rng.standard_normal((5, 3, 3))
    w = rng.dirichlet(np.ones(3), size=5)
    L = np.linalg.cholesky(Ps)
    L_inv = lower_inverse_stack(L)
    plain = weighted_fusion(xs, L, w)
    given_inverse = weighted_fusion(xs, L, w, L_inv=L_inv)
    given_factors = weighted_fusion(xs, L, w, L_inv=L_inv, factors=information_factors(L_inv, w))
    for other in (given_inverse, given_factors):
        np.testing.assert_array_equal(other.P, plain.P)
        np.testing.assert_array_equal(other.x, plain.x)
        np.testing.assert_array_equal(other.gains, plain.gains)


@given(st.integers(1, 3).flatmap(lambda n: st.tuples(
    ill_conditioned_sets(3, n, max_condition=1e8),
    arrays(float, (3,), elements=st.floats(0.0, 1.0)),
)))
def test_the_fused_covariance_bounds_the_returned_gains_for_the_worst_joint(args):
    Ps, raw = args
    if raw.sum() == 0.0:
        raw = np.ones(3)
    w = raw / raw.sum()
    n = Ps[0].shape[0]
    try:
        result = fuse(np.zeros((3, n)), np.stack(Ps), w)
    except IllConditionedError:
        return  # numerically singular fused information (denormal weights of tiny inputs)
    assert_unbiased(result.gains)
    # the information-form bound is good to cond * eps (docs/conventions.rst)
    assert_bound_holds(result.P, result.gains, Ps, tol=fused_bound_tolerance(Ps))


@given(covariance_sets(3, 2), arrays(float, (3,), elements=st.floats(0.01, 1.0)))
def test_the_bound_is_the_independent_covariance_with_unit_weights(Ps, _):
    """With all weights one (naive fusion) P is the exact covariance for independent errors."""
    result = fuse(np.zeros((3, 2)), np.stack(Ps), np.ones(3))
    independent = sum(K @ P @ K.T for K, P in zip(result.gains, Ps))
    np.testing.assert_allclose(result.P, independent, rtol=1e-9, atol=1e-12)
    assert_bound_holds(result.P, result.gains, Ps, rho=0.0)


# ------------------------------------------------------------------ factors
def test_information_factors_match_their_definitions():
    Ps = spd((2,), 3)[None].repeat(2, axis=0)  # batch (2,), N = 2
    Ps[1] = spd((2,), 3)
    w = np.array([[0.3, 0.7], [0.9, 0.1]])
    L_inv = lower_inverse_stack(np.linalg.cholesky(Ps))
    factors = information_factors(L_inv, w)
    J = np.einsum("...k,...kij->...ij", w, np.linalg.inv(Ps))
    P = np.linalg.inv(J)
    np.testing.assert_allclose(factors.R @ np.swapaxes(factors.R, -1, -2), J, rtol=1e-12)
    np.testing.assert_array_equal(np.triu(factors.R, 1), 0.0)
    np.testing.assert_allclose(factors.R_inv, np.linalg.inv(factors.R), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.swapaxes(factors.R_inv, -1, -2) @ factors.R_inv, P, rtol=1e-11)
    L_inv_T = np.swapaxes(L_inv, -1, -2)
    np.testing.assert_allclose(factors.B, P[:, None] @ L_inv_T, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(factors.C, factors.R_inv[:, None] @ L_inv_T, rtol=1e-12,
                               atol=1e-14)
    # trace P = ||R_inv||^2 and Tr(P P_i^-1 P) = ||B_i||^2
    np.testing.assert_allclose(squared_norms(factors.R_inv), np.trace(P, axis1=-2, axis2=-1),
                               rtol=1e-12)
    P_inv_i = np.linalg.inv(Ps)
    np.testing.assert_allclose(squared_norms(factors.B),
                               np.trace(P[:, None] @ P_inv_i @ P[:, None], axis1=-2, axis2=-1),
                               rtol=1e-10)
    np.testing.assert_allclose(information_matrices(np.linalg.cholesky(Ps)), P_inv_i,
                               rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("with_W", [False, True])
def test_trace_curvature_is_the_hessian_factor(with_W):
    Ps = spd((3,), 2)
    w = np.array([0.2, 0.5, 0.3])
    W = np.array([[2.0, 0.5], [0.5, 1.0]]) if with_W else None
    factors = information_factors(lower_inverse_stack(np.linalg.cholesky(Ps)), w)
    P = np.linalg.inv(np.einsum("k,kij->ij", w, np.linalg.inv(Ps)))
    Pi = np.linalg.inv(Ps)
    Wm = np.eye(2) if W is None else W
    expected = np.array([[np.trace(Wm @ P @ Pi[i] @ P @ Pi[j] @ P) for j in range(3)]
                         for i in range(3)])
    np.testing.assert_allclose(trace_curvature(factors, W), expected, rtol=1e-10)


def _pairwise_trace_curvature(factors, W=None):
    """The previous form of :func:`trace_curvature`: every ``B_i^T W B_j`` and
    ``C_j^T C_i`` formed, then ``Tr(B_i^T W B_j C_j^T C_i)`` (O(N^2 n^3))."""
    B, C = factors.B, factors.C
    WB = B if W is None else W[..., None, :, :] @ B
    BtWB = np.einsum("...iab,...jac->...ijbc", B, WB)
    CtC = np.einsum("...iab,...jac->...ijbc", C, C)
    return np.einsum("...ijbc,...jicb->...ij", BtWB, CtC)


def _pairwise_log_det_curvature(factors):
    """The previous form of the log det Hessian: ``||C_i^T C_j||_F^2`` pair by pair."""
    CtC = np.einsum("...iab,...jac->...ijbc", factors.C, factors.C)
    return np.einsum("...ijbc,...ijbc->...ij", CtC, CtC)


@given(st.integers(2, 6).flatmap(lambda count: st.integers(1, 4).flatmap(
    lambda n: st.tuples(st.lists(ill_conditioned_sets(count, n, common_scale=False),
                                 min_size=1, max_size=3),
                        arrays(float, (count,), elements=st.floats(0.05, 1.0))))),
       st.booleans())
def test_frobenius_curvatures_equal_the_pairwise_forms(args, with_W):
    """The Gram forms ``<B_i C_i^T, W B_j C_j^T>_F`` and ``<C_i C_i^T, C_j C_j^T>_F``
    against the pairwise products they replace (issue 21, item 5: N = 1000 CI took 22.9 s,
    85% of it in the pairwise Hessian), batched, at condition numbers up to 1e12 and
    covariances at their own scales: equal to rounding relative to the largest entry."""
    sets, weights = args
    Ps = np.array(sets)
    n = Ps.shape[-1]
    try:
        factors = information_factors(lower_inverse_stack(np.linalg.cholesky(Ps)),
                                      np.broadcast_to(weights, Ps.shape[:-2]))
    except IllConditionedError:
        return
    W = (np.broadcast_to(np.diag(np.arange(1.0, n + 1)), Ps.shape[:1] + (n, n))
         if with_W else None)
    for new, old in ((trace_curvature(factors, W), _pairwise_trace_curvature(factors, W)),
                     (log_det_curvature(factors), _pairwise_log_det_curvature(factors))):
        assert new.shape == old.shape == Ps.shape[:2] + (Ps.shape[1],)
        scale = np.abs(old).max(axis=(-2, -1), keepdims=True)
        assert np.all(np.abs(new - old) <= 64 * n * np.finfo(float).eps * scale)


def test_log_det_curvature_is_the_hessian():
    Ps = spd((3,), 2)
    w = np.array([0.2, 0.5, 0.3])
    factors = information_factors(lower_inverse_stack(np.linalg.cholesky(Ps)), w)
    P = np.linalg.inv(np.einsum("k,kij->ij", w, np.linalg.inv(Ps)))
    Pi = np.linalg.inv(Ps)
    expected = np.array([[np.trace(P @ Pi[i] @ P @ Pi[j]) for j in range(3)]
                         for i in range(3)])
    np.testing.assert_allclose(log_det_curvature(factors), expected, rtol=1e-10)


def test_the_reference_estimate_is_the_most_precise_weighted_one():
    """The remainder ``I - sum`` of the other gains goes to the estimate of largest
    ``w_i / trace(P_i)`` (first of equals; never one of zero weight): with equal weights the
    most precise estimate, not the first (before: the first of largest weight)."""
    L = np.linalg.cholesky(np.array([1e6 * np.eye(2), np.eye(2), 1e-3 * np.eye(2)]))
    assert int(reference_estimates(np.full(3, 1 / 3), L)) == 2
    assert int(reference_estimates(np.array([0.5, 0.5, 0.0]), L)) == 1
    assert int(reference_estimates(np.array([1.0, 1e-12, 0.0]), L)) == 0
    same = np.linalg.cholesky(np.array([np.eye(2)] * 3))
    assert int(reference_estimates(np.ones(3), same)) == 0
    batch = reference_estimates(np.array([[1 / 3] * 3, [0.9, 0.1, 0.0]]), np.stack([L, L]))
    np.testing.assert_array_equal(batch, [2, 1])  # 0.1 / 2 > 0.9 / 2e6
    # the gains: the reference's is exactly I minus the others, batched and single
    xs = np.zeros((3, 2))
    for fused in (weighted_fusion(xs, L, np.full(3, 1 / 3)),
                  weighted_fusion(xs[None], L[None], np.full((1, 3), 1 / 3))):
        gains = fused.gains.reshape(3, 2, 2)
        np.testing.assert_array_equal(gains[2], np.eye(2) - gains[0] - gains[1])


def test_information_factors_failures_raise_or_give_nan_per_problem():
    L_inv = lower_inverse_stack(np.linalg.cholesky(np.stack([np.eye(2), np.diag([1.0, 4.0])])))
    L_inv = np.stack([L_inv, L_inv])  # batch of two problems
    w = np.array([[0.5, 0.5], [0.0, 0.0]])  # the second fused information matrix is zero
    with pytest.raises(IllConditionedError, match=r"^the fused information matrix is too "
                                                   r"ill-conditioned to fuse reliably"):
        information_factors(L_inv, w)
    factors = information_factors(L_inv, w, failures="nan")
    assert np.isnan(factors.R[1]).all() and np.isnan(factors.B[1]).all()
    alone = information_factors(L_inv[:1], w[:1])
    np.testing.assert_array_equal(factors.R[0], alone.R[0])
    np.testing.assert_array_equal(factors.B[0], alone.B[0])


# ------------------------------------------------------------------ checked_cholesky
@pytest.mark.parametrize("bad", [
    np.diag([1.0, 1e-17]),  # Cholesky succeeds; the diagonal spans more than 1 / (n eps)
    np.diag([1.0, -1.0]),  # indefinite: LAPACK fails
    np.zeros((2, 2)),
    np.diag([1.0, np.nan]),
    np.diag([np.inf, 1.0]),
])
def test_checked_cholesky_rejects_numerically_singular_matrices(bad):
    A = np.stack([np.diag([4.0, 9.0]), bad, np.eye(2)])
    with pytest.raises(IllConditionedError, match=r"^S is too ill-conditioned to fuse "
                                                   r"reliably: condition number"):
        checked_cholesky(A, "S")
    R = checked_cholesky(A, "S", failures="nan")
    assert np.isnan(R[1]).all()
    np.testing.assert_array_equal(R[0], np.diag([2.0, 3.0]))
    np.testing.assert_array_equal(R[2], np.eye(2))


def test_checked_cholesky_accepts_what_is_numerically_positive_definite():
    A = np.diag([1.0, 1e-14])  # spread 1e14 < 1 / (2 eps)
    np.testing.assert_array_equal(checked_cholesky(A, "S"), np.diag([1.0, 1e-7]))
    np.testing.assert_allclose(diagonal_spread_squared(np.diag([1.0, 1e-7])), 1e14)
    assert diagonal_spread_squared(np.diag([1.0, 0.0])) == np.inf


# ------------------------------------------------------------------ lower_inverse_stack
@pytest.mark.parametrize("n", [1, 2, 5])
def test_lower_inverse_stack_batch_equals_items_to_rounding(n):
    """A single matrix goes to LAPACK's trtri, a stack to the batched substitution: both
    backward stable, equal to rounding relative to the inverse's scale."""
    L = np.linalg.cholesky(spd((3, 4), n) * 10.0 ** rng.uniform(-6, 6, (3, 4, 1, 1)))
    batch = lower_inverse_stack(L)
    assert batch.shape == L.shape
    for index in np.ndindex(3, 4):
        scale = np.abs(batch[index]).max()
        for single in (lower_inverse_stack(L[index]), lower_inverse_stack(L[index][None])[0]):
            np.testing.assert_allclose(single, batch[index], rtol=0, atol=1e-13 * scale)
            np.testing.assert_array_equal(np.triu(single, 1), 0.0)
    np.testing.assert_allclose(batch @ L, np.broadcast_to(np.eye(n), L.shape), rtol=0,
                               atol=1e-12)
    np.testing.assert_array_equal(np.triu(batch, 1), 0.0)
