"""Trace bounds and correlation coefficient bounds of Wu, Cai & Fu (2018).

For two zero-mean errors ``a`` and ``b`` with covariances ``P_a = X X^T`` and
``P_b = Y Y^T`` and the fused error ``c = K_1 a + K_2 b``:

* :func:`worst_case_trace` is the exact maximum of ``trace(cov(c))`` over every
  cross-covariance whose correlation coefficient is at most ``rho`` (Lemma 2 for
  ``rho = 1``, Lemma 4, Theorems 1 and 2, eqs. (6) and (11));
* :func:`ci_trace_bound` is the looser closed form of Remark 2 and Theorem 2;
* :func:`correlation_bound` is the correlation coefficient bound of eq. (8) (Lemma 3);
* :func:`is_rho_admissible` checks Definition 2, eq. (21), for m vectors, and
  :func:`common_correlation_bound` gives the smallest common ``rho`` for which it holds.
"""

import numbers
from collections.abc import Sequence
from typing import Union, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.linalg import cholesky, solve_lower, symmetrize
from .._numerics.validation import (
    SYMMETRY_RTOL,
    as_float_array,
    as_matrix,
    check_covariances,
    check_finite,
)

__all__ = [
    "ci_trace_bound",
    "common_correlation_bound",
    "correlation_bound",
    "is_rho_admissible",
    "worst_case_trace",
]


# --------------------------------------------------------------------------- validation
def _covariance(P: ArrayLike, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A validated covariance stack (..., n, n) and its lower Cholesky factor."""
    return check_covariances(as_float_array(P, name), name)


def _unit_interval(value: ArrayLike, name: str, batch_shape: tuple[int, ...]
                   ) -> NDArray[np.float64]:
    """``value`` as an array in [0, 1] that broadcasts against ``batch_shape``."""
    array = as_float_array(value, name)
    check_finite(array, name)
    if np.any((array < 0.0) | (array > 1.0)):
        raise ValueError(f"{name} must lie in [0, 1], got {value!r}")
    try:
        return np.broadcast_to(array, np.broadcast_shapes(array.shape, batch_shape))
    except ValueError:
        raise ValueError(
            f"{name} of shape {array.shape} does not broadcast against the batch shape "
            f"{batch_shape}"
        ) from None


def _batch_shape(*arrays):
    try:
        return np.broadcast_shapes(*(a.shape[:-2] for a in arrays))
    except ValueError:
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise ValueError(f"batch shapes of the inputs do not broadcast: {shapes}") from None


def _nuclear_norm(A):
    """Sum of the singular values of each matrix of a stack (eq. (4))."""
    return np.linalg.svd(A, compute_uv=False).sum(axis=-1)


def _scalar_or_array(value):
    """A 0-d result as a NumPy scalar, anything else unchanged."""
    return value[()] if np.ndim(value) == 0 else value


def _trace_terms(Pa, Pb, K1, K2):
    """``Tr(K1 Pa K1^T)``, ``Tr(K2 Pb K2^T)`` and ``||Y^T K2^T K1 X||_*`` (Theorem 1)."""
    Pa, X = _covariance(Pa, "Pa")
    Pb, Y = _covariance(Pb, "Pb")
    K1, K2 = as_matrix(K1, "K1"), as_matrix(K2, "K2")
    if K1.shape[-1] != Pa.shape[-1]:
        raise ValueError(
            f"K1 must have {Pa.shape[-1]} columns to match Pa of shape {Pa.shape[-2:]}, "
            f"got shape {K1.shape}"
        )
    if K2.shape[-1] != Pb.shape[-1]:
        raise ValueError(
            f"K2 must have {Pb.shape[-1]} columns to match Pb of shape {Pb.shape[-2:]}, "
            f"got shape {K2.shape}"
        )
    if K1.shape[-2] != K2.shape[-2]:
        raise ValueError(
            f"K1 and K2 must have the same number of rows, got shapes {K1.shape} and {K2.shape}"
        )
    batch = _batch_shape(Pa, Pb, K1, K2)
    A = K1 @ X  # K1 a = A z_a with cov(z_a) = I, so Tr(K1 Pa K1^T) = ||A||_F^2
    B = K2 @ Y
    t1 = np.einsum("...ij,...ij->...", A, A)
    t2 = np.einsum("...ij,...ij->...", B, B)
    cross = _nuclear_norm(np.swapaxes(B, -1, -2) @ A)  # ||Y^T K2^T K1 X||_*
    return (np.broadcast_to(t1, batch), np.broadcast_to(t2, batch),
            np.broadcast_to(cross, batch), batch)


# --------------------------------------------------------------------------- trace bounds
def worst_case_trace(Pa: ArrayLike, Pb: ArrayLike, K1: ArrayLike, K2: ArrayLike,
                     rho: ArrayLike = 1.0) -> Union[np.float64, NDArray[np.float64]]:
    """Exact worst-case trace of the covariance of ``K1 a + K2 b`` (Theorems 1 and 2).

    With ``Pa = X X^T`` and ``Pb = Y Y^T``, the largest ``trace(cov(K1 a + K2 b))`` over all
    cross-covariances ``E{a b^T}`` whose correlation coefficient bound (eq. (8)) is at most
    ``rho`` is

        ||K1 Pa K1^T||_* + ||K2 Pb K2^T||_* + 2 rho ||Y^T K2^T K1 X||_*      (eq. (11))

    (eq. (6) for ``rho = 1``; Lemmas 2 and 4 for ``K1 = K2 = I``), where ``||.||_*`` is the
    nuclear norm, eq. (4). The maximum is attained by ``E{a b^T} = rho X V U^T Y^T`` with
    ``Y^T K2^T K1 X = U S V^T``.

    Parameters
    ----------
    Pa, Pb : array_like, shape (..., n, n) and (..., p, p)
        Covariances of ``a`` and ``b``, symmetric positive definite.
    K1, K2 : array_like, shape (..., k, n) and (..., k, p)
        The gains. Unlike in the paper they need not be square, nonsingular or sum to the
        identity: the proof of Lemma 4 does not use it.
    rho : float or array_like, shape (...), optional
        Correlation coefficient bound in [0, 1]; default 1 (unknown correlation).

    Returns
    -------
    numpy.float64 or ndarray, shape (...)
        The worst-case trace, one per problem of the broadcast batch.

    Raises
    ------
    ValueError
        Covariances that are not symmetric positive definite, mismatched shapes, non-finite
        values, ``rho`` outside [0, 1].
    TypeError
        Non-numeric input.

    See Also
    --------
    ci_trace_bound : the looser bound of Remark 2 and Theorem 2.

    References
    ----------
    .. [1] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Lemmas 2 and 4, Theorems 1 and 2,
       eqs. (4), (6) and (11), Examples 1 and 2.

    Examples
    --------
    Example 1 and Example 2 of Wu, Cai & Fu (2018):

    >>> import numpy as np
    >>> from cifilter.rules.bounds import worst_case_trace
    >>> Pa, Pb, I = np.diag([1.0, 4.0]), np.diag([4.0, 1.0]), np.eye(2)
    >>> float(worst_case_trace(Pa, Pb, I, I))
    18.0
    >>> K1 = np.diag([0.8, 0.2])
    >>> round(float(worst_case_trace(Pa, Pb, K1, I - K1)), 12)
    2.88
    >>> K1 = np.diag([1.0, 0.0])
    >>> float(worst_case_trace(Pa, Pb, K1, I - K1))
    2.0
    """
    t1, t2, cross, batch = _trace_terms(Pa, Pb, K1, K2)
    rho = _unit_interval(rho, "rho", batch)
    return _scalar_or_array(t1 + t2 + 2.0 * rho * cross)


def ci_trace_bound(Pa: ArrayLike, Pb: ArrayLike, K1: ArrayLike, K2: ArrayLike,
                   rho: ArrayLike = 1.0) -> Union[np.float64, NDArray[np.float64]]:
    """The closed-form trace bound of Remark 2 and Theorem 2.

    With ``t1 = Tr(K1 Pa K1^T)``, ``t2 = Tr(K2 Pb K2^T)`` and ``Pa = X X^T``,
    ``Pb = Y Y^T``,

        (sqrt(t1) + sqrt(t2))^2 - (1 - rho) ||Y^T K2^T K1 X||_*        (Theorem 2)

    which for ``rho = 1`` is the bound behind standard CI (Remark 2, Theorem 1). It is never
    below :func:`worst_case_trace`, because ``||Y^T K2^T K1 X||_* <= sqrt(t1 t2)``
    (Lemma 1, property 4).

    Parameters
    ----------
    Pa, Pb : array_like, shape (..., n, n) and (..., p, p)
        Covariances of ``a`` and ``b``, symmetric positive definite.
    K1, K2 : array_like, shape (..., k, n) and (..., k, p)
        The gains.
    rho : float or array_like, shape (...), optional
        Correlation coefficient bound in [0, 1]; default 1.

    Returns
    -------
    numpy.float64 or ndarray, shape (...)
        The bound, one per problem.

    Raises
    ------
    ValueError
        Covariances that are not symmetric positive definite, mismatched shapes, non-finite
        values, ``rho`` outside [0, 1].
    TypeError
        Non-numeric input.

    See Also
    --------
    worst_case_trace : the exact maximum, eq. (11).

    Notes
    -----
    The factor ``(1 - rho)`` is as printed in Theorem 2. The same argument
    (``2 sqrt(t1 t2) >= 2 ||Y^T K2^T K1 X||_*``) also gives the tighter
    ``(sqrt(t1) + sqrt(t2))^2 - 2 (1 - rho) ||Y^T K2^T K1 X||_*``; both are valid bounds
    and coincide with Remark 2 at ``rho = 1`` (see the documentation page).

    References
    ----------
    .. [1] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Remark 2, Theorems 1 and 2, Example 1.

    Examples
    --------
    Example 1 of Wu, Cai & Fu (2018), the classic bound 20 against the tight 18:

    >>> import numpy as np
    >>> from cifilter.rules.bounds import ci_trace_bound
    >>> I = np.eye(2)
    >>> round(float(ci_trace_bound(np.diag([1.0, 4.0]), np.diag([4.0, 1.0]), I, I)), 12)
    20.0
    """
    t1, t2, cross, batch = _trace_terms(Pa, Pb, K1, K2)
    rho = _unit_interval(rho, "rho", batch)
    return _scalar_or_array((np.sqrt(t1) + np.sqrt(t2)) ** 2 - (1.0 - rho) * cross)


# --------------------------------------------------------------------------- correlation
def correlation_bound(Pa: ArrayLike, Pb: ArrayLike, Pab: ArrayLike
                      ) -> Union[np.float64, NDArray[np.float64]]:
    """The correlation coefficient bound of two random vectors, eq. (8).

    ``rho_ab = sigma_max(X^-1 Pab Y^-T)`` for any factors ``Pa = X X^T``, ``Pb = Y Y^T``
    (here the Cholesky factors). By Lemma 3 it is the smallest ``rho`` with
    ``[[rho Pa, Pab], [Pab^T, rho Pb]] >= 0`` (eq. (9)); for scalars it is the absolute
    value of Pearson's correlation coefficient.

    Parameters
    ----------
    Pa, Pb : array_like, shape (..., n, n) and (..., p, p)
        Covariances of the two vectors, symmetric positive definite.
    Pab : array_like, shape (..., n, p)
        Their cross-covariance ``E{(a - mu_a)(b - mu_b)^T}``.

    Returns
    -------
    numpy.float64 or ndarray, shape (...)
        ``rho_ab``: in [0, 1] when ``[[Pa, Pab], [Pab^T, Pb]]`` is a covariance matrix; a
        value above 1 means that it is not positive semidefinite.

    Raises
    ------
    ValueError
        Covariances that are not symmetric positive definite, mismatched shapes,
        non-finite values.
    TypeError
        Non-numeric input.

    See Also
    --------
    common_correlation_bound : the generalisation to m vectors (Definition 2).

    References
    ----------
    .. [1] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, eqs. (8)-(9), Lemma 3.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.rules.bounds import correlation_bound
    >>> Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    >>> float(correlation_bound(Pa, Pb, np.diag([1.0, 0.5])))  # diag(1/2, 1/4) whitened
    0.5
    """
    Pa, X = _covariance(Pa, "Pa")
    Pb, Y = _covariance(Pb, "Pb")
    Pab = cast("NDArray[np.float64]", as_matrix(Pab, "Pab"))
    if Pab.shape[-2:] != (Pa.shape[-1], Pb.shape[-1]):
        raise ValueError(
            f"Pab must have shape (..., {Pa.shape[-1]}, {Pb.shape[-1]}) to match Pa and Pb, "
            f"got {Pab.shape}"
        )
    batch = _batch_shape(Pa, Pb, Pab)
    X = np.broadcast_to(X, batch + X.shape[-2:])
    Y = np.broadcast_to(Y, batch + Y.shape[-2:])
    left = solve_lower(X, np.broadcast_to(Pab, batch + Pab.shape[-2:]))  # X^-1 Pab
    whitened = solve_lower(Y, np.swapaxes(left, -1, -2))  # Y^-1 Pab^T X^-T
    return _scalar_or_array(np.linalg.svd(whitened, compute_uv=False)[..., 0])


def _block_sizes(block_sizes, dim):
    """Block sizes (n_1, ..., n_m) summing to ``dim``; an int n means m = dim / n blocks."""
    if isinstance(block_sizes, numbers.Integral) and not isinstance(block_sizes, bool):
        if block_sizes < 1 or dim % block_sizes:
            raise ValueError(
                f"block_sizes = {block_sizes} does not divide the joint dimension {dim}"
            )
        sizes = [int(block_sizes)] * (dim // block_sizes)
    else:
        try:
            sizes = [int(s) for s in block_sizes]
        except (TypeError, ValueError):
            raise TypeError(
                "block_sizes must be an int or a sequence of ints, got "
                f"{type(block_sizes).__name__}"
            ) from None
        if any(s != t for s, t in zip(sizes, block_sizes)):
            raise TypeError(f"block_sizes must hold integers, got {block_sizes!r}")
        if any(s < 1 for s in sizes) or sum(sizes) != dim:
            raise ValueError(
                f"block_sizes {tuple(sizes)} must be positive and sum to the joint "
                f"dimension {dim}"
            )
    if len(sizes) < 2:
        raise ValueError(f"the joint covariance must have at least 2 blocks, got {len(sizes)}")
    return sizes


def _whitened_joint(joint, block_sizes):
    """``L^-1 J L^-T`` with ``L`` the block-diagonal Cholesky factor of the diagonal blocks.

    The diagonal blocks of the result are identities, so Definition 2 becomes an eigenvalue
    condition: ``P^(rho) >= 0`` iff ``L^-1 J L^-T - diag((1 - rho_i) I) >= 0``.
    """
    J = as_float_array(joint, "joint")
    if J.ndim < 2 or J.shape[-1] != J.shape[-2]:
        raise ValueError(f"joint must have shape (..., D, D), got {J.shape}")
    check_finite(J, "joint")
    asymmetry = np.abs(J - np.swapaxes(J, -1, -2)).max(axis=(-2, -1))
    if np.any(asymmetry > SYMMETRY_RTOL * np.abs(J).max(axis=(-2, -1))):
        raise ValueError("joint is not symmetric")
    J = symmetrize(J)
    sizes = _block_sizes(block_sizes, J.shape[-1])
    edges = np.cumsum([0, *sizes])
    L = np.zeros(J.shape)
    for i, (start, stop) in enumerate(zip(edges[:-1], edges[1:])):
        block = J[..., start:stop, start:stop]
        L[..., start:stop, start:stop] = cholesky(block, f"diagonal block {i} of joint")
    left = solve_lower(L, J)
    return symmetrize(solve_lower(L, np.swapaxes(left, -1, -2))), sizes


def common_correlation_bound(joint: ArrayLike, block_sizes: Union[int, Sequence[int]]
                             ) -> Union[np.float64, NDArray[np.float64]]:
    """Smallest common ``rho`` for which m vectors satisfy Definition 2, eq. (21).

    With ``D`` the block diagonal of ``joint`` (the covariances ``P_i``), eq. (21) with
    ``rho_i = rho`` reads ``joint - (1 - rho) D >= 0``, i.e.
    ``rho >= 1 - lambda_min(D^-1/2 joint D^-1/2)``. For two vectors this equals the
    correlation coefficient bound of eq. (8) (:func:`correlation_bound`).

    Parameters
    ----------
    joint : array_like, shape (..., D, D)
        Joint covariance of the stacked vectors ``[a_1; ...; a_m]``; positive semidefinite,
        with positive definite diagonal blocks.
    block_sizes : int or sequence of int
        The dimensions ``(n_1, ..., n_m)`` of the vectors, or one int ``n`` for ``m = D / n``
        vectors of equal dimension.

    Returns
    -------
    numpy.float64 or ndarray, shape (...)
        The smallest admissible common ``rho``: in [0, 1] for a positive semidefinite
        ``joint``; above 1 if ``joint`` is not positive semidefinite.

    Raises
    ------
    ValueError
        Non-square, non-symmetric or non-finite ``joint``, block sizes that do not fit,
        diagonal blocks that are not positive definite.
    TypeError
        Non-numeric input or non-integer block sizes.

    See Also
    --------
    correlation_bound : eq. (8) for two vectors.
    is_rho_admissible : check eq. (21) for a given ``rho`` (one per vector).

    References
    ----------
    .. [1] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Definition 2, eq. (21); Lemma 3.

    Examples
    --------
    Three scalars with pairwise correlation 0.5: ``1 - lambda_min = 1 - 0.5 = 0.5``.

    >>> import numpy as np
    >>> from cifilter.rules.bounds import common_correlation_bound
    >>> J = 0.5 * np.eye(3) + 0.5
    >>> round(float(common_correlation_bound(J, 1)), 12)
    0.5
    """
    W, _ = _whitened_joint(joint, block_sizes)
    return _scalar_or_array(1.0 - np.linalg.eigvalsh(W)[..., 0])


def is_rho_admissible(joint: ArrayLike, block_sizes: Union[int, Sequence[int]],
                      rho: ArrayLike, *, tol: float = 1e-9
                      ) -> Union[np.bool_, NDArray[np.bool_]]:
    """Whether m vectors have correlation coefficient bound ``rho`` (Definition 2, eq. (21)).

    Checks that ``P_m^(rho)``, the joint covariance with its diagonal blocks ``P_i``
    replaced by ``rho_i P_i``, is positive semidefinite. For two vectors and a common
    ``rho`` this is Lemma 3: ``correlation_bound(P_1, P_2, P_12) <= rho``; with
    ``(rho_1, rho_2)`` it is ``correlation_bound <= sqrt(rho_1 rho_2)``.

    Parameters
    ----------
    joint : array_like, shape (..., D, D)
        Joint covariance of the stacked vectors ``[a_1; ...; a_m]``, with positive definite
        diagonal blocks.
    block_sizes : int or sequence of int
        The dimensions ``(n_1, ..., n_m)`` of the vectors, or one int ``n`` for ``m = D / n``
        vectors of equal dimension.
    rho : float or array_like, shape (..., m)
        One bound in [0, 1] per vector, or a common scalar.
    tol : float, optional
        Tolerance on the smallest eigenvalue of ``P_m^(rho)`` after whitening by the
        diagonal blocks (a dimensionless number, default 1e-9).

    Returns
    -------
    numpy.bool or ndarray of bool, shape (...)
        True where eq. (21) holds.

    Raises
    ------
    ValueError
        Bad ``joint`` or block sizes (see :func:`common_correlation_bound`), ``rho``
        outside [0, 1] or of the wrong length, negative ``tol``.
    TypeError
        Non-numeric input.

    See Also
    --------
    common_correlation_bound : the smallest admissible common ``rho``.

    References
    ----------
    .. [1] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Definition 2, eq. (21); Lemma 3, eq. (9).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.rules.bounds import is_rho_admissible
    >>> J = 0.5 * np.eye(3) + 0.5  # three scalars, pairwise correlation 0.5
    >>> bool(is_rho_admissible(J, 1, 0.5)), bool(is_rho_admissible(J, 1, 0.4))
    (True, False)
    >>> bool(is_rho_admissible(J, [1, 1, 1], [1.0, 0.5, 0.5]))
    True
    >>> bool(is_rho_admissible(J, [1, 1, 1], [1.0, 0.25, 1.0]))  # rho_2 too small
    False
    """
    W, sizes = _whitened_joint(joint, block_sizes)
    if isinstance(tol, bool) or not isinstance(tol, numbers.Real) or not tol >= 0:
        raise ValueError(f"tol must be a nonnegative number, got {tol!r}")
    count = len(sizes)
    rho = as_float_array(rho, "rho")
    if rho.ndim > 0 and rho.shape[-1] not in (1, count):
        raise ValueError(
            f"rho must be a scalar or have shape (..., {count}) for {count} blocks, "
            f"got shape {rho.shape}"
        )
    rho = _unit_interval(rho if rho.ndim else rho[None], "rho", W.shape[:-2] + (count,))
    # (1 - rho_i) repeated over the n_i coordinates of block i
    complement = np.repeat(1.0 - rho, sizes, axis=-1)
    M = W - complement[..., None, :] * np.eye(W.shape[-1])
    return _scalar_or_array(np.linalg.eigvalsh(symmetrize(M))[..., 0] >= -tol)
