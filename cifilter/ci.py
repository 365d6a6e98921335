"""Covariance Intersection (Julier & Uhlmann 1997) for two or N estimates.

The fused estimate of CI is

    P^-1 = sum_i w_i P_i^-1,    x = P sum_i w_i P_i^-1 x_i,    w on the simplex,

(eq. (2) of Wu, Cai & Fu 2018; the unnumbered CI equations of Weng & Djurić 2012 and of
the journal version, Sec. I), and ``P`` bounds the error covariance for every
cross-covariance of the inputs. The weights are chosen by minimising a criterion of
``P`` (trace, determinant or ``trace(W P)``) or by a fast non-iterative rule.
"""

import numpy as np

from ._information import information_matrices, weighted_information_fusion
from ._linalg import (
    cho_inverse,
    cholesky,
    diagonalise_pair,
    logdet_from_cholesky,
    symmetrize,
)
from ._optimize import minimize_convex_interval, minimize_convex_simplex
from ._validation import (
    as_covariances,
    as_estimates,
    check_psd_weight_matrix,
    check_weights,
    restore_style,
)
from .registry import register_method
from .result import FusionResult

__all__ = ["FAST_OMEGA_RULES", "ci_weights", "covariance_intersection"]


# --------------------------------------------------------------------------- criteria
def _parse_criterion(criterion, n):
    """('trace', None), ('det', None) or ('weighted-trace', W)."""
    if isinstance(criterion, str):
        if criterion in ("trace", "det"):
            return criterion, None
        raise ValueError(
            f"criterion must be 'trace', 'det' or a positive semidefinite {n}x{n} weight "
            f"matrix, got {criterion!r}"
        )
    return "weighted-trace", check_psd_weight_matrix(criterion, n, "criterion")


def _criterion_value(P, kind, W):
    if kind == "det":
        return np.linalg.det(P)
    if kind == "trace":
        return np.trace(P, axis1=-2, axis2=-1)
    return np.einsum("...ij,...ji->...", W, P)


# --------------------------------------------------------------------------- fast rules
def _fast_weights(est):
    """Niehsen (2002): w_i proportional to 1 / trace(P_i) (eq. (2) of Weng & Djurić, journal)."""
    inverse_traces = 1.0 / np.trace(est.P, axis1=-2, axis2=-1)
    return inverse_traces / inverse_traces.sum(axis=-1, keepdims=True)


def _det_ratio_weights(est):
    """Eq. (7) of Weng & Djurić (2012), w_1 = |P_2| / (|P_1| + |P_2|), generalised to N.

    w_i is proportional to 1 / det(P_i); computed from log-determinants (a softmax) so
    that large or small determinants neither overflow nor underflow.
    """
    log_information_det = -logdet_from_cholesky(est.L)
    shifted = log_information_det - log_information_det.max(axis=-1, keepdims=True)
    weights = np.exp(shifted)
    return weights / weights.sum(axis=-1, keepdims=True)


def _improved_fast_weights(est):
    """Franken & Hupper (2005), improved fast CI.

    With I_i = P_i^-1 and I = sum_j I_j,

        w_i = (|I| - |I - I_i| + |I_i|) / (N |I| + sum_j (|I_j| - |I - I_j|)).

    For two estimates this is w_1 = (|I| - |I_2| + |I_1|) / (2 |I|). All determinants are
    divided by |I| (ratios from log-determinants), so nothing overflows. The weights are
    positive and sum to one: |I - I_i| < |I| because I_i is positive definite.
    """
    informations = information_matrices(est.L)
    total = symmetrize(informations.sum(axis=-3))
    log_total = logdet_from_cholesky(cholesky(total, "sum of information matrices"))
    log_own = -logdet_from_cholesky(est.L)
    others = symmetrize(total[..., None, :, :] - informations)
    log_others = logdet_from_cholesky(cholesky(others, "sum of the other information matrices"))
    own = np.exp(log_own - log_total[..., None])
    rest = np.exp(log_others - log_total[..., None])
    numerators = 1.0 - rest + own
    return numerators / numerators.sum(axis=-1, keepdims=True)


FAST_OMEGA_RULES = {
    "fast": _fast_weights,
    "improved-fast": _improved_fast_weights,
    "det-ratio": _det_ratio_weights,
}
"""Non-iterative weight rules accepted as ``omega=<name>``."""


# --------------------------------------------------------------------------- optimal weights
def _two_estimate_weights(est, kind, W):
    """Exact criterion-optimal omega for N = 2 by simultaneous diagonalisation.

    With P_1 = L L^T and L^-1 P_2 L^-T = U diag(lam) U^T, T = L U gives
    P(omega) = T diag(d) T^T with d_k = lam_k / (1 + omega (lam_k - 1)), so the criterion
    is a sum of scalar terms: trace(W P) = sum_k c_k d_k with c = diag(T^T W T), and
    log det P = log det P_1 + sum_k log(d_k / lam_k) + const. Both are convex in omega;
    the derivative is closed-form and its root is found by safeguarded Newton iterations.
    Returns the weights, iterations, convergence flags and the diagonalisation (from
    which the fused estimate is assembled without further inverses).
    """
    pair = diagonalise_pair(est.L[..., 0, :, :], est.P[..., 1, :, :])
    n, size = est.dim, int(np.prod(est.batch_shape, dtype=int))
    a = (pair.lam - 1.0).reshape(size, n)
    if kind == "det":

        def derivatives(omega, index):
            ratio = a[index] / (1.0 + omega[:, None] * a[index])
            return -ratio.sum(axis=-1), (ratio**2).sum(axis=-1)

        scale = np.full(size, float(n))
    else:
        if kind == "trace":
            c = np.einsum("...ik,...ik->...k", pair.T, pair.T)
        else:
            c = np.einsum("...ik,...ij,...jk->...k", pair.T, W, pair.T)
        c = np.broadcast_to(c, est.batch_shape + (n,)).reshape(size, n)
        ca = c * (a + 1.0) * a

        def derivatives(omega, index):
            den = 1.0 + omega[:, None] * a[index]
            term = ca[index] / den**2
            return -term.sum(axis=-1), 2.0 * (term * a[index] / den).sum(axis=-1)

        scale = (c * (a + 1.0)).sum(axis=-1) + c.sum(axis=-1)  # tr(W P_2) + tr(W P_1)
    omega, iterations, converged = minimize_convex_interval(derivatives, size, scale=scale)
    shape = est.batch_shape
    weights = np.stack([omega, 1.0 - omega], axis=-1).reshape(shape + (2,))
    return weights, iterations.reshape(shape), converged.reshape(shape), pair


def _fuse_diagonalised_pair(est, pair, weights):
    """CI of two estimates from their diagonalisation (no further inverses).

    P = T diag(d) T^T; K_1 = omega P P_1^-1 = omega T diag(d) U^T L1^-1 (because
    T^T L1^-T = U^T); K_2 = I - K_1; x = x_2 + K_1 (x_1 - x_2).
    """
    omega = weights[..., 0]
    d = pair.lam / (1.0 + omega[..., None] * (pair.lam - 1.0))
    TD = pair.T * d[..., None, :]
    P = symmetrize(TD @ np.swapaxes(pair.T, -1, -2))
    K1 = omega[..., None, None] * (TD @ np.swapaxes(pair.U, -1, -2) @ pair.L1_inv)
    gains = np.stack([K1, np.eye(est.dim) - K1], axis=-3)
    x1, x2 = est.x[..., 0, :], est.x[..., 1, :]
    x = x2 + np.einsum("...ij,...j->...i", K1, x1 - x2)
    return x, P, gains


def _simplex_weights(est, kind, W):
    """Criterion-optimal weights for any N by an active-set Newton method on the simplex.

    Gradient and Hessian of f(w) = trace(W P(w)), P(w) = (sum_i w_i I_i)^-1:
    g_i = -trace(M I_i) with M = P W P, and H_ij = 2 trace(M I_i P I_j).
    For f(w) = log det P(w): g_i = -trace(P I_i), H_ij = trace(P I_i P I_j).
    """
    informations = information_matrices(est.L)
    count = est.count

    def fused_information(w):
        return symmetrize(np.einsum("...k,...kij->...ij", w, informations))

    def objective(w):
        L = cholesky(fused_information(w), "fused information matrix")
        if kind == "det":
            return -logdet_from_cholesky(L)
        return _criterion_value(cho_inverse(L), kind, W)

    def evaluate(w):
        L = cholesky(fused_information(w), "fused information matrix")
        P = cho_inverse(L)
        C = P[..., None, :, :] @ informations  # C_i = P I_i
        if kind == "det":
            f = -logdet_from_cholesky(L)
            g = -np.trace(C, axis1=-2, axis2=-1)
            H = np.einsum("...iab,...jba->...ij", C, C)
        else:
            PW = P if kind == "trace" else P @ W
            f = np.trace(PW, axis1=-2, axis2=-1)
            M = PW @ P
            E = M[..., None, :, :] @ informations  # E_i = M I_i
            g = -np.trace(E, axis1=-2, axis2=-1)
            H = 2.0 * np.einsum("...iab,...jba->...ij", E, C)
        return f, g, symmetrize(H)

    weights, iterations, converged = minimize_convex_simplex(
        evaluate, objective, count, est.batch_shape
    )
    return weights, iterations, converged, None


def ci_weights(Ps, criterion="trace", *, method="auto"):
    """Criterion-optimal Covariance Intersection weights.

    Parameters
    ----------
    Ps : sequence of array_like or array_like, shape (..., N, n, n)
        Covariances of the N >= 2 estimates.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise: ``trace(P)``, ``det(P)`` or ``trace(W P)`` for a positive
        semidefinite weight matrix ``W``.
    method : {"auto", "diagonalise", "simplex"}, optional
        ``"diagonalise"`` (two estimates only) reduces the problem to one variable by a
        simultaneous diagonalisation of P_1 and P_2; ``"simplex"`` is the active-set
        Newton method for any N; ``"auto"`` picks the first for N = 2.

    Returns
    -------
    omega : ndarray, shape (..., N)
        The weights, on the simplex; optima on the boundary are exact.
    info : dict
        ``iterations`` and ``converged`` per problem, ``solver``.

    Raises
    ------
    ValueError
        Bad covariances or criterion, or ``method="diagonalise"`` with N != 2.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import ci_weights
    >>> omega, info = ci_weights([np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])],
    ...                          criterion="det")
    >>> omega.round(6).tolist(), bool(info["converged"])
    ([0.6, 0.4], True)
    """
    est = as_covariances(Ps)
    kind, W = _parse_criterion(criterion, est.dim)
    omega, info, _ = _optimal_weights(est, kind, W, method)
    return omega, info


def _optimal_weights(est, kind, W, method="auto"):
    if method not in ("auto", "diagonalise", "simplex"):
        raise ValueError(f"method must be 'auto', 'diagonalise' or 'simplex', got {method!r}")
    if method == "diagonalise" and est.count != 2:
        raise ValueError("method='diagonalise' needs exactly two estimates")
    two = est.count == 2 and method != "simplex"
    solver = _two_estimate_weights if two else _simplex_weights
    omega, iterations, converged, pair = solver(est, kind, W)
    info = {
        "iterations": iterations,
        "converged": converged,
        "solver": "diagonalise" if two else "simplex",
    }
    return omega, info, pair


# --------------------------------------------------------------------------- public function
def covariance_intersection(xs, Ps, criterion="trace", omega=None):
    """Covariance Intersection of two or more estimates with unknown cross-correlation.

    Computes ``P^-1 = sum_i w_i P_i^-1`` and ``x = P sum_i w_i P_i^-1 x_i`` with weights
    ``w`` on the probability simplex (Julier & Uhlmann 1997; eq. (2) of Wu, Cai & Fu 2018).
    ``P`` bounds the covariance of the fused error for every admissible cross-covariance.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array of shape (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n). Symmetric
        positive definite.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What the optimal weights minimise: ``trace(P)`` (default, the mean square error
        bound), ``det(P)`` (the volume of the bound), or ``trace(W P)`` for a positive
        semidefinite weight matrix ``W`` (e.g. to weight position over velocity).
    omega : None, float, array_like or str, optional
        ``None`` (default) minimises the criterion exactly over the simplex; the problem
        is convex and the optimum is found to 1e-12 in omega, on the boundary exactly.
        A float gives the weights ``(omega, 1 - omega)`` of two estimates; an array
        (..., N) gives all weights. A string selects a fast non-iterative rule:
        ``"fast"`` (Niehsen 2002, w_i proportional to 1/trace(P_i), eq. (2) of Weng &
        Djurić, journal version), ``"improved-fast"`` (Franken & Hupper 2005) or
        ``"det-ratio"`` (eq. (7) of Weng & Djurić 2012, w_i proportional to 1/det(P_i)).

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``omega`` (..., N), ``gains`` (..., N, n, n) with ``K_i = w_i P P_i^-1`` and
        ``info`` with ``criterion``, ``value`` (criterion at the result), ``rule``
        (``"optimal"``, ``"fixed"`` or the fast rule's name), and for optimal weights
        ``iterations``, ``converged`` and ``solver``.

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, weights off the simplex, an unknown criterion
        or fast rule.
    TypeError
        Non-numeric input.

    See Also
    --------
    ci_weights : the optimal weights alone.
    fuse : the same rule through the registry (``method="ci"``).

    Notes
    -----
    For two estimates the optimal weight comes from a simultaneous diagonalisation of
    ``P_1`` and ``P_2`` that turns the criterion into a sum of scalar terms (one Newton
    iteration costs O(n) per problem); for N > 2 an active-set Newton method on the
    simplex is used. Both stop at exact boundary optima (``omega = 0`` or ``1``).

    References
    ----------
    .. [1] S. J. Julier and J. K. Uhlmann, "A non-divergent estimation algorithm in the
       presence of unknown correlations", ACC 1997.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 2018, eq. (2) and Example 2.
    .. [3] W. Niehsen, "Information fusion based on fast covariance intersection
       filtering", FUSION 2002.
    .. [4] D. Franken and A. Hupper, "Improved fast covariance intersection for
       distributed data fusion", FUSION 2005.
    .. [5] Z. Weng and P. M. Djurić, "A Bayesian approach to covariance estimation and
       data fusion", EUSIPCO 2012, eq. (7).

    Examples
    --------
    Example 2 of Wu, Cai & Fu (2018):

    >>> import numpy as np
    >>> from cifilter import covariance_intersection
    >>> r = covariance_intersection([np.zeros(2), np.zeros(2)],
    ...                             [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    >>> float(r.omega[0]), float(np.trace(r.P))
    (0.5, 3.2)
    >>> np.diag(r.gains[0]).round(6).tolist()
    [0.8, 0.2]
    """
    est = as_estimates(xs, Ps)
    kind, W = _parse_criterion(criterion, est.dim)
    info = {"criterion": kind}
    pair = None
    if omega is None:
        weights, solver_info, pair = _optimal_weights(est, kind, W)
        info.update(rule="optimal", **solver_info)
    elif isinstance(omega, str):
        if omega not in FAST_OMEGA_RULES:
            raise ValueError(
                f"omega must be None, weights or one of {', '.join(map(repr, FAST_OMEGA_RULES))}; "
                f"got {omega!r}"
            )
        weights = FAST_OMEGA_RULES[omega](est)
        info["rule"] = omega
    else:
        weights = check_weights(omega, est.count)
        weights = np.broadcast_to(weights, est.batch_shape + (est.count,)).copy()
        info["rule"] = "fixed"
    if pair is not None:
        x, P, gains = _fuse_diagonalised_pair(est, pair, weights)
    else:
        x, P, gains = weighted_information_fusion(est.x, est.L, weights)
    info["value"] = _criterion_value(P, kind, W)
    return FusionResult(restore_style(x, est.column), P, "ci", weights, gains, info)


def _registered_ci(xs, Ps, criterion="trace", omega=None):
    return covariance_intersection(xs, Ps, criterion=criterion, omega=omega)


register_method(
    "ci",
    _registered_ci,
    summary="Covariance Intersection; omega minimises trace/det of the bound, or a fast rule",
    reference="Julier & Uhlmann 1997; Niehsen 2002; Franken & Hupper 2005",
    guarantee="bound",
)
