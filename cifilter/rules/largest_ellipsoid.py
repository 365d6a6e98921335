"""Largest-ellipsoid ("safe") fusion of two estimates (Benaskeur 2002; Nygårds et al. 2016).

In coordinates where both covariances are diagonal (a simultaneous diagonalisation,
``Pa = T T^T``, ``Pb = T diag(d) T^T``) the rule keeps, direction by direction, the more
informative estimate: its mean coordinate and its variance. The fused covariance
``T diag(min(1, d)) T^T`` is the largest ellipsoid inside the intersection of the two input
ellipsoids, and equals Ellipsoidal Intersection's; the means agree with EI's unregularised
(``eps=0``) mean. No guarantee: see ``docs/methods/largest_ellipsoid.rst``.
"""

from typing import Any

from numpy.typing import ArrayLike

from .._numerics.validation import as_estimates, restore_style
from ..result import FusionResult
from ._ellipsoidal import check_pair, largest_ellipsoid_fusion

__all__ = ["largest_ellipsoid"]


def largest_ellipsoid(xs: ArrayLike, Ps: ArrayLike) -> FusionResult:
    """Largest-ellipsoid (safe) fusion: per decorrelated direction, keep the better estimate.

    With ``Pa = T T^T`` and ``Pb = T diag(d) T^T`` (simultaneous diagonalisation; step 1-2
    of the safe fusion algorithm of Nygårds, Deleskog & Hendeby 2016, the largest
    ellipsoid algorithm of Benaskeur 2002), the fused estimate in the coordinates
    ``y = T^-1 x`` takes, per direction, the coordinate and the variance of the input with
    the smaller variance:

        P = T diag(min(1, d)) T^T,    x = K_a xa + K_b xb,
        K_a = T diag(k) T^-1,  K_b = I - K_a,  k = 1 (d > 1), 0 (d < 1), 1/2 (d = 1).

    Parameters
    ----------
    xs : sequence of array_like or array_like
        The two means, each (n,) or (n, 1) with optional leading batch axes, or one array
        (..., 2, n).
    Ps : sequence of array_like or array_like
        Their covariances, each (..., n, n), or one array (..., 2, n, n); symmetric
        positive definite.

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n)
        symmetric positive definite, ``method="le"``, ``weights=None`` (a per-direction
        selection, not a scalar weighting), ``gains`` (..., 2, n, n) with
        ``x = K_a xa + K_b xb`` and ``K_a + K_b = I``, ``info`` with ``kept`` (..., n) (the
        share of the first estimate in each direction: 1, 0 or 1/2) and ``ties`` (...,)
        (directions in which both are equally informative; there the means are averaged).

    Raises
    ------
    ValueError
        Not exactly two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite.
    IllConditionedError
        (a ValueError) Instead of a ``P`` that is not positive definite (beyond the
        conditioning contract).
    TypeError
        Non-numeric input.

    See Also
    --------
    ellipsoidal_intersection : the same covariance; the mean from an estimated common part.
    covariance_intersection : a bound for any correlation; its ``P`` dominates this one.

    Notes
    -----
    The covariance is exactly EI's (``cifilter.ellipsoidal_intersection``, any
    ``eps`` with the default information regulariser) and the mean is EI's with ``eps=0``;
    it is dominated by CI's covariance (``P_CI >= P_LE``: CI's ellipsoid contains the
    intersection of the input ellipsoids, this one lies inside it). In one dimension, and
    whenever ``Pa <= Pb``, the rule returns the better input, as optimal CI does. It has no
    guarantee: with independent inputs it is too cautious, with correlated ones it can be
    overconfident (``docs/methods/largest_ellipsoid.rst``).

    References
    ----------
    .. [1] A. R. Benaskeur, "Consistent fusion of correlated data sources", IECON 2002.
    .. [2] J. Nygårds, V. Deleskog and G. Hendeby, "Safe fusion compared to established
       distributed fusion methods", IEEE MFI 2016, Algorithm 1.

    Examples
    --------
    Each input is better along one axis; the rule keeps each one's better axis:

    >>> import numpy as np
    >>> from cifilter import largest_ellipsoid
    >>> r = largest_ellipsoid([np.array([1.0, 0.0]), np.array([0.0, 1.0])],
    ...                       [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    >>> r.x.round(6).tolist(), np.diag(r.P).round(6).tolist()
    ([1.0, 1.0], [1.0, 1.0])
    """
    return _largest_ellipsoid(as_estimates(xs, Ps))


def _largest_ellipsoid(est):
    """The ``"le"`` rule on validated estimates (the core of :func:`largest_ellipsoid`)."""
    check_pair(est, "le")
    x, P, gains, info = largest_ellipsoid_fusion(est)
    return FusionResult(restore_style(x, est.column), P, "le", None, gains, info)


REGISTRATION: dict[str, Any] = dict(
    name="le",
    function=largest_ellipsoid,
    core=_largest_ellipsoid,
    summary="Largest ellipsoid / safe fusion: per decorrelated direction keep the better "
            "estimate (EI's covariance)",
    reference="Benaskeur 2002; Nygårds, Deleskog & Hendeby 2016",
    guarantee="none",
    weights="None: a per-direction selection, not a scalar weighting",
)
"""The record of the ``"le"`` rule (registered by :mod:`cifilter.rules`). No guarantee:
the covariance is the largest ellipsoid inside both inputs', which is neither a bound for
correlated inputs nor the error covariance for independent ones."""
