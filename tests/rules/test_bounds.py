"""cifilter.rules.bounds:
the trace bounds and correlation coefficient bounds of Wu, Cai & Fu (2018)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.linalg import sqrtm
from scipy.optimize import minimize
from strategies import finite, spd_matrices

from cifilter import optimal_fusion
from cifilter.rules.bounds import (
    ci_trace_bound,
    common_correlation_bound,
    correlation_bound,
    is_rho_admissible,
    worst_case_trace,
)

PA, PB, I2 = np.diag([1.0, 4.0]), np.diag([4.0, 1.0]), np.eye(2)


def random_spd(n, seed, size=()):
    A = np.random.default_rng(seed).standard_normal(size + (n, n))
    return A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)


def nuclear(A):
    return np.linalg.svd(A, compute_uv=False).sum()


def fused_trace(Pa, Pb, Pab, K1, K2):
    """Tr(cov(K1 a + K2 b)) for the cross-covariance Pab (proof of Lemma 5)."""
    return np.trace(K1 @ Pa @ K1.T + K2 @ Pb @ K2.T + K1 @ Pab @ K2.T + K2 @ Pab.T @ K1.T)


def worst_cross_covariance(Pa, Pb, K1, K2, rho):
    """The maximiser of Lemma 4: Pab = rho X V U^T Y^T with Y^T K2^T K1 X = U S V^T."""
    X, Y = np.linalg.cholesky(Pa), np.linalg.cholesky(Pb)
    U, _, Vt = np.linalg.svd(Y.T @ K2.T @ K1 @ X, full_matrices=False)
    return rho * X @ Vt.T @ U.T @ Y.T


@st.composite
def cross_covariances(draw, Pa, Pb, rho):
    """A cross-covariance Pab = X Gamma Y^T with ||Gamma||_2 <= rho (Lemma 3, eq. (9))."""
    n, p = Pa.shape[0], Pb.shape[0]
    G = draw(arrays(float, (n, p), elements=finite)) + 1e-3 * np.eye(n, p)
    scale = draw(st.floats(0.0, 1.0)) * rho / np.linalg.norm(G, 2)
    return np.linalg.cholesky(Pa) @ (scale * G) @ np.linalg.cholesky(Pb).T


# ----------------------------------------------------------------- paper values
def test_example_1_classic_bound_20_against_tight_bound_18():
    """Example 1: (sqrt(Tr Pa) + sqrt(Tr Pb))^2 = 20, Lemma 2's exact maximum 18."""
    assert ci_trace_bound(PA, PB, I2, I2) == pytest.approx(20.0, abs=1e-12)
    assert worst_case_trace(PA, PB, I2, I2) == pytest.approx(18.0, abs=1e-12)
    # by hand: ||P_a||_* + ||P_b||_* + 2 ||Y^T X||_* = 5 + 5 + 2 ||diag(2, 2)||_* = 18
    X, Y = np.diag([1.0, 2.0]), np.diag([2.0, 1.0])
    assert 5 + 5 + 2 * nuclear(Y.T @ X) == 18.0


def test_example_2_ci_gains_have_true_worst_case_2_88():
    """Example 2: CI's gains K1 = diag(0.8, 0.2) have the exact worst case 2.88 < 3.2."""
    K1 = np.diag([0.8, 0.2])
    assert worst_case_trace(PA, PB, K1, I2 - K1) == pytest.approx(2.88, abs=1e-12)
    # Remark 2's bound for these gains is CI's trace 3.2 (= (sqrt(0.8) + sqrt(0.8))^2)
    assert ci_trace_bound(PA, PB, K1, I2 - K1) == pytest.approx(3.2, abs=1e-12)


@pytest.mark.parametrize("k1, k2", [(0.8, 0.2), (1.0, 0.0), (0.3, -0.4), (1.7, 0.5)])
def test_example_2_closed_form_for_diagonal_gains(k1, k2):
    """Example 2: (|k1| + 2|1 - k1|)^2 + (2|k2| + |1 - k2|)^2 for diagonal gains."""
    K1 = np.diag([k1, k2])
    expected = (abs(k1) + 2 * abs(1 - k1)) ** 2 + (2 * abs(k2) + abs(1 - k2)) ** 2
    assert worst_case_trace(PA, PB, K1, I2 - K1) == pytest.approx(expected, rel=1e-12)


def test_example_2_best_diagonal_gains_give_2():
    grid = np.linspace(-0.5, 1.5, 201)
    k1, k2 = np.meshgrid(grid, grid, indexing="ij")
    K1 = np.zeros(k1.shape + (2, 2))
    K1[..., 0, 0], K1[..., 1, 1] = k1, k2
    values = worst_case_trace(PA, PB, K1, I2 - K1)
    best = np.unravel_index(np.argmin(values), values.shape)
    assert values[best] == pytest.approx(2.0, abs=1e-12)
    assert (k1[best], k2[best]) == (pytest.approx(1.0), pytest.approx(0.0, abs=1e-12))


def test_example_2_diag_1_0_is_optimal_among_all_gains():
    """The claim 'can be verified (although not shown here)' of Example 2, verified.

    Lower bound: for the admissible cross-covariance Pab = I the best linear unbiased
    fusion (over all gains) has trace 2, so no gains have a worst case below 2; K1 =
    diag(1, 0) attains 2. A general-purpose search over all 2x2 gains agrees.
    """
    joint = np.block([[PA, I2], [I2, PB]])
    assert correlation_bound(PA, PB, I2) == pytest.approx(0.5)
    assert np.trace(optimal_fusion(np.zeros((2, 2)), joint).P) == pytest.approx(2.0, abs=1e-12)

    def worst(k):
        K1 = k.reshape(2, 2)
        return float(worst_case_trace(PA, PB, K1, I2 - K1))

    rng = np.random.default_rng(3)
    found = [minimize(worst, rng.standard_normal(4), method="Nelder-Mead",
                      options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000}).fun
             for _ in range(6)]
    assert min(found) >= 2.0 - 1e-12
    assert min(found) == pytest.approx(2.0, abs=1e-6)


# ----------------------------------------------------------------- Lemmas 2 and 4, Theorem 2
@pytest.mark.parametrize("rho", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("seed", range(4))
def test_worst_case_is_attained_by_the_lemma_4_maximiser(rho, seed):
    n = 3
    Pa, Pb = random_spd(n, seed), random_spd(n, seed + 10)
    g = np.random.default_rng(seed)
    K1 = g.standard_normal((n, n))
    K2 = np.eye(n) - K1
    Pab = worst_cross_covariance(Pa, Pb, K1, K2, rho)
    assert correlation_bound(Pa, Pb, Pab) == pytest.approx(rho, abs=1e-12)
    assert fused_trace(Pa, Pb, Pab, K1, K2) == pytest.approx(
        worst_case_trace(Pa, Pb, K1, K2, rho), rel=1e-12)


@given(spd_matrices(3).flatmap(lambda Pa: st.tuples(
    st.just(Pa), spd_matrices(3), st.floats(0.0, 1.0))).flatmap(
        lambda t: st.tuples(st.just(t), cross_covariances(t[0], t[1], t[2]))),
       arrays(float, (3, 3), elements=finite))
def test_no_admissible_cross_covariance_exceeds_the_worst_case(args, K1):
    (Pa, Pb, rho), Pab = args
    K2 = np.eye(3) - K1
    worst = worst_case_trace(Pa, Pb, K1, K2, rho)
    assert fused_trace(Pa, Pb, Pab, K1, K2) <= worst * (1 + 1e-9) + 1e-9
    # Theorem 2's chain: (11) <= Lemma 5's trace (15) <= (sqrt t1 + sqrt t2)^2 - 2(1-rho) N
    # <= the printed bound with (1 - rho) N
    t1, t2 = np.trace(K1 @ Pa @ K1.T), np.trace(K2 @ Pb @ K2.T)
    N = nuclear(np.linalg.cholesky(Pb).T @ K2.T @ K1 @ np.linalg.cholesky(Pa))
    lemma_5 = t1 + t2 + 2 * rho * np.sqrt(t1 * t2)
    doubled = (np.sqrt(t1) + np.sqrt(t2)) ** 2 - 2 * (1 - rho) * N
    tol = 1e-9 * (t1 + t2 + 1)
    assert worst <= lemma_5 + tol
    assert lemma_5 <= doubled + tol
    assert doubled <= ci_trace_bound(Pa, Pb, K1, K2, rho) + tol


@given(spd_matrices(2), spd_matrices(2), st.floats(0.0, 1.0))
def test_lemma_4_does_not_depend_on_the_factorisation(Pa, Pb, rho):
    """Lemma 4 with K = I and symmetric square roots instead of Cholesky factors."""
    X, Y = np.real(sqrtm(Pa)), np.real(sqrtm(Pb))
    expected = np.trace(Pa) + np.trace(Pb) + 2 * rho * nuclear(Y.T @ X)
    assert worst_case_trace(Pa, Pb, np.eye(2), np.eye(2), rho) == pytest.approx(
        expected, rel=1e-9)


def test_ci_trace_bound_at_rho_1_is_remark_2():
    Pa, Pb = random_spd(3, 1), random_spd(3, 2)
    K1 = np.random.default_rng(0).standard_normal((3, 3))
    K2 = np.eye(3) - K1
    t1, t2 = np.trace(K1 @ Pa @ K1.T), np.trace(K2 @ Pb @ K2.T)
    assert ci_trace_bound(Pa, Pb, K1, K2) == pytest.approx((np.sqrt(t1) + np.sqrt(t2)) ** 2)
    N = nuclear(np.linalg.cholesky(Pb).T @ K2.T @ K1 @ np.linalg.cholesky(Pa))
    assert ci_trace_bound(Pa, Pb, K1, K2, 0.25) == pytest.approx(
        (np.sqrt(t1) + np.sqrt(t2)) ** 2 - 0.75 * N)


def test_rectangular_gains_and_different_dimensions():
    """A fused quantity of dimension k from vectors of dimensions 2 and 3."""
    Pa, Pb = random_spd(2, 4), random_spd(3, 5)
    g = np.random.default_rng(1)
    K1, K2 = g.standard_normal((4, 2)), g.standard_normal((4, 3))
    Pab = worst_cross_covariance(Pa, Pb, K1, K2, 0.7)
    assert Pab.shape == (2, 3)
    assert fused_trace(Pa, Pb, Pab, K1, K2) == pytest.approx(
        worst_case_trace(Pa, Pb, K1, K2, 0.7), rel=1e-12)


# ----------------------------------------------------------------- correlation bounds
def test_scalar_correlation_bound_is_pearson():
    assert correlation_bound([[4.0]], [[9.0]], [[-3.0]]) == pytest.approx(0.5)


@given(spd_matrices(2), spd_matrices(3), st.floats(0.0, 1.0),
       arrays(float, (2, 2), elements=finite), arrays(float, (3, 3), elements=finite))
def test_correlation_bound_is_invariant_to_linear_maps_and_lemma_3(Pa, Pb, rho, T, S):
    Pab = np.linalg.cholesky(Pa) @ (rho * np.eye(2, 3)) @ np.linalg.cholesky(Pb).T
    value = correlation_bound(Pa, Pb, Pab)
    assert value == pytest.approx(rho, abs=1e-9)
    T, S = T + 4 * np.eye(2), S + 4 * np.eye(3)  # diagonally dominant: invertible
    if min(np.linalg.svd(T, compute_uv=False)[-1], np.linalg.svd(S, compute_uv=False)[-1]) < 0.5:
        return
    moved = correlation_bound(T @ Pa @ T.T, S @ Pb @ S.T, T @ Pab @ S.T)
    assert moved == pytest.approx(value, abs=1e-7)
    # Lemma 3: [[r Pa, Pab], [Pab^T, r Pb]] >= 0 exactly for r >= rho_ab
    for r, admissible in ((min(value + 1e-3, 1.0), True), (value - 1e-3, False)):
        if r < 0:
            continue
        M = np.block([[r * Pa, Pab], [Pab.T, r * Pb]])
        smallest = np.linalg.eigvalsh(M)[0]
        assert (smallest >= -1e-10 * np.abs(M).max()) == admissible


@given(spd_matrices(2), spd_matrices(2), arrays(float, (6, 6), elements=finite))
def test_shared_part_bounds_the_correlation_coefficient(Ca, Cb, Z):
    """The docs' recipe: with P_ab = E{c_a c_b^T}, C_a <= P_a, C_b <= P_b,
    rho_ab <= sqrt(lambda_max(P_a^-1 C_a) lambda_max(P_b^-1 C_b))."""
    # a = c_a + u_a, b = c_b + u_b: shared parts (c_a, c_b) with a random joint covariance,
    # independent parts u_a, u_b
    G = Z[:4, :4] @ Z[:4, :4].T + 1e-3 * np.eye(4)
    d = np.diag(G)
    corr = G / np.sqrt(np.outer(d, d))  # a random correlation matrix
    S = np.zeros((4, 4))
    S[:2, :2], S[2:, 2:] = np.linalg.cholesky(Ca), np.linalg.cholesky(Cb)
    Ccc = S @ corr @ S.T  # joint covariance of the shared parts (c_a, c_b)
    Ca_eff, Cb_eff, Pab = Ccc[:2, :2], Ccc[2:, 2:], Ccc[:2, 2:]
    Ua, Ub = Z[4:, :2].T @ Z[4:, :2] + 0.1 * np.eye(2), Z[4:, 2:4].T @ Z[4:, 2:4] + 0.1 * np.eye(2)
    Pa, Pb = Ca_eff + Ua, Cb_eff + Ub
    bound = np.sqrt(np.linalg.eigvals(np.linalg.solve(Pa, Ca_eff)).real.max()
                    * np.linalg.eigvals(np.linalg.solve(Pb, Cb_eff)).real.max())
    assert correlation_bound(Pa, Pb, Pab) <= bound * (1 + 1e-9) + 1e-12


def test_common_bound_of_two_blocks_is_eq_8():
    Pa, Pb = random_spd(3, 7), random_spd(3, 8)
    Pab = worst_cross_covariance(Pa, Pb, np.eye(3), np.eye(3), 0.6)
    joint = np.block([[Pa, Pab], [Pab.T, Pb]])
    assert common_correlation_bound(joint, 3) == pytest.approx(0.6, abs=1e-10)
    assert common_correlation_bound(joint, [3, 3]) == pytest.approx(
        correlation_bound(Pa, Pb, Pab), abs=1e-10)


def test_definition_2_for_two_vectors_is_lemma_3_with_the_geometric_mean():
    """[[r1 P1, P12], [P21, r2 P2]] >= 0 iff rho_12 <= sqrt(r1 r2)."""
    Pa, Pb = random_spd(2, 1), random_spd(2, 2)
    Pab = worst_cross_covariance(Pa, Pb, np.eye(2), np.eye(2), 0.5)
    joint = np.block([[Pa, Pab], [Pab.T, Pb]])
    assert is_rho_admissible(joint, 2, [1.0, 0.25 + 1e-6])
    assert not is_rho_admissible(joint, 2, [1.0, 0.25 - 1e-3])
    assert is_rho_admissible(joint, 2, 0.5 + 1e-9)
    assert not is_rho_admissible(joint, 2, 0.49)


def test_three_vectors_and_unequal_blocks():
    g = np.random.default_rng(5)
    Z = g.standard_normal((6, 6))
    joint = Z @ Z.T + 0.5 * np.eye(6)
    sizes = [1, 2, 3]
    rho0 = common_correlation_bound(joint, sizes)
    assert 0 < rho0 < 1
    assert is_rho_admissible(joint, sizes, rho0 + 1e-9)
    assert not is_rho_admissible(joint, sizes, rho0 - 1e-4)
    # per-vector bounds: raising one rho_i never hurts, lowering all below rho0 does
    assert is_rho_admissible(joint, sizes, [1.0, rho0 + 1e-9, 1.0])
    assert not is_rho_admissible(joint, sizes, [rho0 - 1e-3] * 3)
    # eq. (21) written out
    edges = np.cumsum([0, *sizes])
    rho = np.array([0.9, 0.8, 0.95])
    M = joint.copy()
    for i in range(3):
        block = slice(edges[i], edges[i + 1])
        M[block, block] *= rho[i]
    assert is_rho_admissible(joint, sizes, rho) == (np.linalg.eigvalsh(M)[0] >= 0)


def test_independent_vectors_admit_rho_0_and_fully_correlated_need_1():
    Pa, Pb = random_spd(2, 3), random_spd(2, 4)
    independent = np.block([[Pa, np.zeros((2, 2))], [np.zeros((2, 2)), Pb]])
    assert common_correlation_bound(independent, 2) == pytest.approx(0.0, abs=1e-12)
    assert is_rho_admissible(independent, 2, 0.0)
    # b = T a: rank-deficient joint, correlation bound 1
    T = np.array([[1.0, 2.0], [0.0, 1.0]])
    full = np.block([[Pa, Pa @ T.T], [T @ Pa, T @ Pa @ T.T]])
    assert correlation_bound(Pa, T @ Pa @ T.T, Pa @ T.T) == pytest.approx(1.0)
    assert common_correlation_bound(full, 2) == pytest.approx(1.0)
    assert not is_rho_admissible(full, 2, 0.99)
    assert is_rho_admissible(full, 2, 1.0)


# ----------------------------------------------------------------- conventions
def test_batched_equals_per_item():
    batch = (3, 4)
    Pa, Pb = random_spd(3, 1, batch), random_spd(3, 2, batch)
    g = np.random.default_rng(0)
    K1 = g.standard_normal(batch + (3, 3))
    K2 = np.eye(3) - K1
    rho = g.uniform(size=batch)
    Pab = 0.3 * np.linalg.cholesky(Pa) @ np.linalg.cholesky(Pb).swapaxes(-1, -2)
    joint = np.concatenate([np.concatenate([Pa, Pab], -1),
                            np.concatenate([Pab.swapaxes(-1, -2), Pb], -1)], -2)
    worst = worst_case_trace(Pa, Pb, K1, K2, rho)
    loose = ci_trace_bound(Pa, Pb, K1, K2, rho)
    corr = correlation_bound(Pa, Pb, Pab)
    common = common_correlation_bound(joint, 3)
    admissible = is_rho_admissible(joint, 3, rho[..., None])
    for out in (worst, loose, corr, common, admissible):
        assert out.shape == batch
    np.testing.assert_allclose(corr, 0.3, atol=1e-12)
    for i in np.ndindex(*batch):
        assert worst[i] == pytest.approx(worst_case_trace(Pa[i], Pb[i], K1[i], K2[i], rho[i]))
        assert loose[i] == pytest.approx(ci_trace_bound(Pa[i], Pb[i], K1[i], K2[i], rho[i]))
        assert common[i] == pytest.approx(common_correlation_bound(joint[i], [3, 3]))
        assert admissible[i] == is_rho_admissible(joint[i], 3, rho[i])
        assert admissible[i] == (rho[i] >= 0.3)


def test_shared_gains_broadcast_against_batched_covariances():
    Pa, Pb = random_spd(2, 1, (5,)), random_spd(2, 2, (5,))
    K1 = np.diag([0.8, 0.2])
    out = worst_case_trace(Pa, Pb, K1, np.eye(2) - K1)
    assert out.shape == (5,)
    assert isinstance(worst_case_trace(PA, PB, K1, I2 - K1), np.floating)


def test_inputs_are_not_mutated():
    Pa, Pb = random_spd(2, 1), random_spd(2, 2)
    K1 = np.diag([0.8, 0.2])
    K2 = np.eye(2) - K1
    Pab = 0.1 * np.ones((2, 2))
    joint = np.block([[Pa, Pab], [Pab.T, Pb]])
    rho = np.array([0.5, 0.5])
    copies = [a.copy() for a in (Pa, Pb, K1, K2, Pab, joint, rho)]
    worst_case_trace(Pa, Pb, K1, K2, 0.5)
    ci_trace_bound(Pa, Pb, K1, K2, 0.5)
    correlation_bound(Pa, Pb, Pab)
    common_correlation_bound(joint, 2)
    is_rho_admissible(joint, 2, rho)
    for before, after in zip(copies, (Pa, Pb, K1, K2, Pab, joint, rho)):
        np.testing.assert_array_equal(before, after)


@pytest.mark.parametrize("call, error, message", [
    (lambda: worst_case_trace(PA, PB, I2, I2, 1.5), ValueError, r"rho must lie in \[0, 1\]"),
    (lambda: worst_case_trace(PA, PB, I2, I2, -0.1), ValueError, r"rho must lie in \[0, 1\]"),
    (lambda: worst_case_trace(PA, PB, I2, I2, np.nan), ValueError, "non-finite"),
    (lambda: worst_case_trace([PA, PA], PB, I2, I2, [0.1, 0.2, 0.3]), ValueError, "broadcast"),
    (lambda: worst_case_trace(PA, PB, np.eye(3), I2), ValueError, "K1 must have 2 columns"),
    (lambda: worst_case_trace(PA, PB, I2, np.ones((3, 2))), ValueError, "same number of rows"),
    (lambda: worst_case_trace(PA, -PB, I2, I2), ValueError, "Pb is not positive definite"),
    (lambda: worst_case_trace(PA, PB, np.ones(2), I2), ValueError, "K1 must be a matrix"),
    (lambda: ci_trace_bound(PA, [[1.0, 2.0], [0.0, 1.0]], I2, I2), ValueError, "not symmetric"),
    (lambda: worst_case_trace(PA, PB, "I", I2), TypeError, "numeric"),
    (lambda: correlation_bound(PA, PB, np.ones((2, 3))), ValueError, r"\(\.\.\., 2, 2\)"),
    (lambda: correlation_bound(PA, PB, [[np.inf, 0], [0, 0]]), ValueError, "non-finite"),
    (lambda: common_correlation_bound(np.eye(5), 2), ValueError, "does not divide"),
    (lambda: common_correlation_bound(np.eye(4), [1, 2]), ValueError, "sum to the joint"),
    (lambda: common_correlation_bound(np.eye(4), [4]), ValueError, "at least 2 blocks"),
    (lambda: common_correlation_bound(np.eye(4), [1.5, 2.5]), TypeError, "integers"),
    (lambda: common_correlation_bound(np.eye(4), "2"), TypeError, "block_sizes"),
    (lambda: common_correlation_bound(np.ones((4, 3)), 2), ValueError, r"\(\.\.\., D, D\)"),
    (lambda: common_correlation_bound(np.triu(np.ones((4, 4))), 2), ValueError, "symmetric"),
    (lambda: common_correlation_bound(np.diag([1.0, 1, 0, 1]), 2), ValueError,
     "diagonal block 1 of joint is (not positive definite|too ill-conditioned.*singular)"),
    (lambda: is_rho_admissible(np.eye(4), 2, [0.5, 0.5, 0.5]), ValueError, r"\(\.\.\., 2\)"),
    (lambda: is_rho_admissible(np.eye(4), 2, 2.0), ValueError, r"\[0, 1\]"),
    (lambda: is_rho_admissible(np.eye(4), 2, 0.5, tol=-1.0), ValueError, "tol"),
])
def test_bad_input_is_named(call, error, message):
    with pytest.raises(error, match=message):
        call()
