"""Covariance union (Uhlmann 2003): one estimate that covers every input, mean and covariance.

The fused estimate ``(u, U)`` satisfies, for every input ``(x_i, P_i)``,

    U >= P_i + (u - x_i)(u - x_i)^T,

so ``U`` bounds the error covariance of the fused mean whichever input is the right one
(inconsistent or spurious tracks, competing hypotheses). Among such ``U`` the smallest in
determinant or trace is chosen, and the mean ``u`` minimises that criterion. Derivations:
``docs/methods/union.rst``.
"""

from typing import Any, Optional

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.validation import (
    as_estimates,
    as_float_array,
    check_finite,
    restore_style,
    vector_style,
)
from ..result import FusionResult
from ._union import (
    CRITERIA,
    check_union,
    criterion_of,
    mean_candidates_value,
    optimal_pair_mean,
    separable_start,
    sequential_union,
)

__all__ = ["covariance_union"]


def covariance_union(xs: ArrayLike, Ps: ArrayLike, criterion: str = "trace",
                     mean: Optional[ArrayLike] = None) -> FusionResult:
    """Covariance union: the smallest estimate whose covariance covers every input.

    Returns ``(u, U)`` with ``U >= P_i + (u - x_i)(u - x_i)^T`` for every input ``i``
    (Uhlmann 2003, the covariance union condition; MATLAB's ``fusecovunion``), of smallest
    ``trace(U)`` or ``det(U)``. For two estimates ``U`` is the exact minimiser for the
    returned mean, and the mean minimises the criterion over all means (trace: certified
    by a dual bound; det: a stationary point). For three or more, ``U`` is a valid bound
    built by pairwise unions and is not in general the smallest.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n); symmetric
        positive definite.
    criterion : {"trace", "det"}, optional
        What the union minimises: ``trace(U)`` (default; the problem is convex in the mean
        and the optimum is certified) or ``det(U)`` (the volume of the ellipsoid).
    mean : None or array_like, optional
        None (default) chooses the mean: for two estimates the minimiser of the criterion
        (per-direction rule with a descent safeguard), for more the best of the inputs'
        means and their average. An array (..., n) or (..., n, 1) fixes the fused mean
        (for instance to keep one's own track) and only ``U`` is computed.

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``method="cu"``, ``weights=None`` and ``gains=None`` (the union is not a weighting
        of the inputs), ``info`` with ``criterion``, ``value`` (trace or determinant of
        ``P``; for ``"det"`` also ``log_value``), ``rule`` (``"optimal"``,
        ``"candidates"`` or ``"fixed"``), ``optimal_covariance`` (True for two estimates:
        ``P`` is the smallest bound for ``x``) and, for the optimal mean of two estimates,
        ``iterations`` (for the trace, the Newton steps of the smoothed continuation that
        solves every problem not certified at its starting mean, with the kink's Newton
        steps that end it early), ``smoothed`` (True where that continuation finished
        the problem), ``converged`` and ``gap`` (trace: certified relative excess of the
        criterion over its minimum over all means; NaN for det).

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, an unknown criterion, a ``mean`` of the wrong
        shape or with non-finite values.
    IllConditionedError
        (a ValueError) The union is not numerically positive definite (beyond the
        conditioning contract).
    TypeError
        Non-numeric input.

    See Also
    --------
    covariance_intersection : the conservative fusion of consistent estimates.
    fuse : the same rule through the registry (``method="cu"``).

    Notes
    -----
    For two matrices ``A = M_1``, ``B = M_2`` the smallest upper bound is, for the
    determinant, ``T diag(max(1, d)) T^T`` with ``A = T T^T``, ``B = T diag(d) T^T``,
    and for the trace ``A + (B - A)_+``. In the coordinates of these decompositions the
    optimal mean takes, direction by direction, the coordinate of the mean whose matrix
    dominates (between the two at ties); the mean is found by iterating that rule with
    steps onto the kinks of the criterion and Newton steps. The guarantee
    ``P >= M_i`` holds to rounding relative to ``||P||`` for input condition numbers up to
    1e12. Derivations and proofs: ``docs/methods/union.rst``.

    References
    ----------
    .. [1] J. K. Uhlmann, "Covariance consistency methods for fault-tolerant distributed
       data fusion", Information Fusion 4(3), 2003 (the covariance union condition).
    .. [2] S. Reece and S. Roberts, "Generalised covariance union: a unified approach to
       hypothesis merging in tracking", IEEE Trans. AES 46(1), 2010.
    .. [3] MathWorks, Sensor Fusion and Tracking Toolbox, ``fusecovunion``.

    Examples
    --------
    Two scalar tracks that disagree: the union is centred between them and covers both.

    >>> import numpy as np
    >>> from cifilter import covariance_union
    >>> r = covariance_union([np.array([0.0]), np.array([2.0])], [np.eye(1), np.eye(1)])
    >>> r.x.round(6).tolist(), r.P.round(6).tolist()
    ([1.0], [[2.0]])

    A fixed mean (the first track) and the determinant criterion:

    >>> r = covariance_union([np.zeros(2), np.ones(2)], [np.eye(2), np.eye(2)],
    ...                      criterion="det", mean=np.zeros(2))
    >>> r.P.round(6).tolist()
    [[2.0, 1.0], [1.0, 2.0]]
    """
    est = as_estimates(xs, Ps)
    return _covariance_union(est, criterion, mean)


def _check_mean(mean, est):
    u = as_float_array(mean, "mean")
    n = est.dim
    style = vector_style(u, n)
    if style is None:
        raise ValueError(f"mean must have shape (..., {n}) or (..., {n}, 1), got shape {u.shape}")
    if style == "column":
        u = u[..., 0]
    check_finite(u, "mean")
    try:
        batch = np.broadcast_shapes(u.shape[:-1], est.batch_shape)
    except ValueError:
        raise ValueError(f"mean's batch shape {u.shape[:-1]} does not broadcast against the "
                         f"estimates' {est.batch_shape}") from None
    return batch, u


def _covariance_union(est, criterion="trace", mean=None):
    """The ``"cu"`` rule on validated estimates (the core of :func:`covariance_union`)."""
    if not isinstance(criterion, str) or criterion not in CRITERIA:
        raise ValueError(f"criterion must be 'trace' or 'det', got {criterion!r}")
    kind = criterion
    x, P = est.x, est.P
    count = est.count
    info = {"criterion": kind, "optimal_covariance": count == 2}
    # Pairwise unions, largest input first (a fixed order: the result does not depend on the
    # order in which the estimates are given, except between inputs of equal size)
    size = (np.trace(P, axis1=-2, axis2=-1) if kind == "trace"
            else 2.0 * np.log(np.diagonal(est.L, axis1=-2, axis2=-1)).sum(axis=-1))
    order = np.argsort(-size, axis=-1, kind="stable")
    if mean is not None:
        batch, u = _check_mean(mean, est)
        x = np.broadcast_to(x, batch + x.shape[-2:])
        P = np.broadcast_to(P, batch + P.shape[-3:])
        order = np.broadcast_to(order, batch + order.shape[-1:])
        u = np.broadcast_to(u, batch + u.shape[-1:])
        info["rule"] = "fixed"
    else:
        candidates = [x, x.mean(axis=-2, keepdims=True)]
        if count == 2:
            candidates.append(separable_start(P, x, kind)[..., None, :])
        candidates = np.concatenate(candidates, axis=-2)
        values = mean_candidates_value(P, x, candidates, kind, order)
        best = np.argmin(values, axis=-1)
        u = np.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
        if count == 2:
            u, _, _, iterations, converged, gap, smoothed = optimal_pair_mean(P, x, kind, u)
            info.update(rule="optimal", iterations=iterations, converged=converged, gap=gap,
                        smoothed=smoothed)
        else:
            info["rule"] = "candidates"
    U = sequential_union(P, x, u, kind, order)
    check_union(U)
    value = criterion_of(U, kind)
    if kind == "det":
        with np.errstate(over="ignore", under="ignore"):
            info.update(value=np.exp(value), log_value=value)
    else:
        info["value"] = value
    return FusionResult(restore_style(np.array(u), est.column), U, "cu", None, None, info)


REGISTRATION: dict[str, Any] = dict(
    name="cu",
    function=covariance_union,
    core=_covariance_union,
    summary="Covariance union: smallest (trace/det) estimate covering every input's mean "
            "and covariance",
    reference="Uhlmann 2003; Reece & Roberts 2010; MATLAB fusecovunion",
    guarantee="bound",
    weights="None: the union covers the inputs, it does not weight them",
)
"""The record of the ``"cu"`` rule (registered by :mod:`cifilter.rules`).

Its ``"bound"`` is of a different kind than CI's: ``P`` bounds the error covariance of the
fused mean about each input's mean, ``P >= P_i + (x - x_i)(x - x_i)^T`` for every ``i``,
so it holds if any one input is consistent, whatever the others and their correlation."""
