"""Horizon-optimal ``delta`` of partial-correlation CI, for :mod:`cifilter.horizon`.

With correlation coefficient bounds ``rho``, Lemma 7 of Wu, Cai & Fu (2018) bounds the joint
error covariance of the N estimates, in the positive semidefinite order, by
``blockdiag(P_i / w_i(delta))`` for every ``delta`` on the simplex, with eq. (24),
``w_i(delta) = delta_i / (rho_i + (1 - rho_i) delta_i)``. The best linear estimator for that
bound and the filter's future measurements is the Kalman filter started from the fused bound
``(sum_i w_i P_i^-1)^-1`` (eq. 33), so by the superposition formula of :mod:`cifilter.horizon`

    P_kappa(delta) = P_c + exp(2 s) Psi S(delta)^-1 Psi^T,
    S(delta) = sum_i w_i(delta) I_i + Gamma,   I_i = P_i^-1.

The weights do not sum to one (unless ``rho = 1``), so ``S`` is not a convex combination of
``I_i + Gamma``; it is used in this information form. Every criterion is convex in ``delta``
(``docs/methods/horizon.rst``): ``w_i`` is concave, so ``S`` is matrix concave, and the
criteria are convex non-increasing functions of ``S``.

Derivatives, with ``X = S^-1``, are taken in ``w`` and chained through
``w_i' = rho_i / b_i^2`` and ``w_i'' = -2 rho_i (1 - rho_i) / b_i^3``
(``b_i = rho_i + (1 - rho_i) delta_i``): ``g_i = (df/dw_i) w_i'`` and
``H_ij = (d2f/dw_i dw_j) w_i' w_j' + [i = j] (df/dw_i) w_i''``.

* ``f = tr(V X)`` (``V = Psi^T W Psi`` normalised; the constant ``tr(W P_c)`` and the factor
  ``exp(2 s)`` do not move the minimiser): with ``M = X V X``, ``df/dw_i = -tr(M I_i)`` and
  ``d2f/dw_i dw_j = 2 tr(M I_i X I_j)``.
* ``f = log det Z``, ``Z = P_c + exp(2 s) Psi X Psi^T``: with ``C = exp(2 s) Psi^T Z^-1 Psi``
  and ``M_i = C X I_i X``, ``df/dw_i = -tr(M_i)`` and
  ``d2f/dw_i dw_j = 2 tr(M_i I_j X) - tr(M_i M_j)``. The ``delta``-dependent part of
  ``log det Z`` is of the order ``exp(2 s)``, which decays geometrically with the horizon and
  would be lost to rounding against ``log det P_c``; the solver therefore minimises
  ``(log det Z(delta) - log det Z(delta_0)) / exp(2 s)`` for the fixed reference
  ``delta_0 = 1/N``, computed as ``sum_k log1p(e lam_k) / e`` from the eigenvalues ``lam_k`` of
  ``L_0^-1 Psi (X - X_0) Psi^T L_0^-T`` (``Z(delta_0) = L_0 L_0^T``) with
  ``X - X_0 = X (sum_i (w_0i - w_i) I_i) X_0``, which keeps its relative accuracy at every
  horizon, and its gradient and Hessian divided by ``exp(2 s)`` alike. The constant
  ``tr(Z_0^-1 Psi X_0 Psi^T)`` is added to it: the scale of its rounding errors, which the
  solver's test "decrease below the rounding level of ``f``" needs to see (a difference
  near zero would hide it, and the solver would run to its iteration limit at optima it
  cannot certify by a decrease).
"""

import numpy as np

from ._linalg import cho_inverse, cho_solve, cholesky, solve_lower, symmetrize
from ._optimize import minimize_convex_simplex
from ._partial_correlation import NEWTON_RHO_FLOOR as _NEWTON_RHO_FLOOR
from ._partial_correlation import partial_weights as _partial_weights
from ._partial_correlation import weight_derivatives as _weight_derivatives
from ._riccati import propagated_bound

__all__ = ["information_bound", "partial_horizon_delta"]


def _fused_inverse(delta, rho, informations, Gamma):
    """``w(delta)`` (eq. 24) and ``X = (sum_i w_i I_i + Gamma)^-1``."""
    w = _partial_weights(delta, rho)
    S = symmetrize(np.einsum("...k,...kij->...ij", w, informations) + Gamma)
    return w, cho_inverse(cholesky(S, "fused information sum_i w_i P_i^-1 + Gamma"))


def information_bound(informations, terms, weights):
    """``P_c + exp(2 s) Psi (sum_i w_i I_i + Gamma)^-1 Psi^T`` for weights (..., N)."""
    S = symmetrize(np.einsum("...k,...kij->...ij", weights, informations) + terms.Gamma)
    return propagated_bound(terms, cho_inverse(cholesky(S, "fused information")))


def _chain(g_w, H_w, delta, rho):
    """Gradient and Hessian in ``delta`` from those in ``w`` (chain rule through eq. 24)."""
    first, second = _weight_derivatives(delta, rho)
    g = g_w * first
    H = H_w * first[..., :, None] * first[..., None, :]
    H = H + np.einsum("...i,ij->...ij", g_w * second, np.eye(delta.shape[-1]))
    return g, symmetrize(H)


def _trace_problem(informations, Gamma, rho, V):
    """``f(delta) = tr(V X(delta))`` and ``parts(delta) -> (f, df/dw, d2f/dw2)``."""

    def objective(delta):
        _, X = _fused_inverse(delta, rho, informations, Gamma)
        return np.einsum("...ij,...ji->...", V, X)

    def parts(delta):
        _, X = _fused_inverse(delta, rho, informations, Gamma)
        M = X @ V @ X
        MI = M[..., None, :, :] @ informations  # M I_i
        XI = X[..., None, :, :] @ informations  # X I_i
        g_w = -np.trace(MI, axis1=-2, axis2=-1)
        H_w = 2.0 * np.einsum("...iab,...jba->...ij", MI, XI)
        return np.einsum("...ij,...ji->...", V, X), g_w, H_w

    return objective, parts


def _log1p_ratio(x):
    """``log1p(x) / x``, 1 at ``x = 0``."""
    zero = x == 0.0
    return np.where(zero, 1.0, np.log1p(x) / np.where(zero, 1.0, x))


def _det_problem(informations, terms, rho):
    """``f(delta) = (log det Z(delta) - log det Z(1/N)) / exp(2 s) + const``, derivatives."""
    count = informations.shape[-3]
    scale = np.exp(2.0 * terms.log_scale)
    Psi, Psi_T = terms.Psi, np.swapaxes(terms.Psi, -1, -2)
    reference = np.full(informations.shape[:-3] + (count,), 1.0 / count)
    w_0, X_0 = _fused_inverse(reference, rho, informations, terms.Gamma)
    L_0 = cholesky(propagated_bound(terms, X_0), "propagated bound")
    # The objective is a difference; its rounding errors scale like this (divided by exp(2 s))
    # log det Z_0, not like the difference itself. Added as a constant, it tells the solver's
    # rounding test (relative to |f|) the level below which decreases cannot be resolved.
    level = np.trace(cho_solve(L_0, Psi @ X_0 @ Psi_T), axis1=-2, axis2=-1)

    def value(delta):
        w, X = _fused_inverse(delta, rho, informations, terms.Gamma)
        change = X @ np.einsum("...k,...kij->...ij", w_0 - w, informations) @ X_0  # X - X_0
        D = solve_lower(L_0, Psi @ symmetrize(change) @ Psi_T)
        D = solve_lower(L_0, np.swapaxes(D, -1, -2))  # L_0^-1 Psi (X - X_0) Psi^T L_0^-T
        lam = np.linalg.eigvalsh(symmetrize(D))
        return level + (lam * _log1p_ratio(scale[..., None] * lam)).sum(axis=-1), X

    def objective(delta):
        return value(delta)[0]

    def parts(delta):
        f, X = value(delta)
        LZ = cholesky(propagated_bound(terms, X), "propagated bound")
        C = Psi_T @ cho_solve(LZ, Psi)  # exp(2 s) Psi^T Z^-1 Psi, divided by exp(2 s)
        XI = X[..., None, :, :] @ informations  # X I_i
        M = C[..., None, :, :] @ XI @ X[..., None, :, :]  # M_i = C X I_i X
        g_w = -np.trace(M, axis1=-2, axis2=-1)
        IX = np.swapaxes(XI, -1, -2)  # I_i X
        H_w = 2.0 * np.einsum("...iab,...jba->...ij", M, IX)
        H_w = H_w - scale[..., None, None] * np.einsum("...iab,...jba->...ij", M, M)
        return f, g_w, H_w

    return objective, parts


def _problem(informations, terms, rho, weight):
    """The objective, its parts and the factor that turns its differences into the criterion's.

    For the trace criteria ``tr(W P_kappa) = tr(W P_c) + exp(2 s) c tr(V X)`` with
    ``V = Psi^T W Psi / c`` normalised to max entry 1 (the identity if ``Psi^T W Psi = 0``:
    then every ``delta`` is optimal); for ``log det`` the factor is ``exp(2 s)``.
    """
    scale = np.exp(2.0 * terms.log_scale)
    if weight is None:
        return _det_problem(informations, terms, rho) + (scale,)
    Psi = terms.Psi
    V = symmetrize(np.swapaxes(Psi, -1, -2) @ weight @ Psi)
    size = np.abs(V).max(axis=(-2, -1))
    flat = size == 0.0
    V = np.where(flat[..., None, None], np.eye(V.shape[-1]),
                 V / np.where(flat, 1.0, size)[..., None, None])
    return _trace_problem(informations, terms.Gamma, rho, V) + (scale * size,)


def partial_horizon_delta(informations, terms, rho, weight=None):
    """The ``delta`` minimising a criterion of ``P_kappa(delta)``, batched.

    Parameters
    ----------
    informations : ndarray, shape (..., N, n, n)
        ``I_i = P_i^-1``.
    terms : Terms
        The horizon terms, broadcast to the batch shape.
    rho : ndarray, shape (..., N)
        The bounds used for eq. (24) (for two estimates ``sqrt(rho_1 rho_2)`` twice).
    weight : ndarray, shape (..., n, n), or None
        ``W`` of the criterion ``tr(W P_kappa)`` (the identity for the trace); None for
        ``log det P_kappa``.

    Returns
    -------
    delta, iterations, converged : ndarray
        Minimisers on the simplex (exact zeros on faces), iterations and convergence flags
        of :func:`cifilter._optimize.minimize_convex_simplex`.
    gap : ndarray
        A certified bound on the criterion's excess over its minimum, relative to the
        criterion (``tr(W P_kappa)`` or ``det P_kappa``), from convexity with the true
        ``rho``: ``f(delta) - min f <= sum_i g_i delta_i - min_i g_i``.

    Notes
    -----
    Positive bounds below ``_NEWTON_RHO_FLOOR`` (1e-8) are raised to it for the Newton
    iterations, as in partial CI's Newton solver: near ``delta_i = 0`` the curvature in
    ``delta_i`` grows like ``rho_i^-2`` and the solver's normalised KKT system would drop
    every other direction. ``gap`` is computed with the true bounds, so it states how far
    such a ``delta`` can be from the optimum of the true problem.
    """
    positive = rho > 0.0
    floored = np.where(positive, np.maximum(rho, _NEWTON_RHO_FLOOR), 0.0)
    objective, parts, _ = _problem(informations, terms, floored, weight)

    def evaluate(delta):
        f, g_w, H_w = parts(delta)
        return (f,) + _chain(g_w, H_w, delta, floored)

    delta, iterations, converged = minimize_convex_simplex(
        evaluate, objective, informations.shape[-3], informations.shape[:-3])
    # The certificate, with the true bounds: g_i = g_w_i w_i', written so that a tiny rho_i
    # with delta_i = 0 gives a huge (not NaN) g_i and g_i delta_i = 0.
    _, parts, factor = _problem(informations, terms, rho, weight)
    f, g_w, _ = parts(delta)
    base = np.where(positive, rho + (1.0 - rho) * delta, 1.0)
    with np.errstate(over="ignore", divide="ignore"):
        ratio = np.where(positive, rho / base, 0.0)
        g = g_w * ratio / base
        along = (g_w * ratio * _partial_weights(delta, rho)).sum(axis=-1)  # sum g_i delta_i
        excess = factor * np.maximum(along - g.min(axis=-1), 0.0)
        if weight is None:
            gap = np.expm1(excess)  # log det -> det
        else:
            total = np.einsum("...ij,...ji->...", weight, terms.P_c) + factor * f
            gap = excess / total
    return delta, iterations, converged, gap
