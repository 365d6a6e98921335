"""Probabilistically conservative Ellipsoidal Intersection (Naveen & Taylor).

PC-EI enlarges EI's common covariance, ``C_c = C_EI + S S^T`` (eq. (18)), until the
independent parts of the two inputs pass the chi-square test of having the same mean
(eqs. (17), (19)). The whitening and fusion it shares with EI are in
:mod:`cifilter.rules._ellipsoidal`, the constrained problem and its solver in
:mod:`cifilter.rules._pc_constraint`; the derivations are on the documentation page
(``docs/methods/ei.rst``).
"""

from typing import Any

from numpy.typing import ArrayLike

from .._numerics.validation import check_int, check_scalar, restore_style
from ..result import FusionResult
from ._ellipsoidal import DEFAULT_EPS, check_options, check_pair, estimates_from_arguments
from ._pc_constraint import pc_fusion

__all__ = ["pc_ellipsoidal_intersection"]


def pc_ellipsoidal_intersection(xs: ArrayLike, Ps: ArrayLike, *args: ArrayLike,
                                alpha: float = 0.05, eps: float = DEFAULT_EPS,
                                mutual_mean: str = "sijs-lazar",
                                regularizer: str = "information", tol: float = 1e-9,
                                max_iter: int = 300) -> FusionResult:
    """Fuse two estimates by probabilistically conservative Ellipsoidal Intersection.

    Starts from EI's common covariance ``C_EI`` (eq. (11)) and adds the ``S S^T`` of
    eq. (18) that gives the smallest ``det C_c`` such that the independent parts of the
    inputs pass the chi-square test of eq. (17) at significance ``alpha``:

        minimise det(C_EI + S S^T)  subject to  psi(C_EI + S S^T) <= chi2.ppf(1 - alpha, n),

    then fuses with eqs. (7)-(8). A larger common covariance means less shared
    information and a fused covariance below EI's.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        The two means, each (n,) or (n, 1) with optional leading batch axes, or one array
        (..., 2, n) (or (..., 2, n, 1)). In the pairwise form ``(xa, Pa, xb, Pb)``: ``xa``.
    Ps : sequence of array_like or array_like
        Their covariances, each (..., n, n), or one array (..., 2, n, n); symmetric
        positive definite. In the pairwise form: ``Pa``.
    *args
        Either ``alpha`` (positionally), or ``xb, Pb`` (and optionally ``alpha``) for the
        pairwise convenience ``pc_ellipsoidal_intersection(xa, Pa, xb, Pb, alpha, ...)``,
        in which the batch axes of all four arrays broadcast against each other.
    alpha : float, optional
        Significance level in (0, 1), default 0.05: the probability that the test rejects
        independent parts with equal means. Smaller ``alpha`` gives a larger threshold, a
        looser constraint and a result closer to EI.
    eps : float, optional
        As in :func:`ellipsoidal_intersection` (default ``1e-8``). With
        ``regularizer="information"`` it is also the tolerance below which two variances
        count as equal (``|log d_k| <= eps``): such directions are treated as exact ties.
    mutual_mean : {"sijs-lazar", "as-printed"}, optional
        The common mean of eq. (13), see :func:`ellipsoidal_intersection`. With
        ``"sijs-lazar"`` (default) EI's independent parts pass the test except in tied
        directions with different means, so PC-EI differs from EI only there; with
        ``"as-printed"`` they fail whenever the means differ.
    regularizer : {"information", "covariance"}, optional
        Where ``eps`` enters; ``"covariance"`` adds ``eps I`` to ``C_EI`` as in eq. (11).
    tol : float, optional
        Target gap ``(n + 1) / t`` of the barrier method, in (0, 1) (default 1e-9): a bound
        on how far ``log det C_c`` is above that of the KKT point.
    max_iter : int, optional
        Newton iterations per start, ``>= 1`` (default 300).

    Returns
    -------
    FusionResult
        As :func:`ellipsoidal_intersection` (``method="pcei"``, ``weights=None``; ``gains``
        exact for the returned common covariance, though PC-EI as a whole is not linear in
        the means), with ``info`` holding, per problem (shape (...)): ``psi`` (eq. (17) at
        the result; NaN where no feasible point was found) and ``threshold`` (``gamma``),
        ``active`` (EI failed the test), ``feasible`` (a common covariance passing the test
        exists; if not, the result is EI's), ``solver`` (``"ei"``, ``"closed-form"`` or
        ``"interior-point"``), ``iterations``, ``converged`` (the barrier method finished
        with a relative KKT residual below 1e-3; if not, the result is EI's),
        ``kkt_residual``, ``duality_gap`` (``(n + 1) / t``), ``starts`` and
        ``starts_agree`` (feasible starting points, and how many reached the best value
        within 1e-7); and ``common_x``, ``common_P``, ``independent_information``,
        ``independent_information_vector``, ``alpha``, ``mutual_mean``, ``regularizer``,
        ``eps``.

    Raises
    ------
    ValueError
        As :func:`ellipsoidal_intersection`, and ``alpha`` outside (0, 1), ``tol`` outside
        (0, 1), ``max_iter < 1``.
    IllConditionedError
        (a ValueError) Instead of a ``P`` that is not finite and positive definite.
    TypeError
        Non-numeric input or options, more than five positional arguments, or ``alpha``
        given both positionally and by keyword.

    See Also
    --------
    ellipsoidal_intersection : the unconstrained rule.

    Notes
    -----
    Eq. (19) minimises ``|S|``, which is degenerate for n > 1 (every rank-deficient ``S``
    has ``|S| = 0``); ``det C_c`` is minimised instead. If EI passes the test the result
    is EI's exactly; with ties (and always with Sijs & Lazar's mean) the optimum has a
    closed form; otherwise a batched log-barrier method finds a KKT point, reported in
    ``info`` (the constraint is not convex everywhere: no global certificate). Neither EI
    nor PC-EI is conservative. Derivations and measurements: the method's page.

    References
    ----------
    .. [1] A. Naveen and C. Taylor, "Decentralized data fusion with probabilistically
       conservative ellipsoidal intersection", eqs. (17)-(19), Section III.
    .. [2] J. Sijs and M. Lazar, "State fusion with unknown correlation: Ellipsoidal
       intersection", Automatica 48(8), 2012.

    Examples
    --------
    Section III, case 1 (equal variances, means +1 and -1). The common covariance of
    about 1.43 and fused variance of about 0.77 that the paper reports for "alpha = 0.05"
    are what the formulas give at alpha = 0.01:

    >>> import numpy as np
    >>> from cifilter import pc_ellipsoidal_intersection
    >>> r = pc_ellipsoidal_intersection([[1.0], [-1.0]], [[[1.0]], [[1.0]]], 0.01)
    >>> round(float(r.info["common_P"][0, 0]), 4), round(float(r.P[0, 0]), 4)
    (1.4315, 0.7684)
    >>> A = r.info["independent_information"][:, 0, 0]
    >>> (r.info["independent_information_vector"][:, 0] / A).round(3).tolist()
    [3.317, -3.317]

    When EI already passes the test (equal means) the result is EI's (pairwise form):

    >>> r = pc_ellipsoidal_intersection(np.zeros(2), np.eye(2), np.zeros(2), 2 * np.eye(2))
    >>> r.info["solver"], np.diag(r.P).tolist(), r.weights is None
    ('ei', [1.0, 1.0], True)
    """
    est, alpha = estimates_from_arguments(xs, Ps, args, "alpha", alpha, 0.05,
                                          "pc_ellipsoidal_intersection")
    return _pc_ellipsoidal_intersection(est, alpha, eps=eps, mutual_mean=mutual_mean,
                                        regularizer=regularizer, tol=tol, max_iter=max_iter)


def _pc_ellipsoidal_intersection(est, alpha=0.05, *, eps=DEFAULT_EPS, mutual_mean="sijs-lazar",
                                 regularizer="information", tol=1e-9, max_iter=300):
    """The ``"pcei"`` rule on validated estimates (the core of
    :func:`pc_ellipsoidal_intersection`); checks only the options."""
    check_pair(est, "pcei")
    eps = check_options(mutual_mean, regularizer, eps)
    alpha = check_scalar(alpha, "alpha", low=0.0, high=1.0, low_open=True, high_open=True)
    tol = check_scalar(tol, "tol", low=0.0, high=1.0, low_open=True, high_open=True)
    max_iter = check_int(max_iter, "max_iter", low=1)
    x, P, gains, info = pc_fusion(est, alpha, eps, mutual_mean, regularizer, tol, max_iter)
    info.update(alpha=alpha, mutual_mean=mutual_mean, regularizer=regularizer, eps=eps)
    return FusionResult(restore_style(x, est.column), P, "pcei", None, gains, info)


REGISTRATION: dict[str, Any] = dict(
    name="pcei",
    function=pc_ellipsoidal_intersection,
    core=_pc_ellipsoidal_intersection,
    summary="probabilistically conservative EI: common part bounded by a chi-square test",
    reference="Naveen & Taylor, eqs. 17-19; Sijs & Lazar 2012",
    guarantee="none",
    weights="None: PC-EI's fusion is not a scalar weighting of the estimates",
)
"""The record of the ``"pcei"`` rule (registered by :mod:`cifilter.rules`)."""
