"""``kf.fuse`` with the front door's options (issue 22): ``H=``, ``residual=``/``add=``
(the UKF's own ``residual_x`` and ``state_add`` by default), ``times=``/``at=``/``motion=``
and ``lag=``. The filter layer is thin: each equals :func:`cifilter.fuse`; a fusion that
fails leaves the filter bit for bit as it was."""

import subprocess
import sys
from pathlib import Path

import filterpy.kalman as fk
import mpmath
import numpy as np
import pytest
from test_filters import assert_bit_identical, bit_snapshot

import cifilter
from cifilter import IllConditionedError, KalmanFilter, SplitCIKalmanFilter, fuse

ROOT = Path(__file__).resolve().parents[2]
F_CV = np.array([[1.0, 1.0], [0.0, 1.0]])
Q_CV = np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]]) * 0.1


def cv_filter(x=(1.0, 0.5), P=((2.0, 0.3), (0.3, 1.0))):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.Q = F_CV.copy(), Q_CV.copy()
    kf.H, kf.R = np.array([[1.0, 0.0]]), np.eye(1)
    kf.x = np.array(x, dtype=float).reshape(2, 1)
    kf.P = np.array(P, dtype=float)
    return kf


def own(kf):
    return (np.array(kf.x, dtype=float), np.array(kf.P, dtype=float))


# ------------------------------------------------------------------------------------- H
@pytest.mark.parametrize("options", [{}, {"criterion": "det"}, {"omega": "fast"},
                                     {"omega": [0.3, 0.7]}, {"method": "naive"}])
def test_fuse_with_H_equals_the_front_door(options):
    kf = cv_filter()
    other = (np.array([1.4]), np.array([[0.5]]))
    H = np.array([[1.0, 0.0]])
    direct = fuse([own(kf), other], H=[None, H], **options)
    result = kf.fuse(other, H=H, **options)
    np.testing.assert_array_equal(result.x, direct.x)
    np.testing.assert_array_equal(result.P, direct.P)
    np.testing.assert_array_equal(kf.P, direct.P)
    np.testing.assert_array_equal(kf.x, direct.x)
    assert kf.x.shape == (2, 1)


def test_fuse_a_list_with_one_H_per_other():
    kf = cv_filter()
    others = [(np.array([1.4]), np.array([[0.5]])), (np.array([0.9, 0.4]), np.eye(2))]
    H = [np.array([[1.0, 0.0]]), None]
    direct = fuse([own(kf)] + others, H=[None] + H)
    result = kf.fuse(others, H=H)
    np.testing.assert_array_equal(result.P, direct.P)
    assert [K.shape for K in result.info["gains"]] == [(2, 2), (2, 1), (2, 2)]


def test_split_filter_passes_H_to_other_rules():
    kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P = np.array([[1.0], [0.5]]), np.diag([2.0, 1.0])
    other, H = (np.array([1.4]), np.array([[0.5]])), np.array([[1.0, 0.0]])
    direct = fuse([own(kf), other], H=[None, H])
    result = kf.fuse(other, method="ci", H=H)
    np.testing.assert_array_equal(result.P, direct.P)
    np.testing.assert_array_equal(kf.P_dep, direct.P)


# ----------------------------------------------------------------------------- residuals
def wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def heading_residual(a, b):
    d = np.subtract(a, b)
    d[0] = wrap(d[0])
    return d


def unscented(**kwargs):
    points = fk.MerweScaledSigmaPoints(2, alpha=0.1, beta=2.0, kappa=1.0)
    return cifilter.UnscentedKalmanFilter(2, 1, 1.0, hx=lambda x: x[:1],
                                          fx=lambda x, dt: x, points=points, **kwargs)


def test_ukf_with_a_wrapping_residual_fuses_179_and_minus_179_to_180():
    ukf = unscented(residual_x=heading_residual)
    ukf.x, ukf.P = np.array([np.radians(179.0), 0.0]), np.diag([0.01, 1.0])
    result = ukf.fuse((np.array([np.radians(-179.0), 0.0]), np.diag([0.01, 1.0])))
    assert np.degrees(ukf.x[0]) == pytest.approx(180.0, abs=1e-9)
    assert ukf.x.shape == (2,)
    # with state_add (filterpy 2.0) normalising, the same heading as -180
    if "state_add" in vars(ukf):
        ukf = unscented(residual_x=heading_residual,
                        state_add=lambda x, dx: np.array([wrap(x[0] + dx[0]), x[1] + dx[1]]))
        ukf.x, ukf.P = np.array([np.radians(179.0), 0.0]), np.diag([0.01, 1.0])
        ukf.fuse((np.array([np.radians(-179.0), 0.0]), np.diag([0.01, 1.0])))
        assert abs(np.degrees(ukf.x[0])) == pytest.approx(180.0, abs=1e-9)
    assert result.weights[0] == pytest.approx(0.5)


def test_ukf_with_plain_residuals_is_bitwise_the_plain_fusion():
    ukf = unscented()
    ukf.x, ukf.P = np.array([0.3, 0.1]), np.diag([1.0, 4.0])
    other = (np.array([0.5, -0.2]), np.diag([4.0, 1.0]))
    direct = fuse([(ukf.x.copy(), ukf.P.copy()), other])
    ukf.fuse(other)
    np.testing.assert_array_equal(ukf.x, direct.x)
    np.testing.assert_array_equal(ukf.P, direct.P)


def test_kalman_filter_with_residual_equals_the_front_door():
    kf = cv_filter(x=(np.radians(179.0), 0.0))
    other = (np.array([np.radians(-178.0), 0.1]), np.diag([1.0, 2.0]))
    direct = fuse([own(kf), other], residual=heading_residual)
    kf.fuse(other, residual=heading_residual)
    np.testing.assert_array_equal(kf.x, direct.x)
    assert kf.x[0, 0] > np.radians(179.0)


# ---------------------------------------------------------------------------------- time
@pytest.mark.parametrize("k", [1, 3])
@pytest.mark.parametrize("method, options", [("ci", {}), ("ci", {"criterion": "det"})])
def test_positive_lag_equals_explicit_prediction_then_the_rule(k, method, options):
    kf = cv_filter()
    other = (np.array([0.2, 0.4]), np.array([[1.0, 0.2], [0.2, 0.6]]))
    predictor = KalmanFilter(dim_x=2, dim_z=1)
    predictor.F, predictor.Q = F_CV.copy(), Q_CV.copy()
    predictor.x, predictor.P = other[0].reshape(2, 1).copy(), other[1].copy()
    for _ in range(k):
        predictor.predict()
    explicit = fuse([own(kf), (predictor.x, predictor.P)], method, **options)
    result = kf.fuse(other, method, lag=k, **options)
    np.testing.assert_allclose(result.x, explicit.x, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(result.P, explicit.P, rtol=1e-13)
    assert result.info["at"] == 0.0 and result.info["retrodiction_alpha"] == (None, None)


def test_negative_lag_is_the_front_door_with_the_filters_steps():
    kf = cv_filter()
    other = (np.array([2.1, 0.4]), np.array([[1.0, 0.2], [0.2, 0.6]]))

    def motion(dt):
        F, Q = np.eye(2), np.zeros((2, 2))
        for _ in range(int(dt)):
            F, Q = F_CV @ F, F_CV @ Q @ F_CV.T + Q_CV
        return F, Q

    direct = fuse([own(kf), other], times=[0.0, 2.0], at=0.0, motion=motion)
    result = kf.fuse(other, lag=-2)
    np.testing.assert_allclose(result.P, direct.P, rtol=1e-14)
    np.testing.assert_allclose(result.x, direct.x, rtol=1e-14)
    assert 0.0 < float(result.info["retrodiction_alpha"][1]) < 1.0
    # times= on a filter fuses at this filter's own time by default
    kf = cv_filter()
    again = kf.fuse(other, times=[5.0, 7.0], motion=motion)
    assert again.info["at"] == 5.0
    np.testing.assert_allclose(again.P, direct.P, rtol=1e-14)


def _explicit_lag(kf, other, k, **options):
    """``kf.fuse(other, lag=k)`` written out with the filter's F and Q at this moment,
    without the step cache: motion= with a plain function (k > 0: prediction, k < 0:
    retrodiction; both the front door's own, uncached path)."""
    F, Q = np.array(kf.F), np.array(kf.Q)

    def motion(dt):
        F_k, Q_k = np.eye(len(F)), np.zeros_like(Q)
        for _ in range(int(dt)):
            F_k, Q_k = F @ F_k, F @ Q_k @ F.T + Q
        return F_k, Q_k

    return fuse([own(kf), other], times=[0.0, -float(k)], at=0.0, motion=motion, **options)


@pytest.mark.parametrize("k", [2, -2])
@pytest.mark.parametrize("change", ["F", "Q"])
def test_lag_follows_F_and_Q_changed_in_place(k, change):
    """The k-step (F^k, Q_k) (and F^-k) are cached per (F, Q, k): a filter whose F or Q is
    changed in place (same array objects) must not meet the entry of the old model."""
    other = (np.array([0.2, 0.4]), np.array([[1.0, 0.2], [0.2, 0.6]]))
    kf = cv_filter()
    start = kf.x.copy(), kf.P.copy()
    first = kf.fuse(other, lag=k)  # fills the cache for the old model
    kf.x, kf.P = start  # the same filter, its F or Q changed in place below
    matrix = kf.F if change == "F" else kf.Q
    if change == "F":
        matrix[0, 1] = 3.0  # in place: the same array object, other numbers
    else:
        matrix *= 7.0
    expected = _explicit_lag(kf, other, k)
    result = kf.fuse(other, lag=k)
    np.testing.assert_allclose(result.P, expected.P, rtol=1e-12)
    np.testing.assert_allclose(result.x, expected.x, rtol=1e-12, atol=1e-14)
    assert not np.allclose(result.P, first.P)  # the change matters for this case


def test_lag_cache_is_not_shared_across_models():
    """Two filters with different models, called in turn (each call a cache hit after the
    first round), each fuse with their own model's k steps."""
    other = (np.array([0.2, 0.4]), np.array([[1.0, 0.2], [0.2, 0.6]]))
    slow, fast = cv_filter(), cv_filter()
    fast.F = np.array([[1.0, 2.5], [0.0, 1.0]])
    fast.Q = 3.0 * Q_CV
    for _ in range(3):
        for k in (1, 3, -1, -3):
            for kf in (slow, fast):
                reference = cv_filter()
                reference.F, reference.Q = kf.F.copy(), kf.Q.copy()
                expected = _explicit_lag(reference, other, k)
                result = reference.fuse(other, lag=k)
                np.testing.assert_allclose(result.P, expected.P, rtol=1e-12)
                np.testing.assert_allclose(result.x, expected.x, rtol=1e-12, atol=1e-14)


def test_lag_leaves_F_and_Q_alone_and_repeats_bitwise():
    """The cache neither aliases nor changes the filter's matrices, and a repeated call
    (a cache hit) gives bit for bit the first call's result."""
    other = (np.array([0.2, 0.4]), np.array([[1.0, 0.2], [0.2, 0.6]]))
    for k in (1, 2, -2):
        kf = cv_filter()
        kf.F[0, 1] = 1.0 + 0.1234 * k  # a model of this test's own: the first call misses
        start, F, Q = (kf.x.copy(), kf.P.copy()), kf.F.copy(), kf.Q.copy()
        first = kf.fuse(other, lag=k)
        kf.x, kf.P = start
        second = kf.fuse(other, lag=k)
        for a, b in ((first.x, second.x), (first.P, second.P), (first.omega, second.omega)):
            assert a.tobytes() == b.tobytes()
        np.testing.assert_array_equal(kf.F, F)
        np.testing.assert_array_equal(kf.Q, Q)
        kf.F[0, 0] = 1.0  # still the filter's own writable array
        assert kf.F.flags.writeable and kf.Q.flags.writeable


def test_negative_lag_is_conservative_in_the_exact_worst_case():
    """With the weight all on the retrodicted estimate the fused P is its bound: in every
    direction v it dominates (sqrt(u^T P u) + sqrt(u^T Q_k u))^2, u = F^-kT v, the largest
    error variance of any correlation of its error with the process noise (50 digits)."""
    kf = cv_filter()
    P = np.array([[1.0, 0.2], [0.2, 0.6]])
    result = kf.fuse((np.zeros(2), P), lag=-3, omega=[0.0, 1.0])
    F3 = F_CV @ F_CV @ F_CV
    Q3 = Q_CV + F_CV @ Q_CV @ F_CV.T + F_CV @ F_CV @ Q_CV @ F_CV.T @ F_CV.T
    with mpmath.workdps(50):
        F_inv = mpmath.inverse(mpmath.matrix(F3.tolist()))
        Pm, Qm = mpmath.matrix(P.tolist()), mpmath.matrix(Q3.tolist())
        ratios = []
        for angle in np.linspace(0.0, np.pi, 181):
            v = mpmath.matrix([mpmath.cos(angle), mpmath.sin(angle)])
            u = F_inv.T * v
            worst = (mpmath.sqrt((u.T * Pm * u)[0]) + mpmath.sqrt((u.T * Qm * u)[0])) ** 2
            bound = (v.T * mpmath.matrix(result.P.tolist()) * v)[0]
            ratios.append(float(worst / bound))
    assert max(ratios) <= 1.0 + 1e-13
    assert max(ratios) > 0.999  # tight in some direction (alpha is optimal there)


def test_lag_zero_is_no_shift():
    kf, twin = cv_filter(), cv_filter()
    other = (np.array([0.2, 0.4]), np.eye(2))
    a, b = kf.fuse(other, lag=0), twin.fuse(other)
    np.testing.assert_array_equal(a.P, b.P)
    assert "at" not in a.info


def test_lag_needs_the_filters_F_and_Q():
    ukf = unscented()
    with pytest.raises(ValueError, match=r"lag= predicts or retrodicts with the filter's F "
                                         r"and Q, but UnscentedKalmanFilter has no matrix F;"):
        ukf.fuse((np.zeros(2), np.eye(2)), lag=1)


# ------------------------------------------------------------------ errors leave it as it was
@pytest.mark.parametrize("other, options, error, message", [
    ((np.zeros(1), np.eye(1)), {"H": np.array([[1.0, 0.0, 0.0]])}, ValueError,
     r"H\[1\] has shape \(1, 3\).*needs 2 columns"),
    ((np.zeros(1), np.eye(1)), {"H": np.eye(2)}, ValueError, r"needs 1 rows"),
    ((np.zeros(1), np.eye(1)), {"H": np.array([[1.0, 0.0]]), "method": "ei"}, ValueError,
     "method 'ei' does not accept H="),
    ((np.zeros(2), np.eye(2)), {"lag": 1.5}, TypeError, "lag must be an integer"),
    ((np.zeros(2), np.eye(2)), {"lag": True}, TypeError, "lag must be an integer"),
    ((np.zeros(2), np.eye(2)), {"lag": [1, 2]}, ValueError, "lag has 2 entries"),
    ((np.zeros(2), np.eye(2)), {"lag": 1, "times": [0.0, 1.0]}, ValueError,
     "give lag= .* or times="),
    ((np.zeros(2), np.eye(2)), {"lag": 2, "method": "naive"}, ValueError,
     "method 'naive' does not accept times="),
    ((np.zeros(2), np.eye(2)), {"residual": lambda a, b: a[:1]}, ValueError,
     "residual must return 2 numbers"),
    ((np.zeros(2), np.eye(2)), {"times": [0.0, 1.0]}, ValueError, "give motion="),
])
def test_failed_fusion_with_options_leaves_the_filter_bit_identical(other, options, error,
                                                                    message):
    kf = cv_filter()
    kf.fuse((np.zeros(2), np.eye(2)))  # so that last_fusion, x_post, P_post are set too
    before = bit_snapshot(kf)
    with pytest.raises(error, match=message):
        kf.fuse(other, **options)
    assert_bit_identical(kf, before)


def test_singular_F_for_a_negative_lag_is_refused_and_the_filter_is_unchanged():
    kf = cv_filter()
    kf.F = np.array([[1.0, 1.0], [0.0, 0.0]])
    before = bit_snapshot(kf)
    with pytest.raises(IllConditionedError, match="retrodiction needs F"):
        kf.fuse((np.zeros(2), np.eye(2)), lag=-1)
    assert_bit_identical(kf, before)
    kf.fuse((np.zeros(2), np.eye(2)), lag=1)  # prediction needs no inverse


def test_the_example_script_runs():
    completed = subprocess.run([sys.executable, str(ROOT / "examples" /
                                                    "10_partial_and_late_tracks.py")],
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stdout + completed.stderr
    assert "fuse to 180.0 degrees" in completed.stdout


# ------------------------------------------------------------------------ vector styles
@pytest.mark.parametrize("own_shape", [(2, 1), (2,)])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_other_in_either_vector_style_fuses_bit_for_bit_alike(own_shape, criterion):
    """The filter layer gives an other estimate's (n,) or (n, 1) x the filter's own style
    (a view) before the front door; the fused estimate is the same to the bit whichever
    style the other came in, keeps the filter's style, and the other is not touched."""
    x_other = np.array([0.2, 0.4])
    P_other = np.array([[1.0, 0.2], [0.2, 0.6]])
    results = []
    for other_shape in ((2,), (2, 1)):
        kf = cv_filter()
        kf.x = kf.x.reshape(own_shape)
        other = (x_other.reshape(other_shape).copy(), P_other.copy())
        result = kf.fuse(other, criterion=criterion)
        assert result.x.shape == own_shape and kf.x.shape == own_shape
        assert other[0].shape == other_shape
        np.testing.assert_array_equal(other[0].ravel(), x_other)
        results.append(result)
    first, second = results
    for a, b in ((first.x, second.x), (first.P, second.P), (first.omega, second.omega)):
        assert a.tobytes() == b.tobytes()
    assert first.info == second.info
