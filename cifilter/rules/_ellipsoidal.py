"""Ellipsoidal geometry shared by Ellipsoidal Intersection and PC-EI.

Both rules (:mod:`cifilter.rules.ei`, :mod:`cifilter.rules.pcei`) work in the coordinates
``u = T^-1 x`` of a simultaneous diagonalisation ``Pa = T T^T``, ``Pb = T diag(d) T^T``
(eq. (12) of Naveen & Taylor), where both covariances and EI's common covariance are
diagonal. This module holds what they share: the argument forms and option checks, the
whitening (:func:`whiten`), the split of each input into a common and an independent part
for a given common information (:func:`decompose`, eqs. (2)-(6) and (13)), fusion in the
whitened frame (:func:`fuse_diagonal`, :func:`fuse_full`, eqs. (7)-(8)), the map back to
the original coordinates (:func:`to_original`), the result check and the complete EI rule
on validated estimates (:func:`ei_fusion`). The derivations are on the documentation page
``docs/methods/ei.rst`` ("Numerical formulation"); the docstrings here state contracts.

Every function works on stacks with leading batch axes. A single problem (no batch axes)
takes a path written for one problem (:func:`whiten` and :func:`ei_fusion`): direct LAPACK
calls and 2-D products instead of batched machinery, for the latency of one
``kf.fuse(other, method="ei")``. Both paths compute the same quantities by the same
formulas and agree to rounding.
"""

import numbers
from typing import NamedTuple

import numpy as np
from scipy.linalg import lapack

from .._numerics.linalg import (
    IllConditionedError,
    cho_inverse,
    cholesky,
    condition_number,
    ill_conditioned,
    lower_inverse,
    positive_definite,
    solve_lower,
    symmetrize,
)
from .._numerics.validation import (
    Estimates,
    as_estimates,
    as_float_array,
    check_covariances,
    check_finite,
    check_scalar,
    vector_style,
)

__all__ = [
    "DEFAULT_EPS", "MUTUAL_MEANS", "REGULARIZERS", "Decomposition", "Fused", "Whitened",
    "as_full", "check_options", "check_pair", "check_result", "covariance_regularised_base",
    "decompose", "ei_fusion", "ei_in_whitened", "estimates_from_arguments",
    "fuse_diagonal", "fuse_full", "gram", "inverse_root", "largest_ellipsoid_fusion",
    "mean_ratio", "mutual_mean_weights", "pair_estimates", "psi_at_ei", "solve_spd",
    "spd_inverse_stack", "ties", "to_original", "whiten",
]

MUTUAL_MEANS = ("sijs-lazar", "as-printed")
"""Accepted values of ``mutual_mean``: Sijs & Lazar's weighting and eq. (13) as printed."""

REGULARIZERS = ("information", "covariance")
"""Accepted values of ``regularizer``: where ``eps`` enters (see ``ellipsoidal_intersection``)."""

DEFAULT_EPS = 1e-8
"""Default regulariser ``eps`` of EI and PC-EI."""


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


def pair_estimates(xa, Pa, xb, Pb):
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


def check_pair(est, method):
    """``est`` unchanged if it holds exactly two estimates; ``ValueError`` otherwise."""
    if est.count != 2:
        raise ValueError(f"{method!r} fuses exactly two estimates, got {est.count}")
    return est


def check_options(mutual_mean, regularizer, eps):
    """Check the options common to EI and PC-EI; returns ``eps`` as a float."""
    if mutual_mean not in MUTUAL_MEANS:
        raise ValueError(f"mutual_mean must be one of {MUTUAL_MEANS}, got {mutual_mean!r}")
    if regularizer not in REGULARIZERS:
        raise ValueError(f"regularizer must be one of {REGULARIZERS}, got {regularizer!r}")
    return check_scalar(eps, "eps", low=0.0)


# --------------------------------------------------------------------------- argument forms
def estimates_from_arguments(xs, Ps, args, option, value, default, method):
    """Validated estimates and one positional option from the two argument forms.

    ``f(xs, Ps[, option])`` (the package convention) or the pairwise convenience
    ``f(xa, Pa, xb, Pb[, option])``: ``args`` are the positional arguments after the
    first two. ``value`` is the keyword value of ``option`` and ``default`` its default;
    a value given both ways is a ``TypeError``. Returns ``(Estimates, option value)``.
    """
    if len(args) > 3:
        raise TypeError(f"{method}() takes (xs, Ps[, {option}]) or (xa, Pa, xb, Pb[, "
                        f"{option}]) as positional arguments, got {2 + len(args)}")
    if len(args) == 1 and not (isinstance(args[0], numbers.Real)
                               and not isinstance(args[0], bool)):
        raise TypeError(f"{method}() got 3 positional arguments: give (xs, Ps[, {option}]) "
                        f"or (xa, Pa, xb, Pb[, {option}]); the third must be {option}, a "
                        f"real number, got {type(args[0]).__name__}")
    if len(args) in (1, 3):
        if value is not default and value != default:
            raise TypeError(f"{method}() got {option} both as a positional and a keyword "
                            "argument")
        value = args[-1]
    if len(args) >= 2:
        return pair_estimates(xs, Ps, args[0], args[1]), value
    return as_estimates(xs, Ps), value


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

    Returns a :class:`Whitened` with ``Pa = T T^T``, ``Pb = T diag(d) T^T``, ``T^-1`` an
    exact inverse of the computed ``T``, the whitened means and, with ``factor=True``, a
    nonsingular factor ``F`` of EI's fused covariance ``T diag(min(1, d)) T^T = F F^T``
    and ``S = Pa + Pb`` (``None`` otherwise). The pencil is whitened with ``Pa + Pb``,
    not with ``Pa``, and ``F`` is assembled per set of directions, so that errors are of
    order ``eps_mach max(cond(Pa), cond(Pb))`` and ``F F^T`` is positive definite by
    construction: ``docs/methods/ei.rst``, "Numerical formulation", steps 1-3.
    A single problem (no batch axes) takes a path that calls LAPACK directly.
    """
    if not est.batch_shape:
        return _whiten_one(est, factor)
    P, L = est.P, est.L
    S = P[..., 0, :, :] + P[..., 1, :, :]
    Ls = np.linalg.cholesky(S)  # positive definite: Pa and Pb passed their checks
    Ls_inv = lower_inverse(Ls)
    D = symmetrize(Ls_inv @ (P[..., 0, :, :] - P[..., 1, :, :]) @ Ls_inv.swapaxes(-1, -2))
    delta, W = np.linalg.eigh(D)  # c^2 - s^2 ascending
    W, delta = W[..., ::-1], delta[..., ::-1]  # set B (c^2 > s^2) first, then A
    G = Ls @ W
    # La^-1 G and Lb^-1 G in one batched triangular solve: L is (..., 2, n, n)
    Y = solve_lower(L, G[..., None, :, :])
    q = np.einsum("...ij,...ij->...j", Y, Y)
    q_a, q_b = q[..., 0, :], q[..., 1, :]
    root = np.sqrt(q_a)
    T = G / root[..., None, :]
    T_inv = root[..., :, None] * (W.swapaxes(-1, -2) @ Ls_inv)
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


def solve_spd(M, v):
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
            x = vectors @ ((vectors.swapaxes(-1, -2) @ rhs) / values[..., :, None])
    return x[..., 0] if vector else x


def spd_inverse_stack(M):
    """Inverses of a stack of symmetric positive definite matrices, exactly symmetric.

    Through Cholesky factors (``L^-T L^-1``); should a member's factorisation fail by
    rounding (a nearly singular iterate of the PC-EI solver), the whole stack is inverted
    through its eigen-decomposition instead (``V diag(1/w) V^T``: inf/nan where a matrix
    is singular, as a solve would give; no error).
    """
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        values, vectors = np.linalg.eigh(M)
        with np.errstate(divide="ignore", invalid="ignore"):
            return symmetrize((vectors / values[..., None, :]) @ vectors.swapaxes(-1, -2))
    return cho_inverse(L)


def tie_shift(S):
    """``tau`` (..., 1, 1) added to ``S = A + B`` (whitened, of order one) before the solve of
    the mutual mean, eq. (13): ``8 n eps max(1, max|S|)``, a rounding-level change where
    ``S`` is regular. Where ``S`` vanishes (equally informative inputs whose regulariser is
    below rounding, such as ``eps I`` of covariances of order 1e14) the solve then gives the
    limit of any symmetric regulariser, weights 1/2, instead of 0/0."""
    n = S.shape[-1]
    size = np.maximum(np.abs(S).max(axis=(-2, -1)), 1.0)
    return (8.0 * n * np.finfo(float).eps * size)[..., None, None]


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
    tau = tie_shift(S)
    m = solve_spd(S + tau * np.eye(S.shape[-1]), rhs + tau[..., 0] * 0.5 * (a + b))
    Jm = np.einsum("...ij,...j->...i", J, m)
    eta_a, eta_b = a - Jm, lam * b - Jm
    s = eta_a + eta_b
    # A and B in one batched call
    x_a, x_b = solve_spd(np.stack([A, B]), np.stack([eta_a, eta_b]))
    x_s = solve_spd(S, s)
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
    P = gram(w.F)
    return Fused(P, k_a, m, symmetrize(w.S - P), alpha, beta, eta_vec)


def inverse_root(M, name):
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
        tau = tie_shift(A + B)
        R_a = solve_spd(A + B + tau * eye, W_a + 0.5 * tau * eye)
    R_b = eye - R_a
    M = symmetrize(eye + w.lam[..., None] * eye - J if information is None else information)
    P_root = inverse_root(M, "the fused information")
    K_a = P_root @ (P_root.swapaxes(-1, -2) @ (eye - J @ R_a))
    P = gram(w.T @ P_root)
    m = np.einsum("...ij,...j->...i", R_a, w.a) + np.einsum("...ij,...j->...i", R_b, w.b)
    Jm = np.einsum("...ij,...j->...i", J, m)
    eta_vec = np.stack([w.a - Jm, w.lam * w.b - Jm], axis=-2)
    if C_root is None:
        C_root = inverse_root(symmetrize(J), "the common information")
    return Fused(P, K_a, m, gram(w.T @ C_root), symmetrize(A), symmetrize(B), eta_vec)


def _covariance_base(w, eps):
    n = w.d.shape[-1]
    eye = np.eye(n)
    C = symmetrize(np.maximum(w.d, 1.0)[..., None] * eye
                   + eps * w.T_inv @ w.T_inv.swapaxes(-1, -2))
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


def gram(F):
    """``F F^T``, exactly symmetric and positive semidefinite by construction."""
    return symmetrize(F @ F.swapaxes(-1, -2))


def to_original(w, fused, x):
    """Map a whitened fused estimate back to the original coordinates.

    ``K_a = T K_u T^-1``, ``K_b = I - K_a`` and
    ``x = K_a xa + K_b xb`` from the original means ``x`` (..., 2, n), so that the gains
    reproduce the mean and sum to the identity exactly.
    """
    T, T_inv = w.T, w.T_inv
    T_inv_t = T_inv.swapaxes(-1, -2)
    P, common_P = fused.P, fused.common_P
    if fused.diagonal:  # column and row scalings instead of products
        K_a = (T * fused.K_a[..., None, :]) @ T_inv
        roots = np.sqrt(np.stack([fused.A, fused.B], axis=-2))[..., None]
        information = gram(np.swapaxes(roots * T_inv[..., None, :, :], -1, -2))
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
    if not positive_definite(P):
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


# --------------------------------------------------------------------------- one problem
_dpotrf, _dtrtri, _dsyevd = lapack.dpotrf, lapack.dtrtri, lapack.dsyevd
_dgeqrf, _dorgqr = lapack.dgeqrf, lapack.dorgqr


def _factor(M, name):
    """Lower Cholesky factor of one SPD matrix with finite entries (LAPACK directly;
    on failure the error of ``cholesky``)."""
    L, info = _dpotrf(M, lower=1)
    if info != 0:
        return cholesky(M, name)  # raises with the message of the failure
    return L


def _lower_inverse(L):
    """Inverse of one nonsingular lower triangular matrix."""
    L_inv, info = _dtrtri(L, lower=1)
    if info != 0:
        return lower_inverse(L)
    return L_inv


def _orthonormal_columns_one(Y):
    """Householder ``Q`` of one nonsingular ``Y``: its first k columns span Y's first k."""
    qr, tau, _, _ = _dgeqrf(Y)
    Q, _, _ = _dorgqr(qr, tau)
    return Q


def _whiten_one(est, factor):
    """:func:`whiten` for one problem (2-D arrays, LAPACK called directly)."""
    P, L, x = est.P, est.L, est.x
    Pa, Pb, La, Lb = P[0], P[1], L[0], L[1]
    S = Pa + Pb
    Ls = _factor(S, "Pa + Pb")
    Ls_inv = _lower_inverse(Ls)
    D = Ls_inv @ (Pa - Pb) @ Ls_inv.T
    delta, W, info = _dsyevd(D + D.T, lower=1)  # eigenvalues of 2 D (scale irrelevant)
    if info != 0:
        delta, W = np.linalg.eigh(0.5 * (D + D.T))
    W, delta = W[:, ::-1], delta[::-1]  # set B (c^2 > s^2) first, then A
    G = Ls @ W
    Ya, Yb = _lower_inverse(La) @ G, _lower_inverse(Lb) @ G
    q_a, q_b = (Ya * Ya).sum(axis=0), (Yb * Yb).sum(axis=0)
    root = np.sqrt(q_a)
    T = G / root
    T_inv = root[:, None] * (W.T @ Ls_inv)
    ab = x @ T_inv.T
    if not factor:
        return Whitened(T, T_inv, q_a / q_b, ab[0], ab[1], None, None)
    n = G.shape[-1]
    m_a = n - int(np.count_nonzero(delta > 0))
    F = np.empty((n, n))
    if m_a:
        F[:, :m_a] = La @ _orthonormal_columns_one(Ya[:, ::-1])[:, :m_a]
    if m_a < n:
        F[:, m_a:] = (Lb @ _orthonormal_columns_one(Yb)[:, :n - m_a])[:, ::-1]
    return Whitened(T, T_inv, q_a / q_b, ab[0], ab[1], F, S)


def _ei_information_one(est, eps, mutual_mean):
    """EI with the information regulariser for one problem: x, P, gains and info.

    The formulas of :func:`fuse_diagonal` (with :func:`mean_ratio`), :func:`psi_at_ei`
    and :func:`to_original` (diagonal case) written for 2-D arrays.
    """
    w = _whiten_one(est, True)
    d, a, b, T, T_inv, F = w.d, w.a, w.b, w.T, w.T_inv, w.F
    n = d.shape[0]
    lam = 1.0 / d
    alpha, beta = np.maximum(0.0, 1.0 - lam), np.maximum(0.0, lam - 1.0)
    regular = 0.5 * eps * (1.0 + lam)
    w_a, w_b = alpha + regular, beta + regular
    total = w_a + w_b
    own = w_a if mutual_mean == "as-printed" else w_b
    if total.all():
        R_a = own / total
    else:
        R_a = np.where(total > 0, own / np.where(total > 0, total, 1.0), 0.5)
    R_b = 1.0 - R_a
    m = R_a * a + R_b * b
    k_a = np.where(d >= 1.0, 1.0 - R_a / np.maximum(d, 1.0), d * R_b)
    common_info = np.minimum(1.0, lam)
    eta = np.empty((2, n))
    eta[0] = a - common_info * m
    eta[1] = lam * b - common_info * m
    P = F @ F.T
    P += P.T
    P *= 0.5
    common_P = w.S - P
    common_P += common_P.T
    common_P *= 0.5
    gains = np.empty((2, n, n))
    K_a = np.matmul(T * k_a, T_inv, out=gains[0])
    np.negative(K_a, out=gains[1])
    gains[1].flat[::n + 1] += 1.0
    roots = np.empty((2, n, 1))
    roots[0, :, 0], roots[1, :, 0] = alpha, beta
    roots = np.sqrt(roots) * T_inv  # (2, n, n)
    information = roots.swapaxes(-1, -2) @ roots
    information += information.swapaxes(-1, -2)
    information *= 0.5
    x = K_a @ est.x[0] + gains[1] @ est.x[1]
    tie = np.abs(np.log(d)) <= eps
    agree = a == b
    if mutual_mean == "sijs-lazar":
        agree |= ~tie
    info = {"common_x": T @ m, "common_P": common_P, "independent_information": information,
            "independent_information_vector": eta @ T_inv,
            "psi": np.array(0.0 if agree.all() else np.inf),
            "ties": np.count_nonzero(tie)}
    return x, P, gains, info


def _check_one_result(P, est):
    """:func:`check_result` for one problem."""
    if np.isfinite(P).all() and _dpotrf(P, lower=1)[1] == 0:
        return
    check_result(P[None], est)


# --------------------------------------------------------------------------- the EI rule
def ei_fusion(est, eps, mutual_mean, regularizer):
    """EI of two validated estimates (eqs. (7)-(8), (11)-(13)): ``(x, P, gains, info)``.

    ``est`` holds exactly two estimates and the options are checked (see
    :func:`check_options`). ``x`` is in row form (..., n); ``info`` holds ``common_x``,
    ``common_P``, ``independent_information``, ``independent_information_vector``,
    ``psi``, ``ties``, ``mutual_mean``, ``regularizer`` and ``eps`` as documented by
    :func:`cifilter.ellipsoidal_intersection`. Raises ``IllConditionedError`` rather than
    return a ``P`` that is not finite and positive definite.
    """
    covariance = regularizer == "covariance" and eps > 0
    tie_eps = eps if regularizer == "information" else 0.0
    if not est.batch_shape and not covariance:
        x, P, gains, info = _ei_information_one(est, tie_eps, mutual_mean)
        _check_one_result(P, est)
    else:
        w = whiten(est, factor=not covariance)
        fused, psi = ei_in_whitened(w, eps, mutual_mean, regularizer)
        x, P, gains, info = to_original(w, fused, est.x)
        check_result(P, est)
        info.update(psi=psi, ties=ties(w.d, tie_eps).sum(-1))
    info.update(mutual_mean=mutual_mean, regularizer=regularizer, eps=eps)
    return x, P, gains, info


# --------------------------------------------------------------------------- largest ellipsoid
def largest_ellipsoid_fusion(est):
    """Largest-ellipsoid (safe) fusion of two validated estimates: ``(x, P, gains, info)``.

    In the coordinates of :func:`whiten` (``Pa = T T^T``, ``Pb = T diag(d) T^T``) each
    direction keeps the more informative input: the coordinate of ``a`` where ``d > 1``,
    that of ``b`` where ``d < 1`` and their average where ``d == 1``; the covariance is
    ``T diag(min(1, d)) T^T = F F^T``, EI's (Benaskeur 2002; Nygårds, Deleskog & Hendeby
    2016). ``x`` is in row form; ``info`` holds ``kept`` (..., n), the share of ``a`` per
    direction (1, 0 or 1/2) and ``ties`` (..., ), the number of directions with ``d == 1``.
    Raises ``IllConditionedError`` rather than return a ``P`` that is not positive definite.
    """
    w = whiten(est, factor=True)
    kept = np.where(w.d > 1.0, 1.0, np.where(w.d < 1.0, 0.0, 0.5))
    K_a = (w.T * kept[..., None, :]) @ w.T_inv
    gains = np.stack([K_a, np.eye(K_a.shape[-1]) - K_a], axis=-3)
    x = np.einsum("...kij,...kj->...i", gains, est.x)
    P = gram(w.F)
    if est.batch_shape:
        check_result(P, est)
    else:
        _check_one_result(P, est)
    return x, P, gains, {"kept": kept, "ties": np.count_nonzero(w.d == 1.0, axis=-1)}
