"""Consistency and accuracy of estimators over Monte Carlo runs, batched.

The normalised estimation error squared (NEES) of an estimate ``x`` with covariance ``P``
of a true state ``x_true`` is ``(x - x_true)^T P^-1 (x - x_true)`` (Bar-Shalom, Li &
Kirubarajan 2001, Sec. 5.4); a consistent ``n``-dimensional estimator has NEES
distributed as chi-square with ``n`` degrees of freedom. Averaged over ``N`` independent
Monte Carlo runs (the ANEES), ``N * ANEES`` is chi-square with ``N n`` degrees of freedom,
which gives the two-sided bounds of :func:`chi2_bounds`. The normalised innovation
squared (NIS) is the same statistic of an innovation and its covariance ``S``.

Names follow filterpy (:func:`nees` takes the arguments of ``filterpy.stats.NEES``: true
states, estimates, covariances) and the metric outputs of Stone Soup (a value with its
bounds). Every function is vectorised over leading axes; the Monte Carlo runs are one
axis (``axis=0`` by default).

:func:`conservativeness` tests a covariance against the empirical second moment of the
errors: ``P`` is conservative when ``P >= E[e e^T]``, i.e. when the smallest generalised
eigenvalue of ``(P, E[e e^T])`` is at least one; the test gives that eigenvalue with a
confidence interval.

:func:`gospa` is the generalised optimal sub-pattern assignment metric of two finite sets of
states (truth and estimates, for instance at one scan of a multi-target tracker) with its
localisation, missed and false parts (Rahmathullah, García-Fernández & Svensson 2017).
"""

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats
from scipy.optimize import linear_sum_assignment

from ._numerics.linalg import cholesky, mahalanobis_sq, solve_lower
from ._numerics.validation import as_float_array, check_int, check_scalar

__all__ = [
    "ANEESResult",
    "ConservativenessResult",
    "GOSPAResult",
    "anees",
    "chi2_bounds",
    "conservativeness",
    "gospa",
    "nees",
    "nis",
    "pooled_anees_band",
    "rmse",
]


def _as_vectors(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """``(..., n)`` from ``(..., n)`` or filterpy's column ``(..., n, 1)``."""
    array = as_float_array(value, name)
    if array.ndim >= 2 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim < 1:
        raise ValueError(f"{name} must have at least one axis (the state), got a scalar")
    return array


def nees(x_true: ArrayLike, x_est: ArrayLike, P: ArrayLike) -> NDArray[np.float64]:
    """Normalised estimation error squared, ``(x_est - x_true)^T P^-1 (x_est - x_true)``.

    The arguments are those of ``filterpy.stats.NEES`` (true states, estimates,
    covariances), with any leading axes (runs, time steps, nodes, ...).

    Parameters
    ----------
    x_true : array_like, shape (..., n) or (..., n, 1)
        True states.
    x_est : array_like, shape (..., n) or (..., n, 1)
        Estimates; broadcast against ``x_true``.
    P : array_like, shape (..., n, n)
        Covariances of the estimates (symmetric positive definite); broadcast against the
        errors.

    Returns
    -------
    ndarray, shape (...)
        The NEES of every estimate (chi-square with ``n`` degrees of freedom when the
        estimator is consistent).

    Raises
    ------
    ValueError
        If the shapes do not match, a value is not finite or a covariance is not positive
        definite.

    See Also
    --------
    anees : the average over Monte Carlo runs with its chi-square bounds.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import nees
    >>> float(nees(np.zeros(2), np.array([2.0, 1.0]), np.diag([4.0, 1.0])))
    2.0
    """
    error = _as_vectors(x_est, "x_est") - _as_vectors(x_true, "x_true")
    return _normalised_square(error, P, "P")


def nis(innovation: ArrayLike, S: ArrayLike) -> NDArray[np.float64]:
    """Normalised innovation squared, ``y^T S^-1 y``.

    Parameters
    ----------
    innovation : array_like, shape (..., m) or (..., m, 1)
        Innovations ``y = z - H x_prior`` (filterpy's ``kf.y``).
    S : array_like, shape (..., m, m)
        Their covariances (filterpy's ``kf.S``); broadcast against ``innovation``.

    Returns
    -------
    ndarray, shape (...)
        The NIS of every innovation (chi-square with ``m`` degrees of freedom for a
        consistent filter).

    Raises
    ------
    ValueError
        If the shapes do not match, a value is not finite or ``S`` is not positive definite.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import nis
    >>> float(nis(np.array([[3.0]]), np.array([[9.0]])))
    1.0
    """
    return _normalised_square(_as_vectors(innovation, "innovation"), S, "S")


def _normalised_square(error, P, name):
    P = as_float_array(P, name)
    n = error.shape[-1]
    if P.ndim < 2 or P.shape[-2:] != (n, n):
        raise ValueError(
            f"{name} must have shape (..., {n}, {n}) to match vectors of length {n}, "
            f"got {P.shape}")
    try:
        np.broadcast_shapes(error.shape[:-1], P.shape[:-2])
    except ValueError:
        raise ValueError(
            f"the batch axes of {name} {P.shape[:-2]} do not broadcast against those of "
            f"the vectors {error.shape[:-1]}") from None
    shape = np.broadcast_shapes(error.shape[:-1], P.shape[:-2])
    return mahalanobis_sq(np.broadcast_to(error, shape + (n,)),
                          np.broadcast_to(P, shape + (n, n)))


def chi2_bounds(dim: int, runs: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square bounds of an average of ``runs`` NEES (or NIS) values.

    If the estimator is consistent, ``runs * ANEES`` is chi-square with ``runs * dim``
    degrees of freedom; the bounds are its ``(1 - confidence) / 2`` and
    ``(1 + confidence) / 2`` quantiles divided by ``runs`` (Bar-Shalom, Li & Kirubarajan
    2001, eq. (5.4.2-7)).

    Parameters
    ----------
    dim : int
        Dimension of the state (of the measurement for the NIS).
    runs : int
        Number of independent values averaged.
    confidence : float, optional
        Probability of the interval, in (0, 1); default 0.95.

    Returns
    -------
    lower, upper : float
        The bounds of the ANEES (they enclose ``dim``).

    Raises
    ------
    ValueError
        If ``dim`` or ``runs`` is below 1 or ``confidence`` is outside (0, 1).

    Examples
    --------
    >>> from cifilter.metrics import chi2_bounds
    >>> [round(b, 3) for b in chi2_bounds(2, 50)]
    [1.484, 2.591]
    """
    dim, runs = check_int(dim, "dim", low=1), check_int(runs, "runs", low=1)
    confidence = check_scalar(confidence, "confidence", low=0, high=1, low_open=True,
                              high_open=True)
    tail = (1.0 - confidence) / 2.0
    lower, upper = stats.chi2.ppf([tail, 1.0 - tail], df=runs * dim) / runs
    return float(lower), float(upper)


@dataclass(frozen=True)
class ANEESResult:
    """The average NEES over Monte Carlo runs and its chi-square bounds (see :func:`anees`).

    The parameters are also the attributes.

    Parameters
    ----------
    value : ndarray
        ANEES at every remaining index (for instance every time step).
    lower, upper : float
        Two-sided chi-square bounds (:func:`chi2_bounds`).
    dim : int
        Dimension of the state.
    runs : int
        Number of runs averaged.
    confidence : float
        Probability of the bounds.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import anees
    >>> result = anees(np.full((10, 3), 2.0), dim=2)
    >>> result.verdict, result.share_inside
    ('consistent', 1.0)
    """

    value: NDArray[np.float64]
    lower: float
    upper: float
    dim: int
    runs: int
    confidence: float

    @property
    def inside(self) -> NDArray[np.bool_]:
        """Whether each ANEES lies inside the bounds (boolean array like ``value``).

        Returns
        -------
        ndarray of bool
            ``lower <= value <= upper``.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.metrics import anees
        >>> anees(np.array([[1.0, 9.0]]), dim=1).inside.tolist()
        [True, False]
        """
        return (self.value >= self.lower) & (self.value <= self.upper)

    @property
    def share_inside(self) -> float:
        """Share of the ANEES values inside the bounds (``confidence`` when consistent).

        Returns
        -------
        float
            In [0, 1].

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.metrics import anees
        >>> anees(np.array([[1.0, 9.0]]), dim=1).share_inside
        0.5
        """
        return float(np.mean(self.inside))

    @property
    def mean(self) -> float:
        """The ANEES averaged over its remaining indices as well (e.g. over time).

        Returns
        -------
        float
            Mean of ``value``.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.metrics import anees
        >>> anees(np.array([[1.0, 3.0]]), dim=2).mean
        2.0
        """
        return float(np.mean(self.value))

    @property
    def verdict(self) -> str:
        """``"conservative"``, ``"overconfident"`` or ``"consistent"``.

        The mean ANEES (:attr:`mean`) below the lower bound is conservative (the
        covariances are larger than the errors), above the upper bound overconfident,
        otherwise consistent at this number of runs.

        Returns
        -------
        str
            The verdict.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.metrics import anees
        >>> anees(np.full((100, 5), 0.5), dim=2).verdict
        'conservative'
        """
        if self.mean < self.lower:
            return "conservative"
        if self.mean > self.upper:
            return "overconfident"
        return "consistent"


def anees(nees_values: ArrayLike, dim: int, *, axis: int = 0,
          confidence: float = 0.95) -> ANEESResult:
    """Average NEES over Monte Carlo runs, with two-sided chi-square bounds.

    Parameters
    ----------
    nees_values : array_like
        NEES values (:func:`nees`) with the independent Monte Carlo runs along ``axis``;
        other axes (time steps, nodes) are kept. Also for NIS values (then ``dim`` is the
        measurement dimension).
    dim : int
        Dimension of the state.
    axis : int, optional
        The runs axis (default 0).
    confidence : float, optional
        Probability of the bounds, default 0.95.

    Returns
    -------
    ANEESResult
        ``value`` (the ANEES per remaining index), ``lower``, ``upper``, ``inside``,
        ``share_inside``, ``mean`` and ``verdict``.

    Raises
    ------
    ValueError
        If ``nees_values`` is empty along ``axis``, not finite or negative.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import anees
    >>> rng = np.random.default_rng(0)
    >>> values = rng.chisquare(4, size=(200, 50))   # a consistent 4-D estimator
    >>> result = anees(values, dim=4)
    >>> result.value.shape, result.verdict
    ((50,), 'consistent')
    """
    values = as_float_array(nees_values, "nees_values")
    if values.ndim == 0:
        raise ValueError("nees_values must have a runs axis, got a scalar")
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        raise ValueError("nees_values must be finite and non-negative")
    axis = int(axis)
    try:
        runs = values.shape[axis]
    except IndexError:
        raise ValueError(f"axis {axis} is out of range for nees_values of shape "
                         f"{values.shape}") from None
    if runs < 1:
        raise ValueError("nees_values has no runs along the runs axis")
    lower, upper = chi2_bounds(dim, runs, confidence)
    return ANEESResult(np.mean(values, axis=axis), lower, upper, int(dim), int(runs),
                       float(confidence))


def pooled_anees_band(nees_values: ArrayLike, dim: int,
                      confidence: float = 0.95) -> tuple[float, float, float]:
    """The pooled ANEES of correlated NEES values and the band it lies in when consistent.

    The pooled ANEES is the mean of all ``N = K M`` NEES values of each of ``R``
    independent runs (``K`` steps, ``M`` nodes). The values of one run are correlated
    (a step's error carries into the next; the nodes exchange estimates), so the pooled
    mean varies more than a mean of ``R N`` independent chi-square values: by the
    *design effect* ``d = Var(sum of a run's values) / sum of their variances`` (1 for
    independent values, ``N`` when a run's values move together). The band is the spread
    a **consistent** estimator with this correlation would have: each value chi-square
    with ``dim`` degrees of freedom, variance ``2 dim``, so

        ``dim -+ t_{R-1} sqrt(2 dim d / (N R))``

    with ``d`` estimated from the values' own correlation (the variance of the run sums
    over the summed variances of the values, across runs, clipped to ``[1, N]``). That
    ratio does not depend on the scale of the values, so an overconfident estimator (its
    ``P`` too small by any factor) gets the band of a consistent one, not one widened by
    its own spread. The Student t quantile accounts for ``d`` being estimated from ``R``
    runs. The derivation and the coverage measured by simulation are in :doc:`/cli`.

    Parameters
    ----------
    nees_values : array_like, shape (runs, ...)
        NEES values (:func:`nees`), the independent Monte Carlo runs along the first axis
        (the other axes, steps and nodes, may be correlated within a run).
    dim : int
        State dimension (the mean NEES of a consistent estimator).
    confidence : float, optional
        Probability of the band, in (0, 1); default 0.95.

    Returns
    -------
    anees : float
        The pooled ANEES, the mean of every value.
    lower, upper : float
        The band around ``dim`` (the lower end clipped at 0); NaN for a single run (no
        spread between runs to estimate the correlation from).

    Raises
    ------
    ValueError
        If ``nees_values`` is a scalar or empty, not finite or negative, ``dim`` is below
        1 or ``confidence`` is outside (0, 1).
    TypeError
        If ``nees_values`` is not numeric or ``dim`` not an integer.

    See Also
    --------
    anees : the ANEES per step over the runs, with one step's chi-square bounds.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import pooled_anees_band
    >>> rng = np.random.default_rng(0)
    >>> shared = rng.standard_normal((10, 1, 1, 4))      # one error shared in each run
    >>> errors = np.sqrt(0.5) * shared + np.sqrt(0.5) * rng.standard_normal((10, 40, 6, 4))
    >>> nees = np.sum(errors**2, axis=-1)                 # consistent: chi-square(4) each
    >>> m, lo, hi = pooled_anees_band(nees, 4)
    >>> bool(lo < m < hi)
    True
    >>> m2, lo2, hi2 = pooled_anees_band(2 * nees, 4)    # P halved: NEES doubled
    >>> (lo2, hi2) == (lo, hi), bool(m2 > hi2)            # the same band, rejected
    (True, True)
    """
    values = as_float_array(nees_values, "nees_values")
    dim = check_int(dim, "dim", low=1)
    confidence = check_scalar(confidence, "confidence", low=0, high=1, low_open=True,
                              high_open=True)
    if values.ndim == 0 or values.size == 0:
        raise ValueError(f"nees_values must have a runs axis and values, got shape "
                         f"{values.shape}")
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        raise ValueError("nees_values must be finite and non-negative")
    runs = values.shape[0]
    values = values.reshape(runs, -1)
    count = values.shape[1]
    pooled = float(np.mean(values.mean(axis=1)))
    if runs < 2:
        return pooled, float("nan"), float("nan")
    # the design effect: both variances are across runs, so d is free of the values' scale.
    # Differences from the first run (exact for close values) leave the variances as they
    # are and make them exactly 0 where the runs agree.
    centred = values - values[0]
    summed = float(np.sum(np.var(centred, axis=0, ddof=1)))
    effect = float(np.var(centred.sum(axis=1), ddof=1)) / summed if summed > 0 else count
    # Gaussian errors: a covariance of two NEES values is 2 tr(...) >= 0, hence d >= 1;
    # Cauchy-Schwarz: d <= N
    effect = min(max(effect, 1.0), float(count))
    half = float(stats.t.ppf(0.5 + confidence / 2, runs - 1)
                 * np.sqrt(2.0 * dim * effect / (count * runs)))
    return pooled, max(0.0, dim - half), dim + half


def rmse(x_true: ArrayLike, x_est: ArrayLike, *,
         axis: Optional[Union[int, tuple[int, ...]]] = 0,
         components: Optional[Sequence[int]] = None) -> Union[NDArray[np.float64], float]:
    """Root mean square error over Monte Carlo runs.

    ``sqrt(mean_runs(sum_components (x_est - x_true)^2))``: the root of the mean squared
    Euclidean error of the chosen components (for instance the position).

    Parameters
    ----------
    x_true, x_est : array_like, shape (..., n) or (..., n, 1)
        True states and estimates (broadcast against each other).
    axis : int or tuple of int or None, optional
        Axes of the batch (not counting the state axis) averaged over: the runs (default
        0); None averages over every batch axis.
    components : sequence of int, optional
        State components included (default all).

    Returns
    -------
    ndarray or float
        The RMSE at every remaining index.

    Raises
    ------
    ValueError
        If the shapes do not broadcast or a value is not finite.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import rmse
    >>> errors = np.array([[3.0, 4.0], [0.0, 0.0]])     # two runs of a 2-D state
    >>> float(rmse(np.zeros(2), errors))
    3.5355339059327378
    """
    error = _as_vectors(x_est, "x_est") - _as_vectors(x_true, "x_true")
    if not np.all(np.isfinite(error)):
        raise ValueError("x_true and x_est must be finite")
    if components is not None:
        error = error[..., list(components)]
    squared = np.sum(error**2, axis=-1)
    if squared.ndim == 0:
        return float(np.sqrt(squared))
    result = np.sqrt(np.mean(squared, axis=axis))
    return float(result) if np.ndim(result) == 0 else result


@dataclass(frozen=True)
class ConservativenessResult:
    """Whether a covariance bounds the empirical error covariance (see
    :func:`conservativeness`).

    The parameters are also the attributes.

    Parameters
    ----------
    eigenvalue : ndarray or float
        Smallest generalised eigenvalue of ``(P, C)``, ``C`` the empirical second moment
        of the errors: ``P >= C`` exactly when it is at least one.
    lower, upper : ndarray or float
        Confidence interval of the smallest generalised eigenvalue of ``P`` and the true
        second moment.
    samples : int
        Number of independent error samples behind ``C``.
    confidence : float
        Probability of the interval (at least this much: it is a union bound).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import conservativeness
    >>> errors = np.random.default_rng(1).standard_normal((500, 2))
    >>> conservativeness(4.0 * np.eye(2), errors).verdict
    'conservative'
    """

    eigenvalue: Union[NDArray[np.float64], float]
    lower: Union[NDArray[np.float64], float]
    upper: Union[NDArray[np.float64], float]
    samples: int
    confidence: float

    @property
    def verdict(self) -> Union[str, NDArray[np.str_]]:
        """``"conservative"`` (the whole interval >= 1), ``"overconfident"`` (<= 1) or
        ``"inconclusive"``; an array of str for a batch.

        Returns
        -------
        str or ndarray of str
            The verdict.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.metrics import conservativeness
        >>> errors = np.random.default_rng(1).standard_normal((500, 2))
        >>> conservativeness(0.25 * np.eye(2), errors).verdict
        'overconfident'
        """
        verdict = np.where(np.asarray(self.lower) >= 1.0, "conservative",
                           np.where(np.asarray(self.upper) <= 1.0, "overconfident",
                                    "inconclusive"))
        return str(verdict) if verdict.ndim == 0 else verdict


@lru_cache(maxsize=64)
def _white_wishart_extremes(dim, samples, confidence, draws, seed):
    """Quantiles of the extreme eigenvalues of ``W_dim(samples, I) / samples``.

    The ``(1 - confidence) / 2`` quantile of the smallest and the ``(1 + confidence) / 2``
    quantile of the largest eigenvalue, by simulation (no closed form for general dim).
    """
    rng = np.random.default_rng(seed)
    tail = (1.0 - confidence) / 2.0
    smallest, largest = [], []
    block = max(1, min(draws, 2_000_000 // (samples * dim)))
    for start in range(0, draws, block):
        count = min(block, draws - start)
        Z = rng.standard_normal((count, samples, dim))
        eig = np.linalg.eigvalsh(np.einsum("kni,knj->kij", Z, Z) / samples)
        smallest.append(eig[:, 0])
        largest.append(eig[:, -1])
    return (float(np.quantile(np.concatenate(smallest), tail)),
            float(np.quantile(np.concatenate(largest), 1.0 - tail)))


def conservativeness(P: ArrayLike, errors: ArrayLike, *, axis: int = 0,
                     confidence: float = 0.95, draws: int = 4000,
                     rng: Optional[int] = 0) -> ConservativenessResult:
    """Test whether ``P`` bounds the empirical error covariance: smallest generalised
    eigenvalue with a confidence interval.

    With ``C = mean(e e^T)`` over independent error samples (the second moment: a bias
    counts as error), ``lambda = min_u (u^T P u) / (u^T C u)`` is the smallest generalised
    eigenvalue of ``(P, C)``; ``P >= C`` exactly when ``lambda >= 1``. For Gaussian errors
    ``N C`` is Wishart with ``N`` degrees of freedom around the true second moment
    ``Sigma``, and for every direction ``u^T C u / u^T Sigma u`` lies between the extreme
    eigenvalues of a white Wishart matrix ``W(N, I) / N``; with their simulated
    ``(1 -+ confidence) / 2`` quantiles ``l_min``, ``l_max`` the interval
    ``[lambda l_min, lambda l_max]`` contains the eigenvalue of ``(P, Sigma)`` with
    probability at least ``confidence`` (a union bound over the two quantiles).

    Parameters
    ----------
    P : array_like, shape (..., n, n)
        The covariance under test (the same for every sample), symmetric positive
        definite.
    errors : array_like, shape (N, ..., n)
        Independent error samples along ``axis`` (the Monte Carlo runs); the batch axes
        broadcast against those of ``P``.
    axis : int, optional
        The samples axis of ``errors`` (default 0).
    confidence : float, optional
        Probability of the interval, default 0.95.
    draws : int, optional
        Simulated white Wishart matrices behind the quantiles (default 4000).
    rng : int or None, optional
        Seed of that simulation (default 0: the same inputs give the same interval).

    Returns
    -------
    ConservativenessResult
        ``eigenvalue``, ``lower``, ``upper`` (float or arrays of the batch shape),
        ``samples``, ``confidence`` and ``verdict``.

    Raises
    ------
    ValueError
        If ``P`` is not positive definite, the shapes do not match, fewer than ``n``
        samples are given or a value is not finite.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.metrics import conservativeness
    >>> rng = np.random.default_rng(0)
    >>> errors = rng.multivariate_normal([0, 0], [[2.0, 0.5], [0.5, 1.0]], size=2000)
    >>> result = conservativeness([[2.0, 0.5], [0.5, 1.0]], errors)
    >>> bool(result.lower < 1 < result.upper), result.verdict
    (True, 'inconclusive')
    """
    covariance = as_float_array(P, "P")
    errors = _as_vectors(errors, "errors")
    if not np.all(np.isfinite(errors)):
        raise ValueError("errors must be finite")
    n = errors.shape[-1]
    if covariance.ndim < 2 or covariance.shape[-2:] != (n, n):
        raise ValueError(f"P must have shape (..., {n}, {n}) to match errors of length {n}, "
                         f"got {covariance.shape}")
    errors = np.moveaxis(errors, axis, 0)
    samples = errors.shape[0]
    if samples < n:
        raise ValueError(f"at least {n} error samples are needed for a {n}-D covariance, "
                         f"got {samples}")
    confidence = check_scalar(confidence, "confidence", low=0, high=1, low_open=True,
                              high_open=True)
    draws = check_int(draws, "draws", low=100)
    second_moment = np.einsum("k...i,k...j->...ij", errors, errors) / samples
    L = cholesky(covariance, "P")
    shape = np.broadcast_shapes(L.shape[:-2], second_moment.shape[:-2])
    L = np.broadcast_to(L, shape + (n, n))
    # lambda_min(P, C) = 1 / lambda_max(L^-1 C L^-T): no inverse of C (it may be singular)
    half = solve_lower(L, np.broadcast_to(second_moment, shape + (n, n)))
    whitened = solve_lower(L, np.swapaxes(half, -1, -2))
    largest = np.linalg.eigvalsh(0.5 * (whitened + np.swapaxes(whitened, -1, -2)))[..., -1]
    with np.errstate(divide="ignore"):
        eigenvalue = np.where(largest > 0, 1.0 / np.maximum(largest, 1e-300), np.inf)
    low, high = _white_wishart_extremes(n, samples, confidence, draws,
                                        None if rng is None else int(rng))
    result = [eigenvalue, eigenvalue * low, eigenvalue * high]
    if eigenvalue.ndim == 0:
        result = [float(r) for r in result]
    return ConservativenessResult(result[0], result[1], result[2], int(samples),
                                  float(confidence))


@dataclass(frozen=True)
class GOSPAResult:
    """The GOSPA distance of two sets and its parts (see :func:`gospa`).

    The parameters are also the attributes. With ``alpha = 2``,
    ``distance**p == localisation + missed + false``.

    Parameters
    ----------
    distance : float
        The GOSPA distance.
    localisation : float
        Sum of ``d(x, y)**p`` over the assigned pairs.
    missed, false : float
        ``c**p / alpha`` times the number of unassigned truths (missed) and unassigned
        estimates (false).
    assignment : ndarray of int, shape (k, 2)
        The assigned pairs ``(truth index, estimate index)``, by truth index. With
        ``alpha = 2`` only pairs closer than ``c`` are assigned.
    truths, estimates : int
        The sizes of the two sets.
    c, p, alpha : float
        The metric's parameters.

    Examples
    --------
    >>> from cifilter.metrics import gospa
    >>> result = gospa([[0.0, 0.0]], [[3.0, 4.0], [100.0, 0.0]], c=10.0)
    >>> round(result.distance**2, 9), result.localisation, result.false, result.missed_count
    (75.0, 25.0, 50.0, 0)
    """

    distance: float
    localisation: float
    missed: float
    false: float
    assignment: NDArray[np.int_]
    truths: int
    estimates: int
    c: float
    p: float
    alpha: float

    @property
    def missed_count(self) -> int:
        """Number of truths without an estimate assigned.

        Returns
        -------
        int
            ``truths`` minus the assigned pairs.

        Examples
        --------
        >>> from cifilter.metrics import gospa
        >>> gospa([[0.0], [9.0]], [[0.5]], c=2.0).missed_count
        1
        """
        return self.truths - len(self.assignment)

    @property
    def false_count(self) -> int:
        """Number of estimates assigned to no truth.

        Returns
        -------
        int
            ``estimates`` minus the assigned pairs.

        Examples
        --------
        >>> from cifilter.metrics import gospa
        >>> gospa([[0.0]], [[0.5], [7.0]], c=2.0).false_count
        1
        """
        return self.estimates - len(self.assignment)


def _point_set(value, name):
    array = as_float_array(value, name)
    if array.size == 0:
        return array.reshape(0, array.shape[-1] if array.ndim == 2 else 0)
    if array.ndim == 1:
        raise ValueError(f"{name} must have shape (count, dim), got a 1-D array: write one "
                         f"state as [[...]]")
    if array.ndim != 2:
        raise ValueError(f"{name} must have shape (count, dim), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite")
    return array


def gospa(truth: ArrayLike, estimates: ArrayLike, *, c: float, p: float = 2.0,
          alpha: float = 2.0) -> GOSPAResult:
    """Generalised optimal sub-pattern assignment (GOSPA) distance of two sets of states.

    For a truth set ``X`` of ``m`` states and an estimate set ``Y`` of ``n`` states, with
    ``d^(c)(x, y) = min(||x - y||, c)``, Rahmathullah, García-Fernández & Svensson (2017,
    Eq. 1) define, for ``m <= n``,

        ``d_p^(c,alpha)(X, Y) = ( min_pi sum_{i=1}^{m} d^(c)(x_i, y_pi(i))^p
        + c^p / alpha (n - m) )^(1/p)``

    over the injections ``pi`` of ``X`` into ``Y`` (symmetric for ``m > n``). For
    ``alpha = 2`` (their Proposition 1, Eq. 2) it equals the assignment form

        ``( sum_{(i, j) assigned} ||x_i - y_j||^p + c^p / 2 (missed + false) )^(1/p)``

    over assignments of pairs closer than ``c``: localisation errors of the assigned
    pairs, ``c^p / 2`` for each missed truth and each false estimate. The minimum is found
    by :func:`scipy.optimize.linear_sum_assignment` on ``d^(c)(x_i, y_j)^p``; with
    ``alpha = 2`` a pair at distance ``c`` or more counts as one missed and one false (the
    same cost), as Stone Soup's ``GOSPAMetric`` does.

    Parameters
    ----------
    truth : array_like, shape (m, d)
        The true states (``m`` may be 0: an empty array).
    estimates : array_like, shape (n, d)
        The estimates, in the same space (``n`` may be 0). Distances are Euclidean over
        all ``d`` components: pass positions for a position GOSPA.
    c : float
        The cut-off distance, > 0.
    p : float, optional
        The exponent, >= 1 (default 2).
    alpha : float, optional
        In (0, 2] (default 2, the value with the localisation/missed/false parts).

    Returns
    -------
    GOSPAResult
        ``distance``, ``localisation``, ``missed``, ``false``, ``assignment``.

    Raises
    ------
    ValueError
        A set that is not of shape (count, d), not finite, the two of different ``d``,
        ``c`` not positive, ``p`` below 1 or ``alpha`` outside (0, 2].

    References
    ----------
    A. S. Rahmathullah, Á. F. García-Fernández and L. Svensson, "Generalized optimal
    sub-pattern assignment metric", 20th International Conference on Information Fusion,
    2017.

    Examples
    --------
    >>> from cifilter.metrics import gospa
    >>> truth = [[0.0, 0.0], [10.0, 0.0]]
    >>> result = gospa(truth, [[1.0, 0.0]], c=5.0)   # one found 1 m off, one missed
    >>> round(result.distance**2, 9), result.localisation, result.missed, result.false
    (13.5, 1.0, 12.5, 0.0)
    >>> result.assignment.tolist()
    [[0, 0]]
    """
    X = _point_set(truth, "truth")
    Y = _point_set(estimates, "estimates")
    c = check_scalar(c, "c", low=0, low_open=True)
    p = check_scalar(p, "p", low=1)
    alpha = check_scalar(alpha, "alpha", low=0, high=2, low_open=True)
    m, n = len(X), len(Y)
    if m and n and X.shape[1] != Y.shape[1]:
        raise ValueError(f"truth and estimates must have states of one size, got "
                         f"{X.shape[1]} and {Y.shape[1]}")
    unit = c**p / alpha
    pairs = np.zeros((0, 2), dtype=int)
    localisation = 0.0
    if m and n:
        distances = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=-1)
        cost = np.minimum(distances, c) ** p
        rows, cols = linear_sum_assignment(cost)
        if alpha == 2.0:
            keep = distances[rows, cols] < c
            rows, cols = rows[keep], cols[keep]
        localisation = float(np.sum(cost[rows, cols]))
        pairs = np.stack([rows, cols], axis=1).astype(int)
    if alpha == 2.0:
        missed, false = unit * (m - len(pairs)), unit * (n - len(pairs))
    else:
        missed, false = unit * max(m - n, 0), unit * max(n - m, 0)
    distance = float((localisation + missed + false) ** (1.0 / p))
    return GOSPAResult(distance, localisation, float(missed), float(false), pairs, m, n, c, p,
                       alpha)
