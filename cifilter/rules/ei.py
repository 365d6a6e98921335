"""Ellipsoidal Intersection (Sijs & Lazar 2012) as reviewed by Naveen & Taylor.

EI splits each of two estimates into a part they have in common and an independent
part, estimates the common part from the covariances alone (the admissible common
covariance of smallest determinant, eqs. (10)-(12)) and removes it once (eqs. (7)-(8)).
The geometry it shares with PC-EI is in :mod:`cifilter.rules._ellipsoidal`; the derivations are
on the documentation page (``docs/methods/ei.rst``).
"""

from typing import Any

from numpy.typing import ArrayLike

from .._numerics.validation import restore_style
from ..result import FusionResult
from ._ellipsoidal import (
    DEFAULT_EPS,
    MUTUAL_MEANS,
    REGULARIZERS,
    check_options,
    check_pair,
    ei_fusion,
    estimates_from_arguments,
)

__all__ = ["MUTUAL_MEANS", "REGULARIZERS", "ellipsoidal_intersection"]


def ellipsoidal_intersection(xs: ArrayLike, Ps: ArrayLike, *args: ArrayLike,
                             eps: float = DEFAULT_EPS, mutual_mean: str = "sijs-lazar",
                             regularizer: str = "information") -> FusionResult:
    """Fuse two estimates by Ellipsoidal Intersection.

    EI takes as common covariance the admissible one (``C_c >= Pa``, ``C_c >= Pb``) of
    smallest determinant, ``C_c = T diag(max(d_k, 1)) T^T`` with ``Pa = T T^T`` and
    ``Pb = T diag(d) T^T`` (eqs. (10)-(12)), the common mean ``x_c`` of eq. (13), and
    removes the common part once (eqs. (7)-(8) with (5)-(6)):

        P^-1 = Pa^-1 + Pb^-1 - C_c^-1,    x = P (Pa^-1 xa + Pb^-1 xb - C_c^-1 x_c).

    In the eigen-directions of ``T`` this keeps, direction by direction, the input with the
    smaller variance: ``P = T diag(min(d, 1)) T^T``.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        The two means, each (n,) or (n, 1) with optional leading batch axes, or one array
        (..., 2, n) (or (..., 2, n, 1)). In the pairwise form ``(xa, Pa, xb, Pb)``: ``xa``.
    Ps : sequence of array_like or array_like
        Their covariances, each (..., n, n), or one array (..., 2, n, n); symmetric
        positive definite. Batch axes broadcast against those of ``xs``. In the pairwise
        form: ``Pa``.
    *args
        Either ``eps`` (positionally), or ``xb, Pb`` (and optionally ``eps``) for the
        pairwise convenience ``ellipsoidal_intersection(xa, Pa, xb, Pb, ...)``, in which
        the batch axes of all four arrays broadcast against each other.
    eps : float, optional
        Regulariser, ``>= 0``, default ``1e-8``. With ``regularizer="information"`` it is
        relative: ``eps (Pa^-1 + Pb^-1) / 2`` is added to both weights of the mutual mean
        (Sijs & Lazar's ``eta I``, written invariantly), so that directions where the
        inputs are equally informative (the 0/0 of eq. (13)) get the average of the two
        means; elsewhere its effect is of relative order ``eps / |1 - 1/d_k|``. With
        ``regularizer="covariance"`` it is absolute: ``eps I`` is added to the common
        covariance as in eq. (11) (Naveen & Taylor use ``0.01``), which also changes
        ``P``. ``eps = 0`` is the unregularised rule, exact ties resolved by the average.
    mutual_mean : {"sijs-lazar", "as-printed"}, optional
        ``"sijs-lazar"`` (default) weights ``xa`` by b's independent information and ``xb``
        by a's (Sijs & Lazar 2012, eq. (16)); ``"as-printed"`` weights each input by its
        own, as eq. (13) is printed. Only the former gives ``x_c = xb`` when ``C_c = Pb``.
    regularizer : {"information", "covariance"}, optional
        Where ``eps`` enters, see ``eps``.

    Returns
    -------
    FusionResult
        ``x`` (..., n) in the vector style of the first mean, ``P`` (..., n, n) symmetric
        positive definite, ``method="ei"``, ``omega=None`` and ``weights=None`` (EI is not a
        scalar weighting of the estimates), ``gains`` (..., 2, n, n) with
        ``x = K_a xa + K_b xb`` and ``K_a + K_b = I``, and ``info`` with ``common_x``
        (..., n) and ``common_P`` (..., n, n) (the estimated common mean and covariance),
        ``independent_information`` (..., 2, n, n) and ``independent_information_vector``
        (..., 2, n) (``Pa^-1 - C_c^-1`` and ``Pa^-1 xa - C_c^-1 x_c``, and the same for b;
        finite even where an input has no independent information), ``psi`` (...) (eq. (17)
        at ``C_c``: 0 or inf at the unregularised EI covariance, see Notes), ``ties`` (...)
        (eigen-directions with ``|log d_k| <= eps``), ``mutual_mean``, ``regularizer``,
        ``eps``.

    Raises
    ------
    ValueError
        Not exactly two estimates, mismatched dimensions or batch shapes, non-finite
        values, covariances that are not symmetric positive definite, ``eps < 0``, an
        unknown ``mutual_mean`` or ``regularizer``.
    IllConditionedError
        (a ValueError) Instead of a ``P`` that is not finite and positive definite; under
        the conditioning contract (input condition numbers up to 1e12) it is not raised.
    TypeError
        Non-numeric input, more than five positional arguments, or ``eps`` given both
        positionally and by keyword.

    See Also
    --------
    pc_ellipsoidal_intersection : EI with the probabilistic constraint on the common part.
    covariance_intersection : conservative for every correlation.

    Notes
    -----
    EI is not conservative: it assumes the common information is exactly the smallest
    admissible one (see the method's page for measured NEES).

    ``info["psi"]`` at EI's own (unregularised) common covariance is a limit: with Sijs &
    Lazar's mean it is 0 unless the means differ in a tied direction; with the printed
    mean it is infinite unless the means are equal. With ``regularizer="covariance"`` it
    is the finite value of eq. (17).

    References
    ----------
    .. [1] A. Naveen and C. Taylor, "Decentralized data fusion with probabilistically
       conservative ellipsoidal intersection", eqs. (5)-(8) and (10)-(13).
    .. [2] J. Sijs and M. Lazar, "State fusion with unknown correlation: Ellipsoidal
       intersection", Automatica 48(8), 2012, eqs. (11)-(16).

    Examples
    --------
    Section III, case 1 of Naveen & Taylor: equal variances, means +1 and -1. With the
    printed ``eps I`` of eq. (11) the common covariance is 1.01, the independent parts are
    (101, 101) and (-101, 101), the fused variance is about 1:

    >>> import numpy as np
    >>> from cifilter import ellipsoidal_intersection
    >>> r = ellipsoidal_intersection([[1.0], [-1.0]], [[[1.0]], [[1.0]]], eps=0.01,
    ...                              regularizer="covariance")
    >>> A = r.info["independent_information"][:, 0, 0]
    >>> eta = r.info["independent_information_vector"][:, 0]
    >>> (1 / A).round(6).tolist(), (eta / A).round(6).tolist(), round(float(r.P[0, 0]), 4)
    ([101.0, 101.0], [101.0, -101.0], 0.9902)

    The pairwise form; the gains reproduce the fused mean:

    >>> xa, xb = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    >>> r = ellipsoidal_intersection(xa, np.diag([1.0, 4.0]), xb, np.diag([4.0, 1.0]))
    >>> r.x.round(6).tolist(), np.diag(r.P).tolist(), r.weights is None
    ([1.0, 1.0], [1.0, 1.0], True)
    >>> bool(np.allclose(r.gains[0] @ xa + r.gains[1] @ xb, r.x))
    True
    """
    est, eps = estimates_from_arguments(xs, Ps, args, "eps", eps, DEFAULT_EPS,
                                        "ellipsoidal_intersection")
    return _ellipsoidal_intersection(est, eps, mutual_mean=mutual_mean,
                                     regularizer=regularizer)


def _ellipsoidal_intersection(est, eps=DEFAULT_EPS, *, mutual_mean="sijs-lazar",
                              regularizer="information"):
    """The ``"ei"`` rule on validated estimates (the core of
    :func:`ellipsoidal_intersection`); checks only the options."""
    check_pair(est, "ei")
    eps = check_options(mutual_mean, regularizer, eps)
    x, P, gains, info = ei_fusion(est, eps, mutual_mean, regularizer)
    return FusionResult(restore_style(x, est.column), P, "ei", None, gains, info)


REGISTRATION: dict[str, Any] = dict(
    name="ei",
    function=ellipsoidal_intersection,
    core=_ellipsoidal_intersection,
    summary="Ellipsoidal Intersection: removes the largest admissible common part once",
    reference="Sijs & Lazar 2012; Naveen & Taylor, eqs. 7-8, 11-13",
    guarantee="none",
    weights="None: EI's fusion is a per-direction selection, not a scalar weighting",
)
"""The record of the ``"ei"`` rule (registered by :mod:`cifilter.rules`)."""
