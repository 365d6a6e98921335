"""Inverse Covariance Intersection of two estimates: the bound as a fusion of inflated
covariances, its criterion derivatives in omega, and the certified optimum.

Inverse Covariance Intersection (Noack, Sijs, Reinhardt & Hanebeck 2017) fuses

    P^-1 = Pa^-1 + Pb^-1 - Gamma^-1,   Gamma = omega Pa + (1 - omega) Pb,

with gains ``Ka = P (Pa^-1 - omega Gamma^-1)``, ``Kb = P (Pb^-1 - (1 - omega) Gamma^-1)``.
Written as it stands, ``P^-1`` is a difference of information matrices and cancels. The
same ``P`` and gains are (``docs/methods/ici.rst``, "Numerical formulation")

    P^-1 = (1 - omega) Ya^-1 + omega Yb^-1,
    Ya = (1 - omega) Pa + omega Pa Pb^-1 Pa,   Yb = omega Pb + (1 - omega) Pb Pa^-1 Pb,

a weighted information fusion of two covariances that are sums of positive semidefinite
terms: ``K_a = (1 - omega) P Ya^-1``, ``K_b = omega P Yb^-1``. For *any* gains with
``Ka + Kb = I`` and ``t = omega / (1 - omega)``,

    B = Ka Pa Ka^T + Kb Pb Kb^T + t Ka Pa Pb^-1 Pa Ka^T + Kb Pb Pa^-1 Pb Kb^T / t
      = Ka Ya Ka^T / (1 - omega) + Kb Yb Kb^T / omega

bounds the error covariance under the common-information model (every cross-covariance
``Pab = Pa C Pb`` with ``0 <= C <= Pa^-1, C <= Pb^-1``), and for the ICI gains ``B`` is
ICI's ``P``.

The returned fusion (:func:`inverse_ci_fusion`) does *not* go through ``Ya`` and ``Yb``:
their condition numbers reach ``cond(Pa)^2 cond(Pb)``, far beyond what float64 resolves at
condition numbers of 1e9, and gains from their information were off by orders of magnitude
(issue 21). The gains are computed where every quantity is bounded, in the coordinates that
whiten ``Gamma`` (:func:`_whitened_gains`), and ``P`` is ``B`` of those gains computed from
the *inputs* (:func:`common_information_bound`: the products ``Ka Pa``, ``Kb Pb`` as if in
twice the working precision, the rest in extended precision, one rounding at the end). So
the returned ``P`` is the bound of the returned gains to its own rounding in every
direction (measured against 50-digit references: ``docs/methods/ici.rst``). The factors of
``Ya`` and ``Yb`` (QR factorisations of their stacked square-root factors) serve the
derivatives in omega of the robust solver below; its certificate also takes the slope in
the whitened coordinates (:func:`whitened_certificate_slope`).

The criteria ``trace(W P)`` and ``log det P`` are convex in omega (in the basis that
diagonalises Pa and Pb every eigenvalue of ``P`` is a convex linear-fractional function
of omega, and so is its logarithm); their derivatives are

    dP/domega = -P Gamma^-1 (Pa - Pb) Gamma^-1 P,

and the minimum is found by the safeguarded Newton iteration of
:func:`cifilter._numerics.optimize.minimize_convex_interval` and certified by its gap.
"""

from typing import NamedTuple

import numpy as np

from .._numerics.criteria import (
    GAP_TOL,
    SLOPE_ROUNDING,
    GapCertificate,
    criterion_of_factor,
    gap_converged,
    pair_certificate,
    rounding_scale,
    scaled_condition,
)
from .._numerics.information import (
    DIAGONAL_TRUST,
    checked_cholesky,
    diagonal_spread_squared,
    information_factors,
    lower_inverse_stack,
    squared_norms,
)
from .._numerics.optimize import minimize_convex_interval, minimize_convex_scalar

__all__ = ["InversePair", "common_information_bound", "inverse_ci_derivatives",
           "inverse_ci_fusion", "inverse_ci_pair", "optimal_inverse_omega"]


class InversePair(NamedTuple):
    """Precomputed factors of two-estimate problems (batch flattened to one axis)."""

    x: np.ndarray  # (size, 2, n)
    La: np.ndarray  # (size, n, n) Cholesky factor of Pa
    Lb: np.ndarray  # (size, n, n) Cholesky factor of Pb
    Fa: np.ndarray  # (size, n, n) Pa Lb^-T: Pa Pb^-1 Pa = Fa Fa^T
    Fb: np.ndarray  # (size, n, n) Pb La^-T: Pb Pa^-1 Pb = Fb Fb^T
    Pa: np.ndarray  # (size, n, n)
    Pb: np.ndarray  # (size, n, n)


def inverse_ci_pair(x, P, L):
    """The factors of :class:`InversePair` for estimates ``x`` (..., 2, n), ``P``, ``L``."""
    n = x.shape[-1]
    x = x.reshape((-1, 2, n))
    P = P.reshape((-1, 2, n, n))
    L = L.reshape((-1, 2, n, n))
    L_inv = lower_inverse_stack(L)
    Pa, Pb = P[:, 0], P[:, 1]
    Fa = Pa @ L_inv[:, 1].swapaxes(-1, -2)
    Fb = Pb @ L_inv[:, 0].swapaxes(-1, -2)
    return InversePair(x, L[:, 0], L[:, 1], Fa, Fb, Pa, Pb)


def _stacked_factor(A, B, a, b):
    """Lower factor ``L`` (size, n, n) with ``L L^T = a A A^T + b B B^T`` by a QR of the
    stacked square roots ``[sqrt(a) A, sqrt(b) B]^T`` (nothing is squared)."""
    stacked = np.concatenate([np.sqrt(a)[:, None, None] * A, np.sqrt(b)[:, None, None] * B],
                             axis=-1)
    R = np.linalg.qr(stacked.swapaxes(-1, -2), mode="r")  # (size, n, n) upper, R^T R = S S^T
    # A positive diagonal (the Cholesky factor's sign convention) and a lower factor
    signs = np.where(np.diagonal(R, axis1=-2, axis2=-1) < 0.0, -1.0, 1.0)
    return (R * signs[..., :, None]).swapaxes(-1, -2)


def _inflated_factors(pair, omega):
    """Factors ``(L_Ya, L_Yb)`` of the inflated covariances at ``omega`` (size,)."""
    one = 1.0 - omega
    L_Ya = _stacked_factor(pair.La, pair.Fa, one, omega)
    L_Yb = _stacked_factor(pair.Lb, pair.Fb, omega, one)
    return np.stack([L_Ya, L_Yb], axis=1)


def _information_at(pair, omega, failures="raise"):
    L_Y = _inflated_factors(pair, omega)
    L_Y_inv = lower_inverse_stack(L_Y)
    weights = np.stack([1.0 - omega, omega], axis=-1)
    factors = information_factors(L_Y_inv, weights, failures=failures)
    return L_Y, L_Y_inv, weights, factors


def _whitened_gains(pair, omega):
    """ICI gains ``(Ka, Kb)`` (size, n, n) at ``omega`` (size,), computed in the coordinates
    that whiten ``Gamma = omega Pa + (1 - omega) Pb = G G^T``.

    With ``X = G^-1 Pa G^-T`` and ``Y = G^-1 Pb G^-T``, ``omega X + (1 - omega) Y = I``: X and Y
    commute, and in the eigenbasis ``U`` of X (eigenvalues ``x``, ``y``, both in
    ``[0, 1 / omega]`` and ``[0, 1 / (1 - omega)]``) the whitened gains are the scalars
    ``kb = omega x^2 / (omega x^2 + (1 - omega) y^2)`` and ``ka = 1 - kb`` (the ICI equations
    in that basis). Every quantity here is bounded, so rounding stays of order eps in the
    whitened gains; ``Kb = G U diag(kb) U^T G^-1``. ``G`` comes from a QR factorisation of
    ``[sqrt(omega) La, sqrt(1 - omega) Lb]`` (nothing is squared). The gain of the estimate
    of larger weight (``1 - omega`` for a, ``omega`` for b) is ``I`` minus the other, so the
    gains sum to the identity to rounding; at ``omega = 0`` or ``1`` they are exactly
    ``(I, 0)`` or ``(0, I)``.
    """
    n = pair.x.shape[-1]
    G, G_inv, U, x, y = _whitened(pair, omega)
    w = omega[:, None]
    a_part, b_part = w * x * x, (1.0 - w) * y * y
    with np.errstate(invalid="ignore", divide="ignore"):
        total = a_part + b_part
        kb = np.where(total > 0.0, a_part / total, w)
        ka = np.where(total > 0.0, b_part / total, 1.0 - w)
    eye = np.broadcast_to(np.eye(n), G.shape)
    Ka_direct = G @ ((U * ka[:, None, :]) @ U.swapaxes(-1, -2)) @ G_inv
    Kb_direct = G @ ((U * kb[:, None, :]) @ U.swapaxes(-1, -2)) @ G_inv
    # The reference is the estimate whose gain is the larger: the smaller gain is computed
    # directly (its error is then small relative to it) and the reference's is I minus it.
    # (Choosing by omega >= 0.5 made I - K the *small* gain when a fixed omega far from the
    # optimum meets covariances of very different scales: its absolute error eps, against
    # entries of 1e-24, broke B_t(K) by factors up to 1e34; issue 21.)
    b_reference = (squared_norms(Ka_direct) <= squared_norms(Kb_direct))
    b_reference = np.where(omega == 0.0, False, np.where(omega == 1.0, True, b_reference))
    b_reference = b_reference[:, None, None]
    K_small = np.where(b_reference, Ka_direct, Kb_direct)
    Ka = np.where(b_reference, K_small, eye - K_small)
    Kb = np.where(b_reference, eye - K_small, K_small)
    return Ka, Kb


def _whitened(pair, omega, spread=False):
    """``G, G^-1, U, x, y`` of the coordinates that whiten ``Gamma = G G^T`` at ``omega``
    (:func:`_whitened_gains`): ``G^-1 Pa G^-T = U diag(x) U^T``, ``G^-1 Pb G^-T = U diag(y)
    U^T`` with ``omega x + (1 - omega) y = 1``; both Rayleigh quotients from their own
    factors (no ``1 - omega x`` cancellation). ``U`` is the eigenbasis of ``X = G^-1 Pa
    G^-T``; with ``spread``, of ``Y = G^-1 Pb G^-T`` where ``omega >= 1/2``: there
    ``X = (I - (1 - omega) Y) / omega`` has its eigenvalues within ``(1 - omega) / omega``
    times ``Y``'s spread of 1 (all 1 at ``omega = 1``), so its eigenvectors are the less
    well determined (and ``Y``'s where ``omega < 1/2``, all 1 at ``omega = 0``)."""
    G = _stacked_factor(pair.La, pair.Lb, omega, 1.0 - omega)
    G_inv = lower_inverse_stack(G)
    Aa, Ab = G_inv @ pair.La, G_inv @ pair.Lb
    A = np.where((omega >= 0.5)[:, None, None], Ab, Aa) if spread else Aa
    X = A @ A.swapaxes(-1, -2)
    _, U = np.linalg.eigh(0.5 * (X + X.swapaxes(-1, -2)))
    x = _column_squared_norms(Aa.swapaxes(-1, -2) @ U)
    y = _column_squared_norms(Ab.swapaxes(-1, -2) @ U)
    return G, G_inv, U, x, y


def _column_squared_norms(A):
    """Squared Euclidean norms of the columns of ``A`` (..., m, k): shape (..., k)."""
    return np.square(A).sum(axis=-2)


def _extended_cholesky(A):
    """Lower Cholesky factor (size, n, n) of the float matrices ``A`` in ``longdouble``.

    The rows are the loop (the batch is vectorised). ``A`` is taken exactly (every float is
    a ``longdouble``), so the factor's backward error is of order ``eps_ld |L| |L|^T``
    (``eps_ld`` 5.4e-20 on x86), 2048 times below that of a float64 factor. A pivot that
    is not positive (not expected for validated inputs) gives NaN, which the caller's
    positive-definiteness check of the result turns into IllConditionedError.
    """
    A = A.astype(np.longdouble)
    n = A.shape[-1]
    L = np.zeros_like(A)
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(n):
            pivot = A[:, j, j] - np.square(L[:, j, :j]).sum(axis=-1)
            L[:, j, j] = np.sqrt(np.where(pivot > 0.0, pivot, np.nan))
            if j + 1 < n:
                below = A[:, j + 1:, j] - np.einsum("...ik,...k->...i", L[:, j + 1:, :j],
                                                     L[:, j, :j])
                L[:, j + 1:, j] = below / L[:, j, j][:, None]
    return L


def _extended_solve(L, B):
    """``L^-1 B`` (size, n, m) by forward substitution in ``longdouble`` (``L`` lower)."""
    Y = np.zeros(B.shape, dtype=np.longdouble)
    for i in range(L.shape[-1]):
        partial = np.einsum("...k,...km->...m", L[:, i, :i], Y[:, :i, :])
        Y[:, i, :] = (B[:, i, :] - partial) / L[:, i, i][:, None]
    return Y


def _split(a):
    """Dekker's split of float64 ``a`` into ``hi + lo`` of at most 26 significant bits
    each, so that the product of two such halves is exact in float64."""
    c = 134217729.0 * a  # 2^27 + 1
    hi = c - (c - a)
    return hi, a - hi


def _two_sum(a, b):
    """Knuth's error-free sum: ``s + e == a + b`` exactly, ``s = fl(a + b)``."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _compensated_product(K, P):
    """``K @ P`` (size, n, n) of float64 matrices, as if accumulated in twice the working
    precision, returned in ``longdouble``.

    Ogita, Rump & Oishi's Dot2 in float64: each product of two floats is split exactly
    into ``p + e`` (Dekker's TwoProduct, with :func:`_split`), the products are summed by
    Knuth's TwoSum (:func:`_two_sum`) and the errors accumulated beside; ``s + c`` carries
    the result with an error of at most ``eps |K P| + (n eps)^2 |K| |P|`` (Ogita, Rump &
    Oishi 2005, Theorem 5.3). The gains nearly annihilate the large directions of the
    inputs: ``|K| |P|`` exceeds ``|K P|`` by up to 1e19 at condition numbers of 1e12, beyond
    what one ``longdouble`` accumulation (``eps_ld |K| |P|``, ``eps_ld`` 5.4e-20) resolves.
    """
    Kh, Kl = _split(K)
    Ph, Pl = _split(P)
    total = np.zeros(K.shape[:-1] + P.shape[-1:])
    carry = np.zeros_like(total)
    for k in range(K.shape[-1]):
        a, ah, al = K[..., :, k, None], Kh[..., :, k, None], Kl[..., :, k, None]
        b, bh, bl = P[..., None, k, :], Ph[..., None, k, :], Pl[..., None, k, :]
        product = a * b
        error = ((ah * bh - product) + ah * bl + al * bh) + al * bl
        total, sum_error = _two_sum(total, product)
        carry += sum_error + error
    return total.astype(np.longdouble) + carry.astype(np.longdouble)


def common_information_bound(pair, omega, Ka, Kb):
    """``B_t(K)`` (size, n, n) of gains ``Ka + Kb = I`` at ``t = omega / (1 - omega)``.

    ``B_t(K) = Ka Pa Ka^T + Kb Pb Kb^T + t Ka Pa Pb^-1 Pa Ka^T + Kb Pb Pa^-1 Pb Kb^T / t``.
    With ``Ra = Ka Pa`` and ``Rb = Kb Pb`` every term is of the form ``R X^-1 R^T``
    (``Ka Pa Ka^T = Ra Pa^-1 Ra^T``), so ``B_t(K)`` is the sum of four outer products
    ``M M^T`` with ``M^T = La^-1 Ra^T``, ``Lb^-1 Rb^T``, ``sqrt(t) Lb^-1 Ra^T`` and
    ``La^-1 Rb^T / sqrt(t)``, ``La``, ``Lb`` the Cholesky factors of the *inputs* (a zero
    gain contributes nothing). It bounds the error covariance of these gains for every
    admissible common information (``docs/methods/ici.rst``), whatever rounding went into
    the gains.

    The only cancellation is in ``Ra`` and ``Rb`` (the gains nearly annihilate the large
    directions of the inputs): they are formed by :func:`_compensated_product`. The rest
    is in extended precision (``longdouble``: the factors by :func:`_extended_cholesky`,
    the triangular solves by :func:`_extended_solve`, backward stable, so they perturb the
    inputs by ``eps_ld`` relatively), and ``P`` is rounded to float64 once
    (``docs/methods/ici.rst``, "Numerical formulation").
    """
    ld = np.longdouble
    La, Lb = _extended_cholesky(pair.Pa), _extended_cholesky(pair.Pb)
    Ra_T = _compensated_product(Ka, pair.Pa).swapaxes(-1, -2)
    Rb_T = _compensated_product(Kb, pair.Pb).swapaxes(-1, -2)
    w = omega.astype(ld)
    inside = ((omega > 0.0) & (omega < 1.0))[:, None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        root_t = np.where(inside, np.sqrt(w / (1.0 - w))[:, None, None], 0.0).astype(ld)
        root_s = np.where(inside, np.sqrt((1.0 - w) / w)[:, None, None], 0.0).astype(ld)
    factors = [_extended_solve(La, Ra_T), _extended_solve(Lb, Rb_T)]
    factors.append(root_t * _extended_solve(Lb, Ra_T))
    factors.append(root_s * _extended_solve(La, Rb_T))
    P = np.zeros(Ka.shape, dtype=ld)
    for F in factors:  # F = M^T
        P += F.swapaxes(-1, -2) @ F
    return (0.5 * (P + P.swapaxes(-1, -2))).astype(float)


def inverse_ci_fusion(pair, omega):
    """ICI at ``omega`` (size,): ``(x, P, gains)``, ``P`` the bound ``B_t(K)`` of the gains.

    The gains come from the whitened form (:func:`_whitened_gains`), ``P`` from the gains
    and the inputs (:func:`common_information_bound`). Raises IllConditionedError
    where ``P`` is not numerically positive definite (checked by the caller's report).
    """
    Ka, Kb = _whitened_gains(pair, omega)
    xa, xb = pair.x[:, 0], pair.x[:, 1]
    # x = Ka xa + Kb xb = x_ref + K_other (x_other - x_ref), the reference the estimate of
    # the larger gain (as in :func:`_whitened_gains`)
    b_reference = (squared_norms(Ka) <= squared_norms(Kb))[:, None]
    diff_a = (Ka @ (xa - xb)[..., None])[..., 0]
    diff_b = (Kb @ (xb - xa)[..., None])[..., 0]
    x = np.where(b_reference, xb + diff_a, xa + diff_b)
    P = common_information_bound(pair, omega, Ka, Kb)
    return x, P, np.stack([Ka, Kb], axis=1)


def inverse_ci_derivatives(pair, omega, kind, W, *, rounding=False):
    """``(f, f', f'')`` of ``f = trace(W P)`` or ``log det P`` at ``omega`` (size,).

    With ``P = Lp Lp^T``, ``Gamma = G G^T``, ``Z = G^-1 Lp``, ``A_a = G^-1 La``,
    ``S_a = A_a^T Z`` (and likewise for b), ``N = Lp^T Gamma^-1 (Pa - Pb) Gamma^-1 Lp =
    S_a^T S_a - S_b^T S_b`` and ``E = A_a A_a^T - A_b A_b^T``:

    * ``trace(W P)``: ``f' = -trace(W Lp N Lp^T)``,
      ``f'' = 2 trace(W Lp (N N + Z^T E E Z) Lp^T)``;
    * ``log det P``: ``f' = -trace(N)``, ``f'' = ||N||^2 + 2 ||E Z||^2``.

    The slopes are differences of two nonnegative terms (no other cancellation). Problems
    whose fused information is numerically singular get NaN.

    With ``rounding=True`` a fourth array is returned: ``4 (n + 1) eps (kappa_s(J) +
    kappa_s(Gamma) + kappa_s(Pa) + kappa_s(Pb))`` times the sum of the slope's two terms
    (``kappa_s`` the scaled condition numbers,
    :func:`cifilter._numerics.criteria.scaled_condition`, of the fused information
    ``J = P^-1``, of ``Gamma`` and of the inputs): what a relative perturbation of order
    eps of these matrices moves the slope by (as
    :func:`cifilter._numerics.criteria.gradient_rounding` for CI). It does not cover the
    rounding of this formulation itself, whose inflated covariances square condition
    numbers: on 300 mixed-scale pairs at condition numbers 1e9..1e12 the slope at the
    returned omega was outside it in 37 pairs; the robust path's certificate therefore
    joins it with :func:`whitened_certificate_slope` (``docs/methods/ici.rst``).
    """
    _, _, _, factors = _information_at(pair, omega, failures="nan")
    Lp = factors.R_inv.swapaxes(-1, -2)  # P = R_inv^T R_inv = Lp Lp^T
    gamma = omega[:, None, None] * pair.Pa + (1.0 - omega)[:, None, None] * pair.Pb
    G = checked_cholesky(gamma, "Gamma = omega Pa + (1 - omega) Pb", failures="nan")
    G_inv = lower_inverse_stack(G)
    Z = G_inv @ Lp
    Aa, Ab = G_inv @ pair.La, G_inv @ pair.Lb
    Sa, Sb = Aa.swapaxes(-1, -2) @ Z, Ab.swapaxes(-1, -2) @ Z
    N = Sa.swapaxes(-1, -2) @ Sa - Sb.swapaxes(-1, -2) @ Sb
    E = Aa @ Aa.swapaxes(-1, -2) - Ab @ Ab.swapaxes(-1, -2)
    EZ = E @ Z
    f = criterion_of_factor(factors.R_inv, kind, W)
    if kind == "det":
        terms = squared_norms(Sb), squared_norms(Sa)
        curvature = squared_norms(N) + 2.0 * squared_norms(EZ)
    else:
        LSa, LSb = Lp @ Sa.swapaxes(-1, -2), Lp @ Sb.swapaxes(-1, -2)
        LN, LZE = Lp @ N, Lp @ EZ.swapaxes(-1, -2)
        if kind == "trace":
            terms = squared_norms(LSb), squared_norms(LSa)
            curvature = 2.0 * (squared_norms(LN) + squared_norms(LZE))
        else:
            def weighted(M):
                return np.einsum("...ij,...ik,...jk->...", W, M, M)

            terms = weighted(LSb), weighted(LSa)
            curvature = 2.0 * (weighted(LN) + weighted(LZE))
    slope = terms[0] - terms[1]
    if not rounding:
        return f, slope, curvature
    n = pair.x.shape[-1]
    with np.errstate(all="ignore"):
        kappa = (scaled_condition(factors.R, factors.R_inv) + scaled_condition(G, G_inv)
                 + scaled_condition(pair.La, lower_inverse_stack(pair.La))
                 + scaled_condition(pair.Lb, lower_inverse_stack(pair.Lb)))
        error = 4.0 * (n + 1) * _EPS * kappa * (np.abs(terms[0]) + np.abs(terms[1]))
    return f, slope, curvature, error


_EPS = float(np.finfo(float).eps)


def whitened_certificate_slope(pair, omega, kind, W):
    """``(f, f', e)`` at ``omega`` (size,) in the coordinates that whiten ``Gamma``.

    With ``Gamma = G G^T``, ``G^-1 Pa G^-T = U diag(x) U^T``, ``G^-1 Pb G^-T = U diag(y)
    U^T`` (:func:`_whitened`; ``omega x + (1 - omega) y = 1``), ICI's covariance is
    ``P = G U diag(p) U^T G^T`` with ``p = x y / (omega x^2 + (1 - omega) y^2)`` (``1/p =
    1/x + 1/y - 1``, and ``x + y - x y = omega x^2 + (1 - omega) y^2`` on the constraint:
    no cancellation), and ``dP/domega = -G U diag(p^2 (x - y)) U^T G^T``. So, with
    ``c_k = u_k^T G^T W G u_k``,

    * ``trace(W P) = sum c p``, ``f' = sum c p^2 y - sum c p^2 x``;
    * ``log det P = log det Gamma + sum log p``, ``f' = sum p y - sum p x``:

    sums of nonnegative terms, every whitened quantity in ``[0, 1 / min(omega, 1 -
    omega)]``. Unlike :func:`inverse_ci_derivatives` nothing goes through the inflated
    covariances ``Ya``, ``Yb`` (condition numbers up to ``kappa^3``). ``e`` is the same
    term as there, ``4 (n + 1) eps (kappa_s(J) + kappa_s(Gamma) + kappa_s(Pa) +
    kappa_s(Pb))`` times the sum of the slope's two terms: what a relative perturbation eps
    of these matrices moves the slope by. It is not a derived bound of this formulation's
    own rounding (the eigenvectors ``U``): on 300 mixed-scale pairs at condition numbers
    1e9..1e12 the 50-digit slope was outside ``f' +- e`` in 17 (trace; 0 for log det)
    (``docs/methods/ici.rst``). Problems whose whitened quantities are not finite get NaN.
    """
    n = pair.x.shape[-1]
    with np.errstate(all="ignore"):
        G, G_inv, U, x, y = _whitened(pair, omega, spread=True)
        w = omega[:, None]
        p = x * y / (w * x * x + (1.0 - w) * y * y)
        GU = G @ U
        if W is None:
            c = _column_squared_norms(GU)
        else:
            c = np.einsum("...ik,...ij,...jk->...k", GU, W, GU)
        if kind == "det":
            f = 2.0 * np.log(np.diagonal(G, axis1=-2, axis2=-1)).sum(axis=-1) \
                + np.log(p).sum(axis=-1)
            terms = (p * y).sum(axis=-1), (p * x).sum(axis=-1)
        else:
            f = (c * p).sum(axis=-1)
            terms = (c * p * p * y).sum(axis=-1), (c * p * p * x).sum(axis=-1)
        slope = terms[0] - terms[1]
        # J = P^-1 = F F^T with F = G^-T U diag(p^-1/2): its lower factor by a QR (nothing
        # squared), for the scaled condition of the fused information
        F = G_inv.swapaxes(-1, -2) @ (U / np.sqrt(p)[:, None, :])
        R = _stacked_factor(F, np.zeros_like(F), np.ones_like(omega), np.zeros_like(omega))
        kappa = (scaled_condition(R, lower_inverse_stack(R)) + scaled_condition(G, G_inv)
                 + scaled_condition(pair.La, lower_inverse_stack(pair.La))
                 + scaled_condition(pair.Lb, lower_inverse_stack(pair.Lb)))
        error = 4.0 * (n + 1) * _EPS * kappa * (np.abs(terms[0]) + np.abs(terms[1]))
    return f, slope, error


def _diagonal_slope_rounding(lam, omega, c, sigma):
    """A bound of the rounding in the diagonalised slope (:func:`_diagonalised`), as
    :func:`cifilter._numerics.criteria.slope_rounding` for CI: the eigenvalues carry
    absolute rounding ``eps sigma`` and the slope moves by at most
    ``SLOPE_ROUNDING n eps sigma sum_k |dt_k / dlam_k|``, with ``t_k`` the slope's terms:
    ``-c lam^2 (1 - lam) / D^2`` (trace; ``D = omega + (1 - omega) lam^2``), whose derivative
    is ``-c ((2 lam - 3 lam^2) D - 4 (1 - omega) lam^3 (1 - lam)) / D^3``, and
    ``(1 - lam) / g - (1 - lam^2) / D`` (det; ``g = omega + (1 - omega) lam``), whose
    derivative is ``2 lam / D^2 - 1 / g^2``.
    """
    n = lam.shape[-1]
    w = np.asarray(omega, dtype=float)[..., None]
    with np.errstate(all="ignore"):
        D = w + (1.0 - w) * lam * lam
        if c is None:
            g = w + (1.0 - w) * lam
            sensitivity = np.abs(2.0 * lam / (D * D) - 1.0 / (g * g))
        else:
            sensitivity = np.abs(c) * np.abs((2.0 * lam - 3.0 * lam * lam) * D
                                             - 4.0 * (1.0 - w) * lam**3 * (1.0 - lam)) / D**3
        return SLOPE_ROUNDING * n * _EPS * np.asarray(sigma) * sensitivity.sum(axis=-1)


def _diagonalised(pair, kind, W):
    """Proposal, iterations, certificate and trust of the diagonalised problem (size,).

    With ``Pa = La La^T`` and ``La^-1 Pb La^-T = U diag(lam) U^T``, ``T = La U``
    diagonalises both covariances and ``P(omega) = T diag(d) T^T`` with
    ``d = lam g / D``, ``g = omega + (1 - omega) lam``, ``D = omega + (1 - omega) lam^2``:

    * ``trace(W P) = sum_k c_k d_k`` (``c = diag(T^T W T)``), ``d' = -lam^2 (1 - lam) / D^2``,
      ``d'' = 2 lam^2 (1 - lam)^2 (1 + lam) / D^3``;
    * ``log det P = log det Pa + sum_k log d_k``, ``(log d)' = (1 - lam) / g -
      (1 - lam^2) / D``, ``(log d)'' = (1 - lam^2)^2 / D^2 - (1 - lam)^2 / g^2``.

    O(n) per Newton iteration. As for CI, the eigenvalues are accurate only where their
    spread and the squared diagonal spread of both Cholesky factors are at most
    ``DIAGONAL_TRUST``; elsewhere the problem is not ``trusted``. The certificate takes the
    rounding of the slope into account (:func:`_diagonal_slope_rounding`); a problem it
    does not show converged is not ``trusted`` either (the robust path decides).
    """
    size, n = pair.x.shape[0], pair.x.shape[-1]
    La_inv = lower_inverse_stack(pair.La)
    S = La_inv @ pair.Pb @ La_inv.swapaxes(-1, -2)
    lam, U = np.linalg.eigh(0.5 * (S + S.swapaxes(-1, -2)))
    usable = np.all(lam > 0.0, axis=-1) & np.all(np.isfinite(lam), axis=-1)
    lam = np.where(usable[:, None], lam, 1.0)
    one = 1.0 - lam
    if kind == "det":
        def derivatives(omega, index):
            w, lk, ok = omega[:, None], lam[index], one[index]
            g, D = w + (1.0 - w) * lk, w + (1.0 - w) * lk * lk
            a, b = ok / g, ok * (1.0 + lk) / D
            return (a - b).sum(axis=-1), (b * b - a * a).sum(axis=-1)

        def value(omega):
            w = omega[:, None]
            return np.log(lam * (w + (1.0 - w) * lam) / (w + (1.0 - w) * lam * lam)).sum(-1)

        scale = np.full(size, float(n))
        c = None
    else:
        T = pair.La @ U
        if kind == "trace":
            c = np.square(T).sum(axis=-2)
        else:
            c = np.einsum("...ik,...ij,...jk->...k", T, W, T)

        def derivatives(omega, index):
            w, lk, ok, ck = omega[:, None], lam[index], one[index], c[index]
            D = w + (1.0 - w) * lk * lk
            first = -(ck * lk * lk * ok / (D * D)).sum(axis=-1)
            second = (2.0 * ck * lk * lk * ok * ok * (1.0 + lk) / D**3).sum(axis=-1)
            return first, second

        def value(omega):
            w = omega[:, None]
            return (c * lam * (w + (1.0 - w) * lam) / (w + (1.0 - w) * lam * lam)).sum(-1)

        scale = (c * (1.0 + lam)).sum(axis=-1)
    with np.errstate(all="ignore"):
        if size == 1:  # one problem: the same iteration in Python floats
            only = np.zeros(1, dtype=int)

            def derivative(w):
                first, second = derivatives(np.array([w]), only)
                return float(first[0]), float(second[0])

            w, count, _ = minimize_convex_scalar(derivative, scale=float(scale[0]))
            omega, iterations = np.array([w]), np.array([count])
        else:
            omega, iterations, _ = minimize_convex_interval(derivatives, size, scale=scale)
        slope, _ = derivatives(omega, np.arange(size))
        sigma = np.maximum(lam.max(axis=-1), rounding_scale(La_inv, pair.Pb))
        cert = pair_certificate(omega, slope, _diagonal_slope_rounding(lam, omega, c, sigma),
                                None if kind == "det" else value(omega))
        spread = lam.max(axis=-1) / lam.min(axis=-1)
    conditioning = np.maximum(diagonal_spread_squared(pair.La), diagonal_spread_squared(pair.Lb))
    trusted = (usable & (spread <= DIAGONAL_TRUST) & (conditioning <= DIAGONAL_TRUST)
               & gap_converged(*cert) & np.isfinite(omega))
    cert = GapCertificate(*(np.where(trusted, part, np.inf) for part in cert))
    return omega, iterations, cert, trusted


def optimal_inverse_omega(pair, kind, W):
    """Criterion-optimal omega per problem, certified.

    Problems whose simultaneous diagonalisation is trusted are solved and certified in
    the diagonal form (:func:`_diagonalised`); the others by the safeguarded Newton
    iteration on the derivatives of :func:`inverse_ci_derivatives`, from Cholesky and QR
    factors. Returns ``omega, iterations, certificate`` (size,): the
    :class:`~cifilter._numerics.criteria.GapCertificate` whose ``gap`` bounds the excess
    of the criterion over its minimum on [0, 1] (relative for the trace criteria, in log
    det for the determinant), the rounding of the slope included, and whose ``floor`` is
    that rounding's part (infinite where it could not be evaluated); converged is
    :func:`~cifilter._numerics.criteria.gap_converged` of it.
    """
    size, n = pair.x.shape[0], pair.x.shape[-1]
    Wf = None if W is None else np.broadcast_to(W, (size, n, n))
    omega, iterations, cert, trusted = _diagonalised(pair, kind, Wf)
    rest = np.flatnonzero(~trusted)
    if rest.size:
        sub = InversePair(*(array[rest] for array in pair))
        sub_omega, sub_iterations, sub_cert = _robust_omega(
            sub, kind, None if Wf is None else Wf[rest])
        omega[rest], iterations[rest] = sub_omega, sub_iterations
        for part, sub_part in zip(cert, sub_cert):
            part[rest] = sub_part
    return omega, iterations, cert


def _robust_omega(pair, kind, W):
    """:func:`optimal_inverse_omega` from Cholesky and QR factors (any conditioning)."""
    size, n = pair.x.shape[0], pair.x.shape[-1]
    Wf = W

    def subset(index):
        return InversePair(*(array[index] for array in pair))

    def derivatives(omega, index):
        _, slope, curvature = inverse_ci_derivatives(
            subset(index), omega, kind, None if Wf is None else Wf[index])
        # A numerically singular fused information: bisection decides (as for CI)
        bad = ~np.isfinite(slope)
        slope = np.where(bad, np.where(omega >= 0.5, np.inf, -np.inf), slope)
        return slope, np.where(bad | ~np.isfinite(curvature), np.inf, curvature)

    if kind == "det":
        scale = np.full(size, float(n))
    else:
        Wr = np.eye(n) if Wf is None else Wf
        scale = (np.einsum("...ij,...ji->...", Wr, pair.Pa)
                 + np.einsum("...ij,...ji->...", Wr, pair.Pb))
    with np.errstate(invalid="ignore", divide="ignore"):
        omega, iterations, _ = minimize_convex_interval(derivatives, size, scale=scale)
        # The slope from two formulations, each with its rounding term: the certificate
        # takes the interval that holds both (docs/methods/ici.rst, "The robust path's
        # certificate"; measured, not derived). On 300 pairs at condition numbers
        # 1e9..1e12 each alone missed the 50-digit slope in some pairs (trace: 37 and 17;
        # det: 24 and 0), the interval holding both in 5 (trace) and 0 (det).
        f, slope_y, _, error_y = inverse_ci_derivatives(pair, omega, kind, Wf, rounding=True)
        _, slope_w, error_w = whitened_certificate_slope(pair, omega, kind, Wf)
        low = np.fmin(slope_y - error_y, slope_w - error_w)
        high = np.fmax(slope_y + error_y, slope_w + error_w)
        slope, error = 0.5 * (low + high), 0.5 * (high - low)
        cert = pair_certificate(omega, slope, error, None if kind == "det" else f)
    cert = GapCertificate(*(np.where(np.isfinite(cert.gap), part, np.inf) for part in cert))
    return omega, iterations, cert


CERTIFIED = GAP_TOL
"""The gap tolerance of ``converged`` (with the rounding floor:
:func:`~cifilter._numerics.criteria.gap_converged`)."""
