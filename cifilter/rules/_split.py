"""Split Covariance Intersection of two estimates (the second possibly partial, ``H``).

Each estimate carries ``P = P_ind + P_dep``: the errors' independent parts are mutually
independent, the dependent parts arbitrarily correlated. With omega in [0, 1] and

    X_1 = P1_dep / omega + P1_ind,   X_2 = P2_dep / (1 - omega) + P2_ind,

the fused estimate is the Kalman update of estimate 1 by the "measurement" ``z = x_2`` of
``H x`` with noise covariance ``X_2`` (Julier & Uhlmann 2001; Li, Nashashibi & Yang 2013):

    P^-1 = X_1^-1 + H^T X_2^-1 H,   K_1 = P X_1^-1,   K_2 = P H^T X_2^-1,   x = K_1 x_1 + K_2 x_2.

Written with ``V_1 = omega X_1 = P1_dep + omega P1_ind`` and ``V_2 = (1 - omega) X_2``,
``P^-1 = omega V_1^-1 + (1 - omega) H^T V_2^-1 H`` (no division by omega; an end weight
ignores that estimate). The returned covariance is assembled from the gains,

    P_ind = K_1 P1_ind K_1^T + K_2 P2_ind K_2^T,
    P_dep = K_1 P1_dep K_1^T / omega + K_2 P2_dep K_2^T / (1 - omega),   P = P_ind + P_dep,

the split-CI bound of the returned gains (the CI inequality on the dependent parts), and
``P_ind`` is the exact covariance of the fused independent error, so the split can be
fused again. ``trace(W P)`` and ``log det P`` are convex in omega (``P^-1`` is matrix
concave in omega: each ``X_i^-1`` is a parallel sum of ``omega P_dep^-1`` and
``P_ind^-1``); the optimum is found by bisection on the slope

    f'(omega) = -trace(W P dQ P) (trace) or -trace(P dQ) (log det),
    dQ = V_1^-1 P1_dep V_1^-1 - H^T V_2^-1 P2_dep V_2^-1 H,

a difference of two nonnegative terms, and certified by its gap.
"""

import numpy as np

from .._numerics.criteria import GAP_TOL
from .._numerics.information import checked_cholesky, lower_inverse_stack, squared_norms
from .._numerics.linalg import symmetrize
from .._numerics.optimize import interval_gap, minimize_convex_interval

__all__ = ["psd_sqrt", "split_pair", "split_pair_derivative"]


def psd_sqrt(A):
    """A square root ``D`` (..., n, n) with ``D D^T = A`` of PSD matrices (may be singular)."""
    lam, U = np.linalg.eigh(symmetrize(A))
    return U * np.sqrt(np.clip(lam, 0.0, None))[..., None, :]


def _information(V_L_inv, H, omega):
    """``P^-1 = omega V_1^-1 + (1 - omega) H^T V_2^-1 H`` and its factors; NaN if singular."""
    L1i, L2i = V_L_inv
    A1 = L1i.swapaxes(-1, -2) @ L1i
    C2 = L2i @ H
    A2 = C2.swapaxes(-1, -2) @ C2
    J = omega[:, None, None] * A1 + (1.0 - omega)[:, None, None] * A2
    R = checked_cholesky(J, "the fused information matrix", failures="nan")
    R_inv = lower_inverse_stack(R)
    return R, R_inv, R_inv.swapaxes(-1, -2) @ R_inv


def _v_factors(parts, omega, failures="nan"):
    """Cholesky factors (inverses) of ``V_1``, ``V_2`` at omega (size,)."""
    (Pi1, Pd1), (Pi2, Pd2) = parts
    V1 = Pd1 + omega[:, None, None] * Pi1
    V2 = Pd2 + (1.0 - omega)[:, None, None] * Pi2
    L1 = checked_cholesky(V1, "P1_dep + omega P1_ind", failures=failures)
    L2 = checked_cholesky(V2, "P2_dep + (1 - omega) P2_ind", failures=failures)
    return lower_inverse_stack(L1), lower_inverse_stack(L2)


def _sym(A):
    return A + A.swapaxes(-1, -2)


def split_pair_derivative(parts, D, H, omega, kind, W, curvature=False):
    """``(f, f')`` of the split-CI criterion at omega (size,), and ``f''`` with
    ``curvature``; NaN where undefined.

    ``f''`` (for Newton's steps only) from ``d2Q = -sym(V_1^-1 P1_ind V_1^-1 P1_dep V_1^-1)
    - H^T sym(V_2^-1 P2_ind V_2^-1 P2_dep V_2^-1) H`` (``sym(A) = A + A^T``):
    ``2 tr(W P dQ P dQ P) - tr(W P d2Q P)`` or ``tr(P dQ P dQ) - tr(P d2Q)``.
    """
    L1i, L2i = _v_factors(parts, omega)
    _, R_inv, P = _information((L1i, L2i), H, omega)
    V1i = L1i.swapaxes(-1, -2) @ L1i
    V2i = L2i.swapaxes(-1, -2) @ L2i
    T1 = V1i @ D[0]  # V_1^-1 D_1
    T2 = H.swapaxes(-1, -2) @ (V2i @ D[1])  # H^T V_2^-1 D_2
    if curvature:
        (Pi1, _), (Pi2, _) = parts
        Ht = H.swapaxes(-1, -2)
        dQ = T1 @ T1.swapaxes(-1, -2) - T2 @ T2.swapaxes(-1, -2)
        d2Q = -(_sym(V1i @ Pi1 @ T1 @ T1.swapaxes(-1, -2))
                + Ht @ _sym(V2i @ Pi2 @ V2i @ D[1] @ D[1].swapaxes(-1, -2) @ V2i) @ H)
        PdQ = P @ dQ
        if kind == "det":
            second = (np.einsum("...ij,...ji->...", PdQ, PdQ)
                      - np.einsum("...ij,...ji->...", P, d2Q))
        else:
            Wm = np.broadcast_to(np.eye(P.shape[-1]), P.shape) if W is None else W
            second = (2.0 * np.einsum("...ij,...jk,...kl,...li->...", Wm, PdQ, PdQ, P)
                      - np.einsum("...ij,...jk,...kl,...li->...", Wm, P, d2Q, P))
    if kind == "det":
        f = 2.0 * np.log(np.abs(np.diagonal(R_inv, axis1=-2, axis2=-1))).sum(axis=-1)
        Lp_T = R_inv  # P = R_inv^T R_inv: trace(P T T^T) = ||R_inv T||^2
        slope = squared_norms(Lp_T @ T2) - squared_norms(Lp_T @ T1)
    else:
        M1, M2 = P @ T1, P @ T2
        if kind == "trace":
            f = np.trace(P, axis1=-2, axis2=-1)
            slope = squared_norms(M2) - squared_norms(M1)
        else:
            f = np.einsum("...ij,...ji->...", W, P)
            slope = (np.einsum("...ij,...ik,...jk->...", W, M2, M2)
                     - np.einsum("...ij,...ik,...jk->...", W, M1, M1))
    return (f, slope, second) if curvature else (f, slope)


def _optimal_omega(parts, D, H, kind, W, size, n):
    def derivatives(omega, index):
        sub = tuple((a[index], b[index]) for a, b in parts)
        _, slope, second = split_pair_derivative(
            sub, (D[0][index], D[1][index]), H[index], omega, kind,
            None if W is None else W[index], curvature=True)
        # Where V_i is singular at an end (a singular dependent part) the criterion is
        # unbounded there: the slope points away from that end.
        bad = ~np.isfinite(slope)
        slope = np.where(bad, np.where(omega >= 0.5, np.inf, -np.inf), slope)
        return slope, np.where(bad | ~np.isfinite(second), np.inf, second)

    (Pi1, Pd1), _ = parts
    if kind == "det":
        scale = np.full(size, float(n))
    else:
        Wr = np.eye(n) if W is None else W
        scale = np.einsum("...ij,...ji->...", Wr, Pi1 + Pd1)
    with np.errstate(invalid="ignore", divide="ignore"):
        omega, iterations, _ = minimize_convex_interval(derivatives, size, scale=scale)
        f, slope = split_pair_derivative(parts, D, H, omega, kind, W)
        gap = interval_gap(omega, slope)
        if kind != "det":
            gap = gap / f
    gap = np.where(np.isfinite(gap), gap, np.inf)
    return omega, iterations, gap


def split_pair(x1, x2, parts, H, kind, W, omega=None):
    """Split CI of flattened pairs: ``x1`` (size, n), ``x2`` (size, m), ``parts`` the
    ``((P1_ind, P1_dep), (P2_ind, P2_dep))`` stacks, ``H`` (size, m, n).

    Returns ``(x, P, P_ind, P_dep, gains1, gains2, omega, info)``.
    """
    size, n = x1.shape
    (Pi1, Pd1), (Pi2, Pd2) = parts
    D = (psd_sqrt(Pd1), psd_sqrt(Pd2))
    info = {}
    if omega is None:
        omega, iterations, gap = _optimal_omega(parts, D, H, kind, W, size, n)
        info.update(rule="optimal", iterations=iterations, gap=gap, converged=gap <= GAP_TOL)
    else:
        info["rule"] = "fixed"
    # At an end the ignored estimate's V may be singular: any SPD stand-in (zero weight)
    first_end, second_end = omega == 0.0, omega == 1.0
    Pd1s = np.where(first_end[:, None, None], Pi1 + Pd1, Pd1)
    Pd2s = np.where(second_end[:, None, None], Pi2 + Pd2, Pd2)
    L1i, L2i = _v_factors(((Pi1, Pd1s), (Pi2, Pd2s)), omega, failures="raise")
    _, _, P = _information((L1i, L2i), H, omega)
    checked_cholesky(symmetrize(P), "the fused covariance")
    V2i = L2i.swapaxes(-1, -2) @ L2i
    K2 = (1.0 - omega)[:, None, None] * (P @ H.swapaxes(-1, -2) @ V2i)
    K2 = np.where(second_end[:, None, None], 0.0, K2)
    # K_1 = I - K_2 H exactly (the fused mean is unbiased; the bound is about these gains)
    K1 = np.eye(n) - K2 @ H
    K1 = np.where(first_end[:, None, None], 0.0, K1)
    x = (K1 @ x1[..., None])[..., 0] + (K2 @ x2[..., None])[..., 0]
    L_i1, L_i2 = psd_sqrt(Pi1), psd_sqrt(Pi2)
    M1, M2 = K1 @ L_i1, K2 @ L_i2
    P_ind = M1 @ M1.swapaxes(-1, -2) + M2 @ M2.swapaxes(-1, -2)
    P_dep = np.zeros_like(P_ind)
    for K, Dk, w in ((K1, D[0], omega), (K2, D[1], 1.0 - omega)):
        with np.errstate(divide="ignore", invalid="ignore"):
            M = np.where(w[:, None, None] > 0.0, (K @ Dk) / np.sqrt(w)[:, None, None], 0.0)
        P_dep = P_dep + M @ M.swapaxes(-1, -2)
    P_ind, P_dep = symmetrize(P_ind), symmetrize(P_dep)
    P = symmetrize(P_ind + P_dep)
    return x, P, P_ind, P_dep, K1, K2, omega, info
