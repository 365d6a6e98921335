"""Ellipsoidal Intersection (Sijs & Lazar 2012) as reviewed by Naveen & Taylor.

EI splits each of two estimates into a part they have in common and an independent
part, estimates the common part from the covariances alone, and removes it once:

    C_c = T diag(max(d_k, 1)) T^T                          (eqs. (11)-(12))
    C_f^-1 = C_a^-1 + C_b^-1 - C_c^-1,  x_f = C_f (C_a^-1 x_a + C_b^-1 x_b - C_c^-1 x_c)
                                                           (eqs. (7)-(8), with (5)-(6))

where ``C_a = T T^T`` and ``C_b = T diag(d) T^T`` (a simultaneous diagonalisation) and
``x_c`` is the mutual mean of eq. (13). Everything is computed in the coordinates
``T^-1 x``, where both covariances and the common covariance are diagonal; there the
rule fuses each eigen-direction separately.

This module also holds the decomposition shared with the probabilistically conservative
variant (:mod:`cifilter.pcei`): the independent information of each input for a given
common covariance, the mutual mean and the chi-square statistic of eq. (17).
"""

from typing import NamedTuple

import numpy as np

from ._linalg import (
    IllConditionedError,
    cho_inverse,
    cholesky,
    condition_number,
    ill_conditioned,
    lower_inverse,
    solve_lower,
    symmetrize,
)
from ._validation import (
    Estimates,
    as_estimates,
    as_float_array,
    check_covariances,
    check_finite,
    check_scalar,
    restore_style,
    vector_style,
)
from .result import FusionResult

__all__ = ["MUTUAL_MEANS", "REGULARIZERS", "ellipsoidal_intersection"]

MUTUAL_MEANS = ("sijs-lazar", "as-printed")
"""Accepted values of ``mutual_mean``: Sijs & Lazar's weighting and eq. (13) as printed."""

REGULARIZERS = ("information", "covariance")
"""Accepted values of ``regularizer``: where ``eps`` enters (see ``ellipsoidal_intersection``)."""

DEFAULT_EPS = 1e-8


# --------------------------------------------------------------------------- input checks
def _check_one(x, P, x_name, P_name):
    """Check one estimate; returns its mean in row form, the column flag, P and its factor."""
    P = as_float_array(P, P_name)
    if P.ndim < 2 or P.shape[-1] != P.shape[-2] or P.shape[-1] == 0:
        raise ValueError(f"{P_name} must be an n x n covariance (..., n, n), got shape {P.shape}")
    P, L = check_covariances(P, P_name)
    n = P.shape[-1]
    x = as_float_array(x, x_name)
    style = vector_style(x, n)
    column = style == "column"
    if style is None:
        raise ValueError(
            f"{x_name} must have shape (..., {n}) or (..., {n}, 1) to match {P_name} "
            f"({n}x{n}), got shape {x.shape}"
        )
    check_finite(x, x_name)
    return (x[..., 0] if column else x), column, P, L


def _as_pair(xa, Pa, xb, Pb):
    """Validate two estimates and stack them in the canonical layout (..., 2, n).

    The batch axes of all four arguments broadcast against each other; the result comes
    back in the vector style of ``xa``.
    """
    xa, column, Pa, La = _check_one(xa, Pa, "xa", "Pa")
    xb, _, Pb, Lb = _check_one(xb, Pb, "xb", "Pb")
    n = Pa.shape[-1]
    if Pb.shape[-1] != n:
        raise ValueError(f"Pa is {n}x{n} but Pb is {Pb.shape[-1]}x{Pb.shape[-1]}: the states "
                         "must match")
    shapes = {"xa": xa.shape[:-1], "Pa": Pa.shape[:-2], "xb": xb.shape[:-1], "Pb": Pb.shape[:-2]}
    try:
        batch = np.broadcast_shapes(*shapes.values())
    except ValueError:
        listed = ", ".join(f"{name} {shape}" for name, shape in shapes.items())
        raise ValueError(f"batch shapes of {listed} do not broadcast") from None

    def stack(a, b, tail):
        return np.stack([np.broadcast_to(a, batch + tail), np.broadcast_to(b, batch + tail)],
                        axis=-1 - len(tail))

    return Estimates(stack(xa, xb, (n,)), stack(Pa, Pb, (n, n)), stack(La, Lb, (n, n)), column)


def _check_two(est, method):
    if est.count != 2:
        raise ValueError(f"{method!r} fuses exactly two estimates, got {est.count}")
    return est


def _check_options(mutual_mean, regularizer, eps):
    if mutual_mean not in MUTUAL_MEANS:
        raise ValueError(f"mutual_mean must be one of {MUTUAL_MEANS}, got {mutual_mean!r}")
    if regularizer not in REGULARIZERS:
        raise ValueError(f"regularizer must be one of {REGULARIZERS}, got {regularizer!r}")
    return check_scalar(eps, "eps", low=0.0)


# --------------------------------------------------------------------------- whitening
class Whitened(NamedTuple):
    """Two estimates in the coordinates ``u = T^-1 x`` of eq. (12), and EI's covariances.

    ``Pa = T T^T`` and ``Pb = T diag(d) T^T``; ``a``, ``b`` are the whitened means.
    ``F`` is a factor of EI's fused covariance ``P_EI = F F^T`` and ``S = Pa + Pb``,
    both in the original coordinates (see ``whiten``).
    """

    T: np.ndarray  # (..., n, n)
    T_inv: np.ndarray  # (..., n, n)
    d: np.ndarray  # (..., n), generalised eigenvalues of (Pb, Pa)
    a: np.ndarray  # (..., n)
    b: np.ndarray  # (..., n)
    F: np.ndarray  # (..., n, n), nonsingular, P_EI = F F^T
    S: np.ndarray  # (..., n, n), Pa + Pb

    @property
    def lam(self):
        """Information of b in the whitened coordinates (that of a is 1)."""
        return 1.0 / self.d


def _orthonormal_columns(Y):
    """``Q`` with orthonormal columns such that, for every k, the first k columns of ``Q``
    span those of ``Y`` (stacks of nonsingular ``Y``).

    Classical Gram-Schmidt with one reorthogonalisation, vectorised over the batch (the
    loop runs over the n columns); column-wise backward stable like Householder QR and,
    for n <= 6, several times faster than numpy's batched ``qr``.
    """
    n = Y.shape[-1]
    Q = np.empty_like(Y)
    for j in range(n):
        v = Y[..., :, j]
        if j:
            basis = Q[..., :, :j]
            for _ in range(2):
                v = v - np.einsum("...ik,...k->...i", basis,
                                  np.einsum("...ik,...i->...k", basis, v))
        Q[..., :, j] = v / np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]
    return Q


def whiten(est, factor=True):
    """Simultaneous diagonalisation of the two covariances of ``est`` (eq. (12)).

    Eq. (12) whitens with ``C_a`` and eigen-decomposes ``C_a^-1/2 C_b C_a^-1/2``. That
    matrix has condition number up to ``cond(Pa) cond(Pb)``: its small eigenvalues (the
    directions where ``b`` is the more informative input) are rounding noise, even
    negative, and so was EI's covariance ``T diag(min(1, d)) T^T`` built from them.

    Here the pencil is whitened with the sum, ``Pa + Pb = Ls Ls^T``, and

        Ls^-1 (Pa - Pb) Ls^-T = W diag(c^2 - s^2) W^T,   c^2 + s^2 = 1,

    is decomposed: its entries are bounded by 1 and its error is of order
    ``eps_mach max(cond(Pa), cond(Pb))``, not their product. The columns ``g`` of
    ``G = Ls W`` are the generalised eigenvectors; each input's information along them
    is taken from its own Cholesky factor, ``q_a = |La^-1 g|^2`` and
    ``q_b = |Lb^-1 g|^2``. Then ``T = G diag(q_a^-1/2)``, ``d = q_a / q_b`` (in
    ascending order) and ``T^-1 = diag(q_a^1/2) W^T Ls^-1``, an exact inverse of ``T``
    even where ``W`` is perturbed.

    EI's covariance: the decomposition separates the directions where ``a`` is the
    more informative input (``c^2 <= s^2``, set ``A``) from those where ``b`` is (set
    ``B``), except near ties, where the choice does not matter; it need not resolve the
    directions inside a set, whose eigenvalues may cluster far below its accuracy. So

        P_EI = La Pi_A La^T + Lb Pi_B Lb^T,

    with ``Pi_A`` the orthogonal projector onto ``La^-1 span(G_A)`` and ``Pi_B`` that onto
    ``Lb^-1 span(G_B)``: in exact arithmetic ``G_A (G_A^T Pa^-1 G_A)^-1 G_A^T +
    G_B (G_B^T Pb^-1 G_B)^-1 G_B^T = T diag(min(1, d)) T^T`` for any basis of each set
    (eq. (8) with eq. (11)). It is assembled as ``F F^T`` with ``F = [La Q_A, Lb Q_B]``
    (orthonormal bases ``Q``), nonsingular because ``G`` is: positive definite by
    construction, and accurate to about ``eps_mach`` times the inputs' condition
    numbers in every direction. With ``factor=False`` (callers that do not use EI's own
    covariance) ``F`` and ``S`` are ``None``.
    """
    P, L = est.P, est.L
    S = P[..., 0, :, :] + P[..., 1, :, :]
    Ls = np.linalg.cholesky(S)  # positive definite: Pa and Pb passed their checks
    Ls_inv = lower_inverse(Ls)
    D = symmetrize(Ls_inv @ (P[..., 0, :, :] - P[..., 1, :, :]) @ np.swapaxes(Ls_inv, -1, -2))
    delta, W = np.linalg.eigh(D)  # c^2 - s^2 ascending
    W, delta = W[..., ::-1], delta[..., ::-1]  # set B (c^2 > s^2) first, then A
    G = Ls @ W
    # La^-1 G and Lb^-1 G in one batched triangular solve: L is (..., 2, n, n)
    Y = solve_lower(L, G[..., None, :, :])
    q = np.einsum("...ij,...ij->...j", Y, Y)
    q_a, q_b = q[..., 0, :], q[..., 1, :]
    root = np.sqrt(q_a)
    T = G / root[..., None, :]
    T_inv = root[..., :, None] * (np.swapaxes(W, -1, -2) @ Ls_inv)
    a = np.einsum("...ij,...j->...i", T_inv, est.x[..., 0, :])
    b = np.einsum("...ij,...j->...i", T_inv, est.x[..., 1, :])
    if not factor:
        return Whitened(T, T_inv, q_a / q_b, a, b, None, None)
    # Bases: the first m_A columns of Q_A span La^-1 G_A (G_A reversed to the front),
    # the first m_B columns of Q_B span Lb^-1 G_B.
    n = G.shape[-1]
    Q = _orthonormal_columns(np.stack([Y[..., 0, :, ::-1], Y[..., 1, :, :]], axis=-3))
    LQ = L @ Q
    m_a = n - np.sum(delta > 0, axis=-1)
    F = np.where(np.arange(n) < m_a[..., None, None], LQ[..., 0, :, :],
                 LQ[..., 1, :, ::-1])
    return Whitened(T, T_inv, q_a / q_b, a, b, F, S)


def ties(d, eps):
    """Eigen-directions in which the inputs are equally informative (``|log d| <= eps``)."""
    return np.abs(np.log(d)) <= eps


# --------------------------------------------------------------------------- decomposition
class Decomposition(NamedTuple):
    """The split of eqs. (2)-(6) for a given common information ``J`` (whitened).

    ``A = I - J`` and ``B = diag(lam) - J`` are the independent informations of a and b,
    ``S = A + B``, ``m`` the mutual mean, ``eta_a = a - J m`` and ``eta_b = lam b - J m``
    the independent information vectors; ``x_a = A^-1 eta_a``, ``x_b = B^-1 eta_b`` are the
    independent means of eq. (5) and ``x_s = S^-1 (eta_a + eta_b)``.
    """

    S: np.ndarray
    m: np.ndarray
    eta_a: np.ndarray
    eta_b: np.ndarray
    x_a: np.ndarray
    x_b: np.ndarray
    x_s: np.ndarray
    psi: np.ndarray


def _solve(M, v):
    """Solve ``M X = v`` for stacks of small symmetric positive definite ``M``.

    ``v`` is (..., n) or (..., n, k). The callers guarantee positive definiteness, so
    LAPACK's batched solver is used directly (for n <= 6 it is faster than a Cholesky
    factorisation followed by two triangular solves in a Python loop). Solves rather than
    explicit inverses: near a rank-deficient optimum ``A`` or ``B`` is nearly singular and
    ``psi`` depends on the accuracy of ``A^-1 eta_a``.
    """
    vector = v.ndim == M.ndim - 1
    rhs = v[..., None] if vector else v
    try:
        x = np.linalg.solve(M, rhs)
    except np.linalg.LinAlgError:  # an exactly singular member: inf/nan there, not an error
        values, vectors = np.linalg.eigh(M)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = vectors @ ((np.swapaxes(vectors, -1, -2) @ rhs) / values[..., :, None])
    return x[..., 0] if vector else x


def mutual_mean_weights(A, B, mutual_mean):
    """``(W_a, W_b)`` with ``m = (W_a + W_b)^-1 (W_a a + W_b b)``.

    Eq. (13) as printed weights each input by its own independent information
    (``W_a = A``); Sijs & Lazar (2012, eq. (16)) weight ``a`` by ``b``'s independent
    information and ``b`` by ``a``'s (``W_a = B``).
    """
    return (A, B) if mutual_mean == "as-printed" else (B, A)


def decompose(A, B, J, a, b, lam, mutual_mean):
    """Mutual mean, independent parts and ``psi`` (eq. (17)) for positive definite A, B.

    ``psi`` is computed in information form,

        psi = eta_a^T A^-1 eta_a + eta_b^T B^-1 eta_b - s^T (A + B)^-1 s,  s = eta_a + eta_b,

    which equals eq. (17), ``(x_a - x_b)^T (A^-1 + B^-1)^-1 (x_a - x_b)``, but has no
    cancellation between huge terms when ``A`` or ``B`` is nearly singular (near EI's
    common covariance the independent means of eq. (5) run off to infinity while ``psi``
    stays finite).
    """
    S = A + B
    W_a, W_b = mutual_mean_weights(A, B, mutual_mean)
    rhs = np.einsum("...ij,...j->...i", W_a, a) + np.einsum("...ij,...j->...i", W_b, b)
    m = _solve(S, rhs)
    Jm = np.einsum("...ij,...j->...i", J, m)
    eta_a, eta_b = a - Jm, lam * b - Jm
    s = eta_a + eta_b
    # A and B in one batched call
    x_a, x_b = _solve(np.stack([A, B]), np.stack([eta_a, eta_b]))
    x_s = _solve(S, s)
    psi = (np.einsum("...i,...i->...", eta_a, x_a) + np.einsum("...i,...i->...", eta_b, x_b)
           - np.einsum("...i,...i->...", s, x_s))
    return Decomposition(S, m, eta_a, eta_b, x_a, x_b, x_s, np.maximum(psi, 0.0))


def psi_at_ei(w, tie, mutual_mean):
    """``psi`` at EI's common covariance, as the limit from admissible interior points.

    At ``C_c = T diag(max(d, 1)) T^T`` each eigen-direction has independent information in
    at most one input. With Sijs & Lazar's mutual mean the input without independent
    information supplies the common mean there, so the independent means explain the
    difference and ``psi -> 0``; eq. (13) as printed takes the common mean from the other
    input, which leaves an independent part with no information but a mean offset, and
    ``psi -> infinity`` unless the means agree. In tied directions (no independent
    information in either input) ``psi -> infinity`` unless the means agree there.
    """
    e = w.a - w.b
    relevant = tie if mutual_mean == "sijs-lazar" else np.ones_like(tie)
    agree = np.all(np.where(relevant, e == 0.0, True), axis=-1)
    return np.where(agree, 0.0, np.inf)


# --------------------------------------------------------------------------- fusion
class Fused(NamedTuple):
    """A fused estimate: covariances in the original coordinates, the rest whitened.

    ``P`` and ``common_P`` are Gram matrices of nonsingular factors (positive definite
    by construction). EI's closed form is diagonal in ``K_a``, ``A`` and ``B``: then these
    are the diagonals, shape (..., n) (see ``as_full``).
    """

    P: np.ndarray  # (..., n, n), fused covariance (original coordinates)
    K_a: np.ndarray  # (..., n, n), gain of a (that of b is I - K_a), whitened
    m: np.ndarray  # (..., n) mutual mean, whitened
    common_P: np.ndarray  # (..., n, n), common covariance (original coordinates)
    A: np.ndarray  # (..., n, n) independent information of a, whitened
    B: np.ndarray  # (..., n, n) independent information of b, whitened
    eta: np.ndarray  # (..., 2, n) independent information vectors, whitened

    @property
    def diagonal(self):
        return self.K_a.ndim == self.m.ndim


def as_full(fused):
    """``fused`` with diagonal fields (EI's closed form) expanded to matrices."""
    if not fused.diagonal:
        return fused
    return fused._replace(K_a=_diagonal(fused.K_a), A=_diagonal(fused.A),
                          B=_diagonal(fused.B))


def mean_ratio(w, eps, mutual_mean):
    """``R_a`` per eigen-direction of EI's regularised mutual mean (see ``fuse_diagonal``)."""
    lam = w.lam
    alpha, beta = np.maximum(0.0, 1.0 - lam), np.maximum(0.0, lam - 1.0)
    eta = 0.5 * eps * (1.0 + lam)
    w_a, w_b = alpha + eta, beta + eta
    total = w_a + w_b
    own = w_a if mutual_mean == "as-printed" else w_b
    return np.where(total > 0, own / np.where(total > 0, total, 1.0), 0.5)


def _diagonal(v):
    return v[..., None] * np.eye(v.shape[-1])


def fuse_diagonal(w, eps, mutual_mean):
    """EI with the information regulariser, one eigen-direction at a time (closed form).

    With ``c = max(d, 1)``, ``alpha = max(0, 1 - 1/d)`` and ``beta = max(0, 1/d - 1)`` (the
    independent informations of a and b) and ``eta = eps (1 + 1/d) / 2``, the mutual mean
    is ``m = R_a a + R_b b`` with ``R_a = (beta + eta) / (alpha + beta + 2 eta)`` (Sijs &
    Lazar) or ``(alpha + eta) / (alpha + beta + 2 eta)`` (as printed), and the fused
    variance is ``1 / (1 + 1/d - 1/c) = min(1, d)``. Where ``alpha + beta + 2 eta = 0``
    (equal variances and ``eps = 0``: the 0/0 of eq. (13)) ``R_a = 1/2``, the limit of any
    symmetric regulariser.

    The gain of ``a`` is ``k_a = min(1, d) (1 - R_a / c)``, evaluated without
    cancellation as ``1 - R_a / d`` (``d >= 1``) or ``d R_b`` (``d < 1``); that of ``b``
    is ``1 - k_a``. The fused covariance ``T diag(min(1, d)) T^T`` is ``F F^T`` of
    ``whiten`` and the common covariance ``T diag(max(d, 1)) T^T = Pa + Pb - P``
    (``max + min = sum``; it is at least ``(Pa + Pb) / 2``, so the difference loses
    nothing).
    """
    d, lam = w.d, w.lam
    c = np.maximum(d, 1.0)
    alpha, beta = np.maximum(0.0, 1.0 - lam), np.maximum(0.0, lam - 1.0)
    R_a = mean_ratio(w, eps, mutual_mean)
    R_b = 1.0 - R_a
    m = R_a * w.a + R_b * w.b
    k_a = np.where(d >= 1.0, 1.0 - R_a / c, d * R_b)
    common_info = np.minimum(1.0, lam)
    eta_vec = np.stack([w.a - common_info * m, lam * w.b - common_info * m], axis=-2)
    P = _gram(w.F)
    return Fused(P, k_a, m, symmetrize(w.S - P), alpha, beta, eta_vec)


def _inverse_root(M, name):
    """``R`` with ``M^-1 = R R^T`` (``R = L^-T``, ``M = L L^T``) for stacks of SPD ``M``."""
    try:
        L = cholesky(M, name)
    except ValueError:
        raise IllConditionedError(
            f"{name} is not numerically positive definite (condition number "
            f"{float(np.max(condition_number(M))):.3g}); the inputs are too ill-conditioned "
            "to fuse reliably") from None
    return np.swapaxes(lower_inverse(L), -1, -2)


def fuse_full(w, J, A, B, mutual_mean, R_a=None, information=None, C_root=None):
    """Fusion with a general common information ``J`` (whitened), eqs. (5)-(8) and (13).

    ``m = R_a a + R_b b`` with ``R_a = (A + B)^-1 W_a`` unless ``R_a`` is given (where
    ``A + B`` is singular and the mutual mean is known as a limit); the fused information
    is ``M = I + diag(lam) - J`` (eq. (8); pass ``information`` when a form without
    cancellation is known) and ``K_a = M^-1 (I - J R_a)``, ``K_b = I - K_a``
    ``= M^-1 (diag(lam) - J R_b)``, so that ``x = K_a a + K_b b``. The covariances are
    mapped back as Gram matrices through Cholesky factors: ``P = (T L^-T)(T L^-T)^T``
    with ``M = L L^T``, and ``C = J^-1`` likewise unless its root ``C_root`` is given.
    """
    n = J.shape[-1]
    eye = np.eye(n)
    if R_a is None:
        W_a, _ = mutual_mean_weights(A, B, mutual_mean)
        R_a = _solve(A + B, W_a)
    R_b = eye - R_a
    M = symmetrize(eye + w.lam[..., None] * eye - J if information is None else information)
    P_root = _inverse_root(M, "the fused information")
    K_a = P_root @ (np.swapaxes(P_root, -1, -2) @ (eye - J @ R_a))
    P = _gram(w.T @ P_root)
    m = np.einsum("...ij,...j->...i", R_a, w.a) + np.einsum("...ij,...j->...i", R_b, w.b)
    Jm = np.einsum("...ij,...j->...i", J, m)
    eta_vec = np.stack([w.a - Jm, w.lam * w.b - Jm], axis=-2)
    if C_root is None:
        C_root = _inverse_root(symmetrize(J), "the common information")
    return Fused(P, K_a, m, _gram(w.T @ C_root), symmetrize(A), symmetrize(B), eta_vec)


def _covariance_base(w, eps):
    n = w.d.shape[-1]
    eye = np.eye(n)
    C = symmetrize(np.maximum(w.d, 1.0)[..., None] * eye
                   + eps * w.T_inv @ np.swapaxes(w.T_inv, -1, -2))
    L = cholesky(C, "the common covariance")
    J = cho_inverse(L)
    A = symmetrize(J @ (C - eye))
    B = symmetrize(J @ (C - w.d[..., None] * eye) * w.lam[..., None, :])
    return L, C, J, A, B


def covariance_regularised_base(w, eps):
    """Eq. (11) with its ``eps I``: common covariance and informations (whitened).

    ``C = diag(max(d, 1)) + eps T^-1 T^-T``; ``J = C^-1`` (through the Cholesky factor
    of ``C``), ``A = J (C - I)`` and ``B = J (C - diag(d)) diag(1/d)`` are computed from
    the covariance gaps, which are exact, instead of subtracting nearly equal
    informations.
    """
    return _covariance_base(w, eps)[1:]


def _gram(F):
    """``F F^T``, exactly symmetric and positive semidefinite by construction."""
    return symmetrize(F @ np.swapaxes(F, -1, -2))


def to_original(w, fused, x):
    """Map a whitened fused estimate back to the original coordinates.

    ``K_a = T K_u T^-1``, ``K_b = I - K_a`` and
    ``x = K_a xa + K_b xb`` from the original means ``x`` (..., 2, n), so that the gains
    reproduce the mean and sum to the identity exactly.
    """
    T, T_inv = w.T, w.T_inv
    T_inv_t = np.swapaxes(T_inv, -1, -2)
    P, common_P = fused.P, fused.common_P
    if fused.diagonal:  # column and row scalings instead of products
        K_a = (T * fused.K_a[..., None, :]) @ T_inv
        roots = np.sqrt(np.stack([fused.A, fused.B], axis=-2))[..., None]
        information = _gram(np.swapaxes(roots * T_inv[..., None, :, :], -1, -2))
    else:
        K_a = T @ fused.K_a @ T_inv
        information = np.stack([symmetrize(T_inv_t @ fused.A @ T_inv),
                                symmetrize(T_inv_t @ fused.B @ T_inv)], axis=-3)
    K_b = np.eye(K_a.shape[-1]) - K_a
    gains = np.stack([K_a, K_b], axis=-3)
    x_fused = np.einsum("...kij,...kj->...i", gains, x)
    common_x = np.einsum("...ij,...j->...i", T, fused.m)
    vectors = np.einsum("...ij,...kj->...ki", T_inv_t, fused.eta)
    return x_fused, P, gains, {"common_x": common_x, "common_P": common_P,
                               "independent_information": information,
                               "independent_information_vector": vectors}


def check_result(P, est):
    """Raise ``IllConditionedError`` unless every ``P`` is finite and positive definite.

    By construction ``P`` is a Gram matrix of a nonsingular factor; this guards the
    conditioning contract against a factor that rounding made singular (only possible
    far beyond condition numbers of ``MAX_CONDITION``).
    """
    good = np.isfinite(P).all(axis=(-2, -1))
    if good.all():
        try:
            np.linalg.cholesky(P)
            return
        except np.linalg.LinAlgError:
            pass
    raise ill_conditioned("Pa or Pb", condition_number(est.P).max(),
                          "gives a fused covariance that is not numerically positive "
                          "definite")


def ei_in_whitened(w, eps, mutual_mean, regularizer):
    """EI of whitened estimates: the fused pieces and ``psi`` at its common covariance."""
    if regularizer == "covariance" and eps > 0:
        L, _, J, A, B = _covariance_base(w, eps)
        fused = fuse_full(w, J, A, B, mutual_mean, C_root=L)
        psi = decompose(A, B, J, w.a, w.b, w.lam, mutual_mean).psi
        return fused, psi
    fused = fuse_diagonal(w, eps if regularizer == "information" else 0.0, mutual_mean)
    tie = ties(w.d, eps if regularizer == "information" else 0.0)
    return fused, psi_at_ei(w, tie, mutual_mean)


def ellipsoidal_intersection(xa, Pa, xb, Pb, eps=DEFAULT_EPS, *, mutual_mean="sijs-lazar",
                             regularizer="information"):
    """Fuse two estimates by Ellipsoidal Intersection.

    EI estimates the information the two inputs share as the smallest-volume admissible
    common covariance (eq. (10)): ``C_c = T diag(max(d_k, 1)) T^T`` with ``Pa = T T^T``
    and ``Pb = T diag(d) T^T`` (eqs. (11)-(12)). The common mean ``x_c`` follows eq. (13)
    and the fused estimate removes the common part once (eqs. (7)-(8) with (5)-(6)):

        P^-1 = Pa^-1 + Pb^-1 - C_c^-1,    x = P (Pa^-1 xa + Pb^-1 xb - C_c^-1 x_c).

    In the eigen-directions of ``T`` this takes, direction by direction, the input with
    the smaller variance (``P = T diag(min(d, 1)) T^T``); the mean differs from that
    input's only through the regulariser.

    Parameters
    ----------
    xa, xb : array_like, shape (..., n) or (..., n, 1)
        The two means; leading axes are batch axes and broadcast against each other and
        the covariances.
    Pa, Pb : array_like, shape (..., n, n)
        Their covariances, symmetric positive definite.
    eps : float, optional
        Regulariser, ``>= 0``, default ``1e-8``. With ``regularizer="information"``
        (default) it is relative and dimensionless: ``eps (Pa^-1 + Pb^-1) / 2`` is added to
        both weights of the mutual mean (Sijs & Lazar's ``eta I``, eq. (16) of their paper,
        written invariantly), so that directions where the inputs are equally informative
        (the 0/0 of eq. (13)) get the average of the two means and no NaN or inf can
        occur; elsewhere its effect on the mean is of relative order
        ``eps / |1 - 1/d_k|``. With ``regularizer="covariance"`` it is absolute, in the
        units of the covariances: ``eps I`` is added to the common covariance as in
        eq. (11) (Naveen & Taylor use ``eps = 0.01``); this also changes the fused
        covariance. ``eps = 0`` gives the unregularised rule, with exact ties resolved
        by the average.
    mutual_mean : {"sijs-lazar", "as-printed"}, optional
        ``"sijs-lazar"`` (default) weights ``xa`` by ``b``'s independent information and
        ``xb`` by ``a``'s, as in Sijs & Lazar (2012); ``"as-printed"`` weights each input by
        its own independent information, as eq. (13) of Naveen & Taylor is printed. Only
        the former gives ``x_c = xb`` when ``C_c = Pb`` (all of b's information shared).
    regularizer : {"information", "covariance"}, optional
        Where ``eps`` enters, see ``eps``.

    Returns
    -------
    FusionResult
        ``x`` (..., n) in the style of ``xa``, ``P`` (..., n, n), ``omega=None``, ``gains``
        (..., 2, n, n) with ``x = K_a xa + K_b xb`` (the common mean is linear in the
        inputs), and ``info`` with ``common_x`` and ``common_P`` (the estimated common
        mean and covariance), ``independent_information`` (..., 2, n, n) and
        ``independent_information_vector`` (..., 2, n) (the parts ``Pa^-1 - C_c^-1`` and
        ``Pa^-1 xa - C_c^-1 x_c`` of each input, finite even where an input has no
        independent information), ``psi`` (the statistic of eq. (17) at ``C_c``; 0 or inf
        at the unregularised EI covariance, see Notes), ``ties`` (number of eigen-directions
        with ``|log d_k| <= eps``), ``mutual_mean``, ``regularizer`` and ``eps``.

    Raises
    ------
    ValueError
        Mismatched dimensions or batch shapes, non-finite values, covariances that are
        not symmetric positive definite, ``eps < 0``, an unknown ``mutual_mean`` or
        ``regularizer``. :class:`~cifilter.IllConditionedError` (a ValueError) instead of
        a covariance that is not finite and positive definite: under the conditioning
        contract (input condition numbers up to 1e12) ``P`` is always positive definite
        (it is assembled as ``F F^T`` with ``F`` nonsingular; see the method's page).
    TypeError
        Non-numeric input.

    See Also
    --------
    pc_ellipsoidal_intersection : EI with the probabilistic constraint on the common part.
    covariance_intersection : conservative for every correlation.

    Notes
    -----
    EI is not conservative: it assumes that the common information is exactly the
    smallest admissible one. When the inputs share less, the fused covariance is too
    small (see the documentation page for measured NEES).

    ``info["psi"]`` at EI's own (unregularised) common covariance is a limit: with Sijs &
    Lazar's mean it is 0 unless the means differ in a tied direction; with the printed
    mean it is infinite unless the means are equal. With ``regularizer="covariance"`` it
    is the finite value of eq. (17).

    References
    ----------
    .. [1] A. Naveen and C. Taylor, "Decentralized data fusion with probabilistically
       conservative ellipsoidal intersection", eqs. (5)-(8) and (10)-(13).
    .. [2] J. Sijs and M. Lazar, "State fusion with unknown correlation: Ellipsoidal
       intersection", Automatica 48(8), 2012, eqs. (11)-(16).

    Examples
    --------
    Section III, case 1 of Naveen & Taylor: equal variances, means +1 and -1. With the
    printed ``eps I`` of eq. (11) the common covariance is 1.01, the independent parts are
    (101, 101) and (-101, 101), the fused variance is about 1:

    >>> import numpy as np
    >>> from cifilter import ellipsoidal_intersection
    >>> r = ellipsoidal_intersection([1.0], [[1.0]], [-1.0], [[1.0]], eps=0.01,
    ...                              regularizer="covariance")
    >>> A = r.info["independent_information"][:, 0, 0]
    >>> eta = r.info["independent_information_vector"][:, 0]
    >>> (1 / A).round(6).tolist(), (eta / A).round(6).tolist(), round(float(r.P[0, 0]), 4)
    ([101.0, 101.0], [101.0, -101.0], 0.9902)

    The gains reproduce the fused mean:

    >>> r = ellipsoidal_intersection(np.array([1.0, 0.0]), np.diag([1.0, 4.0]),
    ...                              np.array([0.0, 1.0]), np.diag([4.0, 1.0]))
    >>> r.x.round(6).tolist(), np.diag(r.P).tolist()
    ([1.0, 1.0], [1.0, 1.0])
    >>> bool(np.allclose(r.gains[0] @ [1.0, 0.0] + r.gains[1] @ [0.0, 1.0], r.x))
    True
    """
    est = _as_pair(xa, Pa, xb, Pb)
    return _ei(est, eps, mutual_mean, regularizer)


def _ei(est, eps, mutual_mean, regularizer):
    eps = _check_options(mutual_mean, regularizer, eps)
    w = whiten(est, factor=not (regularizer == "covariance" and eps > 0))
    fused, psi = ei_in_whitened(w, eps, mutual_mean, regularizer)
    x, P, gains, info = to_original(w, fused, est.x)
    check_result(P, est)
    info.update(psi=psi, ties=ties(w.d, eps if regularizer == "information" else 0.0).sum(-1),
                mutual_mean=mutual_mean, regularizer=regularizer, eps=eps)
    return FusionResult(restore_style(x, est.column), P, "ei", None, gains, info)


def _ei_core(est, eps=DEFAULT_EPS, mutual_mean="sijs-lazar", regularizer="information"):
    return _ei(_check_two(est, "ei"), eps, mutual_mean, regularizer)


def _registered_ei(xs, Ps, eps=DEFAULT_EPS, mutual_mean="sijs-lazar", regularizer="information"):
    return _ei_core(as_estimates(xs, Ps), eps, mutual_mean, regularizer)


REGISTRATION = dict(
    name="ei",
    function=_registered_ei,
    core=_ei_core,
    summary="Ellipsoidal Intersection: removes the largest admissible common part once",
    reference="Sijs & Lazar 2012; Naveen & Taylor, eqs. 7-8, 11-13",
    guarantee="none",
)
"""The record of the ``"ei"`` rule (registered by :mod:`cifilter._rules`)."""
