"""Bayesian Monte Carlo MMSE fusion with a Wishart prior (Weng & Djurić).

The joint covariance ``P_x`` of N stacked estimates gets the prior ``W(dof, Sigma)`` with a
block-diagonal ``Sigma``. Given the known diagonal blocks ``P_ii``, the off-diagonal blocks
have the conditional density

    p(P_o | P_d)  proportional to  |P_x|^((dof - N n - 1) / 2)    on {P_o : P_x > 0}

(eqs. (28) and (37) of the journal version; ``Sigma`` drops out). For two estimates it is
the inverted matrix-variate t-distribution of eq. (33), sampled by Theorem 1; for more,
the chain decomposition of eqs. (42)-(53) samples one block column at a time, each a
two-block problem. The fused estimate is the average over the samples of the best linear
unbiased fusion (eqs. (18)-(20)), computed by :func:`cifilter.optimal_fusion`.
"""

import numpy as np

from ._linalg import cholesky, solve_lower, symmetrize
from ._validation import (
    as_covariances,
    as_estimates,
    as_rng,
    check_int,
    check_scalar,
    restore_style,
)
from .optimal import optimal_fusion
from .registry import register_method
from .result import FusionResult

__all__ = ["bayesian_fusion", "sample_joint_covariances"]

# Joint-covariance entries held in memory at once by bayesian_fusion (samples x batch
# chunk x (N n)^2): about 16 MB (optimal_fusion makes a few copies), so that long batches
# do not exhaust memory.
_CHUNK_ENTRIES = 2_000_000
# Joint-covariance entries the sampler builds at once (about 4 MB).
_SAMPLER_CHUNK_ENTRIES = 1 << 19
# A sample whose smallest Cholesky pivot ratio G_ii^2 / A_ii is below this is checked with
# numpy's Cholesky factorisation (and redrawn if that fails). Every failure seen in 1.4e7
# draws with blocks of condition number up to 1e9 had a ratio below 1e-12.
_SUSPECT_PIVOT_RATIO = 1e-9
_MAX_REDRAWS = 50


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


def _stage_draws(rng, dof, n, p, rows):
    """``[X, L_S]`` of shape (rows, n, p + n) for one stage of the sampler.

    ``X`` (n x p) is standard normal and ``L_S`` (n x n) the Bartlett factor of
    ``S ~ W_n(dof, I)``: lower triangular, ``L_ii^2 ~ chi^2(dof - i)`` (i = 0, ..., n-1),
    standard normal below the diagonal; real ``dof > n - 1`` is allowed. Then
    ``Y Y^T = X X^T + S``.
    """
    Y = rng.standard_normal((rows, n, p + n))
    chi = np.sqrt(rng.chisquare(dof - np.arange(n), size=(rows, n)))
    for i in range(n):
        Y[:, i, p + i] = chi[:, i]
        Y[:, i, p + i + 1:] = 0.0
    return Y


def _transpose(A):
    return np.ascontiguousarray(np.swapaxes(A, -1, -2))


def _diagonal(A):
    return np.diagonal(A, axis1=-2, axis2=-1)


def _cholesky_failures(A):
    """Indices of the matrices of ``A`` (R, d, d) that numpy's Cholesky rejects (bisection)."""
    try:
        np.linalg.cholesky(A)
        return np.zeros(0, dtype=int)
    except np.linalg.LinAlgError:
        if len(A) == 1:
            return np.zeros(1, dtype=int)
        half = len(A) // 2
        return np.concatenate([_cholesky_failures(A[:half]),
                               half + _cholesky_failures(A[half:])])


def _sample_rows(L, P, dof, rng, out):
    """Write one joint covariance sample per row of ``out`` (R, Nn, Nn).

    ``L`` and ``P`` (R, N, n, n) or (1, N, n, n) hold the Cholesky factors and the blocks.

    Stage j (j = 1, ..., N-1) draws the block row of estimate j given the leading block
    ``B_j`` (the first j estimates, already complete) and ``P_jj``, by Theorem 1 of the
    journal with ``A_11 = B_j`` (size l_1 = j n) and ``A_22 = P_jj`` (l_2 = n):

        S ~ W_n(dof - j n, I),  X ~ N(0, I_n (x) I_{jn}),  C C^T = S + X X^T,
        T = C^-1 X  ~  IT_{n, jn}(dof - (j+1) n + 1, 0, I, I),
        block row j, columns 0 .. j-1 (0-based)  =  L_j T G_j^T,

    eqs. (50)-(53), with Cholesky factors in place of the symmetric square roots (the
    distribution of T is invariant under T -> U T V for orthogonal U, V, so any square root
    gives the same law). The Cholesky factor of ``B_{j+1}`` is then
    ``[[G_j, 0], [L_j T, L_j C^-1 L_S]]`` (``S = L_S L_S^T``): its last block row gives
    ``L_j (T T^T + C^-1 S C^-T) L_j^T = P_jj``. It is only built when a later stage needs it.

    Returns, per sample, the smallest ratio ``G_ii^2 / A_ii`` of a squared Cholesky pivot
    of the joint covariance to its diagonal entry (1 is independent, 0 singular).
    """
    rows, count, n = out.shape[0], L.shape[1], L.shape[-1]
    for j in range(count):
        out[:, j * n:(j + 1) * n, j * n:(j + 1) * n] = P[:, j]
    G = L[:, 0]  # Cholesky factor of B_1 = P_11
    worst_pivot_ratio = np.ones(rows)
    for j in range(1, count):
        p = j * n
        Y = _stage_draws(rng, dof - p, n, p, rows)  # [X, L_S]
        # Contiguous transposes: numpy's stacked matmul is about twice as fast on them.
        C = cholesky(Y @ _transpose(Y), "X X^T + S")
        last = j == count - 1
        TD = solve_lower(C, Y[..., :p] if last else Y)  # [T, C^-1 L_S]
        new_rows = L[:, j] @ TD  # [L_j T, L_j C^-1 L_S]
        cross = new_rows[..., :p] @ _transpose(G)  # block row j, columns < j
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
    return worst_pivot_ratio


def _redraw_unfactorisable(block, ratio, L, P, dof, rng):
    """Redraw, in place, the samples of ``block`` that are singular in floating point.

    A sample is positive definite in exact arithmetic, but when the prior puts it very
    close to full correlation (a chi-square draw near zero, more likely for small ``dof``)
    and the blocks are badly conditioned, the rounded matrix may not be. Only samples with
    a tiny pivot ratio are tested; those numpy cannot factorise are drawn again, so the law
    is conditioned on an event of negligible probability (none in 4e6 draws with
    well-conditioned blocks and ``dof = N n``; 7e-5 of the draws with blocks of condition
    number 1e9).
    """
    for attempt in range(_MAX_REDRAWS + 1):
        suspects = np.flatnonzero(ratio < _SUSPECT_PIVOT_RATIO)
        failed = suspects[_cholesky_failures(block[suspects])] if suspects.size else suspects
        if failed.size == 0:
            return
        if attempt == _MAX_REDRAWS:
            raise ValueError(
                f"could not draw joint covariances that are positive definite in floating "
                f"point after {_MAX_REDRAWS} redraws: the covariances are too badly "
                f"conditioned for dof = {dof:g}; a larger dof puts less prior mass near full "
                "correlation"
            )
        rows = slice(None) if L.shape[0] == 1 else failed
        fresh = np.empty((failed.size,) + block.shape[1:])
        ratio[failed] = _sample_rows(L[rows], P[rows], dof, rng, fresh)
        block[failed] = fresh


def _sample_joint(L, P, dof, size, rng):
    """Joint covariance samples (..., size, N n, N n) for factors ``L`` (..., N, n, n).

    The samples are drawn in chunks of rows (problem, sample) small enough for the
    processor's cache: numpy's stacked products of tiny matrices are several times slower
    on arrays that do not fit in it.
    """
    batch, count, n = L.shape[:-3], L.shape[-3], L.shape[-1]
    dim = count * n
    L_flat = L.reshape((-1, count, n, n))
    P_flat = P.reshape((-1, count, n, n))
    joint = np.empty((L_flat.shape[0] * size, dim, dim))
    chunk = max(1, _SAMPLER_CHUNK_ENTRIES // dim**2)
    for start in range(0, joint.shape[0], chunk):
        stop = min(start + chunk, joint.shape[0])
        if L_flat.shape[0] == 1:  # one problem: broadcast its blocks over the samples
            L_rows, P_rows = L_flat, P_flat
        else:
            problem = np.arange(start, stop) // size
            L_rows, P_rows = L_flat[problem], P_flat[problem]
        block = joint[start:stop]
        ratio = _sample_rows(L_rows, P_rows, dof, rng, block)
        _redraw_unfactorisable(block, ratio, L_rows, P_rows, dof, rng)
    return joint.reshape(batch + (size, dim, dim))


def sample_joint_covariances(Ps, dof, size, rng=None):
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
        for many problems at once.
    dof : float
        Degrees of freedom of the Wishart prior on the whole joint covariance, at least
        ``N*n``. ``N*n + 1`` makes the conditional uniform over all admissible
        cross-covariances; larger values concentrate it on weak correlation.
    size : int
        Number of samples per problem, >= 1.
    rng : numpy.random.Generator, int or None, optional
        Randomness source; the same seed gives the same samples.

    Returns
    -------
    ndarray, shape (..., size, N*n, N*n)
        Symmetric positive definite joint covariances whose diagonal blocks are exactly
        the given ``Ps``.

    Raises
    ------
    ValueError
        Fewer than two blocks, blocks that are not symmetric positive definite,
        ``dof < N*n`` (the message states the requirement), ``size < 1``, or blocks
        so badly conditioned that no positive definite sample is found in floating point.
    TypeError
        Non-numeric ``Ps``, ``dof`` or ``size``, or a bad ``rng``.

    See Also
    --------
    bayesian_fusion : the fusion rule that averages over these samples.

    Notes
    -----
    Every sample is built from its Cholesky factor, lower triangular with a positive
    diagonal, so it is positive definite by construction. The rare samples that are
    singular in floating point (nearly full correlation with badly conditioned blocks) are
    drawn again, so that every returned sample passes a Cholesky factorisation. The
    density exists for ``dof > N*n - 1``, but the papers define the Wishart distribution
    for ``dof >= N*n``; below that the last stage's chi-square draws have fewer than one
    degree of freedom and the prior piles onto full correlation. The conference version states
    Theorem 1 with ``S ~ W(n, I)``; Lemma 3 applied to eq. (10) gives ``W(n - k/2, I)``,
    which is the journal's ``W(n - l_1, I)`` used here (see the method's page).
    Vectorised over samples and batch; the Python loop runs over the N - 1 stages.

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


def _fuse_joint_samples(x, joints):
    """Average the best linear unbiased fusion over joint covariance samples.

    ``x`` (..., N, n) and ``joints`` (..., M, N n, N n). With ``K^(m)`` the gains of
    eq. (18) for sample m, ``K = mean_m K^(m)``, ``x_hat = sum_i K_i x_i`` and
    ``P = K Pbar K^T`` with ``Pbar = mean_m P_x^(m)``: the error covariance of
    ``x_hat`` averaged over the samples. Returns x_hat, P, gains and the mean of the
    per-sample BLUE covariances (eq. (19)).
    """
    count, n = x.shape[-2:]
    best = optimal_fusion(x[..., None, :, :], joints)
    gains = best.gains.mean(axis=-4)
    x_hat = np.einsum("...kij,...kj->...i", gains, x)
    stacked = np.swapaxes(gains, -3, -2).reshape(gains.shape[:-3] + (n, count * n))
    P = symmetrize(stacked @ joints.mean(axis=-3) @ np.swapaxes(stacked, -1, -2))
    return x_hat, P, gains, best.P.mean(axis=-3)


def bayesian_fusion(xs, Ps, dof=None, samples=100, rng=None):
    """Monte Carlo MMSE fusion of estimates with unknown cross-covariances (Wishart prior).

    Draws ``samples`` joint covariances with the known diagonal blocks from their
    conditional distribution under the prior ``W(dof, Sigma)``, block-diagonal ``Sigma``
    (:func:`sample_joint_covariances`), fuses the estimates with the best linear unbiased
    estimator of each sample (eqs. (18)-(20), :func:`optimal_fusion`) and averages:

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
        Randomness source; the same seed gives the same result.

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
    the two differ by a few percent. The cost is M joint samples and M Cholesky
    factorisations of size N n per fusion.

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
    est = as_estimates(xs, Ps)
    count, n = est.count, est.dim
    dof = float(_default_dof(count, n)) if dof is None else _check_dof(dof, count, n)
    samples = check_int(samples, "samples", low=1)
    rng = as_rng(rng)

    batch = est.batch_shape
    flat = int(np.prod(batch, dtype=int))
    x = est.x.reshape((flat, count, n))
    P = est.P.reshape((flat, count, n, n))
    L = est.L.reshape((flat, count, n, n))
    x_hat, P_hat = np.empty((flat, n)), np.empty((flat, n, n))
    gains, sample_P_mean = np.empty((flat, count, n, n)), np.empty((flat, n, n))
    chunk = max(1, _CHUNK_ENTRIES // (samples * (count * n) ** 2))
    for start in range(0, flat, chunk):
        part = slice(start, start + chunk)
        joints = _sample_joint(L[part], P[part], dof, samples, rng)
        x_hat[part], P_hat[part], gains[part], sample_P_mean[part] = _fuse_joint_samples(
            x[part], joints
        )
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


def _registered_bayes(xs, Ps, dof=None, samples=100, rng=None):
    return bayesian_fusion(xs, Ps, dof=dof, samples=samples, rng=rng)


def _bayes_truth_options(joint, rng):
    # The rule does not use the true joint covariance: it only needs randomness.
    return {"rng": rng}


register_method(
    "bayes",
    _registered_bayes,
    summary="Monte Carlo MMSE: BLUE averaged over cross-covariances drawn from a Wishart prior",
    reference="Weng & Djurić, journal, Theorem 1, eqs. 18-20, 46-53; EUSIPCO 2012",
    guarantee="none",
    truth_options=_bayes_truth_options,
)
