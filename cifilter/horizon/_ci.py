"""The CI weights for the bound at a horizon: ``P_c + exp(2 s) Psi (sum_i w_i S_i)^-1 Psi^T``.

The trace criteria, and ``log det`` where ``P_c = 0`` (horizon 0), are Covariance
Intersection problems of the matrices ``S_i^-1`` and are solved by the ``"ci"`` rule's
solver, :func:`cifilter.rules._ci_weights.optimal_weights`; at horizon 0 (and wherever
``Gamma = 0``) these matrices are the covariances themselves, so the weights are those of
the rule. ``log det`` with ``P_c != 0`` has its own solvers: an interval Newton method for
two estimates and the active-set Newton method on the simplex for more. Derivations:
``docs/methods/horizon.rst``.
"""

import numpy as np

from .._numerics.criteria import certified_gap
from .._numerics.information import weighted_information
from .._numerics.linalg import cho_inverse, cho_solve, cholesky, solve_lower, symmetrize
from .._numerics.optimize import minimize_convex_interval, minimize_convex_simplex
from .._numerics.validation import Estimates
from ..rules._ci_weights import optimal_weights
from ._model import propagated_bound

__all__ = ["ci_fused_information", "ci_horizon_weights"]


def ci_fused_information(S, weights):
    """``(sum_i w_i S_i)^-1``: the inverse fused information (..., n, n)."""
    S_w = weighted_information(weights, S)
    return cho_inverse(cholesky(S_w, "fused information"))


def _ci_problem(est, informations, terms, kind, W):
    """The CI problem ``(estimates, kind, W)`` whose optimum is the horizon optimum.

    ``tr(W P_kappa) = tr(W P_c) + exp(2 s) tr(V S(w)^-1)`` with ``V = Psi^T W Psi``, and
    ``log det P_kappa = log det S(w)^-1 + const`` where ``P_c = 0``: CI problems of the
    matrices ``S_i^-1``. Where ``Gamma = 0`` these are the covariances themselves (so
    horizon 0 is the ``"ci"`` rule's problem bit for bit). Otherwise the congruence with
    the factor of the mean ``S_bar = L L^T``, ``S_i -> L^-1 S_i L^-T``, ``V -> L^-1 V L^-T``,
    which changes neither criterion's minimiser, removes the scale ``Gamma`` shares between
    the ``S_i`` (it grows without bound for observed unstable modes).
    """
    n = est.dim
    if terms.Gamma.any():
        S = informations + terms.Gamma[..., None, :, :]
        L = cholesky(symmetrize(S.mean(axis=-3)), "mean of P_i^-1 + Gamma")
        S = symmetrize(solve_lower(L[..., None, :, :], np.swapaxes(
            solve_lower(L[..., None, :, :], S), -1, -2)))
        P = cho_inverse(cholesky(S, "whitened P_i^-1 + Gamma"))
        est = Estimates(np.zeros(P.shape[:-1]), P, cholesky(P, "(P_i^-1 + Gamma)^-1"), False)
    if kind == "det":
        return est, "det", None
    if not terms.Gamma.any() and np.all(terms.Psi == np.eye(n)):
        return est, kind, W
    base = np.eye(n) if kind == "trace" else W
    V = terms.Psi.swapaxes(-1, -2) @ base @ terms.Psi
    if terms.Gamma.any():
        V = solve_lower(L, np.swapaxes(solve_lower(L, V), -1, -2))
    V = symmetrize(V)
    size = np.abs(V).max(axis=(-2, -1), keepdims=True)  # all-zero: a flat criterion
    return est, "weighted-trace", np.where(size > 0, V / np.where(size > 0, size, 1.0),
                                           np.eye(n))


def ci_horizon_weights(est, informations, terms, kind, W):
    """Criterion-optimal CI weights (..., N) for the bound at the horizon of ``terms``.

    ``est`` are the validated estimates (batch shape already that of ``terms``),
    ``informations`` their ``P_i^-1``. Returns the weights and ``{"iterations",
    "converged", "gap", "solver"}``; ``gap`` is a certified bound on the criterion's excess
    over its minimum (relative for the trace criteria, in log det for ``"det"``).
    """
    if kind != "det" or not terms.P_c.any():
        weights, info, _ = optimal_weights(*_ci_problem(est, informations, terms, kind, W))
        return weights, info
    S = symmetrize(informations + terms.Gamma[..., None, :, :])
    if est.count == 2:
        weights, iterations, converged = _pair_det_weights(S, terms)
        solver = "interval"
    else:
        weights, iterations, converged = _simplex_det_weights(S, terms)
        solver = "simplex"
    descent = _det_descent(S, terms, weights)
    gap = certified_gap(weights, descent, None, "det")
    return weights, {"iterations": iterations, "converged": converged, "gap": gap,
                     "solver": solver}


def _det_parts(S, terms, weights):
    """``X = S(w)^-1``, the factor of ``Z = P_c + exp(2 s) Psi X Psi^T`` and
    ``C = Psi^T Z^-1 Psi`` (without the factor ``exp(2 s)``)."""
    X = ci_fused_information(S, weights)
    LZ = cholesky(propagated_bound(terms, X), "propagated bound")
    C = terms.Psi.swapaxes(-1, -2) @ cho_solve(LZ, terms.Psi)
    return X, LZ, C


def _det_descent(S, terms, weights):
    """``-d log det P_kappa / d w_i = exp(2 s) tr(C X S_i X)`` (..., N), all >= 0."""
    X, _, C = _det_parts(S, terms, weights)
    weight = np.exp(2.0 * terms.log_scale)[..., None]
    XS = X[..., None, :, :] @ S  # X S_i
    CX = (C @ X)[..., None, :, :]
    return weight * np.einsum("...kab,...kba->...k", CX, XS)


def _pair_det_weights(S, terms):
    """The optimal omega for two estimates and ``log det P_kappa`` by the interval method.

    With ``M = C X D X`` (``D = S_1 - S_2``): ``f' = -tr(M)`` and
    ``f'' = 2 tr(M D X) - exp(2 s) tr(M M)``, both divided by ``exp(2 s)``. ``S(omega)^-1``
    is factored at every omega (a simultaneous diagonalisation loses its small
    eigenvalues when ``S_1`` and ``S_2`` are ill-conditioned in different directions).
    """
    batch = S.shape[:-3]
    n = S.shape[-1]
    size = int(np.prod(batch, dtype=int))
    flat = type(terms)(*(np.reshape(t, (size,) + np.shape(t)[len(batch):]) for t in terms))
    S_flat = S.reshape(size, 2, n, n)
    D = symmetrize(S_flat[:, 0] - S_flat[:, 1])
    weight = np.exp(2.0 * flat.log_scale)

    def parts(omega, index):
        sub = type(flat)(*(t[index] for t in flat))
        return _det_parts(S_flat[index], sub, np.stack([omega, 1.0 - omega], axis=-1))

    def derivatives(omega, index):
        X, _, C = parts(omega, index)
        M = C @ X @ D[index] @ X
        g = -np.trace(M, axis1=-2, axis2=-1)
        h = 2.0 * ((M @ D[index]) * X.swapaxes(-1, -2)).sum(axis=(-2, -1)) - weight[
            index] * (M * M.swapaxes(-1, -2)).sum(axis=(-2, -1))
        return g, h

    everything = np.arange(size)
    ends = [parts(np.full(size, w), everything) for w in (0.0, 1.0)]
    scale = sum(np.einsum("iab,iba->i", C, X) for X, _, C in ends)
    omega, iterations, converged = minimize_convex_interval(derivatives, size, scale=scale)
    weights = np.stack([omega, 1.0 - omega], axis=-1).reshape(batch + (2,))
    return weights, iterations.reshape(batch), converged.reshape(batch)


def _simplex_det_weights(S, terms):
    """The optimal weights for N > 2 estimates and ``log det P_kappa`` (active-set Newton).

    With ``A_i = X S_i``, ``C`` as in :func:`_det_parts` times ``exp(2 s)`` and
    ``M_i = C A_i X``: ``g_i = -tr(M_i)``, ``H_ij = 2 tr(C A_i A_j X) - tr(M_i M_j)``.
    """
    count = S.shape[-3]
    weight = np.exp(2.0 * terms.log_scale)[..., None, None]
    # log det from a Cholesky factor has rounding errors of order n eps whatever its value;
    # the constant n tells the solver's rounding test (relative to |f|) that level, which it
    # would not see where det P_kappa is near 1 (it then ran to its iteration limit).
    level = float(S.shape[-1])

    def log_det(LZ):
        return level + 2.0 * np.log(np.diagonal(LZ, axis1=-2, axis2=-1)).sum(axis=-1)

    def objective(w):
        return log_det(_det_parts(S, terms, w)[1])

    def evaluate(w):
        X, LZ, C = _det_parts(S, terms, w)
        C = weight * C
        A = X[..., None, :, :] @ S
        Mi = C[..., None, :, :] @ A @ X[..., None, :, :]
        g = -np.trace(Mi, axis1=-2, axis2=-1)
        CA = C[..., None, :, :] @ A
        H = 2.0 * np.einsum("...iab,...jbc,...ca->...ij", CA, A, X)
        H = H - np.einsum("...iab,...jba->...ij", Mi, Mi)
        return log_det(LZ), g, symmetrize(H)

    return minimize_convex_simplex(evaluate, objective, count, S.shape[:-3])
