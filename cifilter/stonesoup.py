"""Stone Soup integration: cifilter's fusion rules as Stone Soup components.

Stone Soup (https://stonesoup.readthedocs.io) is an open framework for tracking. This module
lets its users fuse tracks whose cross-correlation is unknown with any rule registered in
cifilter, with optimal weights:

* :class:`FusionUpdater`, an ``Updater`` that can replace Stone Soup's ``ChernoffUpdater``
  (track-to-track fusion with ``Tracks2GaussianDetectionFeeder`` detections), and that also
  fuses detections of part of the state (a linear measurement model's ``matrix()`` as
  ``H``: generalised CI, :func:`cifilter.fuse` with ``H=``);
* :class:`OptimalCovarianceIntersection`, a drop-in for Stone Soup's
  ``CovarianceIntersection`` reducer (``merge_components``) with optimal weights;
* :func:`fuse_tracks`, which brings tracks to a common time (predicting older ones and
  retrodicting newer ones, through :func:`cifilter.fuse`'s ``times=``/``at=``/``motion=``)
  and fuses them;
* :func:`to_estimate` and :func:`to_gaussian_state`, conversions between Stone Soup states
  and cifilter's ``(x, P)``; particle, ensemble and mixture states are moment-matched and
  say so with a :class:`MomentMatchedWarning`.

Stone Soup is an optional dependency (``pip install ".[stonesoup]"`` from a clone): ``import
cifilter`` never imports it; this module does.
"""

import datetime
import warnings
from collections.abc import Sequence
from functools import lru_cache
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

try:
    from stonesoup.base import Property
    from stonesoup.mixturereducer.base import MixtureReducer
    from stonesoup.models.base import LinearModel
    from stonesoup.models.measurement import MeasurementModel
    from stonesoup.models.transition import TransitionModel
    from stonesoup.types.array import CovarianceMatrix, StateVector
    from stonesoup.types.mixture import GaussianMixture
    from stonesoup.types.prediction import MeasurementPrediction
    from stonesoup.types.state import (
        EnsembleState,
        GaussianState,
        InformationState,
        KernelParticleState,
        ParticleState,
        SqrtGaussianState,
        StateMutableSequence,
    )
    from stonesoup.types.update import Update
    from stonesoup.updater.base import Updater
except ImportError as error:  # pragma: no cover - exercised only without Stone Soup
    raise ImportError(
        "cifilter.stonesoup needs Stone Soup, which is not installed: "
        "python -m pip install \".[stonesoup]\" from a clone of cifilter (once published: "
        "pip install \"cifilter-fusion[stonesoup]\"; the PyPI project named cifilter is "
        "unrelated)"
    ) from error

from ._numerics.criteria import parse_criterion
from ._numerics.validation import as_float_array, check_covariances, check_finite
from .registry import fuse, get_method
from .result import FusionResult

__all__ = [
    "FusionUpdater",
    "MomentMatchedWarning",
    "OptimalCovarianceIntersection",
    "fuse_tracks",
    "to_estimate",
    "to_gaussian_state",
]


class MomentMatchedWarning(UserWarning):
    """A non-Gaussian Stone Soup state was replaced by the Gaussian with its mean and covariance.

    Issued by :func:`to_estimate` (and so by every function of :mod:`cifilter.stonesoup`
    that reads states) for particle, ensemble and kernel-particle states and for Gaussian
    mixtures. The fusion rules are defined for Gaussian estimates; a multimodal or skewed
    density loses its shape in the conversion, and a particle cloud's covariance is a
    sample estimate. Filter it with :func:`warnings.filterwarnings` once you have checked
    that this is what you want.

    Examples
    --------
    >>> import warnings
    >>> import numpy as np
    >>> from stonesoup.types.array import StateVectors
    >>> from stonesoup.types.state import ParticleState
    >>> from cifilter.stonesoup import MomentMatchedWarning, to_estimate
    >>> cloud = ParticleState(StateVectors([[0.0, 1.0, 2.0, 3.0]]),
    ...                       weight=np.full(4, 0.25))
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     x, P = to_estimate(cloud)
    >>> caught[0].category is MomentMatchedWarning, x.tolist(), P.tolist()
    (True, [1.5], [[1.25]])
    """


# ----------------------------------------------------------------------------- conversions
_EXACT_GAUSSIANS = (GaussianState, SqrtGaussianState, InformationState)
_SAMPLED = (ParticleState, EnsembleState, KernelParticleState)


def _latest_state(item):
    """A Track's latest state; other objects unchanged."""
    if isinstance(item, StateMutableSequence):
        if len(item) == 0:
            raise ValueError("a track without states cannot be fused")
        return item.state
    return item


def _mixture_moments(mixture):
    """Mean and covariance of a Gaussian mixture, its weights normalised."""
    components = list(mixture.components)
    if not components:
        raise ValueError("a Gaussian mixture without components has no mean")
    weights = np.array([float(c.weight) for c in components])
    if not (np.all(np.isfinite(weights)) and np.all(weights >= 0) and weights.sum() > 0):
        raise ValueError("the weights of the Gaussian mixture must be non-negative with a "
                         "positive sum")
    weights = weights / weights.sum()
    means = np.stack([np.asarray(c.state_vector, float)[:, 0] for c in components])
    covars = np.stack([np.asarray(c.covar, float) for c in components])
    mean = weights @ means
    spread = means - mean
    covar = np.einsum("k,kij->ij", weights, covars) + np.einsum(
        "k,ki,kj->ij", weights, spread, spread)
    return mean, covar


def to_estimate(state: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The ``(x, P)`` pair of a Stone Soup state, track or Gaussian mixture.

    Gaussian states (``GaussianState`` and its subclasses, ``SqrtGaussianState``,
    ``InformationState``) are converted exactly. Particle, ensemble and kernel-particle
    states and Gaussian mixtures are *moment-matched*: ``x`` and ``P`` are their mean and
    covariance (the mixture's weights normalised; a particle state's weighted sample
    covariance, as Stone Soup's ``ParticleState.covar`` computes it), and a
    :class:`MomentMatchedWarning` says so.

    Parameters
    ----------
    state : State, Track or GaussianMixture
        A Stone Soup state (for a ``Track``, its latest state).

    Returns
    -------
    x : ndarray, shape (n,)
        The mean (a new array).
    P : ndarray, shape (n, n)
        The covariance (a new array with the state's values; validated as
        :func:`cifilter.fuse` validates it, not symmetrised).

    Raises
    ------
    TypeError
        ``state`` is not a Stone Soup state with a mean and a covariance.
    ValueError
        An empty track or mixture, mixture weights that do not sum to a positive number, a
        mean that is not finite, or a covariance that is not finite, square, symmetric (to
        a relative 1e-8, as :func:`cifilter.fuse` checks) and positive definite (the
        message names the state's type).

    Warns
    -----
    MomentMatchedWarning
        For particle, ensemble and kernel-particle states and Gaussian mixtures.

    See Also
    --------
    to_gaussian_state : the conversion back.

    Examples
    --------
    >>> import numpy as np
    >>> from stonesoup.types.state import GaussianState
    >>> from cifilter.stonesoup import to_estimate
    >>> x, P = to_estimate(GaussianState([[1.0], [2.0]], np.diag([3.0, 4.0])))
    >>> x.tolist(), P.tolist()
    ([1.0, 2.0], [[3.0, 0.0], [0.0, 4.0]])
    """
    state = _latest_state(state)
    kind = type(state).__name__
    if isinstance(state, GaussianMixture):
        mean, covar = _mixture_moments(state)
        _check_estimate(mean, covar, f"the {kind}'s mean", f"the {kind}'s covariance")
        _warn_moment_matched(f"a GaussianMixture of {len(state.components)} components")
        return mean, covar
    if isinstance(state, _EXACT_GAUSSIANS):
        mean = np.array(state.mean, dtype=float).reshape(-1)
        covar = np.array(state.covar, dtype=float)
        _check_estimate(mean, covar, f"the {kind}'s mean", f"the {kind}'s covar")
        return mean, covar
    if isinstance(state, _SAMPLED):
        mean = np.array(state.mean, dtype=float).reshape(-1)
        covar = np.array(state.covar, dtype=float).reshape(mean.size, mean.size)
        _check_estimate(mean, covar, f"the {kind}'s mean", f"the {kind}'s covar")
        _warn_moment_matched(f"a {kind}")
        return mean, covar
    raise TypeError(
        "state must be a Stone Soup Gaussian, particle, ensemble or Gaussian mixture state "
        f"(or a Track of them), got {kind}"
    )


def _check_estimate(x, P, x_name, P_name):
    """Validate a mean (n,) and its covariance (n, n) as :func:`cifilter.fuse` does: finite,
    square, of matching size, symmetric and positive definite (``x`` and ``P`` unchanged)."""
    check_finite(x, x_name)
    if P.ndim != 2 or P.shape[0] != P.shape[1]:
        raise ValueError(f"{P_name} must be one square matrix (n, n), got shape {P.shape}")
    if P.shape[0] != x.size:
        raise ValueError(f"{P_name} has shape {P.shape}, which does not match {x_name} of "
                         f"{x.size} entries")
    check_covariances(P, P_name)


def _warn_moment_matched(what):
    warnings.warn(
        f"{what} was moment-matched: cifilter fuses the Gaussian with its mean and "
        "covariance, not the density itself", MomentMatchedWarning, stacklevel=3)


def to_gaussian_state(x: Union[ArrayLike, FusionResult], P: Optional[ArrayLike] = None,
                      timestamp: Optional[datetime.datetime] = None) -> GaussianState:
    """A Stone Soup ``GaussianState`` from ``(x, P)`` or from a :class:`~cifilter.FusionResult`.

    Parameters
    ----------
    x : array_like, shape (n,) or (n, 1), or FusionResult
        The mean, or a fusion result of one estimate (no batch axes), whose ``x`` and ``P``
        are used.
    P : array_like, shape (n, n), optional
        The covariance; required unless ``x`` is a ``FusionResult``.
    timestamp : datetime.datetime, optional
        The state's time.

    Returns
    -------
    GaussianState
        With a column ``StateVector`` and a ``CovarianceMatrix`` (copies).

    Raises
    ------
    ValueError
        ``P`` missing, shapes that do not match, a batched result, an ``x`` that is not
        finite, or a ``P`` that is not finite, symmetric and positive definite (validated
        as :func:`cifilter.fuse` validates a covariance).
    TypeError
        Entries that are not real numbers.

    See Also
    --------
    to_estimate : the conversion to ``(x, P)``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import fuse
    >>> from cifilter.stonesoup import to_gaussian_state
    >>> r = fuse([(np.zeros(2), np.diag([1.0, 4.0])), (np.ones(2), np.diag([4.0, 1.0]))])
    >>> state = to_gaussian_state(r)
    >>> state.state_vector.shape, float(np.trace(state.covar))
    ((2, 1), 3.2)
    """
    if isinstance(x, FusionResult):
        if P is not None:
            raise ValueError("give either a FusionResult or x and P, not both")
        P = x.P  # first: in `x, P = x.x, x.P` mypy takes x for the array in x.P
        x = x.x
    if P is None:
        raise ValueError("P is required unless x is a FusionResult")
    P = as_float_array(P, "P")
    x = as_float_array(x, "x")
    if P.ndim != 2 or P.shape[0] != P.shape[1]:
        raise ValueError(f"P must be one square matrix (n, n), got shape {P.shape}")
    if x.shape not in ((P.shape[0],), (P.shape[0], 1)):
        raise ValueError(
            f"x must have shape ({P.shape[0]},) or ({P.shape[0]}, 1) to match P, got {x.shape}")
    _check_estimate(x.reshape(-1), P, "x", "P")
    return GaussianState(StateVector(x.reshape(-1, 1)), CovarianceMatrix(P),
                         timestamp=timestamp)


# ------------------------------------------------------------------------------ the rules
def _check_rule(method, criterion, omega, options):
    """Validate the rule settings of the components; return the options for ``fuse``.

    Called at construction (early errors) and at every use, so that properties changed
    after construction take effect, as they do in Stone Soup's own components.
    """
    record = get_method(method)  # ValueError listing the registered methods
    if isinstance(criterion, str) and criterion not in ("trace", "det"):
        raise ValueError(  # a weight matrix is checked when its size is known
            f"criterion must be 'trace', 'det' or a positive semidefinite weight matrix, "
            f"got {criterion!r}")
    options = {} if options is None else dict(options)
    accepted = record.signature[0] if record.signature is not None else ()
    for reserved in ("criterion", "omega"):
        if reserved in options:
            raise ValueError(f"give {reserved} as its own property, not in options")
    if criterion is not None and "criterion" in accepted:
        options["criterion"] = criterion
    if omega is not None:
        if record.name != "ci":
            raise ValueError(
                f"omega fixes Covariance Intersection's weight; method {record.name!r} "
                "does not take it")
        options["omega"] = omega
    return record.name, options


def _gate_omega(A, B, criterion):
    """The omega in (0, 1) for which A/(1-omega) + B/omega is smallest under ``criterion``.

    Every member of this family bounds the covariance of a - b for any correlation of the
    errors (docs/stonesoup.rst); the trace criteria have the closed form of the
    minimiser of a/(1-w) + b/w, the determinant is minimised over the generalised
    eigenvalues of (A, B), where log det is convex in omega.
    """
    kind, W = parse_criterion(criterion, A.shape[0])
    if kind == "det":
        from scipy.linalg import eigh
        from scipy.optimize import minimize_scalar
        lam = eigh(A, B, eigvals_only=True)
        lam = np.clip(lam, np.finfo(float).tiny, None)

        def log_det(w):
            return float(np.sum(np.log(lam / (1 - w) + 1 / w)))

        return float(minimize_scalar(log_det, bounds=(1e-12, 1 - 1e-12), method="bounded",
                                     options={"xatol": 1e-10}).x)
    W = np.eye(A.shape[0]) if W is None else W
    a, b = np.sqrt(max(np.sum(W * A), 0.0)), np.sqrt(max(np.sum(W * B), 0.0))
    if a + b == 0:
        return 0.5
    return float(np.clip(b / (a + b), 1e-12, 1 - 1e-12))


def _observation_matrix(measurement_model, n):
    """``H`` of a detection whose model is ``measurement_model`` and a state of dimension n.

    None for a full-state detection (``matrix()`` the n x n identity, as the models of
    ``Tracks2GaussianDetectionFeeder`` have): those keep the full-state path bit for bit.
    A model that is not linear raises a TypeError: its detection is not an estimate of
    ``H x``, and a linearisation at the prediction would lose the Covariance Intersection
    bound (docs/stonesoup.rst, "Detections of part of the state").
    """
    kind = type(measurement_model).__name__
    if not isinstance(measurement_model, LinearModel):
        raise TypeError(
            f"the detection's measurement model must be linear (a Stone Soup LinearModel "
            f"such as LinearGaussian, whose matrix() is the H of an estimate of H x), got "
            f"{kind}: a non-linear detection linearised at the prediction (its Jacobian) "
            "would not keep the Covariance Intersection bound, so FusionUpdater refuses it; "
            "track such detections with an extended or unscented Kalman filter first and "
            "fuse the tracks (Tracks2GaussianDetectionFeeder)")
    H = as_float_array(measurement_model.matrix(), f"the {kind}'s matrix()")
    if H.ndim != 2 or H.shape[0] == 0 or H.shape[1] != n:
        raise ValueError(
            f"the detection's measurement model ({kind}) has matrix() of shape {H.shape}, "
            f"but the predicted state has {n} dimensions: it must be (m, {n})")
    if not np.all(np.isfinite(H)):
        raise ValueError(f"the {kind}'s matrix() contains non-finite values (NaN or inf)")
    if H.shape == (n, n) and np.array_equal(H, np.eye(n)):
        return None
    return H


class FusionUpdater(Updater):
    r"""A Stone Soup updater that fuses Gaussian detections with cifilter's rules.

    A drop-in for Stone Soup's ``ChernoffUpdater``: the measurements are Gaussian
    estimates of the full state, such as the detections ``Tracks2GaussianDetectionFeeder``
    makes from other trackers' tracks (mean ``a``, covariance ``A`` = the detection's
    measurement noise), and the update fuses each with the prediction ``(b, B)`` by the
    rule ``method`` through :func:`cifilter.fuse`, the detection first. With
    ``method="ci"`` the update is Covariance Intersection (the Chernoff rule for Gaussians),

    .. math::

        D = (\omega A^{-1} + (1-\omega) B^{-1})^{-1}, \qquad
        d = D(\omega A^{-1} a + (1-\omega) B^{-1} b),

    where ``omega`` is the weight of the detection as in ``ChernoffUpdater``. With
    ``omega=None`` (the default) it is chosen per hypothesis to minimise ``criterion``
    of ``D``; a number fixes it, and the update is then ``ChernoffUpdater(omega=omega)``'s.

    *Detections of part of the state.* A detection whose measurement model is linear with
    ``H = measurement_model.matrix()`` other than the identity (for instance
    ``LinearGaussian(4, [0, 2], R)``, a position of a constant-velocity state) is fused as
    an estimate :math:`(a, A)` of :math:`H x`: ``cifilter.fuse([(a, A), (b, B)], method,
    H=[H, None], ...)``, generalised CI for ``"ci"``,

    .. math::

        D^{-1} = \omega H^T A^{-1} H + (1-\omega) B^{-1}, \qquad
        d = D(\omega H^T A^{-1} a + (1-\omega) B^{-1} b),

    a bound for every correlation of the two errors (``docs/methods/partial_state.rst``).
    ``"naive"`` and ``"optimal"`` (``joint`` of the detection first) accept such a
    detection too; ``"split-ci"`` takes a partial estimate only second and is refused here,
    and the other rules refuse ``H=`` with the front door's message.
    A non-linear measurement model raises a TypeError (see the documentation page for why
    its Jacobian is not used). Full-state detections take the path above unchanged.

    :meth:`predict_measurement` gives the innovation covariance the gaters and
    hypothesisers use. With a fixed ``omega`` it is Clark & Campbell's
    :math:`V = A/(1-\omega) + B/\omega`, computed as ``ChernoffUpdater`` computes it
    (``1/(1-omega)*A + 1/omega*B``, so the two are bitwise equal). With optimal
    weights it is the member of the same family :math:`A/(1-\theta) + B/\theta` that is
    smallest under ``criterion`` (every member bounds the covariance of :math:`a - b` for
    any correlation of the two errors; the fusion's own ``omega`` may be 0 or 1, where
    Clark & Campbell's formula is infinite). With ``method="naive"`` it is ``A + B``.
    For a detection of :math:`H x` the same holds in measurement space with
    :math:`H B H^T` for :math:`B` (the innovation is :math:`a - H b`). Stone Soup's
    formula and the normalising constant of the Chernoff density differ when
    ``omega != 1/2`` (see the documentation page).

    Parameters
    ----------
    measurement_model : MeasurementModel, optional
        Default measurement model, used when a detection has none (the detections of
        ``Tracks2GaussianDetectionFeeder`` have one, whose noise covariance is the track's
        covariance). Default None.
    omega : float, optional
        Fixed weight of the detection in (0, 1) (``1 - omega`` is the prediction's), for
        ``method="ci"`` only. Default None: optimal per hypothesis.
    method : str, optional
        Any method registered in cifilter (``cifilter.available_methods()``); default
        ``"ci"``.
    criterion : {"trace", "det"} or array_like, optional
        What the optimal weights minimise, for rules that take a criterion (``"ci"``);
        default ``"trace"``. A weight matrix is of the state's size; for a detection of
        part of the state the gate of :meth:`predict_measurement` then uses the trace.
    options : dict, optional
        Further options of the rule, for instance ``{"rho": 0.3}`` for ``"pci"``.

    Raises
    ------
    ValueError
        An unknown method, ``omega`` outside (0, 1) or with a method other than
        ``"ci"``, ``criterion`` or ``omega`` given inside ``options``.

    See Also
    --------
    OptimalCovarianceIntersection, fuse_tracks, cifilter.fuse

    References
    ----------
    .. [1] D. Clark and M. Campbell, "Integrating covariance intersection into Bayesian
       multi-target tracking filters", preprint (TechRxiv); as cited and implemented by
       Stone Soup's ``ChernoffUpdater``.
    .. [2] S. J. Julier and J. K. Uhlmann, "A non-divergent estimation algorithm in the
       presence of unknown correlations", ACC 1997.

    Examples
    --------
    >>> import numpy as np
    >>> from stonesoup.models.measurement.linear import LinearGaussian
    >>> from stonesoup.types.detection import Detection, GaussianDetection
    >>> from stonesoup.types.hypothesis import SingleHypothesis
    >>> from stonesoup.types.prediction import GaussianStatePrediction
    >>> from cifilter.stonesoup import FusionUpdater
    >>> A, B = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    >>> detection = GaussianDetection([[1.0], [0.0]], A,
    ...                               measurement_model=LinearGaussian(2, [0, 1], A))
    >>> prediction = GaussianStatePrediction([[0.0], [1.0]], B)
    >>> update = FusionUpdater().update(SingleHypothesis(prediction, detection))
    >>> float(np.trace(update.covar))
    3.2

    A position-only detection (variance 1) of the same state: the determinant-optimal
    weight of the prediction is 2/3, so the position's variance is
    ``1 / ((2/3) / 4 + (1/3) / 1) = 2`` and the velocity's ``1 / (2/3) = 1.5``:

    >>> position = Detection([[1.0]], measurement_model=LinearGaussian(2, [0], [[1.0]]))
    >>> update = FusionUpdater(criterion="det").update(SingleHypothesis(prediction, position))
    >>> np.round(update.covar, 6).tolist()
    [[2.0, 0.0], [0.0, 1.5]]
    """

    measurement_model: MeasurementModel = Property(
        default=None, doc="Default measurement model (detections normally carry their own).")
    omega: float = Property(
        default=None,
        doc="Fixed weight of the detection in (0, 1), as in ChernoffUpdater (``method='ci'`` "
            "only); None chooses it optimally per hypothesis.")
    method: str = Property(default="ci", doc="The cifilter fusion rule.")
    criterion: object = Property(
        default="trace", doc="What the optimal weights minimise: 'trace', 'det' or a matrix.")
    options: dict = Property(default=None, doc="Further options of the fusion rule.")

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.omega is not None:
            omega = float(self.omega)
            if not 0 < omega < 1:
                raise ValueError(f"omega must be in (0, 1), got {self.omega!r}")
        self._rule()

    def _rule(self):
        """(method name, options for fuse) from the current properties."""
        return _check_rule(self.method, self.criterion, self.omega, self.options)

    def _detection_estimate(self, measurement, measurement_model):
        """Mean and covariance of a Gaussian detection (its covariance, else its noise)."""
        covar = getattr(measurement, "covar", None)
        if covar is None:
            covar = measurement_model.noise_covar
        return (np.asarray(measurement.state_vector, float),
                np.asarray(covar, float))

    @lru_cache  # noqa: B019  (as ChernoffUpdater: the hypothesisers call it per pair)
    def predict_measurement(self, predicted_state: GaussianState,
                            measurement_model: Optional[MeasurementModel] = None,
                            measurement_noise: bool = True,
                            **kwargs: Any) -> MeasurementPrediction:
        r"""The measurement prediction of a state, with the fusion's innovation covariance.

        Parameters
        ----------
        predicted_state : GaussianState
            The predicted state :math:`(b, B)`.
        measurement_model : MeasurementModel, optional
            The detection's model, whose noise covariance is the detection covariance
            :math:`A`; default: the updater's. A linear model whose ``matrix()`` :math:`H`
            is not the identity describes a detection of :math:`H x`.
        measurement_noise : bool, optional
            Whether to include the detection's covariance (default True); False gives
            :math:`B` alone (:math:`H B H^T` for a detection of :math:`H x`), as in
            ``ChernoffUpdater`` and ``KalmanUpdater``.
        **kwargs
            Ignored (accepted for the Updater interface).

        Returns
        -------
        MeasurementPrediction
            In measurement space: mean :math:`H b`, covariance the innovation covariance
            :math:`V` (see the class notes), cross-covariance :math:`B H^T`; for a
            full-state detection :math:`b`, :math:`V` and :math:`B`, as
            ``ChernoffUpdater`` returns them.

        Raises
        ------
        ValueError
            No measurement model, a model matrix without one column per state dimension,
            or a detection covariance whose size is not the model's number of rows.
        TypeError
            A measurement model that is not linear.

        Examples
        --------
        >>> import numpy as np
        >>> from stonesoup.models.measurement.linear import LinearGaussian
        >>> from stonesoup.types.prediction import GaussianStatePrediction
        >>> from cifilter.stonesoup import FusionUpdater
        >>> model = LinearGaussian(2, [0, 1], np.eye(2))
        >>> prediction = GaussianStatePrediction([[0.0], [0.0]], 3 * np.eye(2))
        >>> V = FusionUpdater(omega=0.25).predict_measurement(prediction, model).covar
        >>> np.diag(V).tolist()   # A / 0.75 + B / 0.25
        [13.333333333333334, 13.333333333333334]

        A detection of the first component only (:math:`H = [1, 0]`):

        >>> first = LinearGaussian(2, [0], [[1.0]])
        >>> V = FusionUpdater(omega=0.25).predict_measurement(prediction, first).covar
        >>> V.tolist()   # A / 0.75 + H B H^T / 0.25
        [[13.333333333333334]]
        """
        measurement_model = self._check_measurement_model(measurement_model)
        B = np.asarray(predicted_state.covar, float)
        H = _observation_matrix(measurement_model, B.shape[0])
        if H is not None:
            return self._partial_prediction(predicted_state, measurement_model, H, B,
                                            measurement_noise)
        if measurement_noise:
            A = np.asarray(measurement_model.noise_covar, float)
            if A.shape != B.shape:
                raise ValueError(
                    f"the detection covariance {A.shape} must be of the state's size {B.shape}: "
                    "the measurement model's matrix() is the identity, so the detection is "
                    "an estimate of the full state")
            innovation = self._innovation_covariance(A, B)
        else:
            innovation = B
        return MeasurementPrediction.from_state(
            predicted_state, predicted_state.state_vector, CovarianceMatrix(innovation),
            predicted_state.timestamp, cross_covar=predicted_state.covar)

    def _partial_prediction(self, predicted_state, measurement_model, H, B,
                            measurement_noise):
        """The measurement prediction of a detection of ``H x`` (measurement space)."""
        b = np.asarray(predicted_state.state_vector, float)
        BH = H @ B @ H.T  # as KalmanUpdater forms it; V is symmetrised below
        if measurement_noise:
            A = np.asarray(measurement_model.noise_covar, float)
            m = H.shape[0]
            if A.shape != (m, m):
                raise ValueError(
                    f"the detection covariance {A.shape} must be ({m}, {m}): the measurement "
                    f"model's matrix() has shape {H.shape}")
            innovation = self._innovation_covariance(A, BH, partial=True)
        else:
            innovation = BH
        return MeasurementPrediction.from_state(
            predicted_state, StateVector(H @ b), CovarianceMatrix(innovation),
            predicted_state.timestamp, cross_covar=CovarianceMatrix(B @ H.T))

    def _innovation_covariance(self, A, B, partial=False):
        """Clark & Campbell's family ``A/(1-w) + B/w`` at the fixed or the gate's ``w``
        (``B`` is ``H B H^T`` for a detection of part of the state)."""
        name, _ = self._rule()
        if name == "naive":
            V = A + B
        elif self.omega is not None:
            # As ChernoffUpdater computes it, multiplying by the reciprocals (A / (1 - w)
            # rounds differently, by up to an ulp): the drop-in is bitwise equal at fixed w.
            w = float(self.omega)
            if not partial:
                return 1 / (1 - w) * A + 1 / w * B
            V = 1 / (1 - w) * A + 1 / w * B
        elif partial:
            # In measurement space; a weight matrix weighs the state: the gate uses the trace.
            # The roles swapped (t = 1 - w) so that the generalised eigenvalues of the det
            # gate are taken against A, which is positive definite while H B H^T need not be
            # (an H of dependent rows).
            criterion = self.criterion if isinstance(self.criterion, str) else "trace"
            t = _gate_omega(B, A, criterion)
            V = A / t + B / (1 - t)
        else:
            w = _gate_omega(A, B, self.criterion)
            V = A / (1 - w) + B / w
        return (V + V.T) / 2

    def fuse_hypothesis(self, hypothesis: Any) -> FusionResult:
        """The cifilter fusion of a hypothesis' detection (first) and prediction (second).

        Parameters
        ----------
        hypothesis : SingleHypothesis
            A hypothesis with a prediction and a Gaussian detection: of the full state, or
            of :math:`H x` for a linear measurement model with ``matrix()`` :math:`H`.

        Returns
        -------
        FusionResult
            The rule's result: ``x`` (n, 1), ``P``, ``weights`` (the detection's first:
            for ``"ci"``, ``weights[0]`` is ``omega``), ``info``. For a detection of
            :math:`H x` it is ``cifilter.fuse([(a, A), (b, B)], method, H=[H, None])``'s:
            ``gains`` is None and ``info["gains"]`` holds the gains (n x m, n x n).

        Raises
        ------
        ValueError
            Bad covariances (not symmetric positive definite, mismatched sizes), as
            :func:`cifilter.fuse` raises them; a detection whose size is not the number of
            rows of its model's matrix; a rule that does not accept ``H=`` (or
            ``"split-ci"``, which takes a partial estimate only second) for a detection of
            part of the state.
        TypeError
            A measurement model that is not linear.

        Examples
        --------
        >>> import numpy as np
        >>> from stonesoup.models.measurement.linear import LinearGaussian
        >>> from stonesoup.types.detection import GaussianDetection
        >>> from stonesoup.types.hypothesis import SingleHypothesis
        >>> from stonesoup.types.prediction import GaussianStatePrediction
        >>> from cifilter.stonesoup import FusionUpdater
        >>> A, B = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
        >>> hypothesis = SingleHypothesis(
        ...     GaussianStatePrediction([[0.0], [1.0]], B),
        ...     GaussianDetection([[1.0], [0.0]], A,
        ...                       measurement_model=LinearGaussian(2, [0, 1], A)))
        >>> r = FusionUpdater().fuse_hypothesis(hypothesis)
        >>> float(r.weights[0]), r.info["rule"]
        (0.5, 'optimal')
        """
        measurement = hypothesis.measurement
        model = self._check_measurement_model(measurement.measurement_model)
        prediction = hypothesis.prediction
        b, B = np.asarray(prediction.state_vector, float), np.asarray(prediction.covar, float)
        H = _observation_matrix(model, b.shape[0])
        a, A = self._detection_estimate(measurement, model)
        name, options = self._rule()
        if options.get("omega") is not None:
            options["omega"] = float(options["omega"])
        if H is None:
            if a.shape != b.shape:
                raise ValueError(
                    f"the detection {a.shape} must be an estimate of the full state {b.shape}: "
                    "its measurement model's matrix() is the identity")
            return fuse([(a, A), (b, B)], method=name, **options)
        if a.shape != (H.shape[0], 1):
            raise ValueError(
                f"the detection {a.shape} must have one entry per row of its measurement "
                f"model's matrix() {H.shape}")
        if name == "split-ci":
            raise ValueError(
                "method 'split-ci' fuses an estimate of part of the state only as the second "
                "of two (H=[None, H_2]), but FusionUpdater fuses the detection first; fuse "
                "this detection with 'ci', 'naive' or 'optimal', or call cifilter.fuse([(b, "
                "B), (a, A)], 'split-ci', H=[None, H], independent=...) yourself")
        return fuse([(a, A), (b, B)], method=name, H=[H, None], **options)

    def update(self, hypothesis: Any, force_symmetric_covariance: bool = False,
               **kwargs: Any) -> Update:
        """The fused posterior of a hypothesis.

        Parameters
        ----------
        hypothesis : SingleHypothesis
            The prediction and the associated Gaussian detection (of the full state or of
            :math:`H x`); its measurement prediction is computed if missing (as
            ``ChernoffUpdater`` does).
        force_symmetric_covariance : bool, optional
            Accepted for ``ChernoffUpdater`` compatibility; cifilter's covariances are
            exactly symmetric already.
        **kwargs
            Passed to :meth:`predict_measurement`.

        Returns
        -------
        GaussianStateUpdate
            The fused state (of the full state), at the detection's timestamp.

        Raises
        ------
        ValueError
            Bad covariances, a detection whose size does not match its model.
        TypeError
            A measurement model that is not linear.

        Examples
        --------
        Equal to ``ChernoffUpdater`` at a fixed weight:

        >>> import numpy as np
        >>> from stonesoup.models.measurement.linear import LinearGaussian
        >>> from stonesoup.types.detection import GaussianDetection
        >>> from stonesoup.types.hypothesis import SingleHypothesis
        >>> from stonesoup.types.prediction import GaussianStatePrediction
        >>> from stonesoup.updater.chernoff import ChernoffUpdater
        >>> from cifilter.stonesoup import FusionUpdater
        >>> A, B = np.array([[2.0, 0.5], [0.5, 1.0]]), np.diag([1.0, 3.0])
        >>> def hypothesis():
        ...     return SingleHypothesis(
        ...         GaussianStatePrediction([[0.0], [1.0]], B),
        ...         GaussianDetection([[1.0], [0.0]], A,
        ...                           measurement_model=LinearGaussian(2, [0, 1], A)))
        >>> ours = FusionUpdater(omega=0.3).update(hypothesis())
        >>> theirs = ChernoffUpdater(None, omega=0.3).update(hypothesis())
        >>> bool(np.allclose(ours.covar, theirs.covar) and np.allclose(ours.mean, theirs.mean))
        True
        """
        if hypothesis.measurement_prediction is None:
            hypothesis.measurement_prediction = self.predict_measurement(
                hypothesis.prediction,
                measurement_model=hypothesis.measurement.measurement_model, **kwargs)
        result = self.fuse_hypothesis(hypothesis)
        return Update.from_state(
            hypothesis.prediction, StateVector(np.asarray(result.x).reshape(-1, 1)),
            CovarianceMatrix(result.P), hypothesis=hypothesis,
            timestamp=hypothesis.measurement.timestamp)


class _ClassOrInstanceMethod:
    """A method that, called on the class, runs on a default instance.

    Stone Soup calls ``CovarianceIntersection.merge_components(...)`` on the class; the
    drop-in keeps that working and also uses an instance's properties.
    """

    def __init__(self, function):
        self.function = function
        self.__doc__ = function.__doc__
        self.__name__ = function.__name__
        self.__wrapped__ = function

    def __get__(self, instance, owner):
        if instance is None:
            instance = owner()
        return self.function.__get__(instance, owner)


class OptimalCovarianceIntersection(MixtureReducer):
    r"""Covariance Intersection of N Gaussian states with optimal weights.

    A drop-in for Stone Soup's ``CovarianceIntersection`` reducer: ``merge_components``
    has the same call (on the class or an instance), but ``weights=None`` means the
    weights that minimise ``criterion`` of the merged covariance instead of equal
    weights. The merged state is

    .. math::

        C^{-1} = \sum_i \omega_i C_i^{-1}, \qquad
        \mathbf{x} = C \sum_i \omega_i C_i^{-1} \mathbf{x}_i,

    computed by :func:`cifilter.fuse` (Cholesky factors, no explicit inverses; Stone Soup's
    uses pseudo-inverses). ``method`` may name any registered rule, for instance
    ``"pci"`` with ``options={"rho": 0.3}``.

    Parameters
    ----------
    method : str, optional
        A registered cifilter rule; default ``"ci"``.
    criterion : {"trace", "det"} or array_like, optional
        What the optimal weights minimise (rules that take it); default ``"trace"``.
    options : dict, optional
        Further options of the rule.

    Raises
    ------
    ValueError
        An unknown method or a ``criterion`` given inside ``options``.

    See Also
    --------
    FusionUpdater, fuse_tracks

    Examples
    --------
    >>> import numpy as np
    >>> from stonesoup.types.state import GaussianState
    >>> from cifilter.stonesoup import OptimalCovarianceIntersection
    >>> a = GaussianState([[1.0], [0.0]], np.diag([1.0, 4.0]))
    >>> b = GaussianState([[0.0], [1.0]], np.diag([4.0, 1.0]))
    >>> merged = OptimalCovarianceIntersection.merge_components(a, b)
    >>> float(np.trace(merged.covar))
    3.2
    """

    method: str = Property(default="ci", doc="The cifilter fusion rule.")
    criterion: object = Property(
        default="trace", doc="What the optimal weights minimise: 'trace', 'det' or a matrix.")
    options: dict = Property(default=None, doc="Further options of the fusion rule.")

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _check_rule(self.method, self.criterion, None, self.options)

    @_ClassOrInstanceMethod
    def merge_result(self, *components: Any,
                     weights: Optional[ArrayLike] = None) -> FusionResult:
        """The :class:`~cifilter.FusionResult` of merging the components (class or instance).

        Parameters
        ----------
        *components : GaussianState
            Two or more states of one dimension (other states are converted by
            :func:`to_estimate`, with its warning).
        weights : sequence of float, optional
            Fixed weights (normalised to sum to one, as Stone Soup does), for
            ``method="ci"``; default None: optimal.

        Returns
        -------
        FusionResult
            ``x`` (n, 1), ``P``, ``weights``, ``info``.

        Raises
        ------
        ValueError
            Fewer than two components, weights of the wrong length or sign, bad
            covariances.

        Examples
        --------
        >>> import numpy as np
        >>> from stonesoup.types.state import GaussianState
        >>> from cifilter.stonesoup import OptimalCovarianceIntersection
        >>> a = GaussianState([[0.0]], [[1.0]])
        >>> b = GaussianState([[1.0]], [[2.0]])
        >>> OptimalCovarianceIntersection().merge_result(a, b).weights.tolist()
        [1.0, 0.0]
        """
        name, options = _check_rule(self.method, self.criterion, None, self.options)
        if weights is not None:
            weights = np.asarray(weights, dtype=float)
            if weights.shape != (len(components),):
                raise ValueError(
                    f"weights must have one entry per component ({len(components)}), got "
                    f"shape {weights.shape}")
            if not (np.all(np.isfinite(weights)) and np.all(weights >= 0)
                    and weights.sum() > 0):
                raise ValueError("weights must be non-negative with a positive sum")
            _, options = _check_rule(name, self.criterion, weights / weights.sum(),
                                     self.options)
        estimates = []
        for component in components:
            x, P = to_estimate(component)
            estimates.append((x.reshape(-1, 1), P))
        return fuse(estimates, method=name, **options)

    @_ClassOrInstanceMethod
    def merge_components(self, *components: Any,
                         weights: Optional[ArrayLike] = None) -> GaussianState:
        """Merge Gaussian states by Covariance Intersection (or the chosen rule).

        Called on the class it uses the default properties (optimal trace weights), as
        Stone Soup's ``CovarianceIntersection.merge_components`` is called.

        Parameters
        ----------
        *components : GaussianState
            Two or more states of one dimension.
        weights : sequence of float, optional
            Fixed weights (normalised); default None: optimal weights.

        Returns
        -------
        GaussianState
            The merged state, of the type of the first component (as Stone Soup's
            reducer returns it) with its other properties (timestamp, weight) copied.

        Raises
        ------
        ValueError
            As :meth:`merge_result`.

        Examples
        --------
        >>> import numpy as np
        >>> from stonesoup.types.state import GaussianState
        >>> from cifilter.stonesoup import OptimalCovarianceIntersection
        >>> a = GaussianState([[0.0]], [[1.0]])
        >>> b = GaussianState([[1.0]], [[2.0]])
        >>> OptimalCovarianceIntersection().merge_components(a, b).covar.tolist()
        [[1.0]]
        """
        result = self.merge_result(*components, weights=weights)
        x = StateVector(np.asarray(result.x).reshape(-1, 1))
        P = CovarianceMatrix(result.P)
        first = components[0]
        if isinstance(first, GaussianState):
            return GaussianState.from_state(first, state_vector=x, covar=P)
        return GaussianState(x, P, timestamp=getattr(first, "timestamp", None))


# ---------------------------------------------------------------------------- track fusion
_TIME_KEYWORDS = ("times", "at", "motion")


def _transition_motion(transition_model, intervals):
    """``motion(dt) -> (F, Q)`` of :func:`cifilter.fuse` from a linear Stone Soup transition
    model: ``matrix(time_interval=)`` and ``covar(time_interval=)`` as plain float arrays.

    ``intervals`` maps the seconds the front door asks for (``abs(at - times[i])``, exact
    as floats) to the tracks' exact ``timedelta`` offsets, so that the model sees the very
    interval between the timestamps (microseconds, not a float round trip).
    """
    kind = type(transition_model).__name__
    if not (isinstance(transition_model, TransitionModel)
            and isinstance(transition_model, LinearModel)):
        raise TypeError(
            f"transition_model must be a linear Stone Soup transition model (a LinearModel "
            f"TransitionModel such as ConstantVelocity or CombinedLinearGaussianTransitionModel,"
            f" with matrix(time_interval=) and covar(time_interval=)), got {kind}: fuse_tracks "
            "brings tracks of other times to timestamp with F and Q, through "
            "cifilter.fuse(times=, at=, motion=)")

    def motion(dt):
        interval = intervals.get(dt)
        if interval is None:  # not asked by fuse_tracks' own times; kept well-defined
            interval = datetime.timedelta(seconds=dt)
        F = np.array(transition_model.matrix(time_interval=interval), dtype=float)
        Q = np.array(transition_model.covar(time_interval=interval), dtype=float)
        return F, Q

    return motion


def fuse_tracks(tracks: Sequence[Any], method: str = "ci",
                timestamp: Optional[datetime.datetime] = None, transition_model: Any = None, *,
                return_result: bool = False,
                **options: Any) -> Union[GaussianState, tuple[GaussianState, FusionResult]]:
    r"""Fuse the latest states of tracks, brought to a common time.

    Each track's latest state is converted by :func:`to_estimate` (particle and mixture
    states moment-matched, with a :class:`MomentMatchedWarning`). When all are at
    ``timestamp`` they are fused by ``cifilter.fuse(estimates, method, **options)``.
    Otherwise the front door's time alignment brings them there: ``cifilter.fuse(estimates,
    method, times=..., at=0.0, motion=..., **options)`` with ``times[i]`` the seconds from
    ``timestamp`` to track ``i``'s latest state and ``motion(dt)`` the ``F =
    transition_model.matrix(time_interval=dt)`` and ``Q = transition_model.covar(
    time_interval=dt)`` of the exact interval. An older state is predicted
    (:math:`F x`, :math:`F P F^T + Q`); a *newer* one is retrodicted with the conservative
    bound :math:`F^{-1}(P/\alpha + Q/(1-\alpha))F^{-T}` (its error is correlated with the
    process noise in between; ``docs/methods/time.rst``). The rules that accept ``times=``
    (``"ci"``) fuse tracks of different times; the others refuse them with the front
    door's message.

    Parameters
    ----------
    tracks : sequence of Track or State
        Two or more tracks (or states) of the same target and state space.
    method : str, optional
        A registered cifilter rule; default ``"ci"`` (optimal trace weights).
    timestamp : datetime.datetime, optional
        The time of the fused state; default: the latest of the tracks' latest times.
        Tracks later than it are retrodicted.
    transition_model : TransitionModel, optional
        A linear Stone Soup transition model; needed when the tracks' latest states are
        not all at ``timestamp``.
    return_result : bool, optional
        Also return the :class:`~cifilter.FusionResult` (weights, diagnostics; when the
        tracks were brought to ``timestamp``, ``info["at"]`` is ``0.0``, the seconds from
        ``timestamp``, and ``info["retrodiction_alpha"]`` the :math:`\alpha` of each track,
        None unless retrodicted).
    **options
        Options of the rule, for instance ``criterion="det"`` or ``rho=0.3`` (not
        ``times``, ``at`` or ``motion``: they come from the tracks and ``timestamp``).

    Returns
    -------
    GaussianState
        The fused state at ``timestamp``; with ``return_result=True`` a pair
        ``(state, result)``.

    Raises
    ------
    ValueError
        Fewer than two tracks, an empty track, a state at another time than
        ``timestamp`` without ``transition_model``, a state without a timestamp among
        states with one, a rule that does not accept ``times=`` for tracks of different
        times, states of different dimensions, bad covariances.
    TypeError
        A track that is not a Stone Soup track or state, a ``transition_model`` that is not
        a linear transition model (when one is needed), ``times``, ``at`` or ``motion``
        among the options.
    IllConditionedError
        A newer track whose transition matrix is singular (retrodiction needs
        :math:`F^{-1}`), as :func:`cifilter.fuse` raises it.

    Warns
    -----
    MomentMatchedWarning
        For particle, ensemble and mixture states.

    Examples
    --------
    >>> from datetime import datetime, timedelta
    >>> import numpy as np
    >>> from stonesoup.models.transition.linear import ConstantVelocity
    >>> from stonesoup.types.state import GaussianState
    >>> from stonesoup.types.track import Track
    >>> from cifilter.stonesoup import fuse_tracks
    >>> t0 = datetime(2026, 1, 1)
    >>> a = Track([GaussianState([[0.0], [1.0]], np.diag([1.0, 4.0]), timestamp=t0)])
    >>> b = Track([GaussianState([[1.0], [1.0]], np.diag([4.0, 1.0]),
    ...                          timestamp=t0 + timedelta(seconds=1))])
    >>> fused = fuse_tracks([a, b], transition_model=ConstantVelocity(0.1))
    >>> fused.timestamp == t0 + timedelta(seconds=1), fused.state_vector.shape
    (True, (2, 1))

    At ``a``'s time, ``b`` (one second newer) is retrodicted:

    >>> fused, result = fuse_tracks([a, b], timestamp=t0, return_result=True,
    ...                             transition_model=ConstantVelocity(0.1))
    >>> fused.timestamp == t0, result.info["retrodiction_alpha"][0]
    (True, None)
    """
    if isinstance(tracks, (str, bytes)) or not hasattr(tracks, "__len__"):
        raise TypeError(f"tracks must be a sequence of tracks, got {type(tracks).__name__}")
    reserved = [name for name in _TIME_KEYWORDS if name in options]
    if reserved:
        raise TypeError(
            f"fuse_tracks sets {', '.join(reserved)} itself, from the tracks' timestamps, "
            "timestamp and transition_model; give timestamp= and transition_model= instead")
    states = [_latest_state(track) for track in tracks]
    if len(states) < 2:
        raise ValueError(f"at least 2 tracks are needed, got {len(states)}")
    times = [getattr(state, "timestamp", None) for state in states]
    if timestamp is None:
        known = [t for t in times if t is not None]
        timestamp = max(known) if known else None
    estimates = []
    offsets = []
    for index, (state, time) in enumerate(zip(states, times)):
        x, P = to_estimate(state)
        estimates.append((x.reshape(-1, 1), P))
        if time == timestamp:
            offsets.append(datetime.timedelta(0))
            continue
        if time is None or timestamp is None:
            raise ValueError(
                f"tracks[{index}]: cannot bring a state without a timestamp to a timestamp, "
                "or a state with one to no timestamp")
        if transition_model is None:
            raise ValueError(
                f"tracks[{index}]'s latest state ({time}) is not at timestamp "
                f"({timestamp}): give transition_model to "
                f"{'predict' if time < timestamp else 'retrodict'} it")
        offsets.append(time - timestamp)
    if not any(offsets):
        result = fuse(estimates, method=method, **options)
    else:
        seconds = [offset.total_seconds() for offset in offsets]
        intervals = {abs(s): abs(offset) for s, offset in zip(seconds, offsets)}
        motion = _transition_motion(transition_model, intervals)
        result = fuse(estimates, method=method, times=seconds, at=0.0, motion=motion,
                      **options)
    state = to_gaussian_state(result, timestamp=timestamp)
    return (state, result) if return_result else state
