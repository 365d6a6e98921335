"""Assumed-correlation ("cross") fusion: Bar-Shalom-Campo with an effective correlation
coefficient, as MATLAB's ``fusexcov`` and ``trackFuser`` ('Cross', factor 0.4) offer.

The cross-covariance of estimates i and j is *assumed* to be

    P_ij = rho S_i S_j,   S_i = P_i^(1/2) (symmetric square root),

and the estimates are fused by the best linear unbiased rule for that joint covariance
(Bar-Shalom & Campo 1986 for two estimates). ``P`` is the error covariance of the
returned gains *if* the assumption holds; it is no bound. Derivation and the comparison
with partial-correlation CI: ``docs/methods/cross.rst``.
"""

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.information import checked_cholesky
from .._numerics.linalg import ill_conditioned, symmetrize
from .._numerics.validation import as_estimates, check_scalar, restore_style
from ..result import FusionResult

__all__ = ["cross_covariance_fusion"]

_EPS = np.finfo(float).eps


def cross_covariance_fusion(xs: ArrayLike, Ps: ArrayLike, rho: float = 0.4) -> FusionResult:
    """Fuse estimates with an assumed cross-covariance ``P_ij = rho P_i^1/2 P_j^1/2``.

    The Bar-Shalom-Campo fusion (the best linear unbiased fusion for a known joint
    covariance) with the joint covariance replaced by the assumption
    ``P_ij = rho S_i S_j``, ``S_i`` the symmetric square root of ``P_i``: an effective
    correlation coefficient ``rho`` in every direction. For two estimates

        x = xa + (Pa - Pab) (Pa + Pb - Pab - Pab^T)^-1 (xb - xa),
        P = Pa - (Pa - Pab) (Pa + Pb - Pab - Pab^T)^-1 (Pa - Pab)^T

    (Bar-Shalom & Campo 1986, eqs. (9)-(10)); N estimates get the best linear unbiased
    fusion for the same pairwise assumption. This is the rule of MATLAB's ``fusexcov``
    and of ``trackFuser`` with ``StateFusion='Cross'``, whose default factor is 0.4.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array of shape (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n). Symmetric
        positive definite.
    rho : float, optional
        The assumed (effective) correlation coefficient in [0, 1), default 0.4 (MATLAB's
        default ``crossCovFactor``). ``rho = 0`` is the naive fusion.

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n)
        the error covariance of the returned gains under the assumed joint covariance,
        ``gains`` (..., N, n, n) (they sum to the identity), ``weights`` None (matrix
        gains), ``omega`` None, and ``info`` with ``rho`` and ``rule`` (``"assumed"``).

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, ``rho`` outside [0, 1).
    IllConditionedError
        (a ValueError) The covariance of the differences of the estimates under the
        assumption is numerically singular (equal estimates with rho near 1).
    TypeError
        Non-numeric input or a non-real ``rho``.

    See Also
    --------
    partial_ci : a *bound* for every correlation coefficient up to ``rho``.
    optimal_fusion : the same fusion with the true joint covariance.

    Notes
    -----
    There is no guarantee. If the true cross-covariance is the assumed one, ``P`` is
    exact (the rule is then :func:`optimal_fusion`). If it is smaller, ``P`` is an upper
    bound only when the assumed cross terms enter positively, ``sym(K_i S_i S_j K_j^T)``
    positive semidefinite (for instance both gains positive for scalars); with negative
    gains, which a large ``rho`` produces for dissimilar estimates, a *smaller* true
    correlation can make the fused error larger than ``P``. Partial-correlation CI
    (:func:`partial_ci`) with the same ``rho`` instead bounds the error for every joint
    whose correlation coefficient is at most ``rho``. See ``docs/methods/cross.rst``.

    The gains come from the difference basis (``e_1`` and the differences
    ``e_i - e_1``, whose covariance is factored by a QR factorisation of its square-root
    factor), and ``P`` is assembled as ``M M^T`` from the square-root factor ``M`` of the
    fused error, so it is symmetric positive semidefinite by construction.

    References
    ----------
    .. [1] Y. Bar-Shalom and L. Campo, "The effect of the common process noise on the
       two-sensor fused-track covariance", IEEE TAES 22(6), 1986.
    .. [2] MathWorks, Sensor Fusion and Tracking Toolbox, ``fusexcov`` (crossCovFactor,
       default 0.4) and ``trackFuser`` (``StateFusion='Cross'``).

    Examples
    --------
    Two scalar estimates with variances 1 and 4 and an assumed correlation of 0.4: the
    cross-covariance is 0.4 * 1 * 2 = 0.8, so ``P = 1 - 0.2^2 / 3.4``:

    >>> import numpy as np
    >>> from cifilter import cross_covariance_fusion
    >>> r = cross_covariance_fusion([np.zeros(1), np.ones(1)], [np.eye(1), 4 * np.eye(1)])
    >>> round(float(r.P[0, 0]), 12), round(1 - 0.2**2 / 3.4, 12)
    (0.988235294118, 0.988235294118)
    """
    est = as_estimates(xs, Ps)
    return _cross_covariance_fusion(est, rho)


def _symmetric_sqrt(P):
    """Symmetric square roots of a stack of SPD matrices (eigenvalues clipped at 0)."""
    lam, U = np.linalg.eigh(P)
    return symmetrize((U * np.sqrt(np.clip(lam, 0.0, None))[..., None, :]) @ U.swapaxes(-1, -2))


def _cross_covariance_fusion(est, rho=0.4):
    """The ``"cross"`` rule on validated estimates (the core of the public function)."""
    rho = check_scalar(rho, "rho", low=0.0, high=1.0, high_open=True)
    count, n = est.count, est.dim
    S = _symmetric_sqrt(est.P)  # (..., N, n, n)
    # Joint square root F = blockdiag(S_i) (L_R kron I), R = (1 - rho) I + rho 1 1^T:
    # block row i, block column k is L_R[i, k] S_i.
    R = (1.0 - rho) * np.eye(count) + rho * np.ones((count, count))
    L_R = np.linalg.cholesky(R)
    F = np.einsum("ik,...iab->...iakb", L_R, S).reshape(S.shape[:-3] + (count, n, count * n))
    F1 = F[..., 0, :, :]  # (..., n, N n)
    D = F[..., 1:, :, :] - F1[..., None, :, :]  # differences e_i - e_1: (..., N-1, n, N n)
    D = D.reshape(D.shape[:-3] + ((count - 1) * n, count * n))
    Q, T = np.linalg.qr(D.swapaxes(-1, -2))  # D^T = Q T: cov(differences) = T^T T
    t = np.abs(np.diagonal(T, axis1=-2, axis2=-1))
    if not np.all(t.min(axis=-1) > 4.0 * count * n * _EPS * t.max(axis=-1)):
        raise ill_conditioned(
            "the covariance of the differences of the estimates under the assumed "
            f"correlation rho = {rho}", (t.max(axis=-1) / t.min(axis=-1)) ** 2)
    # Gains of the differences: -cov(e_1, d) cov(d)^-1 = -(F1 Q) T^-T
    rest = -np.linalg.solve(T, (F1 @ Q).swapaxes(-1, -2)).swapaxes(-1, -2)
    rest = rest.reshape(rest.shape[:-1] + (count - 1, n))  # (..., n, N-1, n)
    rest = np.moveaxis(rest, -2, -3)  # (..., N-1, n, n)
    K1 = np.eye(n) - rest.sum(axis=-3)
    gains = np.concatenate([K1[..., None, :, :], rest], axis=-3)
    M = np.einsum("...kab,...kbc->...ac", gains, F)
    P = symmetrize(M @ M.swapaxes(-1, -2))
    x = est.x[..., 0, :] + np.einsum("...kab,...kb->...a", rest,
                                     est.x[..., 1:, :] - est.x[..., :1, :])
    checked_cholesky(P, "the fused covariance")  # finite, numerically positive definite
    info = {"rule": "assumed", "rho": rho}
    return FusionResult(restore_style(x, est.column), P, "cross", None, gains, info)


REGISTRATION: dict[str, Any] = dict(
    name="cross",
    function=cross_covariance_fusion,
    core=_cross_covariance_fusion,
    summary="Bar-Shalom-Campo with an assumed correlation rho (MATLAB fusexcov, default 0.4)",
    reference="Bar-Shalom & Campo 1986; MATLAB fusexcov / trackFuser 'Cross'",
    guarantee="none",
    weights="None: matrix gains of the best linear fusion for the assumed joint covariance",
)
"""The record of the ``"cross"`` rule (registered by :mod:`cifilter.rules`).

No guarantee: ``P`` is exact if the true cross-covariance is the assumed
``rho P_i^1/2 P_j^1/2``; it bounds the error for a smaller true correlation only when the
assumed cross terms of the gains are positive semidefinite.
"""
