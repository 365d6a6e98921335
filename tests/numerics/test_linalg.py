"""Internal batched linear algebra (cifilter._numerics.linalg); input checking is in
test_validation."""

import mpmath
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import ill_conditioned_spd

from cifilter._numerics.linalg import (
    IllConditionedError,
    cho_inverse,
    cho_solve,
    cholesky,
    logdet_from_cholesky,
    lower_inverse,
    mahalanobis_sq,
    solve_lower,
)

rng = np.random.default_rng(7)
EPS = np.finfo(float).eps


def spd(size, n):
    A = rng.standard_normal(size + (n, n))
    return A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(n)


@pytest.mark.parametrize("size", [(), (1,), (5,), (3, 4)])
@pytest.mark.parametrize("n", [1, 2, 5])
def test_triangular_and_cholesky_solves_match_lapack(size, n):
    P = spd(size, n)
    L = cholesky(P)
    B = rng.standard_normal(size + (n, 3))
    np.testing.assert_allclose(solve_lower(L, B), np.linalg.solve(L, B), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(lower_inverse(L), np.linalg.inv(L), rtol=1e-10, atol=1e-12)
    inverse = cho_inverse(L)
    np.testing.assert_array_equal(inverse, np.swapaxes(inverse, -1, -2))
    np.testing.assert_allclose(inverse, np.linalg.inv(P), rtol=1e-8, atol=1e-10)
    b = rng.standard_normal(size + (n,))
    np.testing.assert_allclose(cho_solve(L, b), np.linalg.solve(P, b[..., None])[..., 0],
                               rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(logdet_from_cholesky(L), np.linalg.slogdet(P)[1], rtol=1e-10)


def test_mahalanobis_broadcasts_and_matches_the_definition():
    P = spd((), 3)
    e = rng.standard_normal((6, 3))
    expected = np.einsum("ki,ij,kj->k", e, np.linalg.inv(P), e)
    np.testing.assert_allclose(mahalanobis_sq(e, P), expected, rtol=1e-10)


def test_cholesky_names_the_argument_and_index():
    P = np.stack([np.eye(2), np.diag([1.0, -2.0])])
    with pytest.raises(ValueError, match=r"P\[1\] is not positive definite.*-2"):
        cholesky(P, "P")
    with pytest.raises(ValueError, match="not positive definite"):
        cholesky(np.diag([np.nan, 1.0]), "P")


def rotated(eigenvalues, angle=0.3):
    c, s = np.cos(angle), np.sin(angle)
    Q = np.array([[c, -s], [s, c]])
    A = Q @ np.diag(eigenvalues) @ Q.T
    return 0.5 * (A + A.T)


@pytest.mark.parametrize("A", [
    rotated([1e20, 17.0]),  # PD in exact arithmetic; rounding makes Cholesky fail
    np.ones((2, 2)),  # PSD, singular
    np.zeros((2, 2)),
    np.diag([1.0, -1e-17]),  # indefinite by a rounding-level eigenvalue only
])
def test_numerically_singular_matrices_are_ill_conditioned_not_indefinite(A):
    with pytest.raises(IllConditionedError, match=r"^P is too ill-conditioned for a Cholesky "
                                                  r"factorisation: condition number"):
        cholesky(A, "P")


def test_the_failing_matrix_of_a_stack_is_named():
    P = np.stack([np.eye(2), rotated([1e20, 17.0])])
    with pytest.raises(IllConditionedError, match=r"^P\[1\] "):
        cholesky(P, "P")
    assert issubclass(IllConditionedError, ValueError)


@pytest.mark.parametrize("A, smallest", [
    (-np.eye(2), "-1"),
    (np.array([[1.0, 2.0], [2.0, 1.0]]), "-1"),
    (rotated([1e20, -1e10]), "-1e\\+10"),
])
def test_indefinite_matrices_say_not_positive_definite_with_the_smallest_eigenvalue(A, smallest):
    with pytest.raises(ValueError, match=rf"^P is not positive definite \(smallest eigenvalue "
                                         rf"{smallest}"):
        cholesky(A, "P")


def test_cholesky_success_path_is_unchanged_for_well_conditioned_stacks():
    P = spd((3, 2), 4)
    np.testing.assert_array_equal(cholesky(P, "P"), np.linalg.cholesky(P))


# ------------------------------------------------------------------ single matrices (LAPACK path)
@pytest.mark.parametrize("A, message", [
    (np.array([[1.0, 2.0], [2.0, 1.0]]), r"not positive definite \(smallest eigenvalue -1\b"),
    (np.array([[-1.0]]), r"not positive definite \(smallest eigenvalue -1\b"),
    # leading 3x3 block positive definite: the factorisation fails only at the last pivot
    (np.diag([4.0, 3.0, 2.0, -1e-3]), r"not positive definite \(smallest eigenvalue -0\.001"),
    (np.array([[1.0, np.nan], [np.nan, 1.0]]), "non-finite"),
    (np.array([[np.inf, 0.0], [0.0, 1.0]]), "non-finite"),
])
def test_one_matrix_is_rejected_when_it_is_not_positive_definite(A, message):
    """The single-matrix path (LAPACK called directly) must reject, not return a partial
    factor: each of these was accepted when that path's check was removed."""
    with pytest.raises(ValueError, match=message):
        cholesky(A, "P")
    with pytest.raises(ValueError, match=message):
        mahalanobis_sq(np.ones(A.shape[0]), A)


def test_one_matrix_and_a_stack_of_it_give_the_same_factor():
    A = spd((), 4)
    np.testing.assert_allclose(cholesky(A), cholesky(A[None])[0], rtol=1e-14)
    np.testing.assert_allclose(cholesky(A) @ cholesky(A).T, A, rtol=1e-13)


# ------------------------------------------------------------------ accuracy at condition 1e12
def _forward_substitution_50_digits(L, B):
    """``X = L^-1 B`` and ``|L^-1|`` from the inputs' exact binary values in 50 digits."""
    n, k = B.shape
    with mpmath.workdps(50):
        Lm = [[mpmath.mpf(float(v)) for v in row] for row in L]
        X = [[mpmath.mpf(0)] * k for _ in range(n)]
        for c in range(k):
            for i in range(n):
                s = mpmath.mpf(float(B[i, c]))
                for j in range(i):
                    s -= Lm[i][j] * X[j][c]
                X[i][c] = s / Lm[i][i]
        L_inv = mpmath.inverse(mpmath.matrix(Lm))
        exact = np.array([[float(X[i][c]) for c in range(k)] for i in range(n)])
        abs_inverse = np.array([[float(abs(L_inv[i, j])) for j in range(n)] for i in range(n)])
    return exact, abs_inverse


@given(st.integers(1, 6).flatmap(
    lambda n: st.tuples(ill_conditioned_spd(n), st.integers(0, 2**32 - 1))))
def test_triangular_solves_are_componentwise_accurate_against_50_digits(args):
    """solve_lower on the Cholesky factor of a covariance with condition number up to 1e12
    (scales 1e-12..1e12): every entry of X lies within 2 gamma_n (|L^-1| |L| |X|)_ij of the
    50-digit solution (the componentwise bound of a triangular solve, Higham, Accuracy and
    Stability of Numerical Algorithms, Thm 8.5), for one matrix (LAPACK's dtrtrs) and for a
    stack (the row loop) alike. The one-matrix path used to be numpy.linalg.solve, an LU
    factorisation that pivots rows where an entry below the diagonal is the larger: it
    missed this bound by up to 100 times (P = [[0.75, 1.25], [1.25, 18.74]] already 3x)."""
    P, seed = args
    n = len(P)
    L = np.linalg.cholesky(P)
    B = np.random.default_rng(seed).standard_normal((n, 3)) * np.sqrt(np.diag(P))[:, None]
    exact, abs_inverse = _forward_substitution_50_digits(L, B)
    gamma = n * EPS / (1 - n * EPS)
    bound = 2.0 * gamma * (abs_inverse @ np.abs(L) @ np.abs(exact))
    for X in (solve_lower(L, B), solve_lower(np.stack([L, L]), np.stack([B, B]))[1]):
        excess = np.abs(X - exact) - bound
        assert np.all(excess <= 0.0), (np.abs(X - exact) / bound).max()


def test_one_singular_triangular_matrix_raises_like_numpy():
    with pytest.raises(np.linalg.LinAlgError, match="Singular matrix"):
        solve_lower(np.array([[1.0, 0.0], [1.0, 0.0]]), np.ones((2, 1)))


def test_one_triangular_solve_reads_only_the_lower_triangle_and_copies():
    L = np.array([[2.0, 99.0], [1.0, 4.0]])  # the upper triangle is not part of L
    B = np.array([[2.0], [9.0]])
    before = (L.copy(), B.copy())
    np.testing.assert_array_equal(solve_lower(L, B), [[1.0], [2.0]])
    np.testing.assert_array_equal(L, before[0])
    np.testing.assert_array_equal(B, before[1])
