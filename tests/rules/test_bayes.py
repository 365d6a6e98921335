"""Bayesian Monte Carlo fusion (Weng & Djurić): the sampler's law, the fusion, conventions.

The papers' experiments (``cifilter.cli.reproduce.weng``) are in ``test_reproduce.py``."""

import io
import time
import tracemalloc
from fractions import Fraction
from unittest import mock

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy import stats
from scipy.linalg import block_diag
from strategies import assert_psd, covariance_sets, ill_conditioned_sets, ill_conditioned_spd

from cifilter import (
    IllConditionedError,
    KalmanFilter,
    bayesian_fusion,
    fuse,
    get_method,
    optimal_fusion,
    sample_joint_covariances,
)
from cifilter.cli.demo import run_demo
from cifilter.rules import bayes as bayes_module


def random_spd(n, seed, scale=1.0):
    A = np.random.default_rng(seed).standard_normal((n, n))
    return scale * (A @ A.T + 0.1 * np.eye(n))


def inverse_sqrt(S):
    """Symmetric inverse square roots of a stack of SPD matrices."""
    w, V = np.linalg.eigh(S)
    return (V / np.sqrt(w)[..., None, :]) @ np.swapaxes(V, -1, -2)


def normalised_cross_block(A, n, i, j):
    """A_ii^-1/2 A_ij A_jj^-1/2 (symmetric square roots) for a stack of joint covariances."""
    bi, bj = slice(i * n, (i + 1) * n), slice(j * n, (j + 1) * n)
    return inverse_sqrt(A[..., bi, bi]) @ A[..., bi, bj] @ inverse_sqrt(A[..., bj, bj])


def statistics(R):
    """Scalar summaries of normalised cross blocks (entries and singular values)."""
    singular = np.linalg.svd(R, compute_uv=False)
    return [R[..., 0, 0], R[..., 0, -1], R[..., -1, 0], singular[..., 0], singular[..., -1]]


# ----------------------------------------------------------------- the sampler: structure
@pytest.mark.parametrize("count, n, dof", [(2, 1, 2.5), (2, 2, 5), (2, 3, 6.5), (3, 2, 7),
                                           (4, 2, 9), (5, 1, 5.5)])
def test_samples_are_spd_with_exactly_the_given_blocks(count, n, dof):
    Ps = [random_spd(n, seed) for seed in range(count)]
    A = sample_joint_covariances(Ps, dof, 500, rng=1)
    assert A.shape == (500, count * n, count * n)
    np.testing.assert_array_equal(A, np.swapaxes(A, -1, -2))
    for i, P in enumerate(Ps):
        np.testing.assert_array_equal(A[:, i * n:(i + 1) * n, i * n:(i + 1) * n],
                                      np.broadcast_to(P, (500, n, n)))
    np.linalg.cholesky(A)  # raises if a sample is not positive definite


@given(st.integers(2, 4).flatmap(lambda count: st.integers(1, 3).flatmap(
    lambda n: st.tuples(covariance_sets(count, n), st.floats(0.0, 20.0),
                        st.integers(0, 2**32 - 1)))))
def test_property_samples_are_positive_definite_completions(args):
    Ps, extra_dof, seed = args
    count, n = len(Ps), Ps[0].shape[0]
    A = sample_joint_covariances(Ps, count * n + extra_dof, 20, rng=seed)
    assert np.all(np.linalg.eigvalsh(A)[..., 0] > 0)
    for i, P in enumerate(Ps):
        assert np.array_equal(A[:, i * n:(i + 1) * n, i * n:(i + 1) * n],
                              np.broadcast_to(P, (20, n, n)))


def test_batched_blocks_and_shapes():
    Ps = np.stack([np.stack([random_spd(2, 10 * b + i) for i in range(3)]) for b in range(4)])
    A = sample_joint_covariances(Ps.reshape(2, 2, 3, 2, 2), 8, 7, rng=0)
    assert A.shape == (2, 2, 7, 6, 6)
    A = A.reshape(4, 7, 6, 6)
    for b in range(4):
        for i in range(3):
            np.testing.assert_array_equal(A[b, :, 2 * i:2 * i + 2, 2 * i:2 * i + 2],
                                          np.broadcast_to(Ps[b, i], (7, 2, 2)))


def test_same_seed_same_samples_and_inputs_not_mutated():
    Ps = np.stack([random_spd(2, 0), random_spd(2, 1)])
    before = Ps.copy()
    first = sample_joint_covariances(Ps, 6, 50, rng=3)
    second = sample_joint_covariances(Ps, 6, 50, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(first, second)
    assert not np.array_equal(first, sample_joint_covariances(Ps, 6, 50, rng=4))
    np.testing.assert_array_equal(Ps, before)


def test_chunked_sampling_gives_the_same_samples(monkeypatch):
    """Small chunks (a batch spread over chunks) give the same samples: exact blocks and the
    right moment."""
    Ps = np.stack([np.stack([random_spd(2, 3 * b), random_spd(2, 3 * b + 1)]) for b in range(3)])
    whole = sample_joint_covariances(Ps, 6, 3000, rng=5)
    monkeypatch.setattr(bayes_module, "_CHUNK_ENTRIES", 64 * 7)  # 28 samples, not a divisor
    A = sample_joint_covariances(Ps, 6, 3000, rng=5)
    np.testing.assert_array_equal(A, whole)
    for b in range(3):
        np.testing.assert_array_equal(A[b, :, :2, :2], np.broadcast_to(Ps[b, 0], (3000, 2, 2)))
        R = normalised_cross_block(A[b], 2, 0, 1)
        np.testing.assert_allclose((R @ np.swapaxes(R, -1, -2)).mean(axis=0), np.eye(2) / 3,
                                   atol=0.02)


# ----------------------------------------------------------------- the sampler: its law
@pytest.mark.parametrize("dof", [2.0, 2.5, 3.0, 5.5, 12.0])
def test_scalar_correlation_has_the_exact_beta_law(dof):
    """n = 1, N = 2: density of rho proportional to (1 - rho^2)^((dof - 3)/2) (eq. (28)), i.e.
    (1 + rho)/2 ~ Beta((dof - 1)/2, (dof - 1)/2); dof = 3 is uniform on (-1, 1).

    Five one-sample KS tests with a fixed seed, each at level 0.001 (over 200 seeds the
    p-values of dof = 2 and 3 were uniform)."""
    A = sample_joint_covariances([2.0 * np.eye(1), 0.5 * np.eye(1)], dof, 20_000, rng=11)
    rho = A[:, 0, 1] / np.sqrt(A[:, 0, 0] * A[:, 1, 1])
    a = (dof - 1) / 2
    assert stats.kstest((1 + rho) / 2, stats.beta(a, a).cdf).pvalue > 0.001


@pytest.mark.parametrize("count, n, dof", [(2, 2, 5), (3, 2, 9), (2, 3, 7)])
def test_second_moment_of_the_normalised_cross_blocks(count, n, dof):
    """With A_i = X_i^T X_i, R_ij = U_i^T U_j for orthonormal U_i uniform on the Stiefel
    manifold of R^dof, so E[R_ij R_ij^T] = (n / dof) I for every pair, chain stages included."""
    Ps = [random_spd(n, seed, scale=10.0 ** seed) for seed in range(count)]
    A = sample_joint_covariances(Ps, dof, 100_000, rng=2)
    for i in range(count):
        for j in range(i + 1, count):
            R = normalised_cross_block(A, n, i, j)
            np.testing.assert_allclose((R @ np.swapaxes(R, -1, -2)).mean(axis=0),
                                       np.eye(n) * n / dof, atol=0.01)


def test_normalised_cross_block_does_not_depend_on_the_diagonal_blocks():
    """A_11^-1/2 A_12 A_22^-1/2 has the same law for very different diagonal blocks."""
    size, dof = 4000, 6
    round_ = sample_joint_covariances([np.eye(2), np.eye(2)], dof, size, rng=21)
    skewed = sample_joint_covariances(
        [np.array([[100.0, 9.0], [9.0, 1.0]]), np.array([[0.01, -0.002], [-0.002, 5.0]])],
        dof, size, rng=22)
    for a, b in zip(statistics(normalised_cross_block(round_, 2, 0, 1)),
                    statistics(normalised_cross_block(skewed, 2, 0, 1))):
        assert stats.ks_2samp(a, b).pvalue > 0.01


@pytest.mark.parametrize("count", [2, 3])
def test_normalised_cross_blocks_match_unconditional_wishart_draws(count):
    """Two-sample test against the same quantity from scipy.stats.wishart draws of the whole
    joint covariance with a block-diagonal scale (the blocks of the draws vary, ours do not)."""
    n, dof, size = 2, 3 * count, 4000
    scale = block_diag(*[random_spd(n, 40 + i) for i in range(count)])
    reference = stats.wishart(df=dof, scale=scale).rvs(size=size, random_state=31)
    ours = sample_joint_covariances([random_spd(n, 50 + i) for i in range(count)], dof, size,
                                    rng=32)
    for i in range(count):
        for j in range(i + 1, count):
            for a, b in zip(statistics(normalised_cross_block(ours, n, i, j)),
                            statistics(normalised_cross_block(reference, n, i, j))):
                assert stats.ks_2samp(a, b).pvalue > 0.01, (i, j)


def _conference_theorem_1(A11, A22, n, size, seed):
    """Theorem 1 of the EUSIPCO paper as printed: S ~ W_{k/2}(n, I), symmetric roots."""
    rng = np.random.default_rng(seed)
    m = A11.shape[0]
    S = stats.wishart(df=n, scale=np.eye(m)).rvs(size=size, random_state=rng)
    X = rng.standard_normal((size, m, m))
    T = inverse_sqrt(S + X @ np.swapaxes(X, -1, -2)) @ X
    w1, V1 = np.linalg.eigh(A11)
    w2, V2 = np.linalg.eigh(A22)
    sqrt = [(V1 * np.sqrt(w1)) @ V1.T, (V2 * np.sqrt(w2)) @ V2.T]
    A12T = sqrt[1] @ T @ sqrt[0]
    return np.block([[np.broadcast_to(A11, (size, m, m)), np.swapaxes(A12T, -1, -2)],
                     [A12T, np.broadcast_to(A22, (size, m, m))]])


def test_conference_theorem_1_samples_the_prior_with_k_over_2_more_dof():
    """The EUSIPCO Theorem 1 (S ~ W(n)) is the conditional of the prior W(n + k/2), not W(n):
    Lemma 3 with eq. (10) gives S ~ W(n - k/2), as the journal's Theorem 1 states."""
    A11, A22 = random_spd(2, 60), random_spd(2, 61)
    conference = normalised_cross_block(_conference_theorem_1(A11, A22, 4, 4000, 62), 2, 0, 1)
    as_dof_6 = normalised_cross_block(sample_joint_covariances([A11, A22], 6, 4000, rng=63),
                                      2, 0, 1)
    as_dof_4 = normalised_cross_block(sample_joint_covariances([A11, A22], 4, 4000, rng=64),
                                      2, 0, 1)
    largest = [np.linalg.svd(R, compute_uv=False)[:, 0] for R in (conference, as_dof_6, as_dof_4)]
    assert stats.ks_2samp(largest[0], largest[1]).pvalue > 0.01
    assert stats.ks_2samp(largest[0], largest[2]).pvalue < 1e-6


# ----------------------------------------------------------------- the sampler: bad input
@pytest.mark.parametrize("Ps, dof, size, error, message", [
    ([np.eye(2)] * 2, 3.9, 10, ValueError, r"dof must be at least N\*n = 4"),
    ([np.eye(2)] * 3, 5.0, 10, ValueError, r"N = 3 estimates of dimension n = 2"),
    ([np.eye(2)] * 2, "5", 10, TypeError, "dof must be a real number"),
    ([np.eye(2)] * 2, np.inf, 10, ValueError, "dof must be finite"),
    ([np.eye(2)] * 2, 6.0, 0, ValueError, "size must be >= 1"),
    ([np.eye(2)] * 2, 6.0, 2.5, TypeError, "size must be an integer"),
    ([np.eye(2)], 6.0, 10, ValueError, "at least 2 estimates"),
    ([np.eye(2), -np.eye(2)], 6.0, 10, ValueError, "not positive definite"),
    ([np.eye(2), np.eye(3)], 6.0, 10, ValueError, "shape"),
])
def test_sampler_bad_input(Ps, dof, size, error, message):
    with pytest.raises(error, match=message):
        sample_joint_covariances(Ps, dof, size)


def test_sampler_bad_rng():
    with pytest.raises(TypeError, match="rng must be"):
        sample_joint_covariances([np.eye(2)] * 2, 6, 3, rng="seed")


# ----------------------------------------------------------------- the fusion
def test_fusion_is_the_average_of_the_blue_over_the_same_seeds_samples():
    """bayesian_fusion averages the gains of eq. (18) over the joints that
    sample_joint_covariances draws with the same seed (eqs. (46)-(53))."""
    Ps = [random_spd(2, 60), random_spd(2, 61), random_spd(2, 62)]
    xs = np.random.default_rng(63).standard_normal((3, 2))
    for samples in (1, 25):
        r = bayesian_fusion(xs, Ps, dof=9, samples=samples, rng=64)
        joints = sample_joint_covariances(Ps, 9, samples, rng=64)
        each = [optimal_fusion(xs, joint) for joint in joints]
        np.testing.assert_allclose(r.gains, np.mean([e.gains for e in each], axis=0),
                                   rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(r.info["sample_P_mean"], np.mean([e.P for e in each], axis=0),
                                   rtol=1e-10, atol=1e-12)
        if samples == 1:  # one sample: exactly the optimal fusion with that joint
            np.testing.assert_allclose(r.x, each[0].x, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(r.P, each[0].P, rtol=1e-10, atol=1e-12)


def test_covariance_is_mean_blue_covariance_plus_spread():
    """P = K Pbar K^T = mean_m P_0^(m) + mean_m (K - K^(m)) P^(m) (K - K^(m))^T (Notes)."""
    Ps = [random_spd(2, 70), random_spd(2, 71), random_spd(2, 72)]
    xs = np.random.default_rng(74).standard_normal((3, 2))
    r = bayesian_fusion(xs, Ps, dof=8, samples=30, rng=73)
    joints = sample_joint_covariances(Ps, 8, 30, rng=73)
    K, P, sample_P = r.gains, r.P, r.info["sample_P_mean"]
    spread = np.zeros((2, 2))
    for joint in joints:
        single = optimal_fusion(xs, joint)
        D = np.concatenate(list(K - single.gains), axis=-1)
        spread += D @ joint @ D.T / len(joints)
    np.testing.assert_allclose(P, sample_P + spread, rtol=1e-9, atol=1e-12)
    assert_psd(P - sample_P, what="P - mean BLUE covariance")
    np.testing.assert_allclose(r.x, sum(K[i] @ xs[i] for i in range(3)), rtol=1e-12)


def test_equal_scalar_variances_by_hand():
    """P_11 = P_22 = 1: every sample's BLUE weight is 1/2 (eqs. (24)-(25)), so x is the mean
    and P = (1 + mean rho)/2 with rho the sampled correlations (same seed, same draws)."""
    r = bayesian_fusion([np.array([0.0]), np.array([3.0])], [np.eye(1), np.eye(1)], dof=3,
                        samples=400, rng=90)
    rho = sample_joint_covariances([np.eye(1), np.eye(1)], 3, 400, rng=90)[:, 0, 1]
    np.testing.assert_allclose(r.gains[:, 0, 0], [0.5, 0.5], rtol=1e-12)
    assert r.x[0] == pytest.approx(1.5, rel=1e-12)
    assert r.P[0, 0] == pytest.approx((1 + rho.mean()) / 2, rel=1e-10)


def test_result_fields_defaults_and_determinism():
    xs = [np.array([1.0, 0.0, 2.0]), np.array([0.0, 1.0, 1.0])]
    Ps = [random_spd(3, 1), random_spd(3, 2)]
    r = bayesian_fusion(xs, Ps, rng=5)
    assert r.method == "bayes" and r.omega is None
    assert r.info["dof"] == 7.0 and r.info["samples"] == 100  # N n + 1, M = 100
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r.x, r.gains[0] @ xs[0] + r.gains[1] @ xs[1], rtol=1e-12)
    np.testing.assert_array_equal(r.P, r.P.T)
    assert_psd(r.P - r.info["sample_P_mean"])
    again = bayesian_fusion(xs, Ps, rng=np.random.default_rng(5))
    np.testing.assert_array_equal(r.x, again.x)
    np.testing.assert_array_equal(r.P, again.P)
    assert not np.array_equal(r.x, bayesian_fusion(xs, Ps, rng=6).x)


def test_identical_estimates_are_returned():
    x, P = np.array([1.0, -2.0]), random_spd(2, 3)
    r = bayesian_fusion([x, x, x], [P, P, P], samples=50, rng=0)
    np.testing.assert_allclose(r.x, x, rtol=1e-10)


def test_column_vectors_batches_and_immutability():
    g = np.random.default_rng(1)
    xs = g.standard_normal((3, 2, 2, 1))
    Ps = np.stack([np.stack([random_spd(2, 2 * b), random_spd(2, 2 * b + 1)]) for b in range(3)])
    before = (xs.copy(), Ps.copy())
    r = bayesian_fusion(xs, Ps, samples=20, rng=2)
    assert r.x.shape == (3, 2, 1) and r.P.shape == (3, 2, 2) and r.gains.shape == (3, 2, 2, 2)
    np.testing.assert_array_equal(xs, before[0])
    np.testing.assert_array_equal(Ps, before[1])
    single = bayesian_fusion(list(xs[0]), list(Ps[0]), samples=20, rng=2)
    assert single.x.shape == (2, 1)


def test_long_batches_are_fused_in_chunks(monkeypatch):
    """A batch larger than a memory chunk gives the same kind of answer (exact for equal
    scalar variances, where every sample's weight is 1/2)."""
    monkeypatch.setattr(bayes_module, "_CHUNK_ENTRIES", 500)
    xs = np.random.default_rng(3).standard_normal((50, 2, 1))
    r = bayesian_fusion(xs, np.ones((50, 2, 1, 1)), dof=3, samples=40, rng=4)
    np.testing.assert_allclose(r.x[:, 0], xs.mean(axis=1)[:, 0], rtol=1e-12)
    assert np.all((r.P > 0) & (r.P < 1))


def test_covariance_is_honest_under_the_model():
    """Data from the prior itself (a Wishart joint covariance, the prior's dof): the mean NEES
    of the fused estimate is the state dimension, 2, within Monte Carlo error."""
    g = np.random.default_rng(100)
    runs, dof = 3000, 6
    Z = g.standard_normal((runs, dof, 4))
    joint = np.swapaxes(Z, -1, -2) @ Z
    e = (np.linalg.cholesky(joint) @ g.standard_normal((runs, 4, 1)))[..., 0].reshape(runs, 2, 2)
    Ps = np.stack([joint[:, :2, :2], joint[:, 2:, 2:]], axis=1)
    r = bayesian_fusion(e, Ps, dof=dof, samples=50, rng=101)
    nees = np.einsum("ri,ri->r", r.x, np.linalg.solve(r.P, r.x[..., None])[..., 0])
    assert abs(nees.mean() - 2.0) < 4 * nees.std() / np.sqrt(runs)


@pytest.mark.parametrize("kwargs, error, message", [
    ({"dof": 3.5}, ValueError, r"dof must be at least N\*n = 4 .*needs dof >= 4"),
    ({"dof": -1}, ValueError, "dof must be at least"),
    ({"dof": "7"}, TypeError, "dof must be a real number"),
    ({"samples": 0}, ValueError, "samples must be >= 1"),
    ({"samples": 1.5}, TypeError, "samples must be an integer"),
    ({"rng": "x"}, TypeError, "rng must be"),
])
def test_fusion_bad_options(kwargs, error, message):
    with pytest.raises(error, match=message):
        bayesian_fusion([np.zeros(2)] * 2, [np.eye(2)] * 2, **kwargs)


@pytest.mark.parametrize("xs, Ps, message", [
    ([np.zeros(2)], [np.eye(2)], "at least 2 estimates"),
    ([np.zeros(3)] * 2, [np.eye(2)] * 2, "must have shape"),
    ([np.zeros(2)] * 2, [np.eye(2), np.ones((2, 2))], "not positive definite|numerically singular"),
    ([np.full(2, np.nan)] * 2, [np.eye(2)] * 2, "non-finite"),
])
def test_fusion_bad_estimates(xs, Ps, message):
    with pytest.raises(ValueError, match=message):
        bayesian_fusion(xs, Ps)


def _badly_conditioned(n, condition, seed):
    Q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((n, n)))
    return (Q * np.geomspace(1.0, condition, n)) @ Q.T


def test_samples_singular_in_floating_point_are_redrawn(monkeypatch):
    """dof = N n with blocks of condition number 1e9: about 2e-5 of the raw draws cannot be
    factorised in floating point. They are drawn again, so every returned sample can; with
    redraws forbidden the sampler says why it fails."""
    Ps = [_badly_conditioned(3, 1e9, 1), _badly_conditioned(3, 1e9, 2)]
    A = sample_joint_covariances(Ps, 6, 50_000, rng=3)
    np.linalg.cholesky(A)
    monkeypatch.setattr(bayes_module, "_MAX_REDRAWS", 0)
    with pytest.raises(ValueError, match="too badly conditioned for dof = 6"):
        sample_joint_covariances(Ps, 6, 50_000, rng=3)
    r = bayesian_fusion([np.zeros(3), np.ones(3)], [np.eye(3), 2 * np.eye(3)], samples=200,
                        rng=0)  # well-conditioned blocks, default dof: nothing to redraw
    assert np.all(np.isfinite(r.P))


# ----------------------------------------------------------------- near-singular inputs (issue 9)
def _fraction_inverse(M):
    """Inverse of a square matrix of Fractions (exact Gauss-Jordan elimination)."""
    m = len(M)
    M = [list(row) + [Fraction(int(i == j)) for j in range(m)] for i, row in enumerate(M)]
    for c in range(m):
        pivot = max(range(c, m), key=lambda r: abs(M[r][c]))
        M[c], M[pivot] = M[pivot], M[c]
        M[c] = [v / M[c][c] for v in M[c]]
        for r in range(m):
            if r != c and M[r][c] != 0:
                M[r] = [a - M[r][c] * b for a, b in zip(M[r], M[c])]
    return [row[m:] for row in M]


def _exact_mean_blue(xs, joints):
    """mean_m of the BLUE (eq. (18)) of each joint, exactly (rational arithmetic): the fused
    estimate and the gains, rounded to float at the end."""
    count, n = len(xs), len(xs[0])
    K_sum = [[[Fraction(0)] * n for _ in range(n)] for _ in range(count)]
    for A in joints:
        A_inv = _fraction_inverse([[Fraction(float(v)) for v in row] for row in A])
        # J = I^T A^-1 I (n x n) and I^T A^-1 (n x Nn)
        row_sums = [[sum(A_inv[i * n + a][c] for i in range(count)) for c in range(count * n)]
                    for a in range(n)]
        J = [[sum(row_sums[a][j * n + b] for j in range(count)) for b in range(n)]
             for a in range(n)]
        J_inv = _fraction_inverse(J)
        for i in range(count):
            for r in range(n):
                for c in range(n):
                    K_sum[i][r][c] += sum(J_inv[r][a] * row_sums[a][i * n + c] for a in range(n))
    M = len(joints)
    K = np.array([[[float(v / M) for v in row] for row in Ki] for Ki in K_sum])
    x = np.array([float(sum(K_sum[i][r][c] * Fraction(float(xs[i][c]))
                            for i in range(count) for c in range(n)) / M) for r in range(n)])
    return x, K


def assert_gains_sum_to_identity(gains, ulps=8):
    """sum_i K_i = I to rounding: entrywise within a few ulps of sum_i |K_i| + I."""
    n = gains.shape[-1]
    error = np.abs(gains.sum(axis=-3) - np.eye(n))
    scale = np.abs(gains).sum(axis=-3) + np.eye(n)
    assert np.all(error <= ulps * np.finfo(float).eps * scale), error.max()


def assert_spd_output(r):
    for M in (r.P, r.info["sample_P_mean"]):
        assert np.all(np.isfinite(M))
        np.testing.assert_array_equal(M, np.swapaxes(M, -1, -2))
        np.linalg.cholesky(M)  # raises if not positive definite
    assert np.all(np.isfinite(r.x)) and np.all(np.isfinite(r.gains))


@pytest.mark.parametrize("tiny", [1e-40, 1e-300])
def test_issue_9_near_singular_second_estimate(tiny):
    """The issue's reproducer: P_2 = diag(1, tiny). The second component is known exactly from
    estimate 2, so x[1] = 1; x[0] is the mean over the sampled joints of their BLUEs, here
    computed exactly (rational arithmetic) on the same joints (same seed, same draws), and it
    is the limit of the well-conditioned problem diag(1, 1e-6) with the same draws (the
    whitened draws do not depend on the covariances). The old code gave x[0] = -1.6e4 at 1e-40
    and gains off the identity by 1e134 at 1e-300."""
    xs = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    Ps = [np.diag([1.0, 4.0]), np.diag([1.0, tiny])]
    r = bayesian_fusion(xs, Ps, samples=200, rng=0)
    assert_spd_output(r)
    assert_gains_sum_to_identity(r.gains)
    assert r.x[1] == pytest.approx(1.0, abs=1e-15)
    joints = sample_joint_covariances(Ps, 5, 200, rng=0)
    x_exact, K_exact = _exact_mean_blue(xs, joints)
    assert r.x[0] == pytest.approx(x_exact[0], rel=1e-10)
    np.testing.assert_allclose(r.gains[:, 0], K_exact[:, 0], rtol=1e-9, atol=1e-12)
    moderate = bayesian_fusion(xs, [Ps[0], np.diag([1.0, 1e-6])], samples=200, rng=0)
    assert abs(r.x[0] - moderate.x[0]) < 1e-3  # the limit t -> 0 differs by O(sqrt(t))
    assert 0.2 < r.x[0] < 0.6  # the issue's "about 0.37" (another stream): Monte Carlo noise
    np.testing.assert_allclose(r.P[0, 0], moderate.P[0, 0], rtol=1e-3)
    assert r.P[1, 1] == pytest.approx(tiny, rel=1e-2)  # the error of x[1] is estimate 2's


@pytest.mark.parametrize("d", [[1e3, 1e-3], [1e-6, 1e6], [2.0, 1e10]])
def test_issue_9_reproducer_is_invariant_under_a_change_of_units(d):
    """The reproducer in other units (x -> D x, P -> D P D): the same fused result, to
    rounding (the draws are the same whitened samples)."""
    d = np.array(d)
    xs = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    Ps = [np.diag([1.0, 4.0]), np.diag([1.0, 1e-40])]
    r = bayesian_fusion(xs, Ps, samples=200, rng=0)
    s = bayesian_fusion([d * x for x in xs], [d[:, None] * P * d for P in Ps], samples=200,
                        rng=0)
    np.testing.assert_allclose(s.x / d, r.x, rtol=1e-12)
    np.testing.assert_allclose(s.P / np.outer(d, d), r.P, rtol=1e-12)
    np.testing.assert_allclose(s.gains * d / d[:, None], r.gains, rtol=1e-12, atol=1e-14)


@given(st.integers(2, 4).flatmap(lambda count: st.integers(1, 5).flatmap(
    lambda n: st.tuples(st.booleans().flatmap(lambda common: ill_conditioned_sets(
        count, n, common_scale=common)), st.floats(0.0, 10.0), st.integers(0, 2**32 - 1)))))
def test_property_ill_conditioned_inputs_give_valid_output(args):
    """Conditions to 1e12, scales 1e-12..1e12, n = 1..5, N = 2..4: finite, symmetric, positive
    definite P, gains summing to I to rounding, x = sum_i K_i x_i to rounding."""
    Ps, extra_dof, seed = args
    count, n = len(Ps), Ps[0].shape[0]
    g = np.random.default_rng(seed)
    scale = np.sqrt(np.stack([np.diag(P) for P in Ps]))
    xs = 5.0 * scale.max(axis=0) * g.standard_normal(n) + scale * g.standard_normal((count, n))
    r = bayesian_fusion(list(xs), Ps, dof=count * n + extra_dof, samples=30, rng=seed)
    assert_spd_output(r)
    assert_gains_sum_to_identity(r.gains)
    direct = np.einsum("irc,ic->r", r.gains, xs)
    bound = np.einsum("irc,ic->r", np.abs(r.gains), np.abs(xs))
    assert np.all(np.abs(r.x - direct) <= 1e-12 * bound)
    sd = np.sqrt(np.diag(r.P))
    assert_psd((r.P - r.info["sample_P_mean"]) / np.outer(sd, sd), tol=1e-9,
               what="P - mean BLUE covariance, in units of sd(x)")


@given(st.integers(2, 3).flatmap(lambda count: st.integers(1, 4).flatmap(
    lambda n: st.tuples(ill_conditioned_sets(count, n, common_scale=False),
                        st.lists(st.floats(-6.0, 6.0), min_size=n, max_size=n),
                        st.integers(0, 2**32 - 1)))))
def test_property_invariant_under_a_change_of_units(args):
    """x -> D x, P -> D P D for a diagonal D: the whitened draws do not depend on the
    covariances, so with the same seed the fused result transforms exactly, to rounding:
    x -> D x, P -> D P D, K_i -> D K_i D^-1. "To rounding" is relative to the rounding of the
    input D P D itself: it perturbs the problem by about eps times the condition number
    kappa of the correlation matrices (a diagonal scaling is exact, a rotated
    ill-conditioning is not), and a gain error dK_i moves x by dK_i (x_i - x_j), up to the
    largest input standard deviation; errors are measured in units of the fused standard
    deviations."""
    Ps, log_d, seed = args
    count, n = len(Ps), Ps[0].shape[0]
    d = 10.0 ** np.array(log_d)
    g = np.random.default_rng(seed)
    sd_in = np.sqrt(np.stack([np.diag(P) for P in Ps]))  # (N, n)
    xs = (np.linalg.cholesky(np.stack(Ps)) @ g.standard_normal((count, n, 1)))[..., 0]
    kappa = max(np.linalg.cond(P / np.outer(s, s)) for P, s in zip(Ps, sd_in))
    r = bayesian_fusion(list(xs), Ps, samples=20, rng=seed)
    s = bayesian_fusion(list(xs * d), [d[:, None] * P * d for P in Ps], samples=20, rng=seed)
    sd = np.sqrt(np.diag(r.P))
    tol = 1e-9 + 100 * np.finfo(float).eps * kappa * sd_in.max() / sd.min()
    assert np.all(np.abs(s.x / d - r.x) <= tol * sd + 1e-13 * np.abs(xs).max())
    assert np.all(np.abs(s.P / np.outer(d, d) - r.P) <= tol * np.outer(sd, sd))
    unscaled = s.gains * d[None, None, :] / d[None, :, None]  # D^-1 K'_i D
    assert np.all(np.abs(unscaled - r.gains) <= tol * np.abs(r.gains).max())


@given(st.integers(2, 4).flatmap(lambda count: st.integers(1, 3).flatmap(
    lambda n: st.tuples(ill_conditioned_sets(count, n), st.integers(1, 7),
                        st.integers(0, 2**32 - 1)))))
def test_property_same_seed_same_result_whatever_the_chunk_size(args):
    """The random stream does not depend on the chunking: chunks of 1..7 samples (and a batch
    that spreads problems over chunks) give the default chunking's result to rounding (the
    sums run in another order); the same seed gives the identical result; the first problem
    of a batch gets the draws of the same problem alone."""
    Ps, chunk_samples, seed = args
    count, n = len(Ps), Ps[0].shape[0]
    g = np.random.default_rng(seed)
    xs = np.sqrt(np.stack([np.diag(P) for P in Ps])) * g.standard_normal((3, count, n))
    Pb = np.broadcast_to(np.stack(Ps), (3, count, n, n))
    whole = bayesian_fusion(xs, Pb, samples=13, rng=seed)
    again = bayesian_fusion(xs, Pb, samples=13, rng=np.random.default_rng(seed))
    for a, b in zip((whole.x, whole.P, whole.gains), (again.x, again.P, again.gains)):
        np.testing.assert_array_equal(a, b)
    with mock.patch.object(bayes_module, "_CHUNK_ENTRIES", chunk_samples * (count * n) ** 2):
        chunked = bayesian_fusion(xs, Pb, samples=13, rng=seed)
    single = bayesian_fusion(list(xs[0]), Ps, samples=13, rng=seed)
    for other, index in ((chunked, slice(None)), (single, 0)):
        sd = np.sqrt(np.diagonal(whole.P, axis1=-2, axis2=-1))[index]
        np.testing.assert_allclose(other.x, whole.x[index], rtol=0,
                                   atol=1e-9 * sd.max() + 1e-12 * np.abs(xs).max())
        np.testing.assert_allclose(other.P, whole.P[index], rtol=1e-9,
                                   atol=1e-9 * sd.max() ** 2)
        np.testing.assert_allclose(other.gains.sum(axis=-3), np.broadcast_to(np.eye(n), (
            other.gains.shape[:-3] + (n, n))), atol=1e-12 * max(1.0, np.abs(other.gains).max()))


def test_a_chunk_of_one_sample_sums_like_any_other():
    """The example hypothesis found for the property above: chunks of one sample must give
    the default chunking's result to rounding. numpy's einsum sums a contraction in another
    order when the samples axis has length one; on these nearly singular covariances
    (condition number 1e8) and means of 1e6 that moved x by 3.8 times the tolerance (the
    fusion now keeps a copy of a lone sample beside it)."""
    P = np.array([[50049975.49951273, 49999974.52498776],
                  [49999974.52498776, 49950025.50048728]])
    Pb = np.broadcast_to(P, (3, 2, 2, 2))
    xs = np.sqrt(np.diag(P)) * np.random.default_rng(0).standard_normal((3, 2, 2))
    whole = bayesian_fusion(xs, Pb, samples=13, rng=0)
    for chunk_samples in (1, 2, 5):
        with mock.patch.object(bayes_module, "_CHUNK_ENTRIES", chunk_samples * 16):
            chunked = bayesian_fusion(xs, Pb, samples=13, rng=0)
        sd = np.sqrt(np.diagonal(whole.P, axis1=-2, axis2=-1))
        np.testing.assert_allclose(chunked.x, whole.x, rtol=0,
                                   atol=1e-9 * sd.max() + 1e-12 * np.abs(xs).max())
        np.testing.assert_allclose(chunked.P, whole.P, rtol=1e-9, atol=1e-9 * sd.max() ** 2)


@given(st.integers(2, 4).flatmap(lambda count: st.integers(1, 4).flatmap(
    lambda n: st.tuples(ill_conditioned_sets(count, n, common_scale=False),
                        st.floats(0.0, 5.0), st.integers(0, 2**32 - 1)))))
def test_property_sampler_on_ill_conditioned_blocks(args):
    """sample_joint_covariances on conditions to 1e12 and scales 1e-12..1e12: exact diagonal
    blocks, exactly symmetric, every sample passes a Cholesky factorisation (or the sampler
    raises IllConditionedError)."""
    Ps, extra_dof, seed = args
    count, n = len(Ps), Ps[0].shape[0]
    try:
        A = sample_joint_covariances(Ps, count * n + extra_dof, 25, rng=seed)
    except IllConditionedError:
        return
    assert np.all(np.isfinite(A))
    np.testing.assert_array_equal(A, np.swapaxes(A, -1, -2))
    for i, P in enumerate(Ps):
        np.testing.assert_array_equal(A[:, i * n:(i + 1) * n, i * n:(i + 1) * n],
                                      np.broadcast_to(P, (25, n, n)))
    np.linalg.cholesky(A)


@given(ill_conditioned_spd(3), st.integers(0, 2**32 - 1))
def test_property_fusion_with_a_much_more_precise_estimate(P, seed):
    """Covariances P and 1e-6 P (condition numbers to 1e12, consistent independent errors):
    valid output, and the fused error is of the size of the precise estimate's."""
    g = np.random.default_rng(seed)
    L = np.linalg.cholesky(P)
    xs = [1.0 + L @ g.standard_normal(3), 1.0 + 1e-3 * L @ g.standard_normal(3)]
    r = bayesian_fusion(xs, [P, 1e-6 * P], samples=20, rng=seed)
    assert_spd_output(r)
    assert_gains_sum_to_identity(r.gains)
    assert np.all(np.abs(r.x - 1.0) <= 30 * np.sqrt(np.diag(r.P)))
    assert np.all(np.diag(r.P) <= 2e-6 * np.diag(P))


def test_peak_memory_of_a_million_samples_is_bounded():
    """The issue's memory bound: one fusion of two 4-D estimates (8x8 joint covariances) with
    1e6 samples stays under 500 MB of traced memory (it was 2.6 GB): the samples are processed
    in chunks of bounded size."""
    Ps = [np.kron(np.eye(2), random_spd(2, 1)), np.kron(np.eye(2), random_spd(2, 2))]
    tracemalloc.start()
    try:
        start = time.perf_counter()
        r = bayesian_fusion([np.zeros(4), np.ones(4)], Ps, samples=1_000_000, rng=0)
        elapsed = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 500e6, f"peak traced memory {peak / 1e6:.0f} MB ({elapsed:.1f} s)"
    assert_spd_output(r)
    assert_gains_sum_to_identity(r.gains)


# ----------------------------------------------------------------- registry, filters, demo
def test_registered_rule_and_truth_options():
    record = get_method("bayes")
    assert record.guarantee == "none"
    rng = np.random.default_rng(0)
    assert record.options_given_truth(np.eye(4), rng) == {"rng": rng}
    a, b = (np.array([1.0, 0.0]), np.eye(2)), (np.array([0.0, 1.0]), 2 * np.eye(2))
    via_fuse = fuse([a, b], method="bayes", rng=3, samples=30, dof=6)
    direct = bayesian_fusion([a[0], b[0]], [a[1], b[1]], dof=6, samples=30, rng=3)
    np.testing.assert_array_equal(via_fuse.x, direct.x)
    np.testing.assert_array_equal(via_fuse.P, direct.P)
    with pytest.raises(TypeError, match="does not accept"):
        fuse([a, b], method="bayes", omega=0.5)


def test_filter_fuse_with_bayes():
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x = np.array([[1.0], [0.0]])
    kf.P = np.diag([1.0, 4.0])
    result = kf.fuse((np.array([0.0, 1.0]), np.diag([4.0, 1.0])), method="bayes", rng=0)
    assert kf.last_fusion is result and kf.x.shape == (2, 1)
    np.testing.assert_allclose(kf.P, result.P)


def test_demo_row():
    rows = {row["method"]: row for row in run_demo(seed=0, runs=2, steps=20,
                                                   methods=["bayes", "optimal"],
                                                   out=io.StringIO())}
    assert "error" not in rows["bayes"]
    assert rows["bayes"]["rmse"] < rows["local A"]["rmse"]
