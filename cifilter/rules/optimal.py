"""Linear fusion when the cross-covariances are known: the best linear unbiased fusion
(the yardstick) and its special case of independent errors ("naive" fusion).
"""

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .._kernels import dispatch as kernels
from .._numerics.alignment import PartialEstimates, unobserved_directions
from .._numerics.information import weighted_fusion
from .._numerics.linalg import MAX_CONDITION, cho_inverse, cho_solve, positive_definite, symmetrize
from .._numerics.validation import (
    as_estimates,
    as_float_array,
    as_mean_stack,
    check_finite,
    check_symmetric,
    restore_style,
)
from ..result import FusionResult
from ._generalised_ci import generalised_naive

__all__ = ["naive_fusion", "optimal_fusion"]


def naive_fusion(xs: ArrayLike, Ps: ArrayLike) -> FusionResult:
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
        ``method="naive"``, ``weights`` all one (``P^-1 = sum_i P_i^-1``), ``omega=None``,
        ``gains`` ``K_i = P P_i^-1``.

    Raises
    ------
    ValueError
        Fewer than two estimates, bad shapes, non-finite values, covariances that are not
        symmetric positive definite; :class:`~cifilter.IllConditionedError` (a ValueError)
        where the fused information is numerically singular (only beyond the conditioning
        contract). ``P`` is returned as ``sum_i K_i P_i K_i^T``, the exact error covariance
        of the returned gains for independent errors, symmetric positive semidefinite by
        construction.

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
    return _naive_fusion(as_estimates(xs, Ps))


def _naive_fusion(est):
    """The ``"naive"`` rule on validated estimates (the core of :func:`naive_fusion`).

    Estimates of parts ``H_i x`` (``fuse(..., H=...)``) take
    ``P^-1 = sum_i H_i^T P_i^-1 H_i`` (eq. (H5) of ``docs/methods/partial_state.rst``).
    """
    if isinstance(est, PartialEstimates):
        return generalised_naive(est)
    weights = np.ones(est.batch_shape + (est.count,))
    compiled = kernels.weighted(est, weights, None, None, weighted_fusion)
    if compiled is None:
        fused = weighted_fusion(est.x, est.L, weights)
        x, P, gains = fused.x, fused.P, fused.gains
    else:
        (x, P, gains), _ = compiled
    return FusionResult(restore_style(x, est.column), P, "naive", None, gains, {}, weights)


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


# Rank tolerance of the singular-joint path: eigenvalues of the joint's difference block at
# most RANK_RTOL * N*n * trace(joint) are rounding noise of an exactly singular joint.
RANK_RTOL = 8 * np.finfo(float).eps


def _stacked_identity(count, n):
    """E = [I; ...; I], (N n, n)."""
    return np.tile(np.eye(n), (count, 1))


def _difference_basis(count, n):
    """Orthonormal basis (N n, (N-1) n) of the null space of E^T (combinations of differences).

    ``kron(H, I_n)`` with ``H`` (N, N-1) orthonormal and orthogonal to the ones vector.
    """
    ones = np.full((count, 1), 1.0 / np.sqrt(count))
    Q, _ = np.linalg.qr(np.hstack([ones, np.eye(count)[:, :-1]]))
    H = Q[:, 1:count]
    return np.kron(H, np.eye(n))


def _blue_factors(J, E, n):
    """``(J^-1 E, (E^T J^-1 E)^-1)`` through Cholesky factors; None if the joint (or the
    fused information) is (nearly) singular.

    Used when the joint's Cholesky pivots show a condition number of at most
    MAX_CONDITION (so always within the conditioning contract).
    """
    try:
        L = np.linalg.cholesky(J)
    except np.linalg.LinAlgError:
        return None
    pivots = np.diagonal(L, axis1=-2, axis2=-1)
    if not np.all(np.isfinite(L)) or np.any(
        pivots.min(axis=-1) * np.sqrt(MAX_CONDITION) < pivots.max(axis=-1)
    ):
        return None  # (max_i L_ii / min_i L_ii)^2 <= cond(J): certainly too ill-conditioned
    A = cho_solve(L, np.broadcast_to(E, L.shape[:-1] + (n,)))  # J^-1 E
    information = symmetrize(np.swapaxes(A, -1, -2) @ E)  # E^T J^-1 E
    try:
        L_information = np.linalg.cholesky(information)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(L_information)):
        return None
    return A, cho_inverse(L_information)


def _blue_cholesky(J, count, n):
    """Eqs. (18)-(19) through Cholesky factors; None if the joint is (nearly) singular."""
    factors = _blue_factors(J, _stacked_identity(count, n), n)
    if factors is None:
        return None
    A, P = factors
    blocks = A.reshape(A.shape[:-2] + (count, n, n))  # block i: rows i*n..(i+1)*n of A
    gains = P[..., None, :, :] @ np.swapaxes(blocks, -1, -2)  # K_i = P A_i^T
    return gains, P


def _semidefinite_tolerance(J, name):
    """The rank tolerance ``RANK_RTOL * size * trace(J)`` per joint, after checking that
    each joint is positive semidefinite to it (a clear error naming the worst one)."""
    # >= the largest eigenvalue of a PSD joint (its trace)
    scale = np.abs(np.diagonal(J, axis1=-2, axis2=-1)).sum(axis=-1)
    tol = RANK_RTOL * J.shape[-1] * scale
    if np.any(scale == 0):
        raise ValueError(f"{name} has a zero diagonal: the estimates have zero error "
                         "covariance and there is nothing to fuse")
    eigenvalues = np.linalg.eigvalsh(J)
    smallest = eigenvalues[..., 0]
    if np.any(smallest < -tol):
        index = np.unravel_index(int(np.argmin((smallest / scale).ravel())), smallest.shape)
        where = f"{name}[{', '.join(map(str, index))}]" if index else name
        raise ValueError(
            f"{where} is not positive semidefinite (smallest eigenvalue "
            f"{float(smallest[index]):.3g}, largest {float(eigenvalues[index][-1]):.3g})"
        )
    return tol


def _blue_semidefinite(J, count, n, name):
    """The BLUE for a positive semidefinite, possibly singular joint (failure-safe path).

    In the orthonormal coordinates ``a = E^T x / sqrt(N)`` (the scaled mean of the
    estimates) and ``b = B^T x`` (differences, free of the state because ``B^T E = 0``),
    every unbiased fusion is ``x_0 = (a - G b) / sqrt(N)``; the minimiser of the error
    covariance of eq. (13) is the regression ``G = J_ab J_bb^+`` and the error covariance is
    ``K J K^T`` with ``K = (E^T / sqrt(N) - G B^T) / sqrt(N)`` (eq. (19) when J is
    non-singular). The pseudo-inverse drops eigenvalues of ``J_bb`` at rounding level,
    ``RANK_RTOL * N n * trace(J)``. The error covariance is unique; when ``J_bb`` is
    singular the gains are not, and these are the minimum-norm ones.
    """
    tol = _semidefinite_tolerance(J, name)
    E = _stacked_identity(count, n)
    B = _difference_basis(count, n)
    root = np.sqrt(count)
    JB = J @ B
    J_ab = (E.T @ JB) / root  # (..., n, (N-1) n)
    J_bb = symmetrize(B.T @ JB)
    mu, V = np.linalg.eigh(J_bb)
    keep = mu > tol[..., None]
    inverse_mu = np.divide(1.0, mu, out=np.zeros_like(mu), where=keep)
    G = ((J_ab @ V) * inverse_mu[..., None, :]) @ np.swapaxes(V, -1, -2)
    K = E.T / count - (G @ B.T) / root  # (..., n, N n), K E = I
    P = symmetrize(K @ J @ np.swapaxes(K, -1, -2))
    if not positive_definite(P):
        fused = np.linalg.eigvalsh(P)
        index = np.unravel_index(int(np.argmin((fused[..., 0] / fused[..., -1]).ravel())),
                                 fused.shape[:-1])
        where = f"{name}[{', '.join(map(str, index))}]" if index else name
        raise ValueError(
            f"{where} is singular in a way that leaves the fusion undefined: an unbiased "
            "combination of the estimates has (numerically) zero error variance, so the "
            "fused covariance is not positive definite (eigenvalues from "
            f"{float(fused[index][0]):.3g} to {float(fused[index][-1]):.3g})"
        )
    gains = np.swapaxes(K.reshape(K.shape[:-1] + (count, n)), -2, -3)  # K_i, (..., N, n, n)
    return gains, P


def _optimal(x, column, J, count, n, name="joint"):
    """BLUE of validated means (..., N, n) with a symmetric joint (..., N n, N n)."""
    blue = _blue_cholesky(J, count, n)
    singular = blue is None
    gains, P = _blue_semidefinite(J, count, n, name) if singular else blue
    batch = np.broadcast_shapes(x.shape[:-2], J.shape[:-2])
    x_fused = np.einsum("...kij,...kj->...i", gains, x)
    P = np.broadcast_to(P, batch + (n, n)).copy()
    gains = np.broadcast_to(gains, batch + (count, n, n)).copy()
    info = {"joint": "singular" if singular else "regular"}
    return FusionResult(restore_style(x_fused, column), P, "optimal", None, gains, info)


def _check_joint(joint, name="joint"):
    J = as_float_array(joint, name)
    if J.ndim < 2 or J.shape[-1] != J.shape[-2]:
        raise ValueError(f"{name} must have shape (..., N*n, N*n), got shape {J.shape}")
    return J


def _batch(x_shape, J_shape, x_name="xs", J_name="joint"):
    try:
        return np.broadcast_shapes(x_shape, J_shape)
    except ValueError:
        raise ValueError(
            f"batch shapes of {x_name} {x_shape} and {J_name} {J_shape} do not broadcast"
        ) from None


def optimal_fusion(xs: ArrayLike, joint: ArrayLike) -> FusionResult:
    """Best linear unbiased fusion with a known joint error covariance.

    With ``E = [I, ..., I]^T`` (N stacked n x n identities, eq. (10) of Weng & Djurić,
    journal version) and ``P_x`` the joint covariance of the stacked estimates,

        W^T = (E^T P_x^-1 E)^-1 E^T P_x^-1      (eq. 18)
        P   = (E^T P_x^-1 E)^-1                 (eq. 19)
        x   = W^T [x_1; ...; x_N]               (eq. 20)

    For two estimates this equals eqs. (4)-(6) of Weng & Djurić (2012):
    ``W_1 = (P_22 - P_12^T)(P_11 - P_12 - P_12^T + P_22)^-1``. It is the minimum mean
    square error linear fusion, the yardstick for every rule that does not know ``P_x``.

    ``P_x`` may be singular (positive semidefinite), as it is after two nodes have
    exchanged and fused their estimates: the fusion is then the minimiser of eq. (13)
    under the constraint (17), computed with a pseudo-inverse (see Notes). It is defined
    whenever its error covariance is positive definite.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, (..., n) or (..., n, 1) each, or one array (..., N, n).
    joint : array_like, shape (..., N*n, N*n)
        Symmetric positive semidefinite joint error covariance of the stacked estimates;
        its diagonal blocks are the individual covariances. Batch axes broadcast against
        those of ``xs``.

    Returns
    -------
    FusionResult
        ``method="optimal"``, ``P`` the error covariance of the fusion (``K P_x K^T``),
        ``gains`` the ``K_i`` (the transposed blocks of ``W``, which sum to the identity),
        ``omega=None``, ``info["joint"]`` ``"regular"`` or ``"singular"`` (the path used).

    Raises
    ------
    TypeError
        Non-numeric, boolean or complex input.
    ValueError
        ``joint`` not square, not of dimension N*n, not symmetric, not positive
        semidefinite (beyond rounding), non-finite values, fewer than two estimates, batch
        shapes that do not broadcast, or a joint that leaves the fusion undefined (a
        combination of the estimates with zero error variance).

    See Also
    --------
    naive_fusion : the special case of zero cross-covariances.

    Notes
    -----
    When the Cholesky factor of ``P_x`` exists and its pivots do not show a condition
    number above ``MAX_CONDITION`` (1e12), eqs. (18)-(20) are evaluated through Cholesky
    solves. Otherwise (whole batch) the fusion is computed in the coordinates
    ``a = E^T x / sqrt(N)`` and ``b = B^T x`` (``B`` an orthonormal basis of the
    differences, ``B^T E = 0``): ``x_0 = (a - J_ab J_bb^+ b) / sqrt(N)``, the regression of
    the mean on the differences, with ``J_bb^+`` the pseudo-inverse that drops eigenvalues
    below ``8 eps N n trace(P_x)``. For a non-singular ``P_x`` both are the same fusion.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, "A Bayesian approach to data fusion in sensor
       networks", journal version, eqs. (13)-(20).
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

    Two nodes that have fused hold the same estimate; their joint is singular, and fusing
    again gives the same estimate back:

    >>> r = optimal_fusion([np.array([2.0]), np.array([2.0])], np.full((2, 2), 0.5))
    >>> r.x.tolist(), r.P.tolist(), r.info["joint"]
    ([2.0], [[0.5]], 'singular')
    """
    J = _check_joint(joint)
    count, n = _mean_layout(xs, J.shape[-1])
    x, column = as_mean_stack(xs, n, count, "xs")
    check_finite(x, "xs")
    _batch(x.shape[:-2], J.shape[:-2])
    J = check_symmetric(J, "joint")
    return _optimal(x, column, J, count, n)


def _blue_partial_cholesky(J, E, n):
    """Eqs. (18)-(19) with the stacked observation matrix ``E`` (eq. (H6)) through Cholesky
    factors; None where the joint is (nearly) singular (as :func:`_blue_cholesky`)."""
    factors = _blue_factors(J, E, n)
    if factors is None:
        return None
    A, P = factors
    return P @ np.swapaxes(A, -1, -2), P  # K = P E^T J^-1 (n x sum m_i)


def _blue_partial_semidefinite(J, E, n, name):
    """The BLUE with stacked observations ``E`` (sum m_i x n) for a positive semidefinite
    joint: with ``E = Q_1 R`` and ``Q_2`` the orthogonal complement, every unbiased fusion
    is ``R^-1 (Q_1^T - G Q_2^T) z``, and ``G = J_ab J_bb^+`` (``J_ab = Q_1^T J Q_2``,
    ``J_bb = Q_2^T J Q_2``) minimises its error covariance (as :func:`_blue_semidefinite`,
    whose ``E`` is the stacked identity)."""
    tol = _semidefinite_tolerance(J, name)
    Q, R = np.linalg.qr(E, mode="complete")
    Q1, Q2, R = Q[:, :n], Q[:, n:], R[:n]
    JQ2 = J @ Q2
    J_ab = Q1.T @ JQ2
    J_bb = symmetrize(Q2.T @ JQ2)
    mu, V = np.linalg.eigh(J_bb)
    keep = mu > tol[..., None]
    inverse_mu = np.divide(1.0, mu, out=np.zeros_like(mu), where=keep)
    G = ((J_ab @ V) * inverse_mu[..., None, :]) @ np.swapaxes(V, -1, -2)
    K = np.linalg.solve(R, Q1.T - G @ Q2.T)  # (..., n, sum m_i), K E = I
    P = symmetrize(K @ J @ np.swapaxes(K, -1, -2))
    if not positive_definite(P):
        raise ValueError(
            f"{name} is singular in a way that leaves the fusion undefined: an unbiased "
            "combination of the estimates has (numerically) zero error variance"
        )
    return K, P


def _optimal_partial(est, joint):
    """The ``"optimal"`` rule on partial estimates: the BLUE
    ``x = (E^T J^-1 E)^-1 E^T J^-1 z`` with ``E`` the stacked ``H_i`` and ``J`` the joint
    covariance of the stacked estimates (sum m_i square; eq. (H6))."""
    dims = [xi.shape[-1] for xi in est.x]
    total, n = sum(dims), est.dim
    J = _check_joint(joint)
    if J.shape[-2:] != (total, total):
        raise ValueError(
            f"joint must have shape (..., {total}, {total}) for estimates of dimensions "
            f"{dims} (the sum of the estimates' dimensions), got shape {J.shape}"
        )
    _batch(est.batch_shape, J.shape[:-2], "the estimates", "joint")
    J = check_symmetric(J, "joint")
    offsets = np.cumsum([0] + dims)
    scale = max(float(np.abs(P).max()) for P in est.P)
    for i in range(est.count):
        block = J[..., offsets[i]:offsets[i + 1], offsets[i]:offsets[i + 1]]
        if not np.allclose(block, est.P[i], rtol=1e-8, atol=1e-12 * scale):
            raise ValueError("the diagonal blocks of joint must equal the covariances of the "
                             f"estimates (block {i} differs)")
    E = np.concatenate([est.observation(i) for i in range(est.count)], axis=0)
    unobserved = unobserved_directions(E)
    if unobserved:
        raise ValueError(
            "the estimates together do not observe the state: the stacked H_i are rank "
            f"deficient; unobserved direction(s) of the state: "
            f"{', '.join(str(v) for v in unobserved)}"
        )
    blue = _blue_partial_cholesky(J, E, n)
    singular = blue is None
    K, P = _blue_partial_semidefinite(J, E, n, "joint") if singular else blue
    batch = np.broadcast_shapes(est.batch_shape, J.shape[:-2])
    z = np.concatenate([np.broadcast_to(xi, batch + xi.shape[-1:]) for xi in est.x], axis=-1)
    x = (K @ z[..., None])[..., 0]
    P = np.broadcast_to(P, batch + (n, n)).copy()
    gains = tuple(np.broadcast_to(K[..., offsets[i]:offsets[i + 1]],
                                  batch + (n, dims[i])).copy() for i in range(est.count))
    stacked = np.stack(gains, axis=-3) if all(d == n for d in dims) else None
    info = {"joint": "singular" if singular else "regular", "gains": gains}
    return FusionResult(restore_style(x, est.column), P, "optimal", None, stacked, info)


def _optimal_fusion(est, joint):
    """The ``"optimal"`` rule on validated estimates: ``joint`` is checked against them.

    Estimates of parts ``H_i x`` take :func:`_optimal_partial` (``joint`` is then the joint
    covariance of the stacked partial estimates, sum m_i square).
    """
    if isinstance(est, PartialEstimates):
        return _optimal_partial(est, joint)
    count, n = est.count, est.dim
    J = _check_joint(joint)
    if J.shape[-2:] != (count * n, count * n):
        raise ValueError(
            f"joint must have shape (..., {count * n}, {count * n}) for {count} estimates of "
            f"dimension {n}, got shape {J.shape}"
        )
    _batch(est.batch_shape, J.shape[:-2], "the estimates", "joint")
    J = check_symmetric(J, "joint")
    blocks = np.stack(
        [J[..., i * n:(i + 1) * n, i * n:(i + 1) * n] for i in range(count)], axis=-3
    )
    scale = np.abs(est.P).max()
    if not np.allclose(blocks, est.P, rtol=1e-8, atol=1e-12 * scale):
        raise ValueError("the diagonal blocks of joint must equal the covariances of the estimates")
    return _optimal(est.x, est.column, J, count, n)


def _optimal_truth_options(joint, rng):
    return {"joint": joint}


NAIVE_REGISTRATION: dict[str, Any] = dict(
    name="naive",
    function=naive_fusion,
    core=_naive_fusion,
    summary="information-form product; assumes independent errors (double counts otherwise)",
    reference="the Kalman/information filter update",
    guarantee="none",
    weights="all one: P^-1 = sum_i P_i^-1",
    front_door=("H", "residual"),
)
"""The record of the ``"naive"`` rule (registered by :mod:`cifilter.rules`)."""


def _optimal_with_estimates(xs, Ps, joint):
    # fuse(..., method="optimal") passes the covariances too; their blocks are checked
    return _optimal_fusion(as_estimates(xs, Ps), joint)


OPTIMAL_REGISTRATION: dict[str, Any] = dict(
    name="optimal",
    function=_optimal_with_estimates,
    core=_optimal_fusion,
    summary="best linear unbiased fusion with the known joint covariance (needs joint=)",
    reference="Weng & Djurić, journal, eqs. 18-20; EUSIPCO 2012, eqs. 4-6",
    guarantee="exact",
    truth_options=_optimal_truth_options,
    weights="none (matrix gains from the joint covariance)",
    front_door=("H", "residual"),
)
"""The record of the ``"optimal"`` rule (registered by :mod:`cifilter.rules`)."""
