"""Bayesian Monte Carlo MMSE fusion with a Wishart prior (Weng & Djurić).

The joint covariance ``P_x`` of N stacked estimates gets the prior ``W(dof, Sigma)`` with a
block-diagonal ``Sigma``. Given the known diagonal blocks ``P_ii``, the off-diagonal blocks
have the conditional density

    p(P_o | P_d)  proportional to  |P_x|^((dof - N n - 1) / 2)    on {P_o : P_x > 0}

(eqs. (28) and (37) of the journal version; ``Sigma`` drops out). For two estimates it is
the inverted matrix-variate t-distribution of eq. (33), sampled by Theorem 1; for more,
the chain decomposition of eqs. (42)-(53) samples one block column at a time, each a
two-block problem. The fused estimate is the average over the samples of the best linear
unbiased fusion (eqs. (18)-(20)).

Numerical formulation (docs/methods/bayes.rst, "Numerical formulation"). With
``D = blkdiag(L_1, ..., L_N)`` the inputs' Cholesky factors, every sample is drawn in
whitened form, ``P_x = D R D^T``: the whitened joint ``R`` has identity diagonal blocks, its
law does not depend on the ``P_ii`` and the sampler builds its Cholesky factor ``H``
directly. The per-sample BLUE is the least-squares problem ``min ||H^-1 (D^-1 y - E x)||``
with ``E = D^-1 I_(N)``, solved by a QR factorisation of ``H^-1 E`` (no normal equations,
no inverse of ``P_x``), and the gains are made to sum to the identity exactly, column by
column, by taking each column of one estimate's gain as the complement of the others'.
Samples are processed in chunks of bounded size, with a random stream that does not depend
on the chunking.
"""

from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.linalg import (
    IllConditionedError,
    cholesky,
    cholesky_failures,
    condition_number,
    ill_conditioned,
    lower_inverse,
    positive_definite,
    solve_lower,
    symmetrize,
)
from .._numerics.validation import (
    as_covariances,
    as_estimates,
    as_rng,
    check_int,
    check_scalar,
    restore_style,
)
from ..result import FusionResult

__all__ = ["bayesian_fusion", "sample_joint_covariances"]

# Joint-covariance entries ((N n)^2 per sample) processed at once, by the sampler and by the
# fusion: 512 KB per array (1024 samples of 8 x 8), small enough for the processor's cache
# (the fusion's element-wise passes over the samples cost 2-3 times more per sample on
# 3000-sample chunks than on 1000-sample ones; the sampler's stacked products are no slower
# on smaller chunks) and a bound on the memory of bayesian_fusion whatever ``samples`` and
# the batch are (a few MB for any chunk). The results do not depend on it (see _streams).
_CHUNK_ENTRIES = 1 << 16
# A sample of sample_joint_covariances whose smallest Cholesky pivot ratio G_ii^2 / A_ii is
# below this is checked with numpy's Cholesky factorisation (and redrawn if that fails).
# Every failure seen in 1.4e7 draws with blocks of condition number up to 1e9 had a ratio
# below 1e-12.
_SUSPECT_PIVOT_RATIO = 1e-9
_MAX_REDRAWS = 50
# Column norms of the Householder QR between these bounds are computed from the squares as
# they are (no overflow or underflow in them); outside they are taken again after scaling.
_NORM_SAFE = (1e-150, 1e150)


def _check_dof(dof, count, n):
    """The Wishart degrees of freedom: a real number, at least N*n."""
    dof = check_scalar(dof, "dof")
    dim = count * n
    if not dof >= dim:
        raise ValueError(
            f"dof must be at least N*n = {dim} for N = {count} estimates of dimension n = {n} "
            f"(the Wishart prior W(dof, Sigma) on the {dim}x{dim} joint covariance needs "
            f"dof >= {dim}); got {dof:g}"
        )
    return dof


def _default_dof(count, n):
    """N*n + 1: the conditional density of the cross-covariances is then uniform."""
    return count * n + 1


def _transpose(A):
    return np.ascontiguousarray(np.swapaxes(A, -1, -2))


def _diagonal(A):
    return np.diagonal(A, axis1=-2, axis2=-1)


def _solve_upper(U, B):
    """Solve ``U X = B`` for upper triangular ``U`` (..., m, m) and ``B`` (..., m, k).

    Back substitution as :func:`solve_lower` on the reversed system: with ``J`` the reversal
    permutation, ``J U J`` is lower triangular and ``(J U J)(J X) = J B``.
    """
    return solve_lower(U[..., ::-1, ::-1], B[..., ::-1, :])[..., ::-1, :]


# ----------------------------------------------------------------- the random stream
def _streams(rng):
    """Three generators (normal deviates, chi-square deviates, redraws) derived from ``rng``.

    Four integers drawn from ``rng`` seed a :class:`numpy.random.SeedSequence` whose three
    spawned children drive the streams, so that the same seed gives the same result and a
    Generator passed to successive calls gives fresh draws. Each stream is consumed sample
    after sample, in the order (problem, sample), by draws of whole rows: chunk k consumes the
    next piece of each stream, so the numbers of every sample, and hence every result, do not
    depend on the chunk size (numpy's ``standard_normal`` and ``chisquare`` draw the same
    numbers in pieces as in one call).
    """
    seed = np.random.SeedSequence([int(v) for v in rng.integers(0, 2**63, size=4)])
    return [np.random.Generator(np.random.PCG64(child)) for child in seed.spawn(3)]


def _stage_layout(count, n, dof):
    """Per stage j = 1..N-1: the offset of its normals; all chi-square degrees of freedom."""
    offsets, total = [], 0
    for j in range(1, count):
        offsets.append(total)
        total += n * (j * n + n)
    df = np.concatenate([dof - j * n - np.arange(n) for j in range(1, count)])
    return offsets, total, df


def _deviates(rows, count, n, dof, normal_rng, chi_rng):
    """The random numbers of ``rows`` samples: normals (rows, total) and the square roots of
    the chi-square deviates (rows, (N - 1) n), in the order the streams give them."""
    _, total, df = _stage_layout(count, n, dof)
    normals = normal_rng.standard_normal((rows, total))
    chi = np.sqrt(chi_rng.chisquare(df, size=(rows, df.size)))
    return normals, chi


def _draws(rows, count, n, dof, normal_rng, chi_rng):
    """The random numbers of ``rows`` samples: per stage j = 1..N-1, ``[X, L_S]`` (rows, n, p + n).

    ``X`` (n x p, ``p = j n``) is standard normal and ``L_S`` (n x n) the Bartlett factor of
    ``S ~ W_n(dof - p, I)``: lower triangular, ``L_S,ii^2 ~ chi^2(dof - p - i)``, standard
    normal below the diagonal; real ``dof`` allowed. Every sample consumes
    ``sum_j n (p + n)`` normals and ``(N - 1) n`` chi-squares, in that order within each
    stream, so the draws of a sample do not depend on how the rows are chunked.
    """
    offsets = _stage_layout(count, n, dof)[0]
    normals, chi = _deviates(rows, count, n, dof, normal_rng, chi_rng)
    stages = []
    for j in range(1, count):
        p = j * n
        Y = normals[:, offsets[j - 1]:offsets[j - 1] + n * (p + n)].reshape(rows, n, p + n)
        for i in range(n):
            Y[:, i, p + i] = chi[:, (j - 1) * n + i]
            Y[:, i, p + i + 1:] = 0.0
        stages.append(Y)
    return stages


def _draws_last(rows, count, n, dof, normal_rng, chi_rng):
    """:func:`_draws` in the samples-last layout: per stage ``[X, L_S]`` as (n, p + n, width).

    ``width = max(rows, 2)``: a single sample is followed by a copy of itself, because
    numpy's ``einsum`` sums a contraction in another order when the samples axis has length
    one; from two samples on, every sample's arithmetic is the same whatever the chunk (the
    caller keeps the first ``rows`` results).
    """
    offsets = _stage_layout(count, n, dof)[0]
    normals, chi = _deviates(rows, count, n, dof, normal_rng, chi_rng)
    if rows == 1:
        normals, chi = np.repeat(normals, 2, axis=0), np.repeat(chi, 2, axis=0)
    rows = max(rows, 2)
    normals, chi = np.ascontiguousarray(normals.T), chi.T
    stages = []
    for j in range(1, count):
        p = j * n
        Y = normals[offsets[j - 1]:offsets[j - 1] + n * (p + n)].reshape(n, p + n, rows)
        for i in range(n):
            Y[i, p + i] = chi[(j - 1) * n + i]
            Y[i, p + i + 1:] = 0.0
        stages.append(Y)
    return stages


# ----------------------------------------------------------------- samples last
# The fusion works on its samples in the samples-last layout: a matrix per sample is an
# array (rows, columns, samples), and the per-sample linear algebra (Cholesky, triangular
# solves, Householder QR) is written as loops over the few rows and columns of the matrices
# whose every step is one vectorised pass over the samples. numpy's stacked routines on the
# (samples, rows, columns) layout pay a LAPACK or BLAS call per matrix (microseconds each
# for a 4 x 4), which made them most of the fusion's time. Each sample's arithmetic is the
# same algorithm in the same order whatever the other samples are, so the results do not
# depend on the chunking.
def _cholesky_last(W):
    """Lower Cholesky factor of ``W`` (m, m, rows) (lower triangle read), or None when a pivot
    is not positive (the caller then asks :func:`cholesky` for the message)."""
    m = W.shape[0]
    C = np.zeros(W.shape)
    for j in range(m):
        pivot = W[j, j] - np.einsum("kr,kr->r", C[j, :j], C[j, :j]) if j else W[j, j]
        if not (pivot > 0.0).all():
            return None
        C[j, j] = d = np.sqrt(pivot)
        if j + 1 < m:
            column = (W[j + 1:, j] - np.einsum("ikr,kr->ir", C[j + 1:, :j], C[j, :j]) if j
                      else W[1:, 0])
            C[j + 1:, j] = column / d
    return C


def _solve_lower_last(L, B, identity_rows=0):
    """Solve ``L X = B`` for lower triangular ``L`` (m, m, rows), ``B`` (m, k, rows or 1).

    Forward substitution; the first ``identity_rows`` rows of ``L`` are known to be those of
    the identity (then ``X`` starts as ``B``, which is what the substitution gives there)."""
    X = np.empty(B.shape[:2] + L.shape[-1:])
    X[:identity_rows] = B[:identity_rows]
    for i in range(identity_rows, L.shape[0]):
        row = B[i] - np.einsum("jr,jkr->kr", L[i, :i], X[:i]) if i else B[i]
        X[i] = row / L[i, i]
    return X


def _solve_lower_transposed_last(L, B):
    """Solve ``L^T X = B`` for lower triangular ``L`` (m, m, rows), ``B`` (m, k, rows)."""
    m = L.shape[0]
    X = np.empty(B.shape)
    for i in range(m - 1, -1, -1):
        row = B[i] - np.einsum("jr,jkr->kr", L[i + 1:, i], X[i + 1:]) if i < m - 1 else B[i]
        X[i] = row / L[i, i]
    return X


def _solve_upper_last(U, B):
    """Solve ``U X = B`` for upper triangular ``U`` (m, m, rows), ``B`` (m, k, rows)."""
    m = U.shape[0]
    X = np.empty(B.shape)
    for i in range(m - 1, -1, -1):
        row = B[i] - np.einsum("jr,jkr->kr", U[i, i + 1:], X[i + 1:]) if i < m - 1 else B[i]
        X[i] = row / U[i, i]
    return X


def _qr_last(F):
    """Householder QR ``F = Q R`` of ``F`` (m, k, rows), m >= k: ``Q`` (m, k, rows) with
    orthonormal columns, ``R`` (k, k, rows) upper triangular.

    LAPACK's reflections (``dgeqrf``, ``dorgqr``): column j is mapped to ``beta e_j`` with
    ``beta = -sign(alpha) ||x||``, so ``alpha - beta`` never cancels; a zero column is left
    alone. Where a squared norm could have overflowed or underflowed, the norm is taken again
    of the column divided by its largest entry. Backward stable column by column, as
    LAPACK's.
    """
    m, k, rows = F.shape
    A = F.copy()
    R = np.zeros((k, k, rows))
    reflectors = []
    for j in range(k):
        x = A[j:, j]
        norm = np.sqrt(np.einsum("ir,ir->r", x, x))
        unsafe = ~((norm > _NORM_SAFE[0]) & (norm < _NORM_SAFE[1]))
        if unsafe.any():  # zero, tiny, huge or not finite: scaled, and no reflection at zero
            largest = np.abs(x[:, unsafe]).max(axis=0)
            scale = np.where(largest > 0.0, largest, 1.0)
            y = x[:, unsafe] / scale
            squares = y[0] * y[0]
            for i in range(1, len(y)):  # in order, as for any number of samples
                squares += y[i] * y[i]
            norm[unsafe] = scale * np.sqrt(squares)
        alpha = x[0]
        beta = np.copysign(norm, -alpha)
        shift = alpha - beta
        tau = -shift / beta
        zero = norm == 0.0
        if zero.any():
            beta[zero], tau[zero], shift[zero] = alpha[zero], 0.0, 1.0
        v = x / shift
        v[0] = 1.0
        R[j, j] = beta
        if j + 1 < k:
            rest = A[j:, j + 1:]
            rest -= v[:, None] * (tau * np.einsum("ir,icr->cr", v, rest))
            R[j, j + 1:] = rest[0]
        reflectors.append((v, tau))
    Q = np.zeros((m, k, rows))
    for j in range(k):
        Q[j, j] = 1.0
    for j in range(k - 1, -1, -1):
        v, tau = reflectors[j]
        block = Q[j:, j:]
        block -= v[:, None] * (tau * np.einsum("ir,icr->cr", v, block))
    return Q, R


def _sample_whitened_last(rows, count, n, dof, normal_rng, chi_rng):
    """Whitened joint covariance samples, samples last: ``H`` (N n, N n, width) and the block
    rows of ``R = H H^T`` left of the diagonal, ``[R_10, (R_20, R_21), ...]`` (n, p, width),
    ``width = max(rows, 2)`` (:func:`_draws_last`).

    ``R`` has identity diagonal blocks and is the law of ``D^-1 P_x D^-T`` (``D`` the block
    diagonal of the inputs' Cholesky factors); ``H`` is its lower Cholesky factor, built
    directly. Stage j (j = 1, ..., N-1, ``p = j n``) draws the block row of estimate j given
    the leading block by Theorem 1 of the journal with ``A_11 = R_<j`` (size l_1 = p, factor
    ``H_<j``) and ``A_22 = I_n``, from ``[X, L_S]`` of :func:`_draws`:

        C C^T = S + X X^T,   T = C^-1 X  ~  IT_{n, p}(dof - p - n + 1, 0, I, I),
        block row j of R, columns < p  =  T H_<j^T,
        block row j of H  =  [T, C^-1 L_S],

    eqs. (50)-(53) in whitened coordinates (``L_j^-1`` times the journal's block row times
    ``D_<j^-T``), with Cholesky factors in place of the symmetric square roots (the law of T is
    invariant under T -> U T V for orthogonal U, V). ``T T^T + C^-1 S C^-T = I`` makes the
    new diagonal block of R the identity.
    """
    dim = count * n
    H = np.zeros((dim, dim, max(rows, 2)))  # (a single sample twice: see _draws_last)
    for i in range(n):
        H[i, i] = 1.0
    cross = []
    for j, Y in enumerate(_draws_last(rows, count, n, dof, normal_rng, chi_rng), start=1):
        p = j * n
        W = np.empty((n, n, H.shape[-1]))  # S + X X^T = Y Y^T (lower triangle)
        for a in range(n):
            W[a, :a + 1] = np.einsum("kr,bkr->br", Y[a], Y[:a + 1])
        C = _cholesky_last(W)
        if C is None:  # never for finite draws (S is positive definite): the message
            W = np.moveaxis(W, -1, 0)
            C = np.moveaxis(cholesky(np.tril(W) + np.swapaxes(np.tril(W, -1), -1, -2),
                                     "X X^T + S"), 0, -1)
        TD = _solve_lower_last(C, Y)  # [T, C^-1 L_S]
        H[p:p + n, :p + n] = TD
        if j == 1:  # H_<1 is the identity: the cross block is T itself
            cross.append(TD[:, :p])
        else:
            cross.append(np.einsum("akr,bkr->abr", TD[:, :p], H[:p, :p]))
    return H, cross


def _whitened_blue_last(H, E0):
    """Per-sample BLUE in whitened coordinates by QR (no normal equations), samples last.

    ``H`` (Nn, Nn, rows) the factor of the whitened joint ``R``, ``E0`` (Nn, n, rows or 1).
    With ``F0 = H^-1 E0 = Q R0``: the whitened gains ``V0 = R0^-1 Q^T H^-1`` (n, Nn, rows)
    and ``R0^-1 R0^-T`` (n, n, rows); the BLUE of eqs. (18)-(19) for the joint
    ``P_x = D H H^T D^T`` has gains ``[K_1 ... K_N] = S^-1 V0 D^-1`` and covariance
    ``P_0 = S^-1 R0^-1 R0^-T S^-1``.
    """
    n = E0.shape[1]
    F0 = _solve_lower_last(H, E0, identity_rows=n)
    Q, R0 = _qr_last(F0)
    QtHinv = _solve_lower_transposed_last(H, Q)  # (Q^T H^-1)^T = H^-T Q
    V0 = _solve_upper_last(R0, QtHinv.transpose(1, 0, 2))
    eye = np.zeros((n, n, 1))
    for i in range(n):
        eye[i, i] = 1.0
    R0_inv = _solve_upper_last(R0, np.broadcast_to(eye, R0.shape))
    return V0, np.einsum("akr,bkr->abr", R0_inv, R0_inv)


def _sample_coloured(L, P, dof, normal_rng, chi_rng, out):
    """Write joint covariance samples ``A = D R D^T`` into ``out`` (rows, Nn, Nn).

    The same draws and the same construction as :func:`_sample_whitened`, multiplied out
    with the inputs' factors ``L`` (rows or 1, N, n, n) as it goes: the Cholesky factor of
    ``A`` is ``G = D H``, block row j of ``G`` is ``L_j [T, C^-1 L_S]``, and block row j of
    ``A`` is ``L_j T G_<j^T`` (the journal's eqs. (50)-(53) with Cholesky factors). The
    diagonal blocks are written exactly as ``P``, the cross blocks with their exact
    transposes. ``G`` is only built where a later stage needs it. Returns, per sample, the
    smallest ratio ``G_ii^2 / A_ii`` of a squared Cholesky pivot of ``A`` to its diagonal
    entry (1 is independent, 0 singular).
    """
    rows, count, n = out.shape[0], L.shape[1], L.shape[-1]
    for j in range(count):
        out[:, j * n:(j + 1) * n, j * n:(j + 1) * n] = P[:, j]
    G = L[:, 0]  # Cholesky factor of the first block
    worst_pivot_ratio = np.ones(rows)
    for j, Y in enumerate(_draws(rows, count, n, dof, normal_rng, chi_rng), start=1):
        p = j * n
        C = cholesky(Y @ _transpose(Y), "X X^T + S")
        last = j == count - 1
        TD = solve_lower(C, Y[..., :p] if last else Y)  # [T, C^-1 L_S]
        new_rows = L[:, j] @ TD  # [L_j T, L_j C^-1 L_S]
        cross = new_rows[..., :p] @ _transpose(G)
        out[:, p:p + n, :p] = cross
        out[:, :p, p:p + n] = np.swapaxes(cross, -1, -2)
        # The diagonal of the new factor block L_j C^-1 L_S is a product of diagonals.
        pivots = _diagonal(L[:, j]) * _diagonal(Y[..., p:]) / _diagonal(C)
        ratio = (pivots**2 / _diagonal(P[:, j])).min(axis=-1)
        worst_pivot_ratio = np.minimum(worst_pivot_ratio, ratio)
        if not last:
            G_next = np.zeros((rows, p + n, p + n))
            G_next[:, :p, :p] = G
            G_next[:, p:, :] = new_rows
            G = G_next
    first = (_diagonal(L[:, 0]) ** 2 / _diagonal(P[:, 0])).min(axis=-1)
    return np.minimum(worst_pivot_ratio, first)


def _chunk_rows(dim):
    return max(1, _CHUNK_ENTRIES // dim**2)


# ----------------------------------------------------------------- the sampler (public)
def _unfactorisable(L, P, dof, normal_rng, chi_rng, out):
    """Draw into ``out`` (:func:`_sample_coloured`); return the rows numpy cannot factorise.

    Rows whose smallest pivot ratio is below ``_SUSPECT_PIVOT_RATIO`` are tested with
    numpy's Cholesky factorisation; the indices of those it rejects are returned.
    """
    ratio = _sample_coloured(L, P, dof, normal_rng, chi_rng, out)
    suspects = np.flatnonzero(~(ratio >= _SUSPECT_PIVOT_RATIO))
    return suspects[cholesky_failures(out[suspects])] if suspects.size else suspects


def _sample_joint(L, P, dof, size, rng):
    """Joint covariance samples (..., size, N n, N n) for factors ``L`` (..., N, n, n).

    The whitened construction multiplied out with the inputs' factors
    (:func:`_sample_coloured`), in chunks of rows (problem, sample). The rare samples that
    numpy cannot factorise (nearly full correlation with badly conditioned blocks) are drawn
    again from the redraw stream, all of them together after the last chunk, so the result
    does not depend on the chunking.
    """
    batch, count, n = L.shape[:-3], L.shape[-3], L.shape[-1]
    dim = count * n
    L_flat = L.reshape((-1, count, n, n))
    P_flat = P.reshape((-1, count, n, n))
    total = L_flat.shape[0] * size
    joint = np.empty((total, dim, dim))
    normal_rng, chi_rng, redraw_rng = _streams(rng)

    def problem_rows(index):
        if L_flat.shape[0] == 1:  # one problem: broadcast its blocks over the samples
            return L_flat, P_flat
        problem = index // size
        return L_flat[problem], P_flat[problem]

    failed = []
    chunk = _chunk_rows(dim)
    for start in range(0, total, chunk):
        stop = min(start + chunk, total)
        L_rows, P_rows = problem_rows(np.arange(start, stop))
        bad = _unfactorisable(L_rows, P_rows, dof, normal_rng, chi_rng, joint[start:stop])
        failed.append(start + bad)
    failed = np.concatenate(failed)
    for attempt in range(_MAX_REDRAWS + 1):
        if failed.size == 0:
            break
        if attempt == _MAX_REDRAWS:
            cond = condition_number(P_flat).max()
            raise IllConditionedError(
                f"could not draw joint covariances that are positive definite in floating "
                f"point after {_MAX_REDRAWS} redraws: the covariances are too badly "
                f"conditioned for dof = {dof:g} (largest condition number {cond:.3g}); a "
                "larger dof puts less prior mass near full correlation"
            )
        fresh = np.empty((failed.size, dim, dim))
        bad = _unfactorisable(*problem_rows(failed), dof, redraw_rng, redraw_rng, fresh)
        joint[failed] = fresh
        failed = failed[bad]
    return joint.reshape(batch + (size, dim, dim))


def sample_joint_covariances(Ps: ArrayLike, dof: float, size: int,
                             rng: Union[int, np.random.Generator, None] = None
                             ) -> NDArray[np.float64]:
    """Sample joint covariances with given diagonal blocks under a block-diagonal Wishart prior.

    The joint covariance ``A`` of N estimates of dimension n has the prior
    ``W(dof, Sigma)`` on the (N n) x (N n) matrices, with a block-diagonal ``Sigma``.
    Given the diagonal blocks ``A_ii = P_i``, the off-diagonal blocks are drawn from
    their conditional distribution, whose density is proportional to
    ``|A|^((dof - N n - 1) / 2)`` on the set where ``A`` is positive definite
    (``Sigma`` drops out). Two estimates: the inverted matrix-variate t-distribution
    ``A_12^T | A_11, A_22 ~ IT(dof - 2n + 1, 0, A_22, A_11)`` (eq. (33)), sampled by
    Theorem 1 (``S ~ W_n(dof - n, I)``). More estimates: the chain decomposition of
    eqs. (46)-(53), one block column per stage, stage j with ``S ~ W_n(dof - j n, I)``.

    Parameters
    ----------
    Ps : sequence of array_like or array_like, shape (..., N, n, n)
        The N >= 2 diagonal blocks, symmetric positive definite; leading batch axes draw
        for many problems at once (problem after problem from the same streams).
    dof : float
        Degrees of freedom of the Wishart prior on the whole joint covariance, at least
        ``N*n``. ``N*n + 1`` makes the conditional uniform over all admissible
        cross-covariances; larger values concentrate it on weak correlation.
    size : int
        Number of samples per problem, >= 1.
    rng : numpy.random.Generator, int or None, optional
        Randomness source; the same seed gives the same samples (see Notes); a Generator
        passed to successive calls gives fresh samples.

    Returns
    -------
    ndarray, shape (..., size, N*n, N*n)
        Exactly symmetric joint covariances whose diagonal blocks are exactly the given
        ``Ps`` and which all pass a Cholesky factorisation.

    Raises
    ------
    ValueError
        Fewer than two blocks, blocks that are not symmetric positive definite,
        ``dof < N*n`` (the message states the requirement) or ``size < 1``.
    IllConditionedError
        (a ValueError) Blocks so badly conditioned that no sample positive definite in
        floating point is found after 50 redraws.
    TypeError
        Non-numeric ``Ps``, ``dof`` or ``size``, or a bad ``rng``.

    See Also
    --------
    bayesian_fusion : the fusion rule that averages over these samples.

    Notes
    -----
    Each sample is the whitened sample ``R = D^-1 A D^-T`` (``D`` the block diagonal of the
    blocks' Cholesky factors; ``R`` has identity diagonal blocks and a law that does not
    depend on the blocks) multiplied out: the sampler builds the Cholesky factor
    ``G = D H`` of ``A`` (lower triangular, positive diagonal; ``H`` that of ``R``)
    directly, so ``A`` is positive definite by construction. The rare samples that are
    singular once rounded (nearly full correlation with badly conditioned blocks; the
    pivots of ``G`` flag them for free) are drawn again, so that every returned sample
    passes a Cholesky factorisation; the law is conditioned on an event of small
    probability (at ``dof = N*n``, two blocks: 2e-5 of the draws for condition numbers 1e6
    and 1e9, 1e-3 for 1e12, none in 4e5 draws for well-conditioned blocks). The density
    exists for ``dof > N*n - 1``, but the papers define the Wishart distribution for ``dof >= N*n``;
    below that the last stage's chi-square draws have fewer than one degree of freedom and
    the prior piles onto full correlation. The conference version states Theorem 1 with
    ``S ~ W(n, I)``; Lemma 3 applied to eq. (10) gives ``W(n - k/2, I)``, which is the
    journal's ``W(n - l_1, I)`` used here (see the method's page).

    Randomness: normal deviates, chi-square deviates and redraws come from three
    generators derived from ``rng`` (a SeedSequence seeded by four draws of ``rng``), each
    consumed sample after sample; the samples are built in chunks of bounded size, and the
    same seed gives the same samples whatever the chunk size. :func:`bayesian_fusion` with
    the same seed fuses the same whitened samples (but does not redraw: it never forms
    ``A``).

    Memory: the output holds ``size * (N n)^2`` floats per problem (128 MB per million
    samples of a 4x4 joint covariance), which is inherent to returning them; beyond it
    the sampler uses a few arrays of one chunk (about 0.5 MB each). To average a function of
    many samples, use :func:`bayesian_fusion` or call this in pieces with a Generator.
    Vectorised over samples and batch; the Python loops run over the chunks and the N - 1
    stages.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, "A Bayesian approach to data fusion in sensor
       networks", journal version, Theorem 1, Lemma 3, eqs. (28)-(33), (46)-(53).
    .. [2] Z. Weng and P. M. Djurić, "A Bayesian approach to covariance estimation and
       data fusion", EUSIPCO 2012, eqs. (9)-(10), Theorem 1.
    .. [3] A. K. Gupta and D. K. Nagar, *Matrix Variate Distributions*, Chapman &
       Hall/CRC, 2000, Sec. 4.4 (inverted matrix-variate t-distribution).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import sample_joint_covariances
    >>> P1, P2 = np.diag([1.0, 4.0]), np.array([[2.0, 0.5], [0.5, 1.0]])
    >>> A = sample_joint_covariances([P1, P2], dof=5, size=1000, rng=0)
    >>> A.shape
    (1000, 4, 4)
    >>> bool(np.all(A[:, :2, :2] == P1) and np.all(A[:, 2:, 2:] == P2))
    True
    >>> bool(np.all(np.linalg.eigvalsh(A) > 0))
    True
    """
    est = as_covariances(Ps)
    dof = _check_dof(dof, est.count, est.dim)
    size = check_int(size, "size", low=1)
    return _sample_joint(est.L, est.P, dof, size, as_rng(rng))


# ----------------------------------------------------------------- the fusion
class _Whitening:
    """Per-problem quantities of the whitened BLUE, for inputs' factors ``L`` (B, N, n, n).

    ``E = D^-1 I_(N)`` (B, N n, n), the blocks ``L_i^-1`` stacked, is stored as ``E0 S`` with
    ``S`` (B, n) the powers of two of its columns' largest entries, so that ``E0`` has
    columns of order one whatever the scales of the inputs. ``reference`` (B, n): for
    column c, the estimate i whose ``L_i^-1`` has the largest column c; its gain's column c
    is computed as the complement of the others' (see :func:`_finish`).
    """

    def __init__(self, L):
        self.L = L
        count, n = L.shape[-3], L.shape[-1]
        E = lower_inverse(L).reshape(L.shape[0], count * n, n)  # L_i X = I: a solve
        _, exponent = np.frexp(np.abs(E).max(axis=-2))
        self.S = np.ldexp(1.0, exponent)
        self.E0 = E / self.S[:, None, :]
        column_norms = np.linalg.norm(self.E0.reshape(L.shape[0], count, n, n), axis=-2)
        self.reference = column_norms.argmax(axis=-2)  # (B, n)


class _Accumulator:
    """Sums over the samples of each problem of ``V0``, ``R`` and ``R0^-1 R0^-T``."""

    def __init__(self, problems, count, n):
        dim = count * n
        self.n = n
        self.V0 = np.zeros((problems, n, dim))
        self.R = np.zeros((problems, dim, dim))
        self.P0 = np.zeros((problems, n, n))

    def add(self, problem, V0, cross, P0):
        """Add samples (last axis) whose problems ``problem`` (rows,) are sorted (contiguous
        segments): ``V0`` (n, Nn, rows), the block rows ``cross`` of ``R`` left of its
        diagonal (:func:`_sample_whitened_last`) and ``P0`` (n, n, rows)."""
        starts = np.flatnonzero(np.r_[True, problem[1:] != problem[:-1]])
        owners = problem[starts]
        n = self.n
        self.V0[owners] += np.moveaxis(np.add.reduceat(V0, starts, axis=-1), -1, 0)
        self.P0[owners] += np.moveaxis(np.add.reduceat(P0, starts, axis=-1), -1, 0)
        for j, block in enumerate(cross, start=1):
            self.R[owners, j * n:(j + 1) * n, :j * n] += np.moveaxis(
                np.add.reduceat(block, starts, axis=-1), -1, 0)

    def means(self, samples):
        """The means of ``V0``, ``R`` (its identity diagonal blocks and the exact transposes
        of the blocks left of them, as every sample has) and ``R0^-1 R0^-T``."""
        dim = self.R.shape[-1]
        R = self.R / samples
        R = R + np.swapaxes(R, -1, -2)  # the blocks right of the diagonal (exact transposes)
        R[:, np.arange(dim), np.arange(dim)] = 1.0  # the identity diagonal blocks
        return self.V0 / samples, R, self.P0 / samples


def _finish(x, whitening, V0_mean, R_mean, P0_mean):
    """Fused estimate, covariance, gains and mean BLUE covariance from the sample means.

    ``V = S^-1 mean(V0)`` are the averaged whitened gains ``K D``; ``K_i`` solves
    ``K_i L_i = V_i``. The column c of the reference estimate's gain is replaced by
    ``e_c - sum_{i != ref} K_i[:, c]``, so the gains sum to the identity to rounding; it is the
    column with the largest ``L_i^-1`` column, the one the solve would get least accurately.
    ``x = x_ref + sum_i K_i (x_i - x_ref)`` with ``x_ref[c] = x_ref(c)[c]``: the differences
    ``x_i - x_ref`` are of the size of the errors, not of the state, so the gains' rounding
    is not multiplied by the state. ``P = V Rbar V^T`` through the Cholesky factor of Rbar.
    """
    L, S = whitening.L, whitening.S
    problems, count, n = L.shape[:3]
    V = V0_mean / S[:, :, None]
    V_blocks = np.swapaxes(V.reshape(problems, n, count, n), 1, 2)  # (B, N, n, n)
    gains = np.swapaxes(_solve_upper(np.swapaxes(L, -1, -2), np.swapaxes(V_blocks, -1, -2)),
                        -1, -2)
    is_reference = whitening.reference[:, None, :] == np.arange(count)[None, :, None]
    others = np.where(is_reference[:, :, None, :], 0.0, gains).sum(axis=1)  # (B, n, n)
    gains = np.where(is_reference[:, :, None, :], (np.eye(n) - others)[:, None], gains)
    x_ref = np.take_along_axis(x, whitening.reference[:, None, :], axis=1)[:, 0]
    x_hat = x_ref + np.einsum("birc,bic->br", gains, x - x_ref[:, None, :])
    try:
        B = V @ np.linalg.cholesky(R_mean)
        P = symmetrize(B @ _transpose(B))
    except np.linalg.LinAlgError:  # a mean of nearly singular samples (tiny M)
        P = symmetrize(V @ R_mean @ _transpose(V))
    sample_P_mean = symmetrize(P0_mean / S[:, :, None] / S[:, None, :])
    return x_hat, P, gains, sample_P_mean


def _check_result(x_hat, P, gains, Ps):
    """The conditioning contract: finite, positive definite output, or IllConditionedError."""
    if not (np.isfinite(x_hat).all() and np.isfinite(gains).all() and positive_definite(P)):
        raise ill_conditioned("the covariances", condition_number(Ps),
                              "are too ill-conditioned for the Bayesian fusion")


def bayesian_fusion(xs: ArrayLike, Ps: ArrayLike, dof: Optional[float] = None,
                    samples: int = 100, rng: Union[int, np.random.Generator, None] = None
                    ) -> FusionResult:
    """Monte Carlo MMSE fusion of estimates with unknown cross-covariances (Wishart prior).

    Draws ``samples`` joint covariances with the known diagonal blocks from their
    conditional distribution under the prior ``W(dof, Sigma)``, block-diagonal ``Sigma``
    (:func:`sample_joint_covariances`), fuses the estimates with the best linear unbiased
    estimator of each sample (eqs. (18)-(20), what :func:`optimal_fusion` computes for a
    known joint covariance) and averages:

        x_hat = (1/M) sum_m W^(m)T x = sum_i K_i x_i,    K_i = (1/M) sum_m K_i^(m).

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, (..., n) or (..., n, 1) each, or one array (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n).
    dof : float, optional
        Degrees of freedom of the Wishart prior on the (N n) x (N n) joint covariance, at
        least ``N*n``. Default ``N*n + 1``, for which the conditional density of
        the cross-covariances, proportional to ``|P_x|^((dof - N n - 1)/2)``, is uniform
        over all cross-covariances that keep the joint covariance positive definite.
        Larger values express a belief in weaker correlation; ``N*n`` puts more mass near
        full correlation.
    samples : int, optional
        Monte Carlo samples M per fusion (default 100, as in the journal).
    rng : numpy.random.Generator, int or None, optional
        Randomness source; the same seed gives the same result, whatever the internal chunk
        size; a Generator passed to successive calls gives fresh draws.

    Returns
    -------
    FusionResult
        ``x`` in the style of the first mean; ``gains`` (..., N, n, n) the averaged weight
        matrices ``K_i`` (they sum to the identity); ``omega`` None; ``P`` (..., n, n) the
        error covariance of ``x`` under the model (see Notes); ``info`` with ``dof``,
        ``samples`` and ``sample_P_mean``, the mean of the per-sample BLUE covariances
        (eq. (19)).

    Raises
    ------
    ValueError
        Fewer than two estimates, bad shapes, non-finite values, covariances that are not
        symmetric positive definite, ``dof < N*n`` (the message states the requirement),
        ``samples < 1``.
    IllConditionedError
        (a ValueError) The result would not be finite and positive definite: covariances
        far beyond the conditioning contract (condition numbers above 1e12). Within it the
        result is always finite, symmetric and positive definite.
    TypeError
        Non-numeric input or a bad ``rng``.

    See Also
    --------
    sample_joint_covariances : the sampler.
    optimal_fusion : the fusion with the joint covariance known.
    fuse : the same rule through the registry (``method="bayes"``).

    Notes
    -----
    ``P`` is the Monte Carlo estimate of the error covariance of ``x`` under the model,
    ``E[(x - x_0)(x - x_0)^T | P_11, ..., P_NN]`` with the errors ``N(0, P_x)`` and
    ``P_x`` drawn from its conditional: since the averaged gains ``K`` are fixed,

        P = K Pbar K^T = (1/M) sum_m P_0^(m) + (1/M) sum_m (K - K^(m)) P_x^(m) (K - K^(m))^T,

    with ``Pbar`` the mean of the sampled joint covariances and ``P_0^(m)`` the BLUE
    covariance of sample m (eq. (19)). The first term is the posterior mean of the error
    covariance of the per-sample optimal fusion, the second the spread of the per-sample
    estimators about the average (the identity holds because ``K^(m) P_x^(m)`` equals
    ``P_0^(m)`` stacked N times). So ``P`` is never below ``info["sample_P_mean"]``, and
    with one sample equal to the true joint covariance it is the optimal ``P``. It is
    honest only as far as the prior is: the conditional mean of the cross-covariances is
    zero, so for estimates that are in fact strongly correlated ``P`` is too small, and
    repeated fusion of the same information makes it overconfident (see the method's
    page). For the same reason the average of BLUEs is not the linear rule of least
    expected error under its own prior (that is naive fusion); in the papers' experiments
    the two differ by a few percent.

    Numerical formulation (derived on the method's page). The samples are drawn in
    whitened form, ``P_x = D R D^T`` with ``D = blkdiag(L_i)`` the inputs' Cholesky
    factors: ``R`` has identity diagonal blocks and a law free of the ``P_i``, and the
    sampler builds its Cholesky factor ``H``. The BLUE of a sample is the least-squares
    problem ``min_x ||H^-1 D^-1 (y - I_(N) x)||``; with ``H^-1 E = Q R_0`` (QR,
    ``E = D^-1 I_(N)`` with its columns scaled by powers of two) the whitened gains are
    ``R_0^-1 Q^T H^-1``, so no joint covariance is formed or inverted and no condition number
    is squared. The gains ``K_i`` follow from the averaged whitened gains by triangular
    solves; column c of the gain of the estimate with the largest column c of ``L_i^-1``
    (the most precise one in that direction) is taken as ``e_c`` minus the others', so the
    gains sum to the identity to rounding, and ``x = x_ref + sum_i K_i (x_i - x_ref)`` with
    ``x_ref`` made of those estimates' components. The result transforms exactly under a
    change of units ``x -> T x``, ``P -> T P T`` for a diagonal ``T`` (the whitened draws do not
    depend on the ``P_i``), to rounding. A result that is not finite and positive definite
    raises ``IllConditionedError``.

    Cost and memory: M whitened samples and M QR factorisations of (N n) x n matrices per
    fusion, processed in chunks of about 2^16 / (N n)^2 samples, problem after problem, with
    the samples along the last axis (the per-sample Cholesky factorisations, triangular
    solves and Householder QR are loops over matrix rows and columns whose every step is one
    vectorised pass over the chunk's samples); the memory is that of one chunk (a few MB)
    plus O((N n)^2) per problem, whatever M (3 MB traced for M = 1e6 and two 4-D
    estimates). Randomness: normal and chi-square
    deviates come from two generators derived from ``rng`` (a SeedSequence seeded by four
    draws of ``rng``), each consumed sample after sample, so the chunking does not change
    the draws; :func:`sample_joint_covariances` with the same seed draws the same whitened
    samples. Vectorised over samples and batch; Python loops run over chunks, stages and
    matrix rows and columns.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, "A Bayesian approach to data fusion in sensor
       networks", journal version, eqs. (18)-(20), (28)-(53).
    .. [2] Z. Weng and P. M. Djurić, "A Bayesian approach to covariance estimation and
       data fusion", EUSIPCO 2012, Sec. 3.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import bayesian_fusion
    >>> r = bayesian_fusion([np.array([1.0, 0.0]), np.array([0.0, 1.0])],
    ...                     [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])], samples=200, rng=0)
    >>> r.x.shape, r.info["dof"], r.info["samples"]
    ((2,), 5.0, 200)
    >>> np.allclose(r.gains.sum(axis=0), np.eye(2))
    True
    >>> bool(np.all(np.linalg.eigvalsh(r.P - r.info["sample_P_mean"]) > -1e-12))
    True
    """
    return _bayesian_fusion(as_estimates(xs, Ps), dof, samples, rng)


def _bayesian_fusion(est, dof=None, samples=100, rng=None):
    """The ``"bayes"`` rule on validated estimates (the core of :func:`bayesian_fusion`)."""
    count, n = est.count, est.dim
    dof = float(_default_dof(count, n)) if dof is None else _check_dof(dof, count, n)
    samples = check_int(samples, "samples", low=1)
    rng = as_rng(rng)

    batch = est.batch_shape
    dim = count * n
    problems = int(np.prod(batch, dtype=int))
    x = est.x.reshape((problems, count, n))
    P = est.P.reshape((problems, count, n, n))
    whitening = _Whitening(est.L.reshape((problems, count, n, n)))
    sums = _Accumulator(problems, count, n)
    normal_rng, chi_rng, _ = _streams(rng)
    total, chunk = problems * samples, _chunk_rows(dim)
    E0 = np.ascontiguousarray(whitening.E0.transpose(1, 2, 0))  # (Nn, n, problems)
    for start in range(0, total, chunk):
        stop = min(start + chunk, total)
        problem = np.arange(start, stop) // samples
        rows = stop - start
        H, cross = _sample_whitened_last(rows, count, n, dof, normal_rng, chi_rng)
        V0, P0 = _whitened_blue_last(H, E0 if problems == 1 else E0[..., problem])
        if rows == 1:  # the copy that kept the arithmetic that of any chunk (_draws_last)
            V0, P0, cross = V0[..., :1], P0[..., :1], [block[..., :1] for block in cross]
        sums.add(problem, V0, cross, P0)
    x_hat, P_hat, gains, sample_P_mean = _finish(x, whitening, *sums.means(samples))
    _check_result(x_hat, P_hat, gains, P)
    info = {"dof": dof, "samples": samples,
            "sample_P_mean": sample_P_mean.reshape(batch + (n, n))}
    return FusionResult(
        restore_style(x_hat.reshape(batch + (n,)), est.column),
        P_hat.reshape(batch + (n, n)),
        "bayes",
        None,
        gains.reshape(batch + (count, n, n)),
        info,
    )


def _bayes_truth_options(joint, rng):
    # The rule does not use the true joint covariance: it only needs randomness.
    return {"rng": rng}


REGISTRATION: dict[str, Any] = dict(
    name="bayes",
    function=bayesian_fusion,
    core=_bayesian_fusion,
    summary="Monte Carlo MMSE: BLUE averaged over cross-covariances drawn from a Wishart prior",
    reference="Weng & Djurić, journal, Theorem 1, eqs. 18-20, 46-53; EUSIPCO 2012",
    guarantee="none",
    truth_options=_bayes_truth_options,
    weights="none (matrix gains averaged over the sampled joint covariances)",
)
"""The record of the ``"bayes"`` rule (registered by :mod:`cifilter.rules`)."""
