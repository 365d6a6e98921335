"""Track-to-track association: gated statistics consistent with the fusion rule, and the
optimal assignment.

A source track ``(x_s, P_s)`` estimates ``H x`` of the central state, a central track's
prediction ``(x_c, P_c)`` estimates ``x``. The difference ``d = x_s - H x_c`` has the
covariance ``S = A + B - C - C^T`` with ``A = H P_c H^T``, ``B = P_s`` and the cross
covariance ``C``, which is unknown for CI. For every ``w`` in (0, 1) and every admissible
``C``, ``S <= A / w + B / (1 - w)``; so

    s = max_w d^T (A / w + B / (1 - w))^-1 d

is at most the true normalised distance ``d^T S^-1 d`` whatever the correlation, and equals
it for the worst admissible correlation (the bound is tight). Gating ``s`` with
``chi2.ppf(gate, m)`` rejects a true pair at most as often as ``1 - gate``. The derivation,
the proof and the solver are in ``docs/methods/track_association.rst``.
"""

from typing import Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.special import expit

from .._numerics.linalg import cho_solve, cholesky
from .._numerics.validation import as_float_array

__all__ = [
    "BISECTION_STEPS",
    "LOGIT_BRACKET",
    "ci_distance",
    "gated_assignment",
    "naive_distance",
]

#: Bisection steps on the logit of ``w`` (the bracket is halved each step): the logit is
#: found to ``2 LOGIT_BRACKET / 2**BISECTION_STEPS`` (1.5e-10), where the relative error of
#: the distance (second order at the flat maximum) is below rounding.
BISECTION_STEPS = 40
#: The logit bracket ``[-LOGIT_BRACKET, LOGIT_BRACKET]`` of the optimal ``w``: it holds
#: ``w / (1 - w) = sqrt(lambda)`` for generalised eigenvalues ``lambda`` of ``(A, B)`` from
#: ``e^-160`` to ``e^160`` (about 1e-70 to 1e70).
LOGIT_BRACKET = 80.0


def _checked(d, A, B):
    d = as_float_array(d, "d")
    A = as_float_array(A, "A")
    B = as_float_array(B, "B")
    if d.ndim < 1 or d.shape[-1] == 0:
        raise ValueError(f"d must have shape (..., m) with m >= 1, got {d.shape}")
    m = d.shape[-1]
    for name, M in (("A", A), ("B", B)):
        if M.ndim < 2 or M.shape[-2:] != (m, m):
            raise ValueError(f"{name} must have shape (..., {m}, {m}) to match d, got "
                             f"{M.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("d contains non-finite values (NaN or inf)")
    batch = np.broadcast_shapes(d.shape[:-1], A.shape[:-2], B.shape[:-2])
    d = np.broadcast_to(d, batch + (m,))
    A = np.broadcast_to(A, batch + (m, m))
    B = np.broadcast_to(B, batch + (m, m))
    cholesky(0.5 * (A + np.swapaxes(A, -1, -2)), "A")
    cholesky(0.5 * (B + np.swapaxes(B, -1, -2)), "B")
    return d, 0.5 * (A + np.swapaxes(A, -1, -2)), 0.5 * (B + np.swapaxes(B, -1, -2))


def _quadratic(M, v):
    return np.einsum("...i,...ij,...j->...", v, M, v)


def _value_and_slope(d, A, B, t):
    """``f(w) = w (1 - w) d^T N^-1 d`` with ``N = (1 - w) A + w B`` (``= d^T M^-1 d``,
    ``M = A / w + B / (1 - w)``) at ``w = expit(t)``, and the sign of ``df/dw``:
    ``(1 - w)^2 y^T A y - w^2 y^T B y`` with ``y = N^-1 d``."""
    w, v = expit(t), expit(-t)  # w and 1 - w, each to full relative precision
    N = v[..., None, None] * A + w[..., None, None] * B
    L = np.linalg.cholesky(N)
    y = cho_solve(L, d)
    value = w * v * np.einsum("...i,...i->...", y, d)
    slope = np.sqrt(_quadratic(A, y)) * v - np.sqrt(_quadratic(B, y)) * w
    return value, slope


def ci_distance(d: ArrayLike, A: ArrayLike, B: ArrayLike, *,
                threshold: Optional[float] = None) -> tuple[NDArray[np.float64],
                                                            NDArray[np.float64]]:
    """The association distance of two estimates whose correlation is unknown.

    ``s = max over w in (0, 1) of d^T (A / w + B / (1 - w))^-1 d``: a lower bound of the
    true normalised distance ``d^T S^-1 d`` of the difference ``d`` for every admissible
    correlation of the two estimates (``S`` their difference's covariance), reached by the
    worst one. ``d^T (A / w + B / (1 - w))^-1 d`` is concave in ``w``; its maximum is found
    by bisection on the sign of its derivative in the logit of ``w``, every evaluation a
    Cholesky factorisation of ``(1 - w) A + w B`` (no inverse, no squared condition number).

    Parameters
    ----------
    d : array_like, shape (..., m)
        Differences of the two means (source minus ``H`` times the central prediction).
    A : array_like, shape (..., m, m)
        Covariance of the first estimate in the measured space (``H P_c H^T``).
    B : array_like, shape (..., m, m)
        Covariance of the second estimate (``P_s``). Batch axes broadcast.
    threshold : float, optional
        When given, the pairs whose distance provably exceeds ``threshold`` after one
        evaluation are not solved further: their returned distance is a lower bound above
        ``threshold`` (enough to gate them out) and their ``w`` is that evaluation's.

    Returns
    -------
    s : ndarray, shape (...)
        The distances.
    w : ndarray, shape (...)
        The maximising weight of ``A`` (``A / w``).

    Raises
    ------
    ValueError
        Shapes that do not match, non-finite entries, ``A`` or ``B`` not positive definite.
    TypeError
        Non-numeric input.

    See Also
    --------
    naive_distance : the distance when the estimates are assumed independent.

    Notes
    -----
    Derivation and proof: ``docs/methods/track_association.rst``. One-dimensional case:
    ``s = d^2 / (sqrt(A) + sqrt(B))^2``, the distance for perfectly correlated errors of
    opposite sign.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import ci_distance
    >>> s, w = ci_distance(np.array([3.0]), np.array([[1.0]]), np.array([[4.0]]))
    >>> round(float(s), 12), round(float(w), 9)
    (1.0, 0.333333333)

    Its ``w`` is ``sqrt(A) / (sqrt(A) + sqrt(B))`` there; in more dimensions the distance is
    the smallest true normalised distance over all correlations:

    >>> d, A, B = np.array([1.0, 2.0]), np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    >>> s, w = ci_distance(d, A, B)
    >>> bool(s <= d @ np.linalg.solve(A + B, d))
    True
    """
    dc, Ac, Bc = _checked(d, A, B)
    batch = dc.shape[:-1]
    m = dc.shape[-1]
    dv, Av, Bv = dc.reshape(-1, m), Ac.reshape(-1, m, m), Bc.reshape(-1, m, m)
    # the start: the logit of the optimum of the traces' scalar problem
    tA = np.trace(Av, axis1=-2, axis2=-1)
    tB = np.trace(Bv, axis1=-2, axis2=-1)
    start = np.clip(0.5 * (np.log(tA) - np.log(tB)), -LOGIT_BRACKET, LOGIT_BRACKET)
    s, slope = _value_and_slope(dv, Av, Bv, start)
    t_best = start.copy()
    todo = np.ones(s.shape, dtype=bool) if threshold is None else ~(s > threshold)
    if todo.any():
        dd, AA, BB = dv[todo], Av[todo], Bv[todo]
        # the optimum lies right of the start where f increases there, left otherwise
        rising = slope[todo] > 0
        low = np.where(rising, start[todo], -LOGIT_BRACKET)
        high = np.where(rising, LOGIT_BRACKET, start[todo])
        best = s[todo]
        for _ in range(BISECTION_STEPS):
            middle = 0.5 * (low + high)
            value, slope_m = _value_and_slope(dd, AA, BB, middle)
            better = value > best
            best = np.where(better, value, best)
            rising = slope_m > 0
            low = np.where(rising, middle, low)
            high = np.where(rising, high, middle)
        # w: where the derivative's sign changes; s: the largest value evaluated (f is
        # flat there, so the two agree to rounding)
        s[todo] = best
        t_best[todo] = 0.5 * (low + high)
    return s.reshape(batch), expit(t_best).reshape(batch)


def naive_distance(d: ArrayLike, A: ArrayLike, B: ArrayLike) -> NDArray[np.float64]:
    """The normalised distance of two estimates assumed independent: ``d^T (A + B)^-1 d``.

    Parameters
    ----------
    d : array_like, shape (..., m)
        Differences of the two means.
    A, B : array_like, shape (..., m, m)
        Their covariances (``H P_c H^T`` and ``P_s``). Batch axes broadcast.

    Returns
    -------
    ndarray, shape (...)
        The distances (chi-square with m degrees of freedom for independent Gaussian
        errors; smaller or larger than that for correlated ones).

    Raises
    ------
    ValueError
        Shapes that do not match, non-finite entries, ``A`` or ``B`` not positive definite.
    TypeError
        Non-numeric input.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import naive_distance
    >>> float(naive_distance(np.array([3.0]), np.array([[1.0]]), np.array([[8.0]])))
    1.0
    """
    dc, Ac, Bc = _checked(d, A, B)
    L = np.linalg.cholesky(Ac + Bc)
    return np.asarray(np.einsum("...i,...i->...", cho_solve(L, dc), dc), dtype=np.float64)


def gated_assignment(cost: ArrayLike, threshold: float
                     ) -> list[tuple[int, int]]:
    """The optimal assignment of rows to columns among the pairs inside the gate.

    ``scipy.optimize.linear_sum_assignment`` minimises the total distance over the pairs
    whose distance is at most ``threshold``; a row or column without such a pair stays
    unassigned. Each row and each column is used at most once.

    Parameters
    ----------
    cost : array_like, shape (rows, columns)
        Distances (NaN or inf: never assigned).
    threshold : float
        The gate.

    Returns
    -------
    list of (int, int)
        The assigned ``(row, column)`` pairs, sorted by row.

    Raises
    ------
    ValueError
        ``cost`` not two-dimensional.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import gated_assignment
    >>> gated_assignment(np.array([[1.0, 0.5], [0.2, 9.0]]), threshold=5.0)
    [(0, 1), (1, 0)]
    >>> gated_assignment(np.array([[1.0, 7.0], [0.9, 9.0]]), threshold=5.0)
    [(1, 0)]
    """
    cost = np.array(cost, dtype=float)
    if cost.ndim != 2:
        raise ValueError(f"cost must be a 2-D array (rows, columns), got shape {cost.shape}")
    if cost.size == 0:
        return []
    inside = np.isfinite(cost) & (cost <= threshold)
    if not inside.any():
        return []
    # pairs outside the gate cost more than any assignment of pairs inside it, so the
    # optimum never trades an inside pair for an outside one
    big = 1.0 + float(np.abs(cost[inside]).sum()) * 2.0 + cost.shape[0] + cost.shape[1]
    work = np.where(inside, cost, big)
    rows, columns = linear_sum_assignment(work)
    return sorted((int(r), int(c)) for r, c in zip(rows, columns) if inside[r, c])

