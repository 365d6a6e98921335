"""Linear fusion when the cross-covariances are known: the best linear unbiased fusion
(the yardstick) and its special case of independent errors ("naive" fusion).
"""

import numpy as np

from ._information import weighted_information_fusion
from ._linalg import cho_solve, spd_inverse
from ._validation import (
    as_estimates,
    as_float_array,
    as_mean_stack,
    check_covariances,
    check_finite,
    restore_style,
)
from .registry import register_method
from .result import FusionResult

__all__ = ["naive_fusion", "optimal_fusion"]


def naive_fusion(xs, Ps):
    """Fuse estimates as if their errors were independent (information-form product).

    ``P^-1 = sum_i P_i^-1`` and ``x = P sum_i P_i^-1 x_i``: the optimal fusion when all
    cross-covariances are zero. With correlated errors it double counts the common
    information and ``P`` is too small (overconfident).

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, (..., n) or (..., n, 1) each, or one array (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n).

    Returns
    -------
    FusionResult
        ``method="naive"``, ``omega=None``, ``gains`` ``K_i = P P_i^-1``.

    Raises
    ------
    ValueError
        Fewer than two estimates, bad shapes, non-finite values, covariances that are not
        symmetric positive definite.

    See Also
    --------
    optimal_fusion : the same with known, possibly nonzero, cross-covariances.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import naive_fusion
    >>> r = naive_fusion([np.array([0.0]), np.array([3.0])], [np.eye(1), 2 * np.eye(1)])
    >>> r.x.round(12).tolist(), r.P.round(12).tolist()
    ([1.0], [[0.666666666667]])
    """
    est = as_estimates(xs, Ps)
    x, P, gains = weighted_information_fusion(est.x, est.L, np.ones(est.batch_shape + (est.count,)))
    return FusionResult(restore_style(x, est.column), P, "naive", None, gains, {})


def _mean_layout(xs, dim):
    """Split the joint dimension between N estimates using the shape of ``xs``."""
    if isinstance(xs, (list, tuple)):
        count = len(xs)
        if count < 2 or dim % count:
            raise ValueError(
                f"joint has dimension {dim}, which is not N*n for the N = {count} estimates in xs"
            )
        return count, dim // count
    shape = np.shape(xs)
    if len(shape) >= 2 and shape[-2] * shape[-1] == dim:
        return shape[-2], shape[-1]
    if len(shape) >= 3 and shape[-1] == 1 and shape[-3] * shape[-2] == dim:
        return shape[-3], shape[-2]
    raise ValueError(
        f"xs of shape {shape} does not match joint of dimension {dim}: expected "
        "(..., N, n) or (..., N, n, 1) with N*n equal to the joint dimension"
    )


def optimal_fusion(xs, joint):
    """Best linear unbiased fusion with a known joint error covariance.

    With ``E = [I, ..., I]^T`` (N stacked n x n identities, eq. (10) of Weng & Djurić,
    journal version) and ``P_x`` the joint covariance of the stacked estimates,

        W^T = (E^T P_x^-1 E)^-1 E^T P_x^-1      (eq. 18)
        P   = (E^T P_x^-1 E)^-1                 (eq. 19)
        x   = W^T [x_1; ...; x_N]               (eq. 20)

    For two estimates this equals eqs. (4)-(6) of Weng & Djurić (2012):
    ``W_1 = (P_22 - P_12^T)(P_11 - P_12 - P_12^T + P_22)^-1``. It is the minimum mean
    square error linear fusion, the yardstick for every rule that does not know ``P_x``.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, (..., n) or (..., n, 1) each, or one array (..., N, n).
    joint : array_like, shape (..., N*n, N*n)
        Symmetric positive definite joint error covariance of the stacked estimates; its
        diagonal blocks are the individual covariances.

    Returns
    -------
    FusionResult
        ``method="optimal"``, ``P`` the error covariance of the fusion, ``gains`` the
        ``K_i`` (the transposed blocks of ``W``, which sum to the identity),
        ``omega=None``.

    Raises
    ------
    ValueError
        ``joint`` not square, not of dimension N*n, not symmetric positive definite,
        non-finite values, fewer than two estimates.

    See Also
    --------
    naive_fusion : the special case of zero cross-covariances.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, "A Bayesian approach to data fusion in sensor
       networks", journal version, eqs. (18)-(20).
    .. [2] Z. Weng and P. M. Djurić, "A Bayesian approach to covariance estimation and
       data fusion", EUSIPCO 2012, eqs. (4)-(6).

    Examples
    --------
    Two estimates with correlation 0.5 and variances 1 and 2; by hand,
    ``P = (P11 P22 - P12^2) / (P11 + P22 - 2 P12) = 1.5 / (3 - sqrt(2))``:

    >>> import numpy as np
    >>> from cifilter import optimal_fusion
    >>> c = 0.5 * np.sqrt(2.0)
    >>> r = optimal_fusion([np.array([0.0]), np.array([1.0])], [[1.0, c], [c, 2.0]])
    >>> round(float(r.P[0, 0]), 6), round(1.5 / (3 - 2**0.5), 6)
    (0.945903, 0.945903)
    """
    P_joint = as_float_array(joint, "joint")
    if P_joint.ndim < 2 or P_joint.shape[-1] != P_joint.shape[-2]:
        raise ValueError(f"joint must have shape (..., N*n, N*n), got {P_joint.shape}")
    count, n = _mean_layout(xs, P_joint.shape[-1])
    x, column = as_mean_stack(xs, n, count, "xs")
    check_finite(x, "xs")
    P_joint, L = check_covariances(P_joint, "joint")
    batch = np.broadcast_shapes(x.shape[:-2], P_joint.shape[:-2])
    stacked_identity = np.tile(np.eye(n), (count, 1))  # E, (N n, n)
    A = cho_solve(L, np.broadcast_to(stacked_identity, L.shape[:-1] + (n,)))  # P_x^-1 E
    information = np.swapaxes(A, -1, -2) @ stacked_identity  # E^T P_x^-1 E (symmetric)
    P = spd_inverse(0.5 * (information + np.swapaxes(information, -1, -2)), "E^T joint^-1 E")
    blocks = A.reshape(A.shape[:-2] + (count, n, n))  # block i: rows i*n..(i+1)*n of A
    gains = P[..., None, :, :] @ np.swapaxes(blocks, -1, -2)  # K_i = P A_i^T
    x_fused = np.einsum("...kij,...kj->...i", gains, x)
    P = np.broadcast_to(P, batch + (n, n)).copy()
    gains = np.broadcast_to(gains, batch + (count, n, n)).copy()
    return FusionResult(restore_style(x_fused, column), P, "optimal", None, gains, {})


def _registered_naive(xs, Ps):
    return naive_fusion(xs, Ps)


def _registered_optimal(xs, Ps, joint):
    count, n = Ps.shape[-3], Ps.shape[-1]
    P_joint = as_float_array(joint, "joint")
    if P_joint.shape[-2:] != (count * n, count * n):
        raise ValueError(
            f"joint must have shape (..., {count * n}, {count * n}) for {count} estimates of "
            f"dimension {n}, got {P_joint.shape}"
        )
    blocks = np.stack(
        [P_joint[..., i * n:(i + 1) * n, i * n:(i + 1) * n] for i in range(count)], axis=-3
    )
    scale = np.abs(Ps).max()
    if not np.allclose(blocks, Ps, rtol=1e-8, atol=1e-12 * scale):
        raise ValueError("the diagonal blocks of joint must equal the covariances of the estimates")
    return optimal_fusion(xs, P_joint)


def _optimal_truth_options(joint, rng):
    return {"joint": joint}


register_method(
    "naive",
    _registered_naive,
    summary="information-form product; assumes independent errors (double counts otherwise)",
    reference="the Kalman/information filter update",
    guarantee="none",
)
register_method(
    "optimal",
    _registered_optimal,
    summary="best linear unbiased fusion with the known joint covariance (needs joint=)",
    reference="Weng & Djurić, journal, eqs. 18-20; EUSIPCO 2012, eqs. 4-6",
    guarantee="exact",
    truth_options=_optimal_truth_options,
)
