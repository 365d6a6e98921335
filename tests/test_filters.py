"""Drop-in filterpy filters with fuse()."""

import copy
import pickle

import filterpy.kalman as fk
import numpy as np
import pytest

import cifilter
from cifilter import FusionMixin, KalmanFilter


def tracking_scenario(cls, seed=3, steps=30):
    """A constant-velocity tracker as a filterpy user writes it; returns the history."""
    dt = 1.0
    kf = cls(dim_x=4, dim_z=2)
    kf.F = np.array([[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1]], float)
    kf.H = np.array([[1, 0, 0, 0], [0, 0, 1, 0]], float)
    kf.Q = 0.1 * np.eye(4)
    kf.R = np.diag([4.0, 1.0])
    kf.P *= 50.0
    g = np.random.default_rng(seed)
    history = []
    for k in range(steps):
        kf.predict()
        kf.update(np.array([[k + g.normal()], [0.5 * k + g.normal()]]))
        history.append((kf.x.copy(), kf.P.copy(), kf.K.copy(), kf.log_likelihood))
    kf.batch_filter([np.array([[1.0], [2.0]])] * 3)
    return history, kf


def test_kalman_filter_is_bit_identical_when_fuse_is_never_called():
    theirs, kf_theirs = tracking_scenario(fk.KalmanFilter)
    ours, kf_ours = tracking_scenario(KalmanFilter)
    for (x1, P1, K1, l1), (x2, P2, K2, l2) in zip(theirs, ours):
        np.testing.assert_array_equal(x1, x2)
        np.testing.assert_array_equal(P1, P2)
        np.testing.assert_array_equal(K1, K2)
        assert l1 == l2
    assert isinstance(kf_ours, fk.KalmanFilter)
    assert repr(kf_ours) == repr(kf_theirs)


def test_extended_and_unscented_filters_are_bit_identical():
    def hx(x):
        return np.array([np.hypot(x[0], x[2])])

    def jacobian(x):
        r = np.hypot(x[0, 0], x[2, 0])
        return np.array([[x[0, 0] / r, 0, x[2, 0] / r, 0]])

    def run_ekf(cls):
        ekf = cls(dim_x=4, dim_z=1)
        ekf.x = np.array([[10.0], [1.0], [10.0], [0.0]])
        ekf.F = np.eye(4) + np.eye(4, k=1) * np.array([1, 0, 1, 0])
        for k in range(10):
            ekf.predict()
            ekf.update(np.array([[15.0 + k]]), jacobian, lambda x: hx(x[:, 0]).reshape(1, 1))
        return ekf.x, ekf.P

    for a, b in zip(run_ekf(fk.ExtendedKalmanFilter), run_ekf(cifilter.ExtendedKalmanFilter)):
        np.testing.assert_array_equal(a, b)

    def run_ukf(cls):
        points = fk.MerweScaledSigmaPoints(4, alpha=0.1, beta=2.0, kappa=-1.0)
        ukf = cls(dim_x=4, dim_z=1, dt=1.0, hx=hx,
                  fx=lambda x, dt: np.array([x[0] + dt * x[1], x[1], x[2] + dt * x[3], x[3]]),
                  points=points)
        ukf.x = np.array([10.0, 1.0, 10.0, 0.0])
        for k in range(10):
            ukf.predict()
            ukf.update(np.array([15.0 + k]))
        return ukf.x, ukf.P

    for a, b in zip(run_ukf(fk.UnscentedKalmanFilter), run_ukf(cifilter.UnscentedKalmanFilter)):
        np.testing.assert_array_equal(a, b)


def make_kf(P, x=None):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.P = np.array(P, dtype=float)
    kf.x = np.zeros((2, 1)) if x is None else np.array(x, dtype=float).reshape(2, 1)
    return kf


def test_fuse_with_another_filter_updates_state_like_update_does():
    a = make_kf(np.diag([1.0, 4.0]))
    b = make_kf(np.diag([4.0, 1.0]), x=[1.0, 1.0])
    b_before = copy.deepcopy(b.__dict__)
    result = a.fuse(b)
    assert a.x.shape == (2, 1)
    np.testing.assert_allclose(a.P, 1.6 * np.eye(2))
    np.testing.assert_allclose(a.x[:, 0], [0.2, 0.8])
    np.testing.assert_array_equal(a.x_post, a.x)
    np.testing.assert_array_equal(a.P_post, a.P)
    assert a.x_post is not a.x and a.P_post is not a.P
    assert a.last_fusion is result and result.method == "ci"
    for key, value in b_before.items():  # other is never modified
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, b.__dict__[key])
    assert b.last_fusion is None


def test_fuse_accepts_pairs_lists_and_options():
    a = make_kf(np.diag([1.0, 4.0]))
    pair = (np.array([1.0, 1.0]), np.diag([4.0, 1.0]))
    r = a.fuse(pair, method="ci", omega="fast")
    assert r.info["rule"] == "fast"
    a = make_kf(np.diag([1.0, 4.0]))
    r = a.fuse([make_kf(np.eye(2)), pair], method="naive")
    assert r.gains.shape == (3, 2, 2)
    a = make_kf(np.diag([1.0, 4.0]))
    r = a.fuse([pair, (np.zeros((2, 1)), np.eye(2))], method="ci", criterion="det")
    assert r.info["criterion"] == "det"


def test_unscented_filter_keeps_its_one_dimensional_state():
    points = fk.MerweScaledSigmaPoints(2, alpha=0.1, beta=2.0, kappa=1.0)
    ukf = cifilter.UnscentedKalmanFilter(2, 1, 1.0, hx=lambda x: x[:1], fx=lambda x, dt: x,
                                         points=points)
    ukf.fuse((np.ones((2, 1)), 2 * np.eye(2)))
    assert ukf.x.shape == (2,)


def snapshot(kf):
    state = {k: v for k, v in kf.__dict__.items() if k not in ("inv", "last_fusion")}
    return copy.deepcopy(state), kf.__dict__.get("last_fusion")


def assert_unchanged(kf, before):
    state, last_fusion = before
    after, after_fusion = snapshot(kf)
    assert after_fusion is last_fusion
    assert after.keys() == state.keys()
    for key in state:
        if isinstance(state[key], np.ndarray):
            np.testing.assert_array_equal(state[key], after[key])
        else:
            assert state[key] == after[key], key


@pytest.mark.parametrize("other, options, error", [
    ((np.zeros(3), np.eye(3)), {}, ValueError),  # wrong dimension
    ((np.zeros(2), -np.eye(2)), {}, ValueError),  # not positive definite
    ((np.zeros(2), np.array([[1.0, 2.0], [0.0, 1.0]])), {}, ValueError),  # not symmetric
    ((np.array([np.nan, 0.0]), np.eye(2)), {}, ValueError),  # non-finite
    ((np.zeros((5, 2)), np.eye(2)), {}, ValueError),  # batched: not one estimate
    ("filter", {}, TypeError),
    (42, {}, TypeError),
    ([], {}, TypeError),
    ((np.zeros(2), np.eye(2)), {"method": "unknown"}, ValueError),
    ((np.zeros(2), np.eye(2)), {"criterion": "volume"}, ValueError),
    ((np.zeros(2), np.eye(2)), {"weights": 1}, TypeError),
    ((np.zeros(2), np.eye(2)), {"omega": 2.0}, ValueError),
])
def test_failed_fusion_leaves_the_filter_exactly_as_it_was(other, options, error):
    kf = make_kf(np.diag([1.0, 4.0]), x=[3.0, 4.0])
    kf.fuse((np.zeros(2), np.eye(2)))  # so that last_fusion is set too
    before = snapshot(kf)
    with pytest.raises(error):
        kf.fuse(other, **options)
    assert_unchanged(kf, before)


def test_mixin_adds_fusion_to_a_users_own_filter():
    class CountingFilter(fk.KalmanFilter):  # a user's own filterpy subclass
        def predict(self, *args, **kwargs):
            self.predictions = getattr(self, "predictions", 0) + 1
            return super().predict(*args, **kwargs)

    class FusingCountingFilter(FusionMixin, CountingFilter):
        pass

    f = FusingCountingFilter(dim_x=2, dim_z=1)
    f.predict()
    f.P = np.diag([1.0, 4.0])
    f.fuse((np.ones(2), np.diag([4.0, 1.0])))
    assert f.x.shape == (2, 1) and f.predictions == 1
    assert np.trace(f.P) == pytest.approx(3.2)


def test_filters_pickle_and_copy_with_their_fusion_result():
    kf = make_kf(np.diag([1.0, 4.0]))
    kf.fuse((np.ones(2), np.diag([4.0, 1.0])))
    clone = pickle.loads(pickle.dumps(kf))
    np.testing.assert_array_equal(clone.P, kf.P)
    np.testing.assert_array_equal(clone.last_fusion.P, kf.last_fusion.P)
    deep = copy.deepcopy(kf)
    assert deep.last_fusion.method == "ci"


def bit_snapshot(kf):
    """Every attribute: the object itself and, for arrays, dtype, shape, flags and bytes."""
    state = {}
    for key, value in kf.__dict__.items():
        if isinstance(value, np.ndarray):
            state[key] = (value, value.dtype, value.shape, value.strides,
                          value.flags.writeable, value.tobytes())
        else:
            state[key] = (value,)
    return state


def assert_bit_identical(kf, before):
    after = bit_snapshot(kf)
    assert after.keys() == before.keys()
    for key, old in before.items():
        new = after[key]
        assert new[0] is old[0], key  # the same object, not a copy
        assert new[1:] == old[1:], key  # and its bytes unchanged


@pytest.mark.parametrize("other, options, error, message", [
    ((np.array([1 + 5j, 0.0]), np.eye(2)), {}, TypeError, r"^other's x must be real"),
    ((np.zeros(2), np.ones(2)), {}, ValueError,
     r"^other's P must be a square matrix \(\.\.\., n, n\), got shape \(2,\)"),
    ((np.zeros(2), np.eye(2, dtype=bool)), {}, TypeError, "^other's P must be a numeric array"),
    ((np.zeros(2), -np.eye(2)), {}, ValueError, r"^other's P is not positive definite"),
    ((np.zeros(2), np.ones((2, 2))), {}, ValueError, r"^other's P is too ill-conditioned"),
    ([(np.zeros(2), np.eye(2)), (np.zeros(2), np.eye(2) + np.eye(2, k=1))], {}, ValueError,
     r"^other\[1\]'s P is not symmetric"),
    ((np.zeros(3), np.eye(3)), {}, ValueError,
     r"other's P has shape \(3, 3\), but this filter's P has shape \(2, 2\)"),
    ((np.zeros(2), np.stack([np.eye(2)] * 3)), {}, ValueError,
     r"^other's P has shape \(3, 2, 2\), a batch"),
    ((np.zeros((5, 2)), np.eye(2)), {}, ValueError, r"^other's x has shape \(5, 2\)"),
    ((np.zeros(2), np.eye(2)), {"method": "optimal"}, TypeError,
     r"'optimal' needs the option\(s\) 'joint'"),
    ((np.zeros(2), np.eye(2)), {"method": "optimal", "joint": np.eye(4) + 0j}, TypeError,
     "joint must be real"),
    ((np.zeros(2), np.eye(2)), {"omega": [[0.5, 0.5], [0.5, 0.5]]}, ValueError,
     "omega has shape"),
    ((np.zeros(2), np.eye(2)), {"omega": np.nan}, ValueError, "omega contains non-finite"),
])
def test_failed_fusion_is_named_and_leaves_the_filter_bit_identical(other, options, error,
                                                                    message):
    kf = make_kf(np.diag([1.0, 4.0]), x=[3.0, 4.0])
    kf.fuse((np.zeros(2), np.eye(2)))  # so that last_fusion, x_post, P_post are set too
    before = bit_snapshot(kf)
    with pytest.raises(error, match=message):
        kf.fuse(other, **options)
    assert_bit_identical(kf, before)


@pytest.mark.parametrize("own_x, own_P, message", [
    (np.array([[1 + 1j], [0.0]]), np.eye(2), r"^this filter's x must be real"),
    (np.zeros((2, 1)), np.ones((2, 2)), r"^this filter's P is too ill-conditioned"),
    (np.zeros((2, 1)), np.array([[1.0, 2.0], [0.0, 1.0]]), r"^this filter's P is not symmetric"),
    (np.zeros((2, 1)), np.diag([np.nan, 1.0]), r"^this filter's P contains non-finite"),
])
def test_problems_of_the_filter_itself_are_named_this_filter(own_x, own_P, message):
    kf = make_kf(np.eye(2))
    kf.x, kf.P = own_x, own_P
    before = bit_snapshot(kf)
    with pytest.raises((TypeError, ValueError), match=message):
        kf.fuse((np.zeros(2), np.eye(2)))
    assert_bit_identical(kf, before)


@pytest.mark.parametrize("shape", [(1, 2), (2,), (2, 1)])
def test_a_filter_whose_x_holds_n_numbers_in_any_shape_fuses(shape):
    kf = make_kf(np.diag([1.0, 4.0]))
    kf.x = np.zeros(shape)
    other = KalmanFilter(dim_x=2, dim_z=1)
    other.x, other.P = np.ones((1, 2)), np.diag([4.0, 1.0])
    result = kf.fuse(other)
    assert kf.x.shape == shape
    np.testing.assert_allclose(kf.x.ravel(), [0.2, 0.8])
    np.testing.assert_allclose(kf.P, 1.6 * np.eye(2))
    assert result.method == "ci"
    np.testing.assert_array_equal(other.x, [[1.0, 1.0]])  # other is not modified


def test_fuse_does_not_modify_read_only_or_integer_inputs():
    kf = make_kf(np.diag([1.0, 4.0]))
    x, P = np.array([1, 1]), np.array([[4, 0], [0, 1]])
    for array in (x, P):
        array.flags.writeable = False
    kf.fuse((x, P))
    assert x.dtype.kind == "i" and P.dtype.kind == "i"
    np.testing.assert_array_equal(P, [[4, 0], [0, 1]])
    np.testing.assert_allclose(kf.x[:, 0], [0.2, 0.8])
