"""Drop-in filterpy filters with fuse()."""

import copy
import inspect
import pickle
import re

import filterpy
import filterpy.kalman as fk
import numpy as np
import pytest
from filterpy.common import Saver
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from strategies import ill_conditioned_spd

import cifilter
from cifilter import FusionMixin, KalmanFilter

# filterpy 2.0 renamed and reshaped things cifilter's filters inherit (KalmanFilter.M is
# (dim_x, dim_z), UnscentedKalmanFilter takes state_add=, Saver.to_array takes flatten=);
# the drop-in guarantee is checked against whichever version is installed. .ci/run runs
# this file under filterpy 2.x (the main run) and again under filterpy 1.4.5.
FILTERPY = tuple(int(part) for part in filterpy.__version__.split(".")[:2])


def outcome(function):
    """What a call gives: ("value", result) or ("raises", exception type)."""
    try:
        return ("value", function())
    except Exception as exc:  # any exception: it must be the same on both sides
        return ("raises", type(exc))


def assert_same_outcome(a, b):
    kind_a, value_a = a
    kind_b, value_b = b
    assert kind_a == kind_b, (a, b)
    if kind_a == "raises":
        assert value_a is value_b
    elif isinstance(value_a, np.ndarray):
        assert value_a.dtype == value_b.dtype and value_a.shape == value_b.shape
        assert value_a.tobytes() == value_b.tobytes()
    else:
        assert value_a == value_b or (value_a != value_a and value_b != value_b)  # or NaN


def assert_same_filter(theirs, ours, properties=()):
    """Every array and number attribute bit for bit; properties (and repr) give the same
    value or raise the same exception (filterpy 1.4.5's ``mahalanobis``, used by its
    ``repr``, raises TypeError under numpy >= 2.4 for both classes alike)."""
    assert theirs.__dict__.keys() == ours.__dict__.keys()
    for key, a in theirs.__dict__.items():
        b = ours.__dict__[key]
        if isinstance(a, np.ndarray):
            assert_same_outcome(("value", a), ("value", b))
        elif isinstance(a, (int, float, np.number)) or a is None:
            assert_same_outcome(("value", a), ("value", b))
    for name in properties:
        assert_same_outcome(outcome(lambda name=name: getattr(theirs, name)),
                            outcome(lambda name=name: getattr(ours, name)))
    kind_a, text_a = outcome(lambda: repr(theirs))
    kind_b, text_b = outcome(lambda: repr(ours))
    assert kind_a == kind_b
    if kind_a == "raises":
        assert text_a is text_b
    else:  # the reprs differ only in the class's module and the object's address
        assert text_a.splitlines()[1:] == text_b.splitlines()[1:]


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
    assert len(theirs) == len(ours) == 30
    for (x1, P1, K1, l1), (x2, P2, K2, l2) in zip(theirs, ours):
        for a, b in ((x1, x2), (P1, P2), (K1, K2)):
            assert a.shape == b.shape and a.tobytes() == b.tobytes()
        assert l1 == l2
    assert isinstance(kf_ours, fk.KalmanFilter)
    assert_same_filter(kf_theirs, kf_ours,
                       properties=("log_likelihood", "likelihood", "mahalanobis"))


def test_version_dependent_shapes_and_signatures_are_filterpys():
    kf_theirs, kf_ours = fk.KalmanFilter(dim_x=4, dim_z=2), KalmanFilter(dim_x=4, dim_z=2)
    # M is (dim_z, dim_z) in filterpy 1.4.5 and (dim_x, dim_z) from 2.0 on: ours follows.
    assert kf_ours.M.shape == kf_theirs.M.shape == ((4, 2) if FILTERPY >= (2, 0) else (2, 2))
    accepts_state_add = "state_add" in inspect.signature(fk.UnscentedKalmanFilter).parameters
    assert accepts_state_add == (FILTERPY >= (2, 0))
    assert ("state_add" in inspect.signature(cifilter.UnscentedKalmanFilter).parameters
            ) == accepts_state_add


def test_correlated_update_is_bit_identical():
    """update_correlated with an M of shape (dim_x, dim_z), which both versions use."""
    def run(cls):
        kf = cls(dim_x=4, dim_z=2)
        kf.F = np.eye(4) + np.eye(4, k=1)
        kf.H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
        kf.Q, kf.R, kf.P = 0.1 * np.eye(4), np.diag([4.0, 1.0]), 50.0 * np.eye(4)
        kf.M = 0.05 * np.ones((4, 2))
        g = np.random.default_rng(5)
        for _ in range(10):
            kf.predict()
            kf.update_correlated(g.normal(size=(2, 1)))
        return kf

    assert_same_filter(run(fk.KalmanFilter), run(KalmanFilter),
                       properties=("log_likelihood", "likelihood"))


def test_saver_records_a_fusing_filter_in_both_versions():
    def run(cls, fusing):
        kf = cls(dim_x=2, dim_z=1)
        kf.F, kf.H = np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[1.0, 0.0]])
        saver = Saver(kf)
        for k in range(3):
            kf.predict()
            kf.update(np.array([[float(k)]]))
            if fusing:
                kf.fuse((np.zeros(2), 4.0 * np.eye(2)))
            saver.save()
        if FILTERPY >= (2, 0):
            saver.to_array(flatten=True)  # filterpy 2.0's to_array flattens (n, 1) columns
        else:
            saver.to_array()
        return kf, saver

    theirs = outcome(lambda: run(fk.KalmanFilter, False))
    ours = outcome(lambda: run(KalmanFilter, False))
    assert theirs[0] == ours[0]
    if theirs[0] == "raises":
        # filterpy 1.4.5's Saver evaluates every property, and its mahalanobis calls float()
        # on a (1, 1) array, which numpy >= 2.4 refuses: filterpy's own class fails alike.
        assert theirs[1] is ours[1] is TypeError and FILTERPY < (2, 0)
        pytest.skip("filterpy 1.4.5's Saver fails under this numpy for its own filters too")
    for key in ("x", "P", "K"):
        assert getattr(theirs[1][1], key).tobytes() == getattr(ours[1][1], key).tobytes()
    kf, saver = run(KalmanFilter, True)
    assert saver.x.shape == ((3, 2) if FILTERPY >= (2, 0) else (3, 2, 1))
    np.testing.assert_array_equal(saver.P[-1], kf.P)
    assert [r.method for r in saver.last_fusion] == ["ci"] * 3


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


# ------------------------------------------- the single fusion's validation, its fast path
def _general_path(xs, Ps):
    """The validation's general path (the numbers as nested lists, which the fast path
    never takes): its estimates, or the exception it raises."""
    from cifilter._numerics.validation import as_estimates

    try:
        return as_estimates([x.tolist() for x in xs], [P.tolist() for P in Ps],
                            names=("x", "P"), labels=("this filter", "other"))
    except (TypeError, ValueError) as exc:
        return exc


def _assert_single_validation_is_the_general_paths(xs, Ps, fuse=True):
    """A filter's single fusion (unbatched float64 arrays: the fast path) validates like
    the general path: the same means and symmetrised covariances bit for bit, and each
    factor LAPACK's dpotrf of that covariance (the single problem's factorisation); a
    covariance the general path refuses is refused by kf.fuse with the same message."""
    from scipy.linalg import lapack

    from cifilter._numerics.validation import as_estimates

    xs = [x.reshape(-1, 1) for x in xs]  # (kf.fuse gives the other the filter's style)
    general = _general_path(xs, Ps)
    kf = make_kf(Ps[0])
    kf.x = xs[0]
    if isinstance(general, Exception):
        before = bit_snapshot(kf)
        with pytest.raises(type(general), match="^" + re.escape(str(general)) + "$"):
            kf.fuse((xs[1], Ps[1]))
        assert_bit_identical(kf, before)
        return
    fast = as_estimates(xs, Ps, names=("x", "P"), labels=("this filter", "other"))
    assert fast.column and fast.x.tobytes() == general.x.tobytes()
    assert fast.P.tobytes() == general.P.tobytes()
    for P, L in zip(general.P, fast.L):
        assert L.tobytes() == lapack.dpotrf(P, lower=1, clean=1)[0].tobytes()
    if fuse:  # (not beyond the scales of the conditioning contract: the rule's arithmetic)
        kf.fuse((xs[1], Ps[1]))
        assert np.isfinite(kf.P).all()


@settings(deadline=None)
@given(data=st.data(), n=st.integers(1, 6),
       asymmetry=st.sampled_from([0.0, 1e-15, 1e-12, 1e-9, 1e-7, 1e-3]))
def test_single_fusion_validation_is_the_general_paths(data, n, asymmetry):
    """Condition numbers to 1e12, scales 1e-12..1e12, the other covariance symmetric,
    asymmetric within the tolerance (symmetrised) or beyond it (refused alike)."""
    Ps = [data.draw(ill_conditioned_spd(n)) for _ in range(2)]
    xs = [data.draw(arrays(float, (n,), elements=st.floats(-1e3, 1e3))) for _ in range(2)]
    if n > 1:
        Ps[1] = Ps[1].copy()
        Ps[1][0, n - 1] += asymmetry * np.abs(np.diagonal(Ps[1])).max()
    _assert_single_validation_is_the_general_paths(xs, Ps)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # (the general path's overflows)
@pytest.mark.parametrize("scale", [2.0**1021, 2.0**1022, 1.5 * 2.0**1022, 2.0**1023])
@pytest.mark.parametrize("asymmetric", [False, True])
def test_single_fusion_validation_at_the_largest_scales(scale, asymmetric):
    """Entries near the largest float, where a symmetrised copy may overflow."""
    from cifilter._numerics.validation import _usual_estimates

    P = np.array([[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 0.5]]) * (scale / 2.0)
    other = P.copy()
    if asymmetric:
        other[0, 2] *= 1.0 + 1e-12
    _assert_single_validation_is_the_general_paths([np.zeros(3), np.ones(3)], [P, other],
                                                   fuse=False)
    # the single problem's own factorisation (LAPACK per matrix) for every entry below
    # 2**1023, where neither P - P^T nor P + P^T overflows; the general path beyond
    fast = _usual_estimates([np.zeros(3), np.ones(3)], [P, other])
    assert (fast is not None) == (scale < 2.0**1023)


@pytest.mark.parametrize("where", ["x", "P off", "P diagonal"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_single_fusion_validation_of_non_finite_values(where, value):
    P, x = np.array([[2.0, 0.5], [0.5, 1.0]]), np.zeros(2)
    if where == "x":
        x = np.array([0.0, value])
    else:
        P = P.copy()
        P[(0, 1) if where == "P off" else (1, 1)] = value
        if where == "P off":
            P[1, 0] = value
    _assert_single_validation_is_the_general_paths([np.ones(2), x], [np.eye(2), P])
