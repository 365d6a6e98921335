"""cifilter.stonesoup against the real Stone Soup: ChernoffUpdater and the
CovarianceIntersection reducer at fixed weights, optimal weights, conversions, track
fusion, and a two-radar track-to-track fusion loop built from Stone Soup components."""

import subprocess
import sys
import warnings
from datetime import datetime, timedelta

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats
from scipy.linalg import eigh

pytest.importorskip("stonesoup")

from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.deleter.time import UpdateTimeStepsDeleter
from stonesoup.feeder.track import Tracks2GaussianDetectionFeeder
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.initiator.simple import SimpleMeasurementInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.mixturereducer.gaussianmixture import CovarianceIntersection
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToBearingRange
from stonesoup.models.transition.linear import (
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
    LinearGaussianTimeInvariantTransitionModel,
    RandomWalk,
)
from stonesoup.models.transition.nonlinear import ConstantTurn
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.tracker.simple import MultiTargetTracker
from stonesoup.types.array import StateVectors
from stonesoup.types.detection import Detection, GaussianDetection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.mixture import GaussianMixture
from stonesoup.types.prediction import GaussianStatePrediction
from stonesoup.types.state import (
    GaussianState,
    ParticleState,
    WeightedGaussianState,
)
from stonesoup.types.track import Track
from stonesoup.updater.chernoff import ChernoffUpdater
from stonesoup.updater.kalman import ExtendedKalmanUpdater, KalmanUpdater
from strategies import ill_conditioned_sets, ill_conditioned_spd

from cifilter import IllConditionedError, ci_weights, covariance_intersection, fuse
from cifilter.stonesoup import (
    FusionUpdater,
    MomentMatchedWarning,
    OptimalCovarianceIntersection,
    fuse_tracks,
    to_estimate,
    to_gaussian_state,
)

T0 = datetime(2026, 1, 1)


def random_spd(rng, n, cond=1e3):
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return (Q * np.geomspace(1.0, cond, n)) @ Q.T


def hypothesis(a, A, b, B, timestamp=T0):
    detection = GaussianDetection(np.reshape(a, (-1, 1)), A, timestamp=timestamp,
                                  measurement_model=LinearGaussian(len(a), list(range(len(a))), A))
    prediction = GaussianStatePrediction(np.reshape(b, (-1, 1)), B, timestamp=timestamp)
    return SingleHypothesis(prediction, detection)


# ------------------------------------------------------------------------ optional import
def test_stonesoup_is_optional():
    """import cifilter does not import Stone Soup; without it, cifilter.stonesoup says how
    to install it (one interpreter for both checks: starting one is slow)."""
    code = ("import sys, cifilter\n"
            "assert 'stonesoup' not in sys.modules\n"
            "sys.modules['stonesoup'] = None\n"
            "try:\n    import cifilter.stonesoup\nexcept ImportError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120).stdout
    assert 'pip install ".[stonesoup]" from a clone' in out
    assert '"cifilter-fusion[stonesoup]"' in out


# -------------------------------------------------------------- FusionUpdater vs Chernoff
@pytest.mark.parametrize("omega", [0.1, 0.3, 0.5, 0.77, 0.95])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fixed_omega_equals_chernoff_updater(omega, seed):
    rng = np.random.default_rng(seed)
    n = 4
    A, B = random_spd(rng, n), random_spd(rng, n, 1e2)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    ours_updater, theirs_updater = FusionUpdater(omega=omega), ChernoffUpdater(None, omega=omega)
    ours = ours_updater.update(hypothesis(a, A, b, B))
    theirs = theirs_updater.update(hypothesis(a, A, b, B))
    scale = np.linalg.norm(theirs.covar)
    assert np.allclose(ours.covar, theirs.covar, rtol=1e-9, atol=1e-10 * scale)
    assert np.allclose(ours.state_vector, theirs.state_vector, rtol=1e-8, atol=1e-8)
    assert ours.timestamp == theirs.timestamp and ours.hypothesis is not None
    model = LinearGaussian(n, list(range(n)), A)
    prediction = GaussianStatePrediction(b.reshape(-1, 1), B, timestamp=T0)
    for noise in (True, False):
        V = ours_updater.predict_measurement(prediction, model, measurement_noise=noise)
        W = theirs_updater.predict_measurement(prediction, model, measurement_noise=noise)
        assert np.allclose(V.covar, W.covar, rtol=1e-12)
        assert np.allclose(V.state_vector, W.state_vector)
        assert np.allclose(V.cross_covar, W.cross_covar)


# Stone Soup's own test of ChernoffUpdater (stonesoup/updater/tests/test_chernoff.py, not
# shipped in the wheel): its prediction and detection, with the noise covariance made a
# well-formed 2x2 matrix (the test gives np.array([[0.04, 0.04]]), a 1x2 array).
SS_PREDICTION = (np.array([[-6.45], [0.7]]), np.array([[4.1123, 0.0013], [0.0013, 0.0365]]))
SS_DETECTION = (np.array([[-6.23], [0.83]]), np.diag([0.75, 1.2]))
SS_NOISE = np.diag([0.04, 0.04])


@pytest.mark.parametrize("omega", [0.05, 0.1, 0.2, 0.25, 0.3, 0.5, 0.77, 0.95])
def test_predict_measurement_is_bitwise_chernoff_on_stonesoups_test_inputs(omega):
    """At a fixed omega the innovation covariance is ChernoffUpdater's, bit for bit (A/(1-w)
    and 1/(1-w)*A differ by an ulp at omega = 0.05, 0.1, 0.2, 0.25, 0.77 and 0.95)."""
    model = LinearGaussian(ndim_state=2, mapping=[0, 1], noise_covar=SS_NOISE)
    prediction = GaussianStatePrediction(*SS_PREDICTION)
    ours = FusionUpdater(measurement_model=model, omega=omega).predict_measurement(prediction)
    theirs = ChernoffUpdater(measurement_model=model, omega=omega).predict_measurement(
        prediction)
    assert np.array_equal(np.asarray(ours.covar), np.asarray(theirs.covar))
    assert np.array_equal(np.asarray(ours.state_vector), np.asarray(theirs.state_vector))
    assert np.array_equal(np.asarray(ours.cross_covar), np.asarray(theirs.cross_covar))
    # Stone Soup's own expectations of the test, at its tolerance (atol 1e-14)
    innovation = 1 / (1 - omega) * model.noise_covar + 1 / omega * prediction.covar
    assert np.allclose(ours.covar, innovation, 0, atol=1e-14)
    detection = GaussianDetection(state_vector=SS_DETECTION[0], covar=SS_DETECTION[1],
                                  measurement_model=model)
    posterior = FusionUpdater(measurement_model=model, omega=omega).update(
        SingleHypothesis(prediction=prediction, measurement=detection))
    A_inv, B_inv = np.linalg.inv(SS_DETECTION[1]), np.linalg.inv(SS_PREDICTION[1])
    covar = np.linalg.inv(omega * A_inv + (1 - omega) * B_inv)
    mean = covar @ (omega * A_inv @ SS_DETECTION[0] + (1 - omega) * B_inv @ SS_PREDICTION[0])
    assert np.allclose(posterior.mean, mean, 0, atol=1e-14)
    assert np.allclose(posterior.covar, covar, 0, atol=1e-14)


@pytest.mark.parametrize("seed", range(5))
def test_predict_measurement_is_bitwise_chernoff_on_rounded_covariances(seed):
    """Covariances computed as Q D Q^T are symmetric only to rounding; the drop-in still
    gives ChernoffUpdater's bits (no symmetrisation at a fixed omega)."""
    rng = np.random.default_rng(seed)
    A, B = random_spd(rng, 4), random_spd(rng, 4, 1e6)
    model = LinearGaussian(4, [0, 1, 2, 3], A)
    prediction = GaussianStatePrediction(rng.standard_normal((4, 1)), B, timestamp=T0)
    for omega in (0.05, 0.3, 0.95):
        ours = FusionUpdater(omega=omega).predict_measurement(prediction, model)
        theirs = ChernoffUpdater(None, omega=omega).predict_measurement(prediction, model)
        assert np.array_equal(np.asarray(ours.covar), np.asarray(theirs.covar)), omega


def test_omega_is_the_weight_of_the_detection():
    """omega -> 1 gives the detection, omega -> 0 the prediction (as in ChernoffUpdater)."""
    A, B = np.diag([1.0, 2.0]), np.diag([3.0, 0.5])
    a, b = np.array([1.0, 2.0]), np.array([-1.0, 0.0])
    near_detection = FusionUpdater(omega=1 - 1e-9).update(hypothesis(a, A, b, B))
    near_prediction = FusionUpdater(omega=1e-9).update(hypothesis(a, A, b, B))
    assert np.allclose(near_detection.covar, A, atol=1e-6)
    assert np.allclose(near_prediction.state_vector.ravel(), b, atol=1e-6)
    r = FusionUpdater(omega=0.3).fuse_hypothesis(hypothesis(a, A, b, B))
    assert r.weights.tolist() == pytest.approx([0.3, 0.7])


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_optimal_omega_gives_the_smallest_criterion(criterion):
    rng = np.random.default_rng(7)
    measure = np.trace if criterion == "trace" else np.linalg.det
    for _ in range(5):
        A, B = random_spd(rng, 3, 1e2), random_spd(rng, 3, 1e2)
        a, b = rng.standard_normal(3), rng.standard_normal(3)
        ours = FusionUpdater(criterion=criterion).update(hypothesis(a, A, b, B))
        chernoff = ChernoffUpdater(None).update(hypothesis(a, A, b, B))
        best_fixed = min(
            measure(FusionUpdater(omega=w).update(hypothesis(a, A, b, B)).covar)
            for w in np.linspace(0.01, 0.99, 99))
        assert measure(ours.covar) <= measure(chernoff.covar) * (1 + 1e-9)
        assert measure(ours.covar) <= best_fixed * (1 + 1e-9)
        omega, _ = ci_weights([A, B], criterion=criterion)
        r = FusionUpdater(criterion=criterion).fuse_hypothesis(hypothesis(a, A, b, B))
        assert r.weights[0] == pytest.approx(omega[0], abs=1e-9)
    # a case where omega = 1/2 is far from optimal: strictly smaller
    A, B = np.diag([1.0, 1.0]), np.diag([10.0, 12.0])
    ours = FusionUpdater(criterion=criterion).update(hypothesis([0, 0], A, [1, 1], B))
    chernoff = ChernoffUpdater(None).update(hypothesis([0, 0], A, [1, 1], B))
    assert measure(ours.covar) < 0.6 * measure(chernoff.covar)


def test_properties_changed_after_construction_take_effect():
    h = hypothesis([1.0, 0.0], np.diag([1.0, 4.0]), [0.0, 1.0], np.diag([4.0, 1.0]))
    updater = FusionUpdater()
    updater.omega = 0.2
    assert updater.fuse_hypothesis(h).weights.tolist() == pytest.approx([0.2, 0.8])
    updater.omega, updater.method = None, "naive"
    assert updater.fuse_hypothesis(h).method == "naive"


def test_other_rules_and_options_through_the_updater():
    A, B = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    h = hypothesis([1.0, 0.0], A, [0.0, 1.0], B)
    for method, options in [("naive", None), ("pci", {"rho": 0.3}), ("ei", None)]:
        r = FusionUpdater(method=method, options=options).fuse_hypothesis(h)
        expected = fuse([(np.array([[1.0], [0.0]]), A), (np.array([[0.0], [1.0]]), B)],
                        method=method, **(options or {}))
        assert np.allclose(r.P, expected.P) and np.allclose(r.x, expected.x)
    naive = FusionUpdater(method="naive")
    V = naive.predict_measurement(h.prediction, h.measurement.measurement_model).covar
    assert np.allclose(V, A + B)


def test_updater_rejects_bad_settings():
    with pytest.raises(ValueError, match="omega must be in"):
        FusionUpdater(omega=1.0)
    with pytest.raises(ValueError, match="does not take it"):
        FusionUpdater(method="pci", omega=0.5)
    with pytest.raises(ValueError, match=r"nope"):
        FusionUpdater(method="nope")
    with pytest.raises(ValueError, match="criterion must be"):
        FusionUpdater(criterion="volume")
    with pytest.raises(ValueError, match="criterion"):
        FusionUpdater(criterion=-np.eye(2)).predict_measurement(
            GaussianStatePrediction(np.zeros((2, 1)), np.eye(2)),
            LinearGaussian(2, [0, 1], np.eye(2)))
    with pytest.raises(ValueError, match="own property"):
        FusionUpdater(options={"criterion": "det"})
    # a model of a one-dimensional state cannot describe a detection of a 2-state target
    with pytest.raises(ValueError, match=r"matrix\(\) of shape \(1, 1\).* 2 dimensions"):
        FusionUpdater().fuse_hypothesis(hypothesis([0.0], np.eye(1), [0.0, 0.0], np.eye(2)))
    with pytest.raises(ValueError, match=r"positive definite|symmetric"):
        FusionUpdater().fuse_hypothesis(
            hypothesis([0.0, 0.0], np.diag([1.0, -1.0]), [0.0, 0.0], np.eye(2)))


@settings(max_examples=25, deadline=None)
@given(ill_conditioned_sets(2, 3), st.sampled_from(["trace", "det"]),
       st.floats(0.0, 1.0), st.floats(0.05, 0.95))
def test_updater_is_the_front_door_on_ill_conditioned_input(Ps, criterion, fixed, omega):
    """The updater's numbers are cifilter.fuse's (the conditioning contract carries over):
    symmetric positive definite, and the gate bounds the innovation in the worst direction."""
    A, B = Ps
    a = np.sqrt(np.diag(A))
    b = -np.sqrt(np.diag(B))
    omega = omega if fixed > 0.5 else None
    updater = FusionUpdater(criterion=criterion, omega=omega)
    update = updater.update(hypothesis(a, A, b, B))
    options = {"criterion": criterion} if omega is None else {"omega": omega}
    expected = fuse([(a[:, None], A), (b[:, None], B)], method="ci", **options)
    assert np.array_equal(update.covar, expected.P)
    assert np.array_equal(np.asarray(update.state_vector), expected.x)
    assert np.array_equal(update.covar, update.covar.T)
    assert np.all(np.linalg.eigvalsh(update.covar) > 0)
    V = np.asarray(updater.predict_measurement(
        GaussianStatePrediction(b[:, None], B, timestamp=T0),
        LinearGaussian(3, [0, 1, 2], A)).covar)
    assert np.array_equal(V, V.T)
    for u in eigh(A, B)[1].T:  # the worst directions of the innovation
        worst = (np.sqrt(u @ A @ u) + np.sqrt(u @ B @ u)) ** 2
        # to rounding: the quadratic forms carry an error of order eps |u|^T |V| |u|, which
        # for a nearly singular B is far above 1e-8 of the (small) worst case itself
        rounding = 64 * np.finfo(float).eps * (np.abs(u) @ np.abs(V) @ np.abs(u))
        assert u @ V @ u >= worst * (1 - 1e-8) - rounding


def test_reducer_is_permutation_invariant():
    rng = np.random.default_rng(4)
    states = [GaussianState(rng.standard_normal((3, 1)), random_spd(rng, 3, 1e6) * s)
              for s in (1.0, 2.0, 5.0)]
    merged = OptimalCovarianceIntersection.merge_result(*states)
    swapped = OptimalCovarianceIntersection.merge_result(*states[::-1])
    assert np.allclose(merged.P, swapped.P, rtol=1e-9)
    assert np.allclose(merged.x, swapped.x, rtol=1e-9, atol=1e-12)
    assert np.allclose(merged.weights, swapped.weights[::-1], atol=1e-9)


def admissible_cross_covariance(rng, A, B):
    """A cross-covariance C with [[A, C], [C^T, B]] positive semidefinite."""
    La, Lb = np.linalg.cholesky(A), np.linalg.cholesky(B)
    K = rng.standard_normal(A.shape)
    K /= np.linalg.norm(K, 2) * rng.uniform(1.0, 1.5)
    return La @ K @ Lb.T


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_gate_covariance_bounds_the_innovation_for_every_correlation(criterion):
    """u^T V u >= (sqrt(u^T A u) + sqrt(u^T B u))^2 = max over admissible C of
    u^T cov(a - b) u, in random and in the generalised eigen-directions of (A, B)."""
    rng = np.random.default_rng(3)
    for _ in range(10):
        A, B = random_spd(rng, 3, 1e4), random_spd(rng, 3, 1e2) * rng.uniform(0.01, 100)
        prediction = GaussianStatePrediction(np.zeros((3, 1)), B, timestamp=T0)
        V = FusionUpdater(criterion=criterion).predict_measurement(
            prediction, LinearGaussian(3, [0, 1, 2], A)).covar
        _, vectors = eigh(A, B)
        directions = np.hstack([vectors, rng.standard_normal((3, 50))])
        for u in directions.T:
            worst = (np.sqrt(u @ A @ u) + np.sqrt(u @ B @ u)) ** 2
            assert u @ V @ u >= worst * (1 - 1e-9)
        for _ in range(20):
            C = admissible_cross_covariance(rng, A, B)
            difference = A + B - C - C.T
            assert np.linalg.eigvalsh(V - difference).min() >= -1e-9 * np.linalg.norm(V)


def test_gate_is_the_smallest_of_clark_campbells_family():
    A, B = np.diag([1.0, 4.0]), np.diag([9.0, 2.0])
    prediction = GaussianStatePrediction(np.zeros((2, 1)), B, timestamp=T0)
    model = LinearGaussian(2, [0, 1], A)
    V = FusionUpdater().predict_measurement(prediction, model).covar
    family = [np.trace(A / (1 - w) + B / w) for w in np.linspace(1e-3, 1 - 1e-3, 999)]
    assert np.trace(V) <= min(family) * (1 + 1e-12)
    assert np.trace(V) == pytest.approx((np.sqrt(5.0) + np.sqrt(11.0)) ** 2)


def test_chernoff_normaliser_is_a_over_omega_plus_b_over_one_minus_omega():
    """The normalising constant of N(x; a, A)^w N(x; b, B)^(1-w), as a function of a, is
    N(a; b, A/w + B/(1-w)); Stone Soup's documented V = A/(1-w) + B/w swaps the roles
    of w and 1-w (both agree at w = 1/2). Checked by quadrature in one dimension."""
    A, B, b, w = 2.0, 0.5, 0.0, 0.2

    def normaliser(a):
        def integrand(x):
            return (stats.norm.pdf(x, a, np.sqrt(A)) ** w
                    * stats.norm.pdf(x, b, np.sqrt(B)) ** (1 - w))
        return integrate.quad(integrand, -60, 60, limit=200)[0]

    ratio = normaliser(3.0) / normaliser(0.5)
    chernoff = stats.norm.pdf(3.0, b, np.sqrt(A / w + B / (1 - w))) / stats.norm.pdf(
        0.5, b, np.sqrt(A / w + B / (1 - w)))
    stonesoup = stats.norm.pdf(3.0, b, np.sqrt(A / (1 - w) + B / w)) / stats.norm.pdf(
        0.5, b, np.sqrt(A / (1 - w) + B / w))
    assert ratio == pytest.approx(chernoff, rel=1e-7)
    assert abs(ratio - stonesoup) > 0.1 * ratio


# ------------------------------------------------------- detections of part of the state
POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])  # of [x, vx, y, vy]
CV2D = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.3)] * 2)


def cv_prediction(rng, cond=1e3):
    """A Kalman prediction (KalmanPredictor, CV model) of a 4-state track, 1 s ahead."""
    prior = GaussianState(rng.standard_normal((4, 1)) * [[100.0], [5.0], [100.0], [5.0]],
                          random_spd(rng, 4, cond), timestamp=T0 - timedelta(seconds=1))
    return KalmanPredictor(CV2D).predict(prior, timestamp=T0)


def position_detection(z, R, gaussian=False):
    """A position-only detection of a CV 4-state target (LinearGaussian mapping [0, 2])."""
    model = LinearGaussian(4, [0, 2], R)
    if gaussian:
        return GaussianDetection(np.reshape(z, (2, 1)), R, timestamp=T0,
                                 measurement_model=model)
    return Detection(np.reshape(z, (2, 1)), timestamp=T0, measurement_model=model)


PARTIAL_SETTINGS = [{}, {"criterion": "det"}, {"omega": 0.3},
                    {"criterion": np.diag([1.0, 10.0, 1.0, 10.0])}, {"method": "naive"}]


@pytest.mark.parametrize("settings", PARTIAL_SETTINGS,
                         ids=["trace", "det", "omega", "weighted", "naive"])
def test_position_detection_is_the_front_door_with_H(settings):
    """A CV 4-state prediction and a position-only detection through FusionUpdater: bit for
    bit cifilter.fuse([(z, R), (b, B)], H=[H, None]) (the detection first, as for full-state
    detections), and to rounding the same fusion with the prediction first."""
    rng = np.random.default_rng(31)
    prediction = cv_prediction(rng)
    b, B = np.asarray(prediction.state_vector, float), np.asarray(prediction.covar, float)
    R = np.array([[4.0, 1.0], [1.0, 9.0]])
    z = POSITION @ b + rng.standard_normal((2, 1)) * 3.0
    options = {k: v for k, v in settings.items() if k != "method"}
    method = settings.get("method", "ci")
    expected = fuse([(z, R), (b, B)], method, H=[POSITION, None], **options)
    updater = FusionUpdater(**settings)
    for gaussian in (False, True):
        hypothesis = SingleHypothesis(prediction, position_detection(z, R, gaussian))
        update = updater.update(hypothesis)
        assert np.array_equal(np.asarray(update.covar), expected.P)
        assert np.array_equal(np.asarray(update.state_vector), expected.x)
        assert update.timestamp == T0 and update.state_vector.shape == (4, 1)
        result = updater.fuse_hypothesis(hypothesis)
        assert np.array_equal(result.weights, expected.weights)
    if "omega" in options:
        assert result.weights.tolist() == pytest.approx([0.3, 0.7])
        options["omega"] = 1 - options["omega"]
    swapped = fuse([(b, B), (z, R)], method, H=[None, POSITION], **options)
    scale = np.abs(expected.P).max()
    assert np.allclose(swapped.P, expected.P, rtol=1e-12, atol=1e-12 * scale)
    assert np.allclose(swapped.x, expected.x, rtol=1e-12, atol=1e-10)
    # the gains: n x m for the detection, n x n for the prediction, unbiased
    K_z, K_b = result.info["gains"]
    assert K_z.shape == (4, 2) and K_b.shape == (4, 4) and result.gains is None
    assert np.allclose(K_z @ POSITION + K_b, np.eye(4), atol=1e-12)


def test_position_detection_by_hand():
    """The det-optimal fusion of a position fix into an uncorrelated CV state, by hand
    (docs/methods/partial_state.rst): prediction variances 4 (position) and 1 (velocity),
    a fix of variance 1 in x and y; log det P = -2 log(w/4 + 1 - w) - 2 log w is smallest at
    w = 2/3 (the prediction's weight): P = diag(2, 1.5, 2, 1.5)."""
    prediction = GaussianStatePrediction([[0.0], [1.0], [0.0], [-1.0]],
                                         np.diag([4.0, 1.0, 4.0, 1.0]), timestamp=T0)
    detection = position_detection([3.0, -3.0], np.eye(2))
    update = FusionUpdater(criterion="det").update(SingleHypothesis(prediction, detection))
    assert np.allclose(update.covar, np.diag([2.0, 1.5, 2.0, 1.5]), rtol=1e-9)
    # x = P (w B^-1 b + (1 - w) H^T R^-1 z): position 2 (2/3 * 0/4 + 1/3 * 3) = 2
    assert np.allclose(np.asarray(update.state_vector).ravel(), [2.0, 1.0, -2.0, -1.0],
                       rtol=1e-9)


def test_permuted_full_mapping_is_fused_through_H():
    """A detection of all four components in another order (LinearGaussian mapping
    [2, 0, 3, 1]) is an estimate of H x with H a permutation, not of x: fused through H it
    equals the full-state fusion of the detection put back in the state's order."""
    rng = np.random.default_rng(32)
    prediction = cv_prediction(rng)
    mapping = [2, 0, 3, 1]
    Pm = np.eye(4)[mapping]
    A = random_spd(rng, 4, 1e2)
    a = rng.standard_normal((4, 1))
    detection = GaussianDetection(a, A, timestamp=T0,
                                  measurement_model=LinearGaussian(4, mapping, A))
    update = FusionUpdater().update(SingleHypothesis(prediction, detection))
    in_order = fuse([(Pm.T @ a, Pm.T @ A @ Pm), (prediction.state_vector, prediction.covar)])
    assert np.allclose(update.covar, in_order.P, rtol=1e-10)
    assert np.allclose(update.state_vector, in_order.x, rtol=1e-9, atol=1e-9)
    V = FusionUpdater(omega=0.5).predict_measurement(prediction, detection.measurement_model)
    assert np.array_equal(np.asarray(V.state_vector), Pm @ np.asarray(prediction.state_vector))


def test_partial_measurement_prediction_is_in_measurement_space():
    """predict_measurement for a detection of H x: mean H b and cross-covariance B H^T as
    Stone Soup's KalmanUpdater gives them, and the innovation covariance of Clark &
    Campbell's family with H B H^T for B: 1/(1-w) R + 1/w H B H^T at a fixed w, the
    family's smallest member with optimal weights, R + H B H^T for the naive rule."""
    rng = np.random.default_rng(33)
    prediction = cv_prediction(rng)
    B = np.asarray(prediction.covar, float)
    R = np.array([[4.0, 1.0], [1.0, 9.0]])
    model = LinearGaussian(4, [0, 2], R)
    BH = B[np.ix_([0, 2], [0, 2])]
    kalman = KalmanUpdater(model).predict_measurement(prediction, model)
    for updater in (FusionUpdater(), FusionUpdater(omega=0.3), FusionUpdater(method="naive"),
                    FusionUpdater(criterion="det")):
        ours = updater.predict_measurement(prediction, model)
        assert np.array_equal(np.asarray(ours.state_vector), POSITION @ prediction.state_vector)
        assert np.allclose(ours.state_vector, kalman.state_vector, rtol=1e-15)
        assert np.allclose(ours.cross_covar, kalman.cross_covar, rtol=1e-15)
        assert ours.covar.shape == (2, 2) and np.array_equal(ours.covar, ours.covar.T)
        without = updater.predict_measurement(prediction, model, measurement_noise=False)
        assert np.array_equal(np.asarray(without.covar), BH)
    def symmetric(M):
        return (M + M.T) / 2

    V = FusionUpdater(omega=0.3).predict_measurement(prediction, model).covar
    assert np.array_equal(np.asarray(V), symmetric(1 / 0.7 * R + 1 / 0.3 * BH))
    V = FusionUpdater(method="naive").predict_measurement(prediction, model).covar
    assert np.array_equal(np.asarray(V), symmetric(R + BH))
    V = FusionUpdater().predict_measurement(prediction, model).covar
    assert np.trace(V) == pytest.approx((np.sqrt(np.trace(R)) + np.sqrt(np.trace(BH))) ** 2,
                                        rel=1e-14)
    weighted = FusionUpdater(criterion=np.diag([1.0, 5.0, 1.0, 5.0]))
    assert np.array_equal(weighted.predict_measurement(prediction, model).covar, V)
    V = FusionUpdater(criterion="det").predict_measurement(prediction, model).covar
    family = [np.linalg.det(R / (1 - w) + BH / w) for w in np.linspace(1e-3, 1 - 1e-3, 999)]
    assert np.linalg.det(V) <= min(family) * (1 + 1e-9)
    # an H of dependent rows (x reported twice): H B H^T is singular, the gate is not
    twice = LinearGaussian(4, [0, 0], np.diag([1.0, 2.0]))
    for criterion in ("trace", "det"):
        V = FusionUpdater(criterion=criterion).predict_measurement(prediction, twice).covar
        assert np.all(np.linalg.eigvalsh(V) > 0)


def partial_worst_case(u, R, BH):
    """(sqrt(u^T R u) + sqrt(u^T H B H^T u))^2 at 50 digits from the inputs: the largest
    variance of u^T (z - H b) over every correlation of the two errors."""
    with mpmath.workdps(50):
        def form(M):
            return mpmath.fsum(mpmath.mpf(float(u[i])) * mpmath.mpf(float(M[i, j]))
                               * mpmath.mpf(float(u[j]))
                               for i in range(len(u)) for j in range(len(u)))
        return (mpmath.sqrt(form(R)) + mpmath.sqrt(form(BH))) ** 2


@settings(max_examples=25, deadline=None)
@given(st.floats(-12.0, 12.0), st.data(), st.sampled_from(["trace", "det"]),
       st.floats(0.0, 1.0), st.floats(0.05, 0.95))
def test_partial_updater_is_the_front_door_on_ill_conditioned_input(log_scale, data, criterion,
                                                                    fixed, omega):
    """Condition numbers to 1e12 and scales 1e-12..1e12: the update is cifilter.fuse with
    H (bit for bit), symmetric positive definite, and the gate bounds the innovation
    z - H b for every correlation in the exact worst direction (from the inputs, 50
    digits), to the rounding of V's entries."""
    scale = (10.0 ** log_scale,) * 2
    B = data.draw(ill_conditioned_spd(4, scales=scale), label="B")
    R = data.draw(ill_conditioned_spd(2, scales=scale), label="R")
    b = np.sqrt(np.diag(B))[:, None]
    z = -np.sqrt(np.diag(R))[:, None]
    omega = omega if fixed > 0.5 else None
    updater = FusionUpdater(criterion=criterion, omega=omega)
    prediction = GaussianStatePrediction(b, B, timestamp=T0)
    update = updater.update(SingleHypothesis(prediction, position_detection(z, R)))
    options = {"criterion": criterion} if omega is None else {"omega": omega}
    expected = fuse([(z, R), (b, B)], "ci", H=[POSITION, None], **options)
    assert np.array_equal(update.covar, expected.P)
    assert np.array_equal(np.asarray(update.state_vector), expected.x)
    assert np.array_equal(update.covar, update.covar.T)
    assert np.all(np.linalg.eigvalsh(update.covar) > 0)
    V = np.asarray(updater.predict_measurement(prediction, LinearGaussian(4, [0, 2], R)).covar)
    BH = B[np.ix_([0, 2], [0, 2])]
    assert np.array_equal(V, V.T)
    directions = np.hstack([eigh(R, BH)[1], np.eye(2), [[1.0, 1.0], [1.0, -1.0]]])
    for u in directions.T:
        rounding = 64 * np.finfo(float).eps * (np.abs(u) @ np.abs(V) @ np.abs(u))
        assert u @ V @ u >= float(partial_worst_case(u, R, BH)) * (1 - 1e-12) - rounding


def tight_direction(gains, Ps, weights):
    """A unit v along which CI's P is the exact worst case of its gains: with
    G_i = K_i P_i K_i^T and s_i = sqrt(v^T G_i v), v^T P v = sum_i s_i^2 / w_i equals
    (sum_i s_i)^2 exactly when s_i is proportional to w_i, that is where
    v^T (G_1 / w_1^2 - G_2 / w_2^2) v = 0 (between an eigenvector of positive and one of
    negative eigenvalue)."""
    G = [K @ P @ K.T for K, P in zip(gains, Ps)]
    D = G[0] / weights[0] ** 2 - G[1] / weights[1] ** 2
    values, vectors = np.linalg.eigh(D)
    assert values[0] < 0 < values[-1]
    angle = np.arctan(np.sqrt(values[-1] / -values[0]))
    return np.cos(angle) * vectors[:, -1] + np.sin(angle) * vectors[:, 0]


def worst_joint(gains, Ps, v):
    """The factor M of the joint covariance M M^T of (e_z, e_b) (2 + 4 square) with the
    given marginals that attains the worst case of the gains along v: perfectly
    correlated u_i^T L_i^-1 e_i, u_i = L_i^T K_i^T v / s_i (tests/worst_case.py)."""
    blocks = []
    for K, P in zip(gains, Ps):
        L = np.linalg.cholesky(P)
        u = L.T @ K.T @ v
        blocks.append((L, u / np.linalg.norm(u)))
    sizes = [L.shape[0] for L, _ in blocks]
    M = np.zeros((sum(sizes), 1 + sum(sizes)))  # one common, then independent draws
    row = 0
    for (L, u), m in zip(blocks, sizes):
        M[row:row + m, 0] = L @ u
        M[row:row + m, 1 + row:1 + row + m] = L @ (np.eye(m) - np.outer(u, u))
        row += m
    return M


def worst_case_problem(seed=34):
    """A CV 4-state prediction, a position-only detection's covariance, the CI update's
    gains and weights, a direction v where its P is exact, and the factor of the joint
    covariance that is worst for the gains along v."""
    rng = np.random.default_rng(seed)
    prediction = cv_prediction(rng)
    B = np.asarray(prediction.covar, float)
    R = np.array([[30.0, 8.0], [8.0, 20.0]])
    template = SingleHypothesis(prediction, position_detection(np.zeros(2), R))
    result = FusionUpdater().fuse_hypothesis(template)
    v = tight_direction(result.info["gains"], [R, B], result.weights)
    M = worst_joint(result.info["gains"], [R, B], v)
    return rng, prediction, R, result, v, M


def test_partial_detection_bound_in_the_exact_worst_case():
    """The partial update's P dominates the error covariance of its gains under the
    admissible joint that is worst along v, and equals it along v (the bound is tight
    there; at the optimum such a v exists, docs/stonesoup.rst)."""
    _, prediction, R, result, v, M = worst_case_problem()
    B = np.asarray(prediction.covar, float)
    assert 0.05 < result.weights[0] < 0.95  # an interior optimum: tight along some v
    joint = M @ M.T
    assert np.allclose(joint[:2, :2], R, rtol=1e-12) and np.allclose(joint[2:, 2:], B,
                                                                      rtol=1e-12)
    K = np.hstack(result.info["gains"])
    fused = K @ joint @ K.T
    assert np.linalg.eigvalsh(result.P - fused).min() >= -1e-9 * np.abs(result.P).max()
    assert v @ fused @ v == pytest.approx(v @ result.P @ v, rel=1e-9)
    # the naive update's P (independence) is below the same error along v
    naive = fuse([(np.zeros(2), R), (np.zeros(4), B)], "naive", H=[POSITION, None])
    K = np.hstack(naive.info["gains"])
    assert v @ naive.P @ v < 0.9 * (v @ K @ joint @ K.T @ v)


@pytest.mark.slow
def test_partial_detection_is_conservative_by_monte_carlo():
    """3000 runs of a CV 4-state prediction fused with a position-only detection whose
    error is correlated with the prediction's in the worst way for the update's gains
    along one direction v (perfectly correlated there). Every run goes through Stone
    Soup objects and FusionUpdater.update. CI's P bounds the error: its ANEES is under the
    chi-square band's upper end (4 degrees of freedom), and along v, where the bound is
    exact, the NEES is inside the band of a consistent estimate (1 degree). The naive
    update (independence) on the same draws is overconfident along v: the check has
    power."""
    rng, prediction, R, _, v, M = worst_case_problem()
    B = np.asarray(prediction.covar, float)
    runs = 3000
    updaters = {"ci": FusionUpdater(), "naive": FusionUpdater(method="naive")}
    nees = {name: np.empty(runs) for name in updaters}
    along = {name: np.empty(runs) for name in updaters}
    truth = np.asarray(prediction.state_vector, float)
    for k in range(runs):
        errors = M @ rng.standard_normal(M.shape[1])
        z = POSITION @ truth + errors[:2, None]
        b = truth + errors[2:, None]
        for name, updater in updaters.items():
            update = updater.update(SingleHypothesis(
                GaussianStatePrediction(b, B, timestamp=T0), position_detection(z, R)))
            e = np.asarray(update.state_vector, float).ravel() - truth.ravel()
            P = np.asarray(update.covar, float)
            nees[name][k] = e @ np.linalg.solve(P, e)
            along[name][k] = (v @ e) ** 2 / (v @ P @ v)
    band4 = stats.chi2.ppf([0.005, 0.995], 4 * runs) / runs
    band1 = stats.chi2.ppf([0.005, 0.995], runs) / runs
    print(f"runs {runs}: ANEES ci {nees['ci'].mean():.3f}, naive {nees['naive'].mean():.3f}"
          f" (band {band4.round(3)}); NEES along v ci {along['ci'].mean():.3f}, naive "
          f"{along['naive'].mean():.3f} (band {band1.round(3)})")
    assert nees["ci"].mean() <= band4[1], (nees["ci"].mean(), band4)
    assert band1[0] <= along["ci"].mean() <= band1[1], (along["ci"].mean(), band1)
    assert along["naive"].mean() > band1[1], (along["naive"].mean(), band1)


def test_partial_detections_in_a_stone_soup_tracker():
    """A Stone Soup MultiTargetTracker whose updater is FusionUpdater, fed position-only
    detections (LinearGaussian mapping [0, 2]) of one CV target: the hypothesiser gates
    with FusionUpdater's measurement-space innovation covariance (Mahalanobis), every
    detection is associated with the one track, and the track stays consistent."""
    rng = np.random.default_rng(35)
    dt, steps = timedelta(seconds=1), 30
    F, Q = CV2D.matrix(time_interval=dt), CV2D.covar(time_interval=dt)
    R = np.diag([25.0, 25.0])
    model = LinearGaussian(4, [0, 2], R)
    truth = [np.array([0.0, 10.0, 0.0, 5.0])]
    for _ in range(steps):
        truth.append(F @ truth[-1] + rng.multivariate_normal(np.zeros(4), Q))
    detections = [(T0 + k * dt, {Detection((POSITION @ truth[k] + rng.multivariate_normal(
        np.zeros(2), R))[:, None], timestamp=T0 + k * dt, measurement_model=model)})
        for k in range(1, steps + 1)]
    predictor = KalmanPredictor(CV2D)
    updater = FusionUpdater()
    tracker = MultiTargetTracker(
        initiator=SimpleMeasurementInitiator(
            GaussianState(np.zeros((4, 1)), np.diag([0.0, 100.0, 0.0, 100.0])),
            measurement_model=model),
        deleter=UpdateTimeStepsDeleter(3),
        detector=iter(detections),
        data_associator=GNNWith2DAssignment(
            DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=5)),
        updater=updater)
    all_tracks, nees = set(), []
    for time, tracks in tracker:
        all_tracks |= tracks
        k = round((time - T0) / dt)
        for track in tracks:
            if len(track) > 5:
                error = np.asarray(track.state.state_vector).ravel() - truth[k]
                nees.append(error @ np.linalg.solve(track.state.covar, error))
    assert len(all_tracks) == 1 and len(next(iter(all_tracks))) == steps
    assert np.mean(nees) <= stats.chi2.ppf(0.99, 4 * len(nees)) / len(nees)


def test_non_linear_detections_are_refused():
    """A bearing-range detection is not an estimate of H x: a clear TypeError from the
    update, the measurement prediction and fuse_hypothesis (no Jacobian linearisation:
    it would not keep the CI bound)."""
    radar = CartesianToBearingRange(4, [0, 2], np.diag([np.radians(1.0) ** 2, 25.0]))
    prediction = cv_prediction(np.random.default_rng(36))
    detection = Detection(np.array([[0.3], [500.0]]), timestamp=T0, measurement_model=radar)
    hypothesis = SingleHypothesis(prediction, detection)
    message = "measurement model must be linear .*got CartesianToBearingRange"
    with pytest.raises(TypeError, match=message):
        FusionUpdater().update(hypothesis)
    with pytest.raises(TypeError, match=message):
        FusionUpdater().fuse_hypothesis(hypothesis)
    with pytest.raises(TypeError, match=message):
        FusionUpdater().predict_measurement(prediction, radar)


def test_partial_detection_errors():
    prediction = cv_prediction(np.random.default_rng(37))
    R = np.eye(2)
    # a detection whose size is not the model's number of rows
    wrong = GaussianDetection(np.zeros((3, 1)), np.eye(3), timestamp=T0,
                              measurement_model=LinearGaussian(4, [0, 2], R))
    with pytest.raises(ValueError, match=r"detection \(3, 1\) must have one entry per row"):
        FusionUpdater().fuse_hypothesis(SingleHypothesis(prediction, wrong))
    # a model of another state dimension
    with pytest.raises(ValueError, match=r"matrix\(\) of shape \(2, 6\).* 4 dimensions"):
        FusionUpdater().predict_measurement(prediction, LinearGaussian(6, [0, 2], R))
    # the rules that do not accept H= say which do
    for method, options in (("ei", None),):
        with pytest.raises(ValueError, match="does not accept H=; the rules that accept H "
                                             "are 'ci', 'naive'"):
            FusionUpdater(method=method, options=options).update(
                SingleHypothesis(prediction, position_detection(np.zeros(2), R)))
    with pytest.raises(ValueError, match="'split-ci' fuses an estimate of part of the state "
                                         "only as the second"):
        FusionUpdater(method="split-ci").update(
            SingleHypothesis(prediction, position_detection(np.zeros(2), R)))
    # the optimal fusion takes the joint of the detection (first) and the prediction
    B = np.asarray(prediction.covar, float)
    joint = np.block([[R, np.zeros((2, 4))], [np.zeros((4, 2)), B]])
    z = np.array([[1.0], [2.0]])
    ours = FusionUpdater(method="optimal", options={"joint": joint}).fuse_hypothesis(
        SingleHypothesis(prediction, position_detection(z, R)))
    naive = fuse([(z, R), (prediction.state_vector, B)], "naive", H=[POSITION, None])
    assert np.allclose(ours.P, naive.P, rtol=1e-10)  # independent: optimal is naive
    # a detection covariance that is not positive definite: the front door's message
    bad = position_detection(np.zeros(2), np.array([[1.0, 2.0], [2.0, 1.0]]), gaussian=True)
    with pytest.raises(ValueError, match="not positive definite"):
        FusionUpdater().fuse_hypothesis(SingleHypothesis(prediction, bad))


def test_partial_update_does_not_modify_its_inputs():
    rng = np.random.default_rng(38)
    prediction = cv_prediction(rng)
    detection = position_detection(rng.standard_normal(2), np.array([[4.0, 1.0], [1.0, 9.0]]),
                                   gaussian=True)
    before = [np.array(a, copy=True) for a in (prediction.state_vector, prediction.covar,
                                               detection.state_vector, detection.covar)]
    FusionUpdater().update(SingleHypothesis(prediction, detection))
    after = (prediction.state_vector, prediction.covar, detection.state_vector, detection.covar)
    for old, new in zip(before, after):
        assert np.array_equal(old, np.asarray(new))


# ------------------------------------------------------------------------------- reducer
def test_reducer_equals_stonesoup_at_fixed_weights():
    rng = np.random.default_rng(11)
    states = [GaussianState(rng.standard_normal((3, 1)), random_spd(rng, 3, 1e2),
                            timestamp=T0) for _ in range(4)]
    for weights in (None, [1.0, 2.0, 3.0, 4.0]):
        fixed = np.ones(4) if weights is None else weights
        ours = OptimalCovarianceIntersection.merge_components(*states, weights=fixed)
        theirs = CovarianceIntersection.merge_components(*states, weights=weights)
        assert np.allclose(ours.covar, theirs.covar, rtol=1e-9)
        assert np.allclose(ours.state_vector, theirs.state_vector, rtol=1e-8, atol=1e-10)
        assert ours.timestamp == T0


def test_reducer_optimal_weights_beat_equal_weights_and_keep_type():
    rng = np.random.default_rng(12)
    states = [WeightedGaussianState(rng.standard_normal((3, 1)), random_spd(rng, 3, 1e2) * s,
                                    weight=0.25, timestamp=T0) for s in (1, 3, 10)]
    equal = CovarianceIntersection.merge_components(*states)
    for merger in (OptimalCovarianceIntersection, OptimalCovarianceIntersection()):
        ours = merger.merge_components(*states)
        assert isinstance(ours, WeightedGaussianState) and ours.weight == 0.25
        assert np.trace(ours.covar) < np.trace(equal.covar)
    det = OptimalCovarianceIntersection(criterion="det").merge_result(*states)
    expected = covariance_intersection([s.state_vector for s in states],
                                       [s.covar for s in states], criterion="det")
    assert np.allclose(det.P, expected.P) and np.allclose(det.weights, expected.weights)
    ci = OptimalCovarianceIntersection().merge_result(*states)
    pci = OptimalCovarianceIntersection(method="pci", options={"rho": 0.2}).merge_result(*states)
    assert pci.method == "pci" and np.trace(pci.P) < np.trace(ci.P)
    with pytest.raises(ValueError, match="one entry per component"):
        OptimalCovarianceIntersection.merge_components(*states, weights=[1.0, 1.0])


# --------------------------------------------------------------------------- conversions
def test_conversions_round_trip_without_warnings():
    state = GaussianState([[1.0], [2.0]], [[2.0, 0.3], [0.3, 1.0]], timestamp=T0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        x, P = to_estimate(state)
        back = to_gaussian_state(x, P, timestamp=T0)
        from_track = to_estimate(Track([state]))
    assert x.shape == (2,) and np.array_equal(P, state.covar)
    assert np.array_equal(back.state_vector, state.state_vector)
    assert np.array_equal(back.covar, state.covar) and back.timestamp == T0
    assert np.array_equal(from_track[0], x)
    x[0] = 99.0  # a copy: the state is not modified
    assert state.state_vector[0, 0] == 1.0
    r = fuse([(np.zeros((2, 1)), np.eye(2)), (np.ones((2, 1)), 2 * np.eye(2))])
    assert np.array_equal(to_gaussian_state(r).covar, r.P)
    with pytest.raises(ValueError, match="P is required"):
        to_gaussian_state(np.zeros(2))
    with pytest.raises(ValueError, match="to match P"):
        to_gaussian_state(np.zeros(3), np.eye(2))
    with pytest.raises(TypeError, match="must be a Stone Soup"):
        to_estimate(np.zeros(2))


BAD_COVARIANCES = [
    ([[1.0, np.nan], [np.nan, 1.0]], "non-finite"),
    ([[1.0, np.inf], [0.0, 1.0]], "non-finite"),
    ([[1.0, 2.0], [2.0, 1.0]], "not positive definite"),
    ([[-1.0, 0.0], [0.0, 1.0]], "not positive definite"),
    ([[1.0, 0.5], [0.4, 1.0]], "not symmetric"),
]


@pytest.mark.parametrize("covar, problem", BAD_COVARIANCES)
def test_to_estimate_validates_the_covariance_as_the_front_door(covar, problem):
    state = GaussianState([[1.0], [2.0]], covar, timestamp=T0)
    with pytest.raises(ValueError, match=rf"GaussianState's covar .*{problem}"):
        to_estimate(state)
    with pytest.raises(ValueError, match=rf"GaussianState's covar .*{problem}"):
        to_estimate(Track([state]))
    with pytest.raises(ValueError, match=problem):  # the front door says the same
        fuse([(np.zeros(2), np.asarray(covar, float)), (np.zeros(2), np.eye(2))])


@pytest.mark.parametrize("covar, problem", BAD_COVARIANCES)
def test_to_gaussian_state_validates_the_covariance_as_the_front_door(covar, problem):
    given = np.array(covar, dtype=float)
    before = given.copy()
    with pytest.raises(ValueError, match=rf"^P .*{problem}"):
        to_gaussian_state(np.zeros(2), given)
    np.testing.assert_array_equal(given, before)  # not modified


def test_converters_validate_means_and_mixtures():
    with pytest.raises(ValueError, match="x contains non-finite"):
        to_gaussian_state([np.nan, 0.0], np.eye(2))
    with pytest.raises(TypeError, match="P"):
        to_gaussian_state(np.zeros(2), [["a", "b"], ["c", "d"]])
    with pytest.raises(ValueError, match="GaussianState's mean contains non-finite"):
        to_estimate(GaussianState([[np.inf], [0.0]], np.eye(2)))
    components = [WeightedGaussianState([[0.0]], [[-1.0]], weight=1.0),
                  WeightedGaussianState([[0.0]], [[-2.0]], weight=1.0)]
    with pytest.raises(ValueError, match="GaussianMixture's covariance is not positive"):
        to_estimate(GaussianMixture(components))
    # ordinary input at condition number 1e12 passes unchanged (not symmetrised)
    P = random_spd(np.random.default_rng(3), 4, 1e12)
    x, Q = to_estimate(GaussianState(np.ones((4, 1)), P))
    assert np.array_equal(Q, P)
    assert np.array_equal(to_gaussian_state(x, P).covar, P)


def test_particle_and_mixture_states_are_moment_matched_with_a_warning():
    rng = np.random.default_rng(5)
    points = rng.standard_normal((2, 500)) * [[1.0], [3.0]]
    weights = rng.uniform(size=500)
    weights /= weights.sum()
    cloud = ParticleState(StateVectors(points), weight=weights, timestamp=T0)
    with pytest.warns(MomentMatchedWarning, match="ParticleState was moment-matched"):
        x, P = to_estimate(cloud)
    mean = points @ weights
    assert np.allclose(x, mean)
    assert np.allclose(P, ((points - mean[:, None]) * weights) @ (points - mean[:, None]).T)
    components = [WeightedGaussianState([[0.0]], [[1.0]], weight=1.0),
                  WeightedGaussianState([[4.0]], [[2.0]], weight=3.0)]
    with pytest.warns(MomentMatchedWarning, match="GaussianMixture of 2 components"):
        x, P = to_estimate(GaussianMixture(components))
    assert x.tolist() == [3.0]
    assert P.tolist() == [[0.25 * 1 + 0.75 * 2 + 0.25 * 9 + 0.75 * 1]]
    with pytest.warns(MomentMatchedWarning):
        fused = fuse_tracks([Track([cloud]), GaussianState(x.reshape(-1, 1)[:1].repeat(2, 0),
                                                            np.eye(2), timestamp=T0)])
    assert fused.timestamp == T0


# --------------------------------------------------------------------------- fuse_tracks
def test_fuse_tracks_predicts_to_a_common_time():
    model = ConstantVelocity(0.2)
    a = Track([GaussianState([[0.0], [1.0]], np.diag([1.0, 4.0]), timestamp=T0)])
    b = Track([GaussianState([[5.0], [0.5]], np.diag([4.0, 1.0]), timestamp=T0),
               GaussianState([[2.0], [1.0]], np.diag([3.0, 0.5]),
                             timestamp=T0 + timedelta(seconds=2))])
    t = T0 + timedelta(seconds=3)
    fused, result = fuse_tracks([a, b], transition_model=model, timestamp=t,
                                return_result=True, criterion="det")
    predicted = []
    for state, dt in ((a.state, 3.0), (b.state, 1.0)):
        F, Q = model.matrix(time_interval=timedelta(seconds=dt)), model.covar(
            time_interval=timedelta(seconds=dt))
        predicted.append((F @ np.asarray(state.state_vector), F @ state.covar @ F.T + Q))
    expected = covariance_intersection([p[0] for p in predicted], [p[1] for p in predicted],
                                       criterion="det")
    assert fused.timestamp == t
    assert np.allclose(fused.covar, expected.P) and np.allclose(fused.state_vector, expected.x)
    assert result.info["criterion"] == "det"
    assert result.info["at"] == 0.0 and result.info["retrodiction_alpha"] == (None, None)
    latest = fuse_tracks([a, b], transition_model=model)
    assert latest.timestamp == T0 + timedelta(seconds=2)


def model_motion(model):
    """The front door's motion(dt) from a Stone Soup transition model (dt in seconds)."""
    def motion(dt):
        interval = timedelta(seconds=dt)
        return model.matrix(time_interval=interval), model.covar(time_interval=interval)
    return motion


def cv_tracks(rng, offsets):
    """One 4-state track per offset (seconds after T0), each of two states, the latest at
    the offset, with covariances of condition number up to 1e4."""
    tracks = []
    for offset in offsets:
        latest = T0 + timedelta(seconds=offset)
        tracks.append(Track([
            GaussianState(rng.standard_normal((4, 1)), random_spd(rng, 4, 1e2),
                          timestamp=latest - timedelta(seconds=1)),
            GaussianState(rng.standard_normal((4, 1)) * [[10.0], [1.0], [10.0], [1.0]],
                          random_spd(rng, 4, 1e4), timestamp=latest)]))
    return tracks


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_fuse_tracks_of_other_times_is_the_front_door(criterion):
    """Tracks whose latest states are at 0, 2.5 and 4 s, fused at 3 s (two predicted, one
    retrodicted) and at the latest time: the same numbers, bit for bit, as cifilter.fuse
    with times=, at= and a motion built from the same transition model."""
    rng = np.random.default_rng(21)
    tracks = cv_tracks(rng, [0.0, 2.5, 4.0])
    estimates = [(np.asarray(t.state.state_vector, float), np.asarray(t.state.covar, float))
                 for t in tracks]
    for at, timestamp in ((3.0, T0 + timedelta(seconds=3)), (4.0, None)):
        fused, result = fuse_tracks(tracks, timestamp=timestamp, transition_model=CV2D,
                                    return_result=True, criterion=criterion)
        expected = fuse(estimates, "ci", times=[0.0, 2.5, 4.0], at=at,
                        motion=model_motion(CV2D), criterion=criterion)
        assert fused.timestamp == T0 + timedelta(seconds=at)
        assert np.array_equal(np.asarray(fused.covar), expected.P)
        assert np.array_equal(np.asarray(fused.state_vector), expected.x)
        assert np.array_equal(result.weights, expected.weights)
        alpha = result.info["retrodiction_alpha"]
        assert alpha == expected.info["retrodiction_alpha"]
        assert alpha[:2] == (None, None)
        if at == 3.0:  # the newer track was retrodicted
            assert 0.0 < alpha[2] < 1.0
        else:
            assert alpha[2] is None


def test_fuse_tracks_retrodicts_a_newer_track_with_the_bound():
    """A newer track is brought back by the bound F^-1 (P/alpha + Q/(1-alpha)) F^-T with the
    trace-minimising alpha (docs/methods/time.rst, T5-T6), here checked by hand: fused with
    an older track whose covariance is huge (so that CI puts all the weight on the newer
    one), the fused covariance is the retrodicted one."""
    model = ConstantVelocity(0.5)
    newer = GaussianState([[4.0], [2.0]], np.array([[2.0, 0.5], [0.5, 1.0]]),
                          timestamp=T0 + timedelta(seconds=2))
    vague = GaussianState([[0.0], [0.0]], 1e10 * np.eye(2), timestamp=T0)
    fused, result = fuse_tracks([vague, newer], timestamp=T0, transition_model=model,
                                return_result=True)
    F = np.array([[1.0, 2.0], [0.0, 1.0]])
    F_inv = np.array([[1.0, -2.0], [0.0, 1.0]])
    Q = 0.5 * np.array([[8.0 / 3.0, 2.0], [2.0, 2.0]])  # q [[dt^3/3, dt^2/2], [dt^2/2, dt]]
    assert np.allclose(model.matrix(time_interval=timedelta(seconds=2)), F)
    assert np.allclose(model.covar(time_interval=timedelta(seconds=2)), Q)
    A, B = F_inv @ newer.covar @ F_inv.T, F_inv @ Q @ F_inv.T
    alpha = np.sqrt(np.trace(A)) / (np.sqrt(np.trace(A)) + np.sqrt(np.trace(B)))
    bound = A / alpha + B / (1 - alpha)
    assert result.info["retrodiction_alpha"][1] == pytest.approx(alpha, rel=1e-12)
    assert result.weights.tolist() == pytest.approx([0.0, 1.0], abs=1e-6)
    assert np.allclose(fused.covar, bound, rtol=1e-6)
    assert np.allclose(np.asarray(fused.state_vector).ravel(), [0.0, 2.0], atol=1e-5)
    # the plain sum F^-1 (P + Q) F^-T is smaller: it is not a bound (time.rst, T2)
    assert np.linalg.eigvalsh(bound - (A + B)).min() > 0


def test_fuse_tracks_at_one_time_is_unchanged():
    """Tracks at one time: cifilter.fuse without times= (as before), so every rule fuses
    them, bit for bit as the front door, and the result has no time entries."""
    rng = np.random.default_rng(22)
    tracks = cv_tracks(rng, [1.0, 1.0, 1.0])
    estimates = [(np.asarray(t.state.state_vector, float), np.asarray(t.state.covar, float))
                 for t in tracks]
    for method, options in (("ci", {}), ("naive", {}), ("pci", {"rho": 0.3}),
                            ("ci", {"criterion": "det"})):
        fused, result = fuse_tracks(tracks, method, transition_model=CV2D,
                                    return_result=True, **options)
        expected = fuse(estimates, method, **options)
        assert np.array_equal(np.asarray(fused.covar), expected.P), method
        assert np.array_equal(np.asarray(fused.state_vector), expected.x), method
        assert "at" not in result.info and fused.timestamp == T0 + timedelta(seconds=1)
    untimed = [GaussianState(t.state.state_vector, t.state.covar) for t in tracks]
    assert fuse_tracks(untimed).timestamp is None


def test_fuse_tracks_errors():
    a = Track([GaussianState([[0.0]], [[1.0]], timestamp=T0)])
    b = Track([GaussianState([[1.0]], [[1.0]], timestamp=T0 + timedelta(seconds=1))])
    with pytest.raises(ValueError, match=r"tracks\[0\].*give transition_model to predict"):
        fuse_tracks([a, b])
    with pytest.raises(ValueError, match=r"tracks\[1\].*give transition_model to retrodict"):
        fuse_tracks([a, b], timestamp=T0)
    with pytest.raises(ValueError, match="at least 2"):
        fuse_tracks([a])
    with pytest.raises(ValueError, match="without states"):
        fuse_tracks([a, Track()])
    with pytest.raises(TypeError, match="sequence of tracks"):
        fuse_tracks(a.state)
    with pytest.raises(ValueError, match="without a timestamp"):
        fuse_tracks([a, GaussianState([[1.0]], [[1.0]])], transition_model=RandomWalk(0.1))


def test_fuse_tracks_refuses_what_the_time_alignment_cannot_do():
    rng = np.random.default_rng(23)
    tracks = cv_tracks(rng, [0.0, 1.0])
    # a non-linear transition model has no F
    with pytest.raises(TypeError, match=r"transition_model must be a linear .*got ConstantTurn"):
        fuse_tracks(tracks, transition_model=ConstantTurn([0.1, 0.1], np.radians(3.0)))
    # a measurement model is not a transition model
    with pytest.raises(TypeError, match="transition_model must be a linear"):
        fuse_tracks(tracks, transition_model=LinearGaussian(4, [0, 2], np.eye(2)))
    # the rules that need exact covariances refuse estimates brought from other times
    with pytest.raises(ValueError, match=r"'naive' does not accept times=.*'ci'"):
        fuse_tracks(tracks, "naive", transition_model=CV2D)
    # the time keywords come from the tracks
    with pytest.raises(TypeError, match="fuse_tracks sets times"):
        fuse_tracks(tracks, transition_model=CV2D, times=[0.0, 1.0])
    # retrodiction needs F^-1
    singular = LinearGaussianTimeInvariantTransitionModel(
        transition_matrix=np.array([[1.0, 1.0], [0.0, 0.0]]), covariance_matrix=np.eye(2))
    pair = [Track([GaussianState([[0.0], [1.0]], np.eye(2), timestamp=T0)]),
            Track([GaussianState([[1.0], [1.0]], np.eye(2), timestamp=T0 + timedelta(1))])]
    with pytest.raises(IllConditionedError, match="cannot be brought back in time"):
        fuse_tracks(pair, timestamp=T0, transition_model=singular)
    assert fuse_tracks(pair, transition_model=singular).timestamp == T0 + timedelta(1)


# ----------------------------------------------------- a two-radar track-to-track loop
def two_radar_fusion_run(updater, seed, steps=30):
    """One target, two bearing-range radars each tracked by an EKF, their tracks fed
    through Tracks2GaussianDetectionFeeder to a Stone Soup MultiTargetTracker whose updater
    is ``updater``. Returns (NEES of the fused track per step, traces, number of tracks,
    number of updates of the fused track)."""
    rng = np.random.default_rng(seed)
    dt = timedelta(seconds=1)
    transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(0.05)] * 2)
    F, Q = transition.matrix(time_interval=dt), transition.covar(time_interval=dt)
    radars = [CartesianToBearingRange(4, [0, 2], np.diag([np.radians(0.5) ** 2, 25.0]),
                                      translation_offset=np.array([[px], [0.0]]))
              for px in (0.0, 1500.0)]
    truth = [np.array([500.0, 5.0, 800.0, -2.0])]
    for _ in range(steps):
        truth.append(F @ truth[-1] + rng.multivariate_normal(np.zeros(4), Q))
    P0 = np.diag([400.0, 25.0, 400.0, 25.0])
    local = [Track([GaussianState((truth[0] + rng.multivariate_normal(np.zeros(4), P0))[:, None],
                                  P0, timestamp=T0)]) for _ in radars]
    predictor = KalmanPredictor(transition)

    def radar_tracks():  # the radar trackers, run in step with the fusion tracker
        for k in range(1, steps + 1):
            t = T0 + k * dt
            for radar, track in zip(radars, local):
                z = radar.function(GaussianState(truth[k][:, None], np.eye(4)), noise=False)
                z = z + rng.multivariate_normal(np.zeros(2), radar.covar())[:, None]
                detection = Detection(z, timestamp=t, measurement_model=radar)
                prediction = predictor.predict(track.state, timestamp=t)
                track.append(ExtendedKalmanUpdater(radar).update(
                    SingleHypothesis(prediction, detection)))
                yield t, {track}

    fusion = MultiTargetTracker(
        initiator=SimpleMeasurementInitiator(GaussianState(np.zeros((4, 1)), np.zeros((4, 4)))),
        deleter=UpdateTimeStepsDeleter(5),
        detector=Tracks2GaussianDetectionFeeder(radar_tracks()),
        data_associator=GNNWith2DAssignment(
            DistanceHypothesiser(predictor, updater, Mahalanobis(), missed_distance=5)),
        updater=updater)
    nees, traces, all_tracks = {}, {}, set()
    for time, tracks in fusion:
        all_tracks |= tracks
        k = round((time - T0) / dt)
        for track in tracks:  # overwritten by the second radar's track of the step
            if track.state.timestamp == time and len(track) > 1:
                error = np.asarray(track.state.state_vector).ravel() - truth[k]
                nees[k] = error @ np.linalg.solve(track.state.covar, error)
                traces[k] = np.trace(track.state.covar)
    updates = max(len(track) for track in all_tracks)
    return np.array(list(nees.values())), np.array(list(traces.values())), len(all_tracks), updates


def test_two_radar_fusion_loop_is_consistent_and_tighter_than_chernoff():
    runs, steps = 4, 30
    ours, theirs = [], []
    for seed in range(runs):
        nees, traces, count, updates = two_radar_fusion_run(FusionUpdater(), seed, steps)
        assert count == 1 and updates == 2 * steps  # every track update associated, no births
        ours.append((nees, traces))
        _, chernoff_traces, count, _ = two_radar_fusion_run(ChernoffUpdater(None), seed, steps)
        assert count == 1
        theirs.append(chernoff_traces)
    nees = np.concatenate([n for n, _ in ours])
    # conservative: the mean NEES is not above the chi-square bound of its mean (99%)
    upper = stats.chi2.ppf(0.99, 4 * nees.size) / nees.size
    assert nees.mean() <= upper, nees.mean()
    assert nees.mean() > 0.5  # and not vacuous (an absurdly inflated covariance fails)
    assert np.mean([t.mean() for _, t in ours]) < np.mean([t.mean() for t in theirs])
