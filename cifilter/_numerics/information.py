"""Information-form fusion with scalar weights, shared by CI, partial CI and naive fusion.

With weights ``w_i > 0`` (on the simplex for CI, eq. (24) of Wu, Cai & Fu for partial CI,
all one for the naive fusion) the gains are ``K_i = w_i P P_i^-1`` with
``P^-1 = sum_i w_i P_i^-1``, and the fused mean is ``x = sum_i K_i x_i``.

The covariance returned is not ``(sum_i w_i P_i^-1)^-1`` evaluated as such but the bound
*of the gains actually returned*,

    P = sum_i K_i P_i K_i^T / w_i,

which equals it in exact arithmetic. For any gains with ``sum_i K_i = I`` this ``P`` bounds
the error covariance of ``sum_i K_i e_i`` for every joint covariance the rule admits
(arbitrary correlation when ``w`` is on the simplex; Theorem 5 of Wu, Cai & Fu for the
partial-correlation weights; it is the exact covariance for independent errors when all
``w_i = 1``); see ``docs/methods/ci.rst``, "Numerical formulation". So rounding in the
weights, the factorisations or the gains can make ``P`` larger than the optimum, never
smaller than the error covariance of what is returned. It is formed as a sum of outer
products ``w_i B_i B_i^T`` (``B_i = P L_i^-T``), so it is symmetric positive semidefinite
by construction, and no step squares a condition number: the information matrices are
built from the inverse Cholesky factors, and only triangular inverses are taken.
"""

import math
from typing import NamedTuple

import numpy as np

from .linalg import (
    cholesky_failures,
    cholesky_single,
    condition_number,
    ill_conditioned,
    lower_inverse,
    lower_inverse_single,
    symmetrize,
)

__all__ = [
    "DIAGONAL_TRUST",
    "InformationFactors",
    "WeightedFusion",
    "checked_cholesky",
    "diagonal_spread_squared",
    "information_factors",
    "information_matrices",
    "log_det_curvature",
    "lower_inverse_stack",
    "reference_estimates",
    "single_diagonalisation_trusted",
    "squared_norms",
    "trace_curvature",
    "weighted_fusion",
    "weighted_information",
]

_EPS = np.finfo(float).eps


def lower_inverse_stack(L):
    """Inverse of lower triangular matrices (..., n, n).

    One matrix (any number of unit leading axes) goes to LAPACK's triangular inverse, a
    stack to the batched forward substitution; both are backward stable, their results
    agree to rounding.
    """
    n = L.shape[-1]
    if L.size == n * n:
        return lower_inverse_single(L.reshape(n, n)).reshape(L.shape)
    if L.ndim == 3 and L.shape[0] <= 8:  # the estimates of one problem (no batch axes)
        return np.stack([lower_inverse_single(item) for item in L])
    return lower_inverse(L.reshape((-1,) + L.shape[-2:])).reshape(L.shape)


def information_matrices(L):
    """``P_i^-1 = L_i^-T L_i^-1`` for Cholesky factors ``L`` of shape (..., N, n, n)."""
    L_inv = lower_inverse_stack(L)
    return L_inv.swapaxes(-1, -2) @ L_inv


class WeightedFusion(NamedTuple):
    """Everything the weighted information fusion computes (one batch of problems).

    ``factors`` give the criteria and their gradients at the weights without further
    solves (see :func:`information_factors`).
    """

    x: np.ndarray  # (..., n) fused mean
    P: np.ndarray  # (..., n, n) bound of the gains, symmetric positive definite
    gains: np.ndarray  # (..., N, n, n), summing to the identity
    factors: "InformationFactors"  # of P^-1 = sum_i w_i P_i^-1 (gradients of the criteria)


# A simultaneous diagonalisation of two covariances (the two-estimate solvers of CI and
# partial CI) is trusted where the eigenvalues it rests on are accurate: their spread, and
# the squared diagonal spread of both Cholesky factors, at most this (rounding of
# eps * 1e6 = 2e-10 relative, well below the solvers' gap tolerances). Elsewhere the
# Cholesky-based paths decide.
DIAGONAL_TRUST = 1e6


def single_diagonalisation_trusted(lam, factors):
    """:data:`DIAGONAL_TRUST` for one problem: ``lam`` the ascending generalised eigenvalues
    (a list of floats), ``factors`` the two triangular Cholesky factors (or their inverses,
    whose squared diagonal spread is the same)."""
    if not (lam[0] > 0.0 and math.isfinite(lam[-1])) or lam[-1] > DIAGONAL_TRUST * lam[0]:
        return False
    for factor in factors:
        d = [abs(v) for v in factor.diagonal().tolist()]
        if max(d) ** 2 > DIAGONAL_TRUST * min(d) ** 2:
            return False
    return True


def diagonal_spread_squared(L):
    """``(max / min |diagonal|)^2`` of triangular factors: a lower bound of the condition
    number of ``L L^T`` (inf for a zero, NaN for a non-finite diagonal)."""
    d = np.abs(np.diagonal(L, axis1=-2, axis2=-1))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return (d.max(axis=-1) / d.min(axis=-1)) ** 2


def _numerically_positive_definite(R, n):
    """Factors whose diagonal spans less than ``1 / (n eps)`` in square, per problem.

    Beyond that the factor is rounding noise, and so would be every result formed from it.
    """
    finite = np.isfinite(R).all(axis=(-2, -1))
    with np.errstate(invalid="ignore"):
        return finite & (diagonal_spread_squared(R) < 1.0 / (n * _EPS))


def checked_cholesky(A, name, *, failures="raise"):
    """Lower Cholesky factors of a stack of SPD matrices, rejecting numerically singular ones.

    Parameters
    ----------
    A : ndarray, shape (..., n, n)
        Symmetric matrices.
    name : str
        Their name in the error message.
    failures : {"raise", "nan"}
        ``"raise"``: IllConditionedError (with the condition number) if any matrix is not
        numerically positive definite. ``"nan"``: such matrices get a factor of NaN.

    Returns
    -------
    ndarray, shape (..., n, n)
    """
    n = A.shape[-1]
    if A.size == n * n:  # one matrix: LAPACK directly, the checks on its diagonal in Python
        R = cholesky_single(A.reshape(n, n))
        if R is not None:
            d = [abs(v) for v in R.diagonal().tolist()]
            if max(d) ** 2 < min(d) ** 2 / (n * _EPS):
                return R.reshape(A.shape)
    try:
        R = np.linalg.cholesky(A)
        ok = _numerically_positive_definite(R, n)
    except np.linalg.LinAlgError:
        # Some matrix of the stack failed: find which (failure path only), factor the rest.
        ok = ~cholesky_failures(A)
        R = np.linalg.cholesky(np.where(ok[..., None, None], A, np.eye(n)))
        ok = ok & _numerically_positive_definite(R, n)
    if not np.all(ok):
        if failures == "raise":
            bad = np.where(ok[..., None, None], np.eye(n), A)
            raise ill_conditioned(name, condition_number(bad).max())
        R = np.where(ok[..., None, None], R, np.nan)
    return R


class InformationFactors(NamedTuple):
    """Factors of ``P = (sum_i w_i P_i^-1)^-1`` from which the criteria and gains follow."""

    R: np.ndarray  # (..., n, n), lower Cholesky factor of P^-1 = sum_i w_i P_i^-1
    R_inv: np.ndarray  # (..., n, n), its inverse
    B: np.ndarray  # (..., N, n, n), B_i = P L_i^-T = R^-T C_i
    C: np.ndarray  # (..., N, n, n), C_i = R^-1 L_i^-T


def weighted_information(weights, informations):
    """``sum_i w_i I_i`` (..., n, n), symmetric, for weights (..., N) and information
    matrices (..., N, n, n): the fused information of every scalar-weight rule."""
    return symmetrize(np.einsum("...k,...kij->...ij", weights, informations))


def information_factors(L_inv, weights, *, failures="raise"):
    """The factors of the weighted information fusion (no gains, no fused mean).

    Parameters
    ----------
    L_inv : ndarray, shape (..., N, n, n)
        Inverses of the inputs' lower Cholesky factors.
    weights : ndarray, shape (..., N)
        Nonnegative weights, at least one positive per problem.
    failures : {"raise", "nan"}
        What a numerically singular fused information matrix gives: IllConditionedError, or
        NaN factors for that problem (for solvers that step back from such weights).

    Returns
    -------
    InformationFactors
        With ``P = R_inv^T R_inv``: ``trace(W P) = trace(W R_inv^T R_inv)``,
        ``-d trace(W P) / d w_i = trace(W B_i B_i^T)``, ``log det P = 2 log |det R_inv|``
        and ``-d log det P / d w_i = ||C_i||_F^2``.

    Raises
    ------
    IllConditionedError
        The fused information matrix is numerically singular.
    """
    # Loops run over the N estimates, never over the batch: on stacks of small matrices a
    # matmul per estimate is faster than einsum or a reduction over the estimate axis.
    count = L_inv.shape[-3]
    J = None
    for k in range(count):
        Lk = L_inv[..., k, :, :]
        term = weights[..., k, None, None] * (Lk.swapaxes(-1, -2) @ Lk)
        J = term if J is None else J + term
    # (potrf reads one triangle only: J need not be symmetrised)
    R = checked_cholesky(J, "the fused information matrix", failures=failures)
    R_inv = lower_inverse_stack(R)
    C = R_inv[..., None, :, :] @ L_inv.swapaxes(-1, -2)
    B = R_inv.swapaxes(-1, -2)[..., None, :, :] @ C
    return InformationFactors(R, R_inv, B, C)


def reference_estimates(weights, L):
    """The estimate whose gain is ``I`` minus the others, per problem (int, shape (...,)).

    The most precise weighted estimate: the first of largest ``w_i / trace(P_i)`` among
    those of positive weight (``trace(P_i) = ||L_i||_F^2``). The remainder's rounding, of
    order ``eps`` times the other gains, enters the bound of the gains multiplied by the
    reference's own covariance (``dK_r P_r dK_r^T / w_r``); the estimate of largest weight
    can be the least precise one (equal weights, covariances of very different scales),
    and then that term is as large as ``P`` itself. The compiled kernels take the same
    choice (``_kernels/dispatch.py``), so both backends agree (``docs/backend.rst``).
    """
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        precision = weights / np.einsum("...kij,...kij->...k", L, L)
        precision = np.where(weights > 0.0, np.nan_to_num(precision, nan=0.0), -1.0)
    return np.argmax(precision, axis=-1)


def weighted_fusion(x, L, weights, L_inv=None, factors=None):
    """Fuse estimates in information form with scalar weights (see the module docstring).

    Parameters
    ----------
    x : ndarray, shape (..., N, n)
        Means.
    L : ndarray, shape (..., N, n, n)
        Cholesky factors of the input covariances.
    weights : ndarray, shape (..., N)
        Nonnegative weights, at least one positive per problem (on the simplex for CI,
        eq. (24) of Wu, Cai & Fu for partial CI, ones for the naive fusion). A zero weight
        gives a zero gain: the estimate is ignored.
    L_inv : ndarray, shape (..., N, n, n), optional
        ``L^-1`` if already computed.
    factors : InformationFactors, optional
        :func:`information_factors` at ``weights`` if already computed (finite).

    Returns
    -------
    WeightedFusion
        ``x``, ``P`` (the bound of the returned gains), ``gains`` (exactly
        ``I - sum`` of the others for the most precise weighted estimate,
        :func:`reference_estimates`, so that they sum to the identity to rounding), and the
        information ``factors`` at the weights.

    Raises
    ------
    IllConditionedError
        The fused information matrix is numerically singular.
    """
    if L_inv is None:
        L_inv = lower_inverse_stack(L)
    if factors is None:
        factors = information_factors(L_inv, weights)
    if weights.ndim == 1:
        return _single_weighted_fusion(x, L, weights, L_inv, factors)
    B = factors.B
    n, count = x.shape[-1], x.shape[-2]
    # K_i = w_i P P_i^-1 = w_i B_i L_i^-1. The gains sum to I in exact arithmetic; make it
    # hold to rounding by giving the most precise weighted estimate the remainder, so that
    # the fused mean is unbiased and the error is exactly sum_i K_i e_i, the quantity the
    # bound below is about.
    reference = reference_estimates(weights, L)
    gains = np.empty(B.shape)
    remainder = np.broadcast_to(np.eye(n), B.shape[:-3] + (n, n)).copy()
    for k in range(count):
        mine = (reference == k)[..., None, None]
        K = B[..., k, :, :] @ L_inv[..., k, :, :]
        K = np.where(mine, 0.0, weights[..., k, None, None] * K)
        gains[..., k, :, :] = K
        remainder -= K
    x_ref = np.take_along_axis(x, reference[..., None, None], axis=-2)[..., 0, :]
    x_fused = x_ref.copy()
    for k in range(count):
        mine = (reference == k)[..., None, None]
        gains[..., k, :, :] = np.where(mine, remainder, gains[..., k, :, :])
        x_fused += (gains[..., k, :, :] @ (x[..., k, :] - x_ref)[..., None])[..., 0] * (
            reference != k)[..., None]
    # The bound of these gains: sum_i K_i P_i K_i^T / w_i = sum_i (K_i L_i)(K_i L_i)^T / w_i,
    # a sum of outer products (zero weight: zero gain, no term).
    P = np.zeros(B.shape[:-3] + (n, n))
    for k in range(count):
        w = weights[..., k, None, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            M = np.where(w > 0.0, (gains[..., k, :, :] @ L[..., k, :, :]) / np.sqrt(w), 0.0)
        P += M @ M.swapaxes(-1, -2)
    P = symmetrize(P)
    return WeightedFusion(x_fused, P, gains, factors)


def _single_weighted_fusion(x, L, weights, L_inv, factors):
    """:func:`weighted_fusion` of one problem (no batch axes): the same gains, mean and
    bound, with Python control flow instead of masks over a batch."""
    count, n = x.shape
    w = weights.tolist()
    reference = int(reference_estimates(weights, L))
    gains = np.empty((count, n, n))
    remainder = np.eye(n)
    x_ref = x[reference]
    x_fused = x_ref.copy()
    for k in range(count):
        if k == reference:
            continue
        K = w[k] * (factors.B[k] @ L_inv[k]) if w[k] > 0.0 else np.zeros((n, n))
        gains[k] = K
        remainder -= K
        x_fused += K @ (x[k] - x_ref)
    gains[reference] = remainder
    P = np.zeros((n, n))
    for k in range(count):
        if w[k] > 0.0:
            M = (gains[k] @ L[k]) / math.sqrt(w[k])
            P += M @ M.T
    return WeightedFusion(x_fused, 0.5 * (P + P.T), gains, factors)


def squared_norms(A):
    """Squared Frobenius norms over the last two axes (``trace P = ||R_inv||^2``,
    ``Tr(P P_i^-1 P) = ||B_i||^2``, ``Tr(P P_i^-1) = ||C_i||^2``)."""
    return np.square(A).sum(axis=(-2, -1))


def trace_curvature(factors, W=None):
    """``Tr(W P P_i^-1 P P_j^-1 P)`` for every pair (i, j), shape (..., N, N).

    With ``P P_i^-1 P = B_i B_i^T`` and ``L_i^-1 P L_j^-T = C_i^T C_j`` it is
    ``Tr(B_i^T W B_j C_j^T C_i) = <B_i C_i^T, W B_j C_j^T>_F``: the Gram matrix of the N
    products ``B_i C_i^T`` (n x n each) against ``W B_j C_j^T``, one matrix product of
    (N, n^2) by (n^2, N) after N small ones, O(N n^3 + N^2 n^2) instead of the
    O(N^2 n^3) of forming every ``B_i^T W B_j`` and ``C_j^T C_i``. The Hessian factor of
    ``Tr(W P(w))`` in the weights (CI: ``2 x`` this; partial CI: with the chain rule of
    eq. (24)). ``W = None`` is ``I`` (then the result is a Gram matrix, positive
    semidefinite by construction).
    """
    B, C = factors.B, factors.C
    Ct = C.swapaxes(-1, -2)
    left = B @ Ct  # B_i C_i^T
    right = left if W is None else (W[..., None, :, :] @ B) @ Ct
    flat = left.shape[:-2] + (-1,)
    return left.reshape(flat) @ right.reshape(flat).swapaxes(-1, -2)


def log_det_curvature(factors):
    """``||C_i^T C_j||_F^2 = Tr(P P_i^-1 P P_j^-1)`` for every pair (i, j), shape (..., N, N):
    the Hessian of ``log det P(w)`` in the weights.

    ``||C_i^T C_j||_F^2 = <C_i C_i^T, C_j C_j^T>_F``: the Gram matrix of the N products
    ``C_i C_i^T``, O(N n^3 + N^2 n^2) (as :func:`trace_curvature`), positive semidefinite by
    construction.
    """
    C = factors.C
    G = C @ C.swapaxes(-1, -2)
    flat = G.reshape(G.shape[:-2] + (-1,))
    return flat @ flat.swapaxes(-1, -2)
