"""Criteria of a fused covariance bound: parsing, values, gradients and certified gaps.

Shared by Covariance Intersection, its horizon form and the fast path of the filter
classes. A criterion is ``"trace"``, ``"det"`` or a weight matrix ``W`` (``trace(W P)``);
internally it is the pair ``(kind, W)`` with ``kind`` in ``{"trace", "det",
"weighted-trace"}``. Gradients are taken in the weights of an information-form fusion
``P^-1 = sum_i w_i P_i^-1`` from the factors of
:func:`cifilter._numerics.information.information_factors`.
"""

from typing import NamedTuple

import numpy as np

from .information import checked_cholesky, squared_norms
from .linalg import logdet_from_cholesky
from .optimize import frank_wolfe_gap, interval_gap
from .validation import check_psd_weight_matrix

__all__ = [
    "GAP_FLOOR_SAFETY",
    "GAP_TOL",
    "SLOPE_ROUNDING",
    "GapCertificate",
    "certified_gap",
    "criterion_gradient",
    "criterion_of_factor",
    "criterion_report",
    "criterion_value",
    "gap_certificate",
    "gap_converged",
    "gradient_rounding",
    "pair_certificate",
    "parse_criterion",
    "parsed_or_none",
    "rounding_scale",
    "scaled_condition",
    "slope_rounding",
    "slope_rounding_single",
]

_EPS = float(np.finfo(float).eps)


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


def parsed_or_none(criterion, n):
    """:func:`parse_criterion`'s answer, or None where it raises: for the short routes of
    single calls, which leave the error to the usual route (it raises it after the
    estimates' own errors, which come first)."""
    if type(criterion) is str and criterion in ("trace", "det"):
        return criterion, None
    try:
        return parse_criterion(criterion, n)
    except (TypeError, ValueError):
        return None


def criterion_value(P, kind, W):
    if kind == "det":
        return np.linalg.det(P)
    if kind == "trace":
        return np.trace(P, axis1=-2, axis2=-1)
    return np.einsum("...ij,...ji->...", W, P)


# A weight vector is accepted as optimal when its certified gap (below) is at most GAP_TOL:
# relative for trace(W P), absolute in log det P (a relative excess of det P), or, where
# the rounding of the inputs alone allows more, at most GAP_FLOOR_SAFETY times that
# rounding floor (:func:`gap_converged`; docs/conventions.rst, "converged").
GAP_TOL = 1e-9
GAP_FLOOR_SAFETY = 2.0


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


def scaled_condition(L, L_inv):
    """An upper bound of the condition number of ``D^-1 L L^T D^-1`` (..., ), ``D`` the
    square roots of the diagonal of ``L L^T``, from a triangular factor and its inverse.

    ``||D^-1 L||_F^2 = n`` (its rows have unit norm), so the bound is ``n ||L^-1 D||_F^2``.
    This scaled condition governs the rounding of a Cholesky factorisation (its backward
    error is small relative to the diagonal, so graded matrices, mixed units, are not
    penalised for their grading).
    """
    n = L.shape[-1]
    d = np.sqrt(np.square(L).sum(axis=-1))
    return n * squared_norms(L_inv * d[..., None, :])


def gradient_rounding(factors, L, L_inv, g):
    """A bound of the rounding in the gradients ``g`` (..., N) of
    :func:`criterion_gradient`, per problem (..., ): ``rho * max_i |g_i|`` with

        rho = 4 (n + 1) eps (kappa_s(J) + max_i kappa_s(P_i)),

    ``kappa_s`` the scaled condition numbers (:func:`scaled_condition`) of the fused
    information ``J = R R^T`` and of the inputs ``P_i = L_i L_i^T``. Each gradient is a
    trace of products of the inverse factors; a relative perturbation ``eta`` of the
    matrices they factor (in their own metric) changes it by at most about ``2 eta`` of its
    size, and the Cholesky factorisations and triangular inverses are backward stable with
    ``eta = (n + 1) eps kappa_s`` each (first order; the factor 4 covers the two
    factorisations and the products). It is also what a relative perturbation of the
    inputs of order ``eps`` can change the exact gradients by: double precision cannot
    resolve the gradients more finely.
    """
    n = factors.R.shape[-1]
    with np.errstate(over="ignore", invalid="ignore"):
        kappa = (scaled_condition(factors.R, factors.R_inv)
                 + scaled_condition(L, L_inv).max(axis=-1))
        return 4.0 * (n + 1) * _EPS * kappa * np.abs(g).max(axis=-1)


class GapCertificate(NamedTuple):
    """A certified optimality gap and its parts (arrays of the batch shape).

    ``gap`` bounds the excess of the exact criterion at the returned weights over its
    minimum, rounding included; ``floor`` is the part of it that the rounding of the
    inputs alone creates (what double precision cannot resolve); ``computed`` is the gap
    of the computed gradients, without the rounding (``gap <= computed + floor``).
    """

    gap: np.ndarray
    floor: np.ndarray
    computed: np.ndarray


def gap_converged(gap, floor, computed):
    """``converged``: optimal to the precision the inputs allow (docs/conventions.rst).

    ``gap <= max(GAP_TOL, GAP_FLOOR_SAFETY * floor)`` and ``computed <= GAP_TOL + floor``:
    the certified gap is within the tolerance or, where the rounding floor exceeds it,
    within a small multiple of that floor; and the gap of the computed gradients never
    exceeds the tolerance by more than the floor (so a solver stopped short of the optimum
    is never reported converged because the floor is large).
    """
    if isinstance(gap, float):  # one problem (the single-call path): Python floats
        return gap <= max(GAP_TOL, GAP_FLOOR_SAFETY * floor) and computed <= GAP_TOL + floor
    with np.errstate(invalid="ignore"):
        return ((gap <= np.maximum(GAP_TOL, GAP_FLOOR_SAFETY * floor))
                & (computed <= GAP_TOL + floor))


def gap_certificate(weights, g, value, kind, rounding):
    """The Frank-Wolfe certificate of :func:`certified_gap` with its parts.

    ``rounding`` (..., ): a bound ``r`` of ``max_i |g_i - g_i^exact|`` (for instance
    :func:`gradient_rounding`). The gap is the largest over every gradient within ``r`` of
    ``g``, ``max_i (g_i + 2 r (1 - w_i)) - sum_i w_i g_i``, plus the rounding of that sum
    (``N eps |sum_i w_i g_i|``), so it bounds the excess of the exact criterion even where
    the computed gap rounds to zero. (At a vertex whose gradient exceeds every other by
    more than ``2 r`` it stays at the rounding of the sum: the vertex is then provably
    optimal.) The floor is ``2 r + N eps |sum_i w_i g_i|``, of which the gap exceeds the
    computed one by at most. Relative to ``value`` for the trace criteria, in log det units
    for the determinant.
    """
    count = g.shape[-1]
    r = np.asarray(rounding)[..., None]
    with np.errstate(invalid="ignore", over="ignore"):
        along = np.einsum("...i,...i->...", weights, g)
        computed = frank_wolfe_gap(weights, -g)
        summed = count * _EPS * np.abs(along)
        gap = np.maximum((g + 2.0 * r * (1.0 - weights)).max(axis=-1) - along, 0.0) + summed
        floor = 2.0 * r[..., 0] + summed
        if kind != "det":
            gap, floor, computed = gap / value, floor / value, computed / value
    return GapCertificate(gap, floor, computed)


def certified_gap(weights, g, value, kind, rounding=None):
    """Frank-Wolfe gap: a certified bound on ``f(w) - min_simplex f``.

    ``f`` is convex on the simplex with gradient ``-g``, so ``min f >= f(w) - gap`` with
    ``gap = max_i g_i - sum_i w_i g_i``. Relative to ``f`` for the trace criteria, in
    log det units (a relative excess of det P) for the determinant.

    ``rounding`` (..., ), optional: a bound of the rounding in ``g``; the gap then includes
    it (:func:`gap_certificate`, whose ``gap`` this returns).
    """
    if rounding is not None:
        return gap_certificate(weights, g, value, kind, rounding).gap
    gap = frank_wolfe_gap(weights, -g)
    return gap if kind == "det" else gap / value


# The rounding of the diagonalised slope: the eigenvalues of S = L_1^-1 P_2 L_1^-T carry
# absolute rounding of about eps sigma, sigma = max(lam_max, ||L_1^-1||_F^2 ||P_2||_F) (the
# size of S and of the rounding in forming it; a relative perturbation eps of P_1 moves
# them as much), and the slope is a sum of terms t_k(lam_k), so to first order it moves by
# at most eps sigma sum_k |dt_k / dlam_k|, times this constant (the eigensolver's and the
# products' rounding, n terms summed) and n. The compiled kernel uses the same bound
# (``_kernels/compiled.py``).
SLOPE_ROUNDING = 16.0


def rounding_scale(L1_inv, P2):
    """``||L_1^-1||_F^2 ||P_2||_F`` (...,), each norm scaled by its largest entry so that
    neither overflows at extreme scales."""
    a = np.abs(L1_inv).max(axis=(-2, -1))
    b = np.abs(P2).max(axis=(-2, -1))
    with np.errstate(all="ignore"):
        na = squared_norms(L1_inv / a[..., None, None])
        nb = np.sqrt(squared_norms(P2 / b[..., None, None]))
        return (a * a * b) * na * nb


def slope_rounding(lam, omega, c, sigma):
    """A bound ``e`` of the rounding in the diagonalised slope ``f'`` (..., ).

    ``lam`` (..., n) the generalised eigenvalues, ``c`` (..., n) the criterion's weights of
    the diagonal terms (None for det), ``sigma`` (..., ) the scale of their rounding.
    ``f' = -sum_k t_k`` with ``t_k = c_k lam_k (lam_k - 1) / D_k^2`` (trace) or
    ``(lam_k - 1) / D_k`` (det), ``D_k = 1 + omega (lam_k - 1)``;
    ``e = SLOPE_ROUNDING n eps sigma sum_k |dt_k / dlam_k|``.
    """
    lam = np.asarray(lam, dtype=float)
    n = lam.shape[-1]
    w = np.asarray(omega, dtype=float)[..., None]
    with np.errstate(all="ignore"):
        D = 1.0 + w * (lam - 1.0)
        if c is None:
            sensitivity = 1.0 / (D * D)
        else:
            sensitivity = np.abs(c) * np.abs((2.0 * lam - 1.0) * D
                                             - 2.0 * w * lam * (lam - 1.0)) / D**3
        return (SLOPE_ROUNDING * n * _EPS * np.asarray(sigma)
                * sensitivity.sum(axis=-1))


def slope_rounding_single(lam, omega, c, sigma):
    """:func:`slope_rounding` of one problem in Python floats (``lam`` and ``c`` lists,
    ``c`` None for det): the single-call path, where numpy's per-call cost would dominate."""
    total = 0.0
    for k, value in enumerate(lam):
        D = 1.0 + omega * (value - 1.0)
        if c is None:
            total += 1.0 / (D * D)
        else:
            total += abs(c[k]) * abs((2.0 * value - 1.0) * D
                                     - 2.0 * omega * value * (value - 1.0)) / (D * D * D)
    return SLOPE_ROUNDING * len(lam) * _EPS * sigma * total


def pair_certificate(omega, slope, rounding, value=None):
    """The certificate of a two-estimate weight from its slope (arrays or floats).

    ``gap`` is the larger of the :func:`interval_gap` at the slopes ``f' +- e`` (it is
    convex in the slope, so one of the two ends bounds it over every slope within ``e``)
    plus the rounding of that product, ``2 eps (|f'| + e)`` (so it is never 0.0 where
    ``e > 0``); ``floor = e + 2 eps (|f'| + e)`` (the gap exceeds the computed one by at
    most that); ``computed`` the interval gap of the computed slope; all divided by
    ``value`` (the trace criterion at ``omega``) unless it is None (det: log det units).
    """
    if (type(slope) is float and type(rounding) is float and type(omega) is float
            and (value is None or type(value) is float)):
        # one problem in Python floats (the single-call path): no numpy warning to silence
        return _pair_certificate(max, omega, slope, rounding, value)
    maximum = max if isinstance(slope, float) else np.maximum
    with np.errstate(all="ignore"):
        return _pair_certificate(maximum, omega, slope, rounding, value)


def _pair_certificate(maximum, omega, slope, rounding, value):
    product = 2.0 * _EPS * (abs(slope) + rounding)
    gap = maximum(interval_gap(omega, slope - rounding),
                  interval_gap(omega, slope + rounding)) + product
    computed = interval_gap(omega, slope)
    floor = rounding + product
    if value is not None:
        gap, floor, computed = gap / value, floor / value, computed / value
    return GapCertificate(gap, floor, computed)


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
