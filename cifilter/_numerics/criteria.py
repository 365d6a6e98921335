"""Criteria of a fused covariance bound: parsing, values, gradients and certified gaps.

Shared by Covariance Intersection, its horizon form and the fast path of the filter
classes. A criterion is ``"trace"``, ``"det"`` or a weight matrix ``W`` (``trace(W P)``);
internally it is the pair ``(kind, W)`` with ``kind`` in ``{"trace", "det",
"weighted-trace"}``. Gradients are taken in the weights of an information-form fusion
``P^-1 = sum_i w_i P_i^-1`` from the factors of
:func:`cifilter._numerics.information.information_factors`.
"""

import numpy as np

from .information import checked_cholesky, squared_norms
from .linalg import logdet_from_cholesky
from .optimize import frank_wolfe_gap
from .validation import check_psd_weight_matrix

__all__ = [
    "GAP_TOL",
    "certified_gap",
    "criterion_gradient",
    "criterion_of_factor",
    "criterion_report",
    "criterion_value",
    "parse_criterion",
]


def parse_criterion(criterion, n):
    """('trace', None), ('det', None) or ('weighted-trace', W)."""
    if isinstance(criterion, str):
        if criterion in ("trace", "det"):
            return criterion, None
        raise ValueError(
            f"criterion must be 'trace', 'det' or a positive semidefinite {n}x{n} weight "
            f"matrix, got {criterion!r}"
        )
    return "weighted-trace", check_psd_weight_matrix(criterion, n, "criterion")


def criterion_value(P, kind, W):
    if kind == "det":
        return np.linalg.det(P)
    if kind == "trace":
        return np.trace(P, axis1=-2, axis2=-1)
    return np.einsum("...ij,...ji->...", W, P)


# A weight vector is accepted as optimal when its certified gap (below) is at most GAP_TOL:
# relative for trace(W P), absolute in log det P (a relative excess of det P).
GAP_TOL = 1e-9


def criterion_gradient(factors, kind, W):
    """``g_i = -d f / d w_i >= 0`` from the information factors, without cancellation.

    ``f = trace(W P)``: ``g_i = trace(W B_i B_i^T)``; ``f = log det P``: ``g_i = ||C_i||^2``
    (``B_i = P L_i^-T``, ``C_i = R^-1 L_i^-T``; see ``_information.information_factors``).
    """
    if kind == "det":
        return squared_norms(factors.C)
    if kind == "trace":
        return squared_norms(factors.B)
    return np.einsum("...ij,...kjl,...kil->...k", W, factors.B, factors.B)


def criterion_of_factor(R_inv, kind, W):
    """``trace(W P)`` or ``log det P`` for ``P = R_inv^T R_inv``."""
    if kind == "det":
        return 2.0 * np.log(np.abs(np.diagonal(R_inv, axis1=-2, axis2=-1))).sum(axis=-1)
    if kind == "trace":
        return squared_norms(R_inv)
    return np.einsum("...ij,...ki,...kj->...", W, R_inv, R_inv)


def certified_gap(weights, g, value, kind):
    """Frank-Wolfe gap: a certified bound on ``f(w) - min_simplex f``.

    ``f`` is convex on the simplex with gradient ``-g``, so ``min f >= f(w) - gap`` with
    ``gap = max_i g_i - sum_i w_i g_i``. Relative to ``f`` for the trace criteria, in
    log det units (a relative excess of det P) for the determinant.
    """
    gap = frank_wolfe_gap(weights, -g)
    return gap if kind == "det" else gap / value


def criterion_report(P, kind, W):
    """``value`` (and ``log_value`` for det) of the criterion at the returned ``P``.

    Also the final check of the conditioning contract: ``P`` must be finite and
    numerically positive definite, else IllConditionedError.
    """
    L = checked_cholesky(P, "the fused covariance")
    if kind == "det":
        log_det = logdet_from_cholesky(L)
        with np.errstate(over="ignore", under="ignore"):
            return {"value": np.exp(log_det), "log_value": log_det}
    if kind == "trace" and P.ndim == 2:
        return {"value": P.trace()}  # (one problem: the method, not numpy's dispatch)
    return {"value": criterion_value(P, kind, W)}
