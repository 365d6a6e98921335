"""cifilter.stonesoup against the real Stone Soup: ChernoffUpdater and the
CovarianceIntersection reducer at fixed weights, optimal weights, conversions, track
fusion, and a two-radar track-to-track fusion loop built from Stone Soup components."""

import subprocess
import sys
import warnings
from datetime import datetime, timedelta

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
)
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
from stonesoup.updater.kalman import ExtendedKalmanUpdater
from strategies import ill_conditioned_sets

from cifilter import ci_weights, covariance_intersection, fuse
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
    with pytest.raises(ValueError, match="full state"):
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
    latest = fuse_tracks([a, b], method="naive", transition_model=model)
    assert latest.timestamp == T0 + timedelta(seconds=2)


def test_fuse_tracks_errors():
    a = Track([GaussianState([[0.0]], [[1.0]], timestamp=T0)])
    b = Track([GaussianState([[1.0]], [[1.0]], timestamp=T0 + timedelta(seconds=1))])
    with pytest.raises(ValueError, match="give transition_model"):
        fuse_tracks([a, b])
    with pytest.raises(ValueError, match="predicts forward only"):
        fuse_tracks([a, b], timestamp=T0, transition_model=ConstantVelocity(0.1))
    with pytest.raises(ValueError, match="at least 2"):
        fuse_tracks([a])
    with pytest.raises(ValueError, match="without states"):
        fuse_tracks([a, Track()])
    with pytest.raises(TypeError, match="sequence of tracks"):
        fuse_tracks(a.state)


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
