"""Sampling Covariance Intersection (Tian, Bar-Shalom & Chen 2010).

The fused estimate has the naive (independent-errors) fusion's mean and shape,

    P = rho P_0,    P_0^-1 = sum_i P_i^-1,    x = P_0 sum_i P_i^-1 x_i,

scaled by a factor ``rho`` in [1, N] read off random directions: for a direction ``z``
the ratio ``r(z) = z^T P_0^-1 z / max_i z^T P_i^-1 z`` says how much larger the naive
ellipsoid must be to reach the intersection of the input ellipsoids along ``z``;
``rho = u min r + (1 - u) max r`` over the sampled directions. It is CI with equal weights
``1 / rho`` on all inputs. No guarantee: see ``docs/methods/sampling_ci.rst``.
"""

from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.information import information_factors, lower_inverse_stack, weighted_fusion
from .._numerics.validation import as_estimates, as_rng, check_int, check_scalar, restore_style
from ..result import FusionResult

__all__ = ["sampling_ci"]

DEFAULT_SEED = 0
"""The seed used when ``rng`` is None: the rule is then a deterministic function of its
inputs, like every other fusion rule."""


def sampling_ci(xs: ArrayLike, Ps: ArrayLike, samples: Optional[int] = None, u: float = 0.5,
                rng: Union[int, np.random.Generator, None] = None) -> FusionResult:
    """Sampling Covariance Intersection: the naive fusion scaled to reach the inputs' intersection.

    ``P = rho P_0`` and ``x = P_0 sum_i P_i^-1 x_i`` with ``P_0^-1 = sum_i P_i^-1`` (the
    naive fusion), ``rho = u r_min + (1 - u) r_max`` and ``r_min``, ``r_max`` the extremes
    of ``r(z) = z^T P_0^-1 z / max_i z^T P_i^-1 z`` over ``samples`` directions
    ``z ~ N(0, P_0)`` (Tian, Bar-Shalom & Chen 2010; the NRL Tracker Component Library's
    ``covarianceIntersectSCI``). Equivalently CI with the equal weights ``1 / rho``:
    ``P^-1 = sum_i P_i^-1 / rho``.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n); symmetric
        positive definite.
    samples : int, optional
        Number of random directions per problem, ``>= 1``; default ``100 (N - 1)`` (the
        NRL library's default). More samples move ``r_min`` and ``r_max`` towards the
        true extremes of ``r`` (``r_max`` from below, ``r_min`` from above).
    u : float, optional
        Interpolation in [0, 1] between the extremes: ``u = 0`` takes ``r_max``, the
        smallest multiple of ``P_0`` whose ellipsoid contains the intersection of the
        input ellipsoids along every sampled direction; ``u = 1`` takes ``r_min``; the
        default ``0.5`` is the NRL library's.
    rng : numpy.random.Generator, int or None, optional
        Source of the directions. None (default) uses the fixed seed ``0``, so that the
        rule is a deterministic function of its inputs (the same fusion twice gives the
        same answer, and a filter's ``fuse`` is reproducible); pass a Generator or
        another seed for other draws. The same seed gives the same result.

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``method="sci"``, ``weights`` (..., N), all equal to ``1 / rho``
        (``P^-1 = sum_i w_i P_i^-1``; they sum to ``N / rho >= 1``), ``gains``
        (..., N, n, n) ``K_i = P_0 P_i^-1`` (the naive fusion's, summing to ``I``) and
        ``info`` with ``rho``, ``r_min``, ``r_max`` (...), ``samples``, ``u`` and
        ``rule="sampled"``.

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, ``samples < 1`` or ``u`` outside [0, 1].
    IllConditionedError
        (a ValueError) The fused information is numerically singular (beyond the
        conditioning contract).
    TypeError
        Non-numeric input, a non-integer ``samples``, a non-real ``u`` or a bad ``rng``.

    See Also
    --------
    covariance_intersection : a bound for every correlation, optimal weights.
    naive_fusion : ``P_0``, the fusion of independent estimates.

    Notes
    -----
    ``1 <= r(z) <= N`` for every direction, hence ``P_0 <= P <= N P_0``: the result is
    never smaller than the independent-errors fusion nor larger than CI with equal weights
    ``1/N``. It is a bound for every correlation only when ``rho = N`` (then it is that
    CI); otherwise there are correlations for which the error covariance of its gains
    exceeds ``P`` (``docs/methods/sampling_ci.rst``). The NRL library divides ``P_0`` by
    ``rho`` instead of multiplying; that ``P`` would be smaller than the independent
    fusion's, and this implementation does not follow it (see the method's page).

    References
    ----------
    .. [1] X. Tian, Y. Bar-Shalom and G. Chen, "A no-loss covariance intersection
       algorithm for track-to-track fusion", Proc. SPIE 7698, Signal and Data Processing
       of Small Targets, 2010 (sampling covariance intersection).
    .. [2] D. F. Crouse, the Tracker Component Library (U.S. Naval Research Laboratory),
       ``covarianceIntersectSCI``, 2015.

    Examples
    --------
    Two estimates, each precise along one axis (the NRL library's example without the
    means): ``r`` reaches 2 along the diagonal, so ``u = 0`` gives CI with weights 1/2.

    >>> import numpy as np
    >>> from cifilter import sampling_ci
    >>> xs = [np.array([1.0, -2.0]), np.array([-2.0, -1.0])]
    >>> Ps = [np.diag([1.0, 100.0]), np.diag([100.0, 1.0])]
    >>> r = sampling_ci(xs, Ps, samples=2000, u=0.0, rng=1)
    >>> round(float(r.info["r_max"]), 2), r.weights.round(2).tolist()
    (2.0, [0.5, 0.5])
    >>> bool(np.allclose(sampling_ci(xs, Ps).P, sampling_ci(xs, Ps, rng=0).P))
    True
    """
    return _sampling_ci(as_estimates(xs, Ps), samples, u, rng)


def _sampling_ci(est, samples=None, u=0.5, rng=None):
    """The ``"sci"`` rule on validated estimates (the core of :func:`sampling_ci`)."""
    count = est.count
    samples = 100 * (count - 1) if samples is None else check_int(samples, "samples", low=1)
    u = check_scalar(u, "u", low=0.0, high=1.0)
    generator = as_rng(DEFAULT_SEED if rng is None else rng)
    L_inv = lower_inverse_stack(est.L)
    factors = information_factors(L_inv, np.ones(est.batch_shape + (count,)))
    # In the coordinates z = R^T x of the naive information R R^T, z^T z = x^T P_0^-1 x and
    # x^T P_i^-1 x = |C_i^T z|^2 with C_i = R^-1 L_i^-T, sum_i C_i C_i^T = I: the ratio is
    # |z|^2 / max_i |C_i^T z|^2, in [1, N], and z ~ N(0, I) is x ~ N(0, P_0).
    z = generator.standard_normal(est.batch_shape + (samples, est.dim))
    projected = np.einsum("...kji,...sj->...ski", factors.C, z)
    largest = np.einsum("...ski,...ski->...sk", projected, projected).max(axis=-1)
    ratio = np.clip(np.einsum("...si,...si->...s", z, z) / largest, 1.0, float(count))
    r_min, r_max = ratio.min(axis=-1), ratio.max(axis=-1)
    # the interpolation can round past an extreme (by 2 ulp where r_min == r_max): clip
    rho = np.clip(u * r_min + (1.0 - u) * r_max, r_min, r_max)
    weights = np.broadcast_to((1.0 / rho)[..., None], est.batch_shape + (count,))
    fused = weighted_fusion(est.x, est.L, np.ascontiguousarray(weights), L_inv=L_inv)
    info = {"rule": "sampled", "rho": rho, "r_min": r_min, "r_max": r_max,
            "samples": samples, "u": u}
    return FusionResult(restore_style(fused.x, est.column), fused.P, "sci", None,
                        fused.gains, info, weights)


REGISTRATION: dict[str, Any] = dict(
    name="sci",
    function=sampling_ci,
    core=_sampling_ci,
    summary="Sampling CI: the naive fusion scaled until it reaches the inputs' "
            "intersection along random directions",
    reference="Tian, Bar-Shalom & Chen 2010; NRL Tracker Component Library",
    guarantee="none",
    weights="1/rho for every estimate: P^-1 = sum_i P_i^-1 / rho, rho in [1, N]",
)
"""The record of the ``"sci"`` rule (registered by :mod:`cifilter.rules`). No guarantee
unless ``rho = N`` (CI with equal weights); deterministic by default (fixed seed)."""
