"""Hypothesis strategies for covariances and admissible joint covariances.

``joint_covariances`` builds every kind of cross-covariance the fusion rules must survive:
independent, partially and fully correlated (rank-deficient correlation), by whitening
a random Gram matrix block by block so that the diagonal blocks are exactly the given
covariances.
"""

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)


@st.composite
def spd_matrices(draw, n, min_eigenvalue=0.05, max_eigenvalue=20.0):
    """Symmetric positive definite n x n matrices with bounded condition number."""
    A = draw(arrays(float, (n, n), elements=finite))
    Q, _ = np.linalg.qr(A + 1e-3 * np.eye(n))
    eigenvalues = draw(
        arrays(float, (n,), elements=st.floats(min_eigenvalue, max_eigenvalue))
    )
    P = (Q * eigenvalues) @ Q.T
    return 0.5 * (P + P.T)


@st.composite
def covariance_sets(draw, count, n):
    """A list of ``count`` covariances of dimension n."""
    return [draw(spd_matrices(n)) for _ in range(count)]


def _inverse_sqrt(S):
    eigenvalues, vectors = np.linalg.eigh(S)
    return (vectors / np.sqrt(eigenvalues)) @ vectors.T


def joint_from_correlation(Ps, Z):
    """Joint covariance with diagonal blocks ``Ps`` from a random factor ``Z`` (N*n x k)."""
    count, n = len(Ps), Ps[0].shape[0]
    S = Z @ Z.T + 1e-9 * np.eye(count * n)
    D = np.zeros_like(S)
    for i in range(count):
        block = slice(i * n, (i + 1) * n)
        D[block, block] = np.linalg.cholesky(Ps[i]) @ _inverse_sqrt(S[block, block])
    joint = D @ S @ D.T
    joint = 0.5 * (joint + joint.T)
    for i in range(count):  # exact diagonal blocks
        block = slice(i * n, (i + 1) * n)
        joint[block, block] = Ps[i]
    return joint


@st.composite
def joint_covariances(draw, Ps):
    """An admissible joint covariance (positive semidefinite) with diagonal blocks ``Ps``."""
    count, n = len(Ps), Ps[0].shape[0]
    rank = draw(st.integers(1, count * n))  # small rank: strongly/fully correlated
    Z = draw(arrays(float, (count * n, rank), elements=finite))
    Z = Z + 1e-3 * np.eye(count * n, rank)
    return joint_from_correlation(Ps, Z)


def fused_error_covariance(gains, joint):
    """Covariance of sum_i K_i e_i when the stacked errors have covariance ``joint``."""
    K = np.concatenate(list(gains), axis=-1)  # [K_1 ... K_N], n x N*n
    return K @ joint @ K.T


def assert_psd(M, tol=1e-8, what="matrix"):
    """Assert that a symmetric matrix is positive semidefinite up to a relative tolerance."""
    smallest = np.linalg.eigvalsh(0.5 * (M + M.T))[0]
    scale = max(1.0, float(np.abs(M).max()))
    assert smallest >= -tol * scale, f"{what} has eigenvalue {smallest:.3g} < 0"
