"""Batched linear algebra for symmetric positive definite matrices.

Every function works on stacks of matrices (leading batch axes) without a Python
loop over the batch. Inverses and solves go through the Cholesky factor, so the
results are symmetric and positive definite by construction rather than by luck.
"""

import math

import numpy as np
from scipy.linalg import lapack

__all__ = [
    "MAX_CONDITION",
    "IllConditionedError",
    "cho_inverse",
    "cho_solve",
    "cholesky",
    "cholesky_failures",
    "cholesky_single",
    "condition_number",
    "eigh_single",
    "ill_conditioned",
    "logdet_from_cholesky",
    "lower_inverse",
    "lower_inverse_single",
    "mahalanobis_sq",
    "positive_definite",
    "solve_lower",
    "symmetrize",
]


# The conditioning contract (docs/conventions.rst): for inputs whose condition numbers are
# at most MAX_CONDITION every rule returns a finite, symmetric, positive definite answer
# (a conservative rule's one a valid bound); beyond it a rule either still does or raises
# IllConditionedError, a ValueError that says by how much.
MAX_CONDITION = 1e12


class IllConditionedError(ValueError):
    """A covariance (input or intermediate) too ill-conditioned to compute with reliably.

    Raised under the conditioning contract (see the documentation's conventions): results
    are guaranteed for input condition numbers up to ``1e12``; beyond that a rule either
    still answers correctly or raises this error. A subclass of :class:`ValueError`; the
    message names the matrix and gives its condition number.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import IllConditionedError, covariance_intersection
    >>> P = np.diag([1.0, 1e-30])  # numerically singular
    >>> try:
    ...     covariance_intersection([np.zeros(2)] * 2, [P, P], omega=0.5)
    ... except IllConditionedError as error:
    ...     print(str(error).split(":")[0])
    the fused information matrix is too ill-conditioned to fuse reliably
    """


def condition_number(A):
    """2-norm condition numbers of a stack of symmetric matrices (inf if not PD).

    For messages and checks only (one ``eigvalsh`` per matrix).
    """
    A = np.asarray(A, dtype=float)
    eigenvalues = np.linalg.eigvalsh(A)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.abs(eigenvalues[..., -1]) / eigenvalues[..., 0]
    return np.where(eigenvalues[..., 0] > 0, ratio, np.inf)


def ill_conditioned(name, cond, what="is too ill-conditioned to fuse reliably"):
    """The :class:`IllConditionedError` for ``name`` with condition number ``cond``."""
    cond = float(np.max(cond))
    shown = "infinite (numerically singular)" if not np.isfinite(cond) else f"{cond:.3g}"
    return IllConditionedError(
        f"{name} {what}: condition number {shown}; cifilter's results are guaranteed for "
        f"condition numbers up to {MAX_CONDITION:.0e} (see the conditioning contract in the "
        "documentation's conventions)"
    )


def symmetrize(A):
    """Return ``(A + A^T) / 2`` over the last two axes (a new array)."""
    A = np.asarray(A)
    return 0.5 * (A + A.swapaxes(-1, -2))


# Eigenvalues of a symmetric matrix are computed with an absolute error of about
# n * eps * ||A||; a smallest eigenvalue above -EIGENVALUE_RTOL * n * ||A|| is therefore
# indistinguishable from zero (the matrix is numerically singular, not indefinite).
EIGENVALUE_RTOL = 8 * np.finfo(float).eps


def cholesky_failures(A):
    """Which matrices of a stack (..., n, n) numpy's Cholesky factorisation rejects.

    Returns a bool array (...): True where the factorisation raises or gives a non-finite
    factor. Found by bisection over the stack, so a failure path costs a few
    factorisations per failing matrix, not one per matrix. The one helper that locates
    failing factors (for messages, for solvers that step back, for samplers that redraw).
    """
    flat = A.reshape((-1,) + A.shape[-2:])
    failed = np.zeros(len(flat), dtype=bool)

    def visit(lo, hi):
        try:
            if np.isfinite(np.linalg.cholesky(flat[lo:hi])).all():
                return
        except np.linalg.LinAlgError:
            pass
        if hi - lo == 1:
            failed[lo] = True
            return
        middle = (lo + hi) // 2
        visit(lo, middle)
        visit(middle, hi)

    if len(flat):
        visit(0, len(flat))
    return failed.reshape(A.shape[:-2])


def positive_definite(A):
    """Whether every matrix of a stack (..., n, n) is finite and numerically positive
    definite: numpy's Cholesky factorisation accepts it and gives a finite factor.

    The check of the conditioning contract on a rule's result (a result that is not finite,
    symmetric and positive definite is an error, not an answer).
    """
    if not np.isfinite(A).all():
        return False
    try:
        return bool(np.isfinite(np.linalg.cholesky(A)).all())
    except np.linalg.LinAlgError:
        return False


def cholesky(A, name="matrix"):
    """Lower Cholesky factor of a stack of symmetric positive definite matrices.

    Parameters
    ----------
    A : array_like, shape (..., n, n)
        Symmetric positive definite matrices.
    name : str, optional
        Name used in the error message.

    Returns
    -------
    L : ndarray, shape (..., n, n)
        Lower triangular factors with ``A = L @ L^T``.

    Raises
    ------
    IllConditionedError
        (a ``ValueError``) If a matrix is positive semidefinite up to rounding but
        numerically singular: its smallest eigenvalue is positive or within rounding
        (``8 n eps ||A||``) of zero and the factorisation fails. The message names
        ``name``, the offending index and the condition number (infinite when the
        smallest eigenvalue is not positive).
    ValueError
        If a matrix is not positive definite beyond rounding; the message names ``name``,
        the offending index and its smallest eigenvalue. If a matrix has non-finite
        entries, the message says so.

    Notes
    -----
    The success path is one LAPACK factorisation; eigenvalues are computed only to
    write the message of a failure.
    """
    A = np.asarray(A, dtype=float)
    if A.ndim == 2 and A.shape[0] == A.shape[1]:  # one matrix: LAPACK directly
        L = cholesky_single(A)
        if L is not None:  # (a finite diagonal: finite input gives a finite factor)
            return L
    try:
        L = np.linalg.cholesky(A)
        if np.isfinite(L).all():  # LAPACK passes NaN through instead of failing
            return L
    except np.linalg.LinAlgError:
        pass
    failed = cholesky_failures(A)
    index = np.unravel_index(int(np.argmax(failed.ravel())), A.shape[:-2])
    index = tuple(int(i) for i in index)
    where = f"{name}[{', '.join(map(str, index))}]" if index else name
    matrix = A[index]
    smallest = largest = np.nan
    if np.isfinite(matrix).all():
        eigenvalues = np.linalg.eigvalsh(matrix)
        smallest, largest = float(eigenvalues[0]), float(np.abs(eigenvalues).max())
    if np.isnan(smallest):
        raise ValueError(
            f"{where} is not positive definite: it has non-finite entries (NaN or inf)"
        )
    if smallest >= -EIGENVALUE_RTOL * A.shape[-1] * largest:
        cond = largest / smallest if smallest > 0 else np.inf
        raise ill_conditioned(
            where, cond, what="is too ill-conditioned for a Cholesky factorisation"
        )
    raise ValueError(f"{where} is not positive definite (smallest eigenvalue {smallest:.3g})")


def solve_lower(L, B):
    """Solve ``L X = B`` for lower triangular ``L`` (..., n, n) and ``B`` (..., n, k).

    Forward substitution: one matrix by LAPACK's triangular solver (``dtrtrs``); a stack
    vectorised over the batch, the loop running over the n rows. Both are componentwise
    backward stable, ``(L + dL) X = B`` with ``|dL| <= n eps |L|``, so the error of ``X`` is
    at most about ``n eps |L^-1| |L| |X|`` entry by entry, which for the factors of
    ill-conditioned covariances is far below ``cond(L) eps ||X||``. (An LU factorisation,
    ``numpy.linalg.solve``, pivots rows when an entry below the diagonal is the larger and
    loses that: up to 100 times the bound was seen at condition numbers to 1e12.) For stacks
    of small matrices the row loop is close to the fastest numpy formulation measured
    (4 x 4 to 8 x 8: batched LU is as fast at 30 matrices and 1.3 to 3.4 times slower from
    60 on; an einsum row loop or a samples-last layout gain nothing at 30 to 60 matrices and
    10% to 35% at 200 to 3000, and would change the rounding of every caller; a LAPACK call
    per matrix is slower from 8 matrices on).

    Raises ``numpy.linalg.LinAlgError`` for one matrix with a zero on its diagonal.
    """
    if L.ndim == 2 and B.ndim == 2:
        X, info = lapack.dtrtrs(L, B, lower=1)
        if info > 0:
            raise np.linalg.LinAlgError("Singular matrix")
        if info == 0:
            return X
        return np.linalg.solve(L, B)  # (arguments LAPACK rejects: numpy explains)
    n = L.shape[-1]
    X = np.empty(np.broadcast_shapes(L.shape[:-2], B.shape[:-2]) + B.shape[-2:])
    for i in range(n):
        row = B[..., i, :]
        if i:
            row = row - (L[..., i:i + 1, :i] @ X[..., :i, :])[..., 0, :]
        X[..., i, :] = row / L[..., i, i, None]
    return X


def lower_inverse(L):
    """Inverse of lower triangular matrices (..., n, n)."""
    return solve_lower(L, np.broadcast_to(np.eye(L.shape[-1]), L.shape))


def cho_inverse(L):
    """Inverse of ``A = L L^T`` from its Cholesky factor, exactly symmetric."""
    L_inv = lower_inverse(L)
    return L_inv.swapaxes(-1, -2) @ L_inv


def cho_solve(L, B):
    """Solve ``(L L^T) X = B`` for a stack of Cholesky factors.

    ``B`` has shape (..., n) (vectors) or (..., n, k) (matrices).
    """
    vector = B.ndim == L.ndim - 1
    B2 = B[..., None] if vector else B
    if L.ndim == 2 and B2.ndim == 2:  # one system: LAPACK's potrs directly
        X, info = lapack.dpotrs(L, B2, lower=1)
        if info == 0:
            return X[..., 0] if vector else X
    Y = solve_lower(L, B2)
    X = np.linalg.solve(L.swapaxes(-1, -2), Y)
    return X[..., 0] if vector else X


def logdet_from_cholesky(L):
    """``log det(L L^T)`` for a stack of Cholesky factors."""
    return 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)


def mahalanobis_sq(e, P):
    """Squared Mahalanobis distance ``e^T P^{-1} e`` for stacks of vectors and covariances.

    Parameters
    ----------
    e : array_like, shape (..., n)
        Vectors (for instance estimation errors).
    P : array_like, shape (..., n, n)
        Symmetric positive definite covariances; batch axes broadcast against ``e``.

    Returns
    -------
    ndarray, shape (...)
        The squared distances (the NEES when ``e`` is an error and ``P`` its covariance).

    Raises
    ------
    ValueError
        If a covariance is not positive definite.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import mahalanobis_sq
    >>> float(mahalanobis_sq(np.array([2.0, 0.0]), np.diag([4.0, 1.0])))
    1.0
    """
    e = np.asarray(e, dtype=float)
    L = cholesky(P, "P")
    L = np.broadcast_to(L, e.shape[:-1] + L.shape[-2:])
    z = solve_lower(L, e[..., None])[..., 0]
    return np.einsum("...i,...i->...", z, z)


# Single matrices: LAPACK called directly. numpy's linalg functions cost several
# microseconds of dispatch per call on a 4x4 matrix, LAPACK itself a fraction of that; the
# single-call path of the filters (one fusion of one track) is made of such calls.
def cholesky_single(A):
    """Lower Cholesky factor of one symmetric matrix (n, n), or None if LAPACK fails.

    Only the lower triangle of ``A`` is read. None also for a non-finite factor; the
    caller then takes the batched path, whose messages explain the failure.
    """
    L, info = lapack.dpotrf(A, lower=1, clean=1)
    if info != 0 or not math.isfinite(float(L.trace())):
        return None
    return L


def lower_inverse_single(L):
    """Inverse of one lower triangular, non-singular matrix (n, n) (LAPACK ``dtrtri``)."""
    L_inv, _ = lapack.dtrtri(L, lower=1)
    return L_inv


def eigh_single(S):
    """Eigenvalues (ascending) and eigenvectors of one symmetric matrix (LAPACK ``dsyevd``)."""
    lam, U, _ = lapack.dsyevd(S, compute_v=1, lower=1)
    return lam, U
