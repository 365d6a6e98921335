"""Information-form fusion shared by CI and naive fusion.

``P^-1 = sum_i w_i P_i^-1``, ``x = P sum_i w_i P_i^-1 x_i`` and ``K_i = w_i P P_i^-1``.
"""

import numpy as np

from ._linalg import cho_inverse, cholesky, symmetrize

__all__ = ["information_matrices", "weighted_information_fusion"]


def information_matrices(L):
    """``P_i^-1`` for Cholesky factors ``L`` of shape (..., N, n, n)."""
    return cho_inverse(L)


def weighted_information_fusion(x, L, weights, informations=None):
    """Fuse estimates in information form with scalar weights.

    Parameters
    ----------
    x : ndarray, shape (..., N, n)
    L : ndarray, shape (..., N, n, n)
        Cholesky factors of the input covariances.
    weights : ndarray, shape (..., N)
        Nonnegative weights (1 for naive fusion, on the simplex for CI).
    informations : ndarray, shape (..., N, n, n), optional
        ``P_i^-1`` if already computed.

    Returns
    -------
    x_fused : ndarray, shape (..., n)
    P_fused : ndarray, shape (..., n, n), symmetric
    gains : ndarray, shape (..., N, n, n)
    """
    if informations is None:
        informations = information_matrices(L)
    weighted = weights[..., None, None] * informations
    J = symmetrize(weighted.sum(axis=-3))
    L_fused = cholesky(J, "fused information matrix")
    P = cho_inverse(L_fused)
    # K_i = w_i P P_i^-1, so x = sum_i K_i x_i; both come from the same gains.
    gains = P[..., None, :, :] @ weighted
    x_fused = np.einsum("...kij,...kj->...i", gains, x)
    return x_fused, P, gains

