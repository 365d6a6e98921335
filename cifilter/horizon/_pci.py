"""The partial-CI ``delta`` for the bound at a horizon (Wu, Cai & Fu 2018, eq. 24).

With ``w_i(delta) = delta_i / (rho_i + (1 - rho_i) delta_i)`` the bound at the horizon is
``P_c + exp(2 s) Psi S(delta)^-1 Psi^T`` with ``S(delta) = sum_i w_i P_i^-1 + Gamma``, convex
in ``delta``; the active-set Newton method on the simplex minimises it with exact gradients
and Hessians chained through eq. (24). At horizon 0 the trace criterion is the ``"pci"``
rule's problem (35) and its solver, :func:`cifilter.rules._partial_correlation.newton_delta`, is
used. Derivations, the ``log det`` reformulation and the floor of tiny bounds:
``docs/methods/horizon.rst``, "Partial-correlation CI".
"""

import numpy as np

from .._numerics.information import squared_norms, weighted_information
from .._numerics.linalg import cho_inverse, cho_solve, cholesky, solve_lower, symmetrize
from .._numerics.optimize import minimize_convex_segment, minimize_convex_simplex
from ..rules._partial_correlation import (
    NEWTON_RHO_FLOOR,
    bound_and_spread,
    newton_delta,
    partial_weights,
    relative_gap,
    weight_derivatives,
)
from ._model import propagated_bound

__all__ = ["delta_problem", "information_bound", "pci_horizon_delta"]

# The "pci" rule's defaults (cifilter.partial_ci), used for its problem at horizon 0.
RULE_TOL, RULE_MAX_ITER = 1e-10, 100


def _fused_inverse(delta, rho, informations, Gamma):
    """``w(delta)`` (eq. 24) and ``X = (sum_i w_i I_i + Gamma)^-1``."""
    w = partial_weights(delta, rho)
    S = weighted_information(w, informations) + Gamma
    return w, cho_inverse(cholesky(S, "fused information sum_i w_i P_i^-1 + Gamma"))


def information_bound(informations, terms, weights):
    """``P_c + exp(2 s) Psi (sum_i w_i I_i + Gamma)^-1 Psi^T`` for weights (..., N)."""
    S = weighted_information(weights, informations) + terms.Gamma
    return propagated_bound(terms, cho_inverse(cholesky(S, "fused information")))


def _chain(g_w, H_w, delta, rho):
    """Gradient and Hessian in ``delta`` from those in ``w`` (chain rule through eq. 24)."""
    first, second = weight_derivatives(delta, rho)
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
    Psi, Psi_T = terms.Psi, terms.Psi.swapaxes(-1, -2)
    reference = np.full(informations.shape[:-3] + (count,), 1.0 / count)
    w_0, X_0 = _fused_inverse(reference, rho, informations, terms.Gamma)
    L_0 = cholesky(propagated_bound(terms, X_0), "propagated bound")
    # The objective is a difference; its rounding errors scale like this (divided by exp(2 s))
    # log det Z_0, not like the difference itself. Added as a constant, it tells the solver's
    # rounding test (relative to |f|) the level below which decreases cannot be resolved.
    level = np.trace(cho_solve(L_0, Psi @ X_0 @ Psi_T), axis1=-2, axis2=-1)

    def value(delta):
        w, X = _fused_inverse(delta, rho, informations, terms.Gamma)
        change = X @ weighted_information(w_0 - w, informations) @ X_0  # X - X_0
        D = solve_lower(L_0, Psi @ symmetrize(change) @ Psi_T)
        D = solve_lower(L_0, D.swapaxes(-1, -2))  # L_0^-1 Psi (X - X_0) Psi^T L_0^-T
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
        IX = XI.swapaxes(-1, -2)  # I_i X
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
    V = symmetrize(Psi.swapaxes(-1, -2) @ weight @ Psi)
    size = np.abs(V).max(axis=(-2, -1))
    flat = size == 0.0
    V = np.where(flat[..., None, None], np.eye(V.shape[-1]),
                 V / np.where(flat, 1.0, size)[..., None, None])
    return _trace_problem(informations, terms.Gamma, rho, V) + (scale * size,)


def delta_problem(informations, terms, rho, weight):
    """``(objective, derivatives, factor)`` of the solver, for tests of its derivatives.

    ``objective(delta)`` is the criterion up to a constant and the positive ``factor``;
    ``derivatives(delta)`` its gradient (..., N) and Hessian (..., N, N) in ``delta``.
    ``weight`` is ``W`` of ``tr(W P_kappa)`` or None for ``log det``.
    """
    objective, parts, factor = _problem(informations, terms, rho, weight)

    def derivatives(delta):
        return _chain(*parts(delta)[1:], delta, rho)

    return objective, derivatives, factor


def _is_rule_problem(terms, weight):
    """Horizon 0 with the trace: ``P_c = 0``, ``Gamma = 0``, ``Psi = I`` and ``W = I``."""
    n = terms.Psi.shape[-1]
    return (weight is not None and not terms.P_c.any() and not terms.Gamma.any()
            and np.all(terms.Psi == np.eye(n)) and not terms.log_scale.any()
            and np.all(weight == np.eye(n)))


def pci_horizon_delta(L_inv, informations, terms, rho, weight=None):
    """The ``delta`` minimising a criterion of ``P_kappa(delta)``, batched.

    Parameters
    ----------
    L_inv : ndarray, shape (..., N, n, n)
        Inverse Cholesky factors of the covariances.
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
    delta, iterations, converged, gap, solver
        Minimisers on the simplex (exact zeros on faces), iterations, convergence flags,
        a certified bound on the criterion's excess over its minimum relative to the
        criterion (``tr(W P_kappa)`` or ``det P_kappa``, from convexity with the true
        ``rho``) and the solver's name.
    """
    if _is_rule_problem(terms, weight):
        delta, iterations = newton_delta(L_inv, rho, RULE_TOL, RULE_MAX_ITER)
        _, factors, spread = bound_and_spread(delta, rho, L_inv)
        with np.errstate(over="ignore", invalid="ignore"):
            gap = relative_gap(delta, rho, squared_norms(factors.R_inv), spread)
        return delta, iterations, gap <= RULE_TOL, gap, "newton"
    positive = rho > 0.0
    floored = np.where(positive, np.maximum(rho, NEWTON_RHO_FLOOR), 0.0)
    objective, parts, _ = _problem(informations, terms, floored, weight)

    def evaluate(delta):
        f, g_w, H_w = parts(delta)
        return (f,) + _chain(g_w, H_w, delta, floored)

    if informations.shape[-3:-2] == (2,) and informations.ndim == 3:
        # one problem of two estimates: the segment method of two-estimate CI, without the
        # simplex solver's batch bookkeeping
        def evaluate_one(w, index):
            f, g, H = evaluate(w[0])
            return f, g[None], H[None]

        scale = np.array([abs(float(objective(np.array([0.5, 0.5]))))])
        with np.errstate(all="ignore"):
            delta, iterations, converged = minimize_convex_segment(evaluate_one, 1,
                                                                   scale=scale)
        delta, iterations, converged = delta[0], iterations.reshape(()), converged.reshape(())
    else:
        delta, iterations, converged = minimize_convex_simplex(
            evaluate, objective, informations.shape[-3], informations.shape[:-3])
    # The certificate, with the true bounds: df/dw_i = g_w_i <= 0 (the "spread" of
    # relative_gap is -g_w_i), relative to the criterion.
    _, parts, factor = _problem(informations, terms, rho, weight)
    f, g_w, _ = parts(delta)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        if weight is None:
            gap = np.expm1(factor * relative_gap(delta, rho, 1.0, -g_w))  # log det -> det
        else:
            total = np.einsum("...ij,...ji->...", weight, terms.P_c) + factor * f
            gap = relative_gap(delta, rho, total / factor, -g_w)
    return delta, iterations, converged, gap, "simplex"
