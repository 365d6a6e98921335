"""The front door's short way of ``kf.fuse(other, lag=k)`` (``alignment.aligned_pair`` on
numpy; where single calls run on the kernels, ``alignment.pair_step`` and one compiled call
of ``_kernels/shift.py``'s ``shifted_pair`` that brings and fuses): the same answers as the
usual path (validation, ``align_estimates``, the rule), the same errors, and taken for the
usual call."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_spd

import cifilter
import cifilter.rules.ci as ci_module
from cifilter import KalmanFilter
from cifilter._kernels import dispatch
from cifilter._numerics import alignment
from cifilter.backend import numba_available

if numba_available():
    from cifilter._kernels.shift import shift_single

F_CV = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0],
                 [0.0, 0.0, 0.0, 1.0]])
Q_CV = 0.05 * np.array([[1 / 3, 0.0, 1 / 2, 0.0], [0.0, 1 / 3, 0.0, 1 / 2],
                        [1 / 2, 0.0, 1.0, 0.0], [0.0, 1 / 2, 0.0, 1.0]])
BACKENDS = ["numpy"] + (["numba"] if numba_available() else [])


def cv_filter(P):
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.Q = F_CV.copy(), Q_CV.copy()
    kf.x = np.array([1.0, -2.0, 0.5, 0.25]).reshape(4, 1)
    kf.P = np.array(P, dtype=float)
    return kf


def usual(kf, other, monkeypatch, **options):
    """``kf.fuse(other, **options)`` on a copy of the filter, the short way turned off."""
    copy = cv_filter(kf.P)
    copy.x = kf.x.copy()
    with monkeypatch.context() as m:
        m.setattr(ci_module, "aligned_pair", lambda *args, **kwargs: None)
        m.setattr(ci_module, "pair_step", lambda *args, **kwargs: None)
        return copy.fuse(other, **options)


def assert_same_fusion(a, b, rtol):
    scale = np.abs(b.P).max()
    assert np.abs(a.P - b.P).max() <= rtol * scale
    np.testing.assert_allclose(a.omega, b.omega, rtol=0, atol=1e-6)
    assert a.info["at"] == b.info["at"]
    alpha_a, alpha_b = a.info["retrodiction_alpha"], b.info["retrodiction_alpha"]
    assert (alpha_a[1] is None) == (alpha_b[1] is None)
    if alpha_b[1] is not None:
        assert float(alpha_a[1]) == pytest.approx(float(alpha_b[1]), rel=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k", [1, 3, -1, -2])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_the_short_way_is_the_usual_path(backend, k, criterion, monkeypatch):
    rng = np.random.default_rng(abs(k) + 10 * (criterion == "det"))
    for _ in range(20):
        A, B = rng.standard_normal((2, 4, 4))
        P_own, P_other = A @ A.T + 0.1 * np.eye(4), B @ B.T + 0.1 * np.eye(4)
        other = (rng.standard_normal(4), 0.5 * (P_other + P_other.T))
        kf = cv_filter(0.5 * (P_own + P_own.T))
        with cifilter.use_backend(backend):
            expected = usual(kf, other, monkeypatch, lag=k, criterion=criterion)
            result = kf.fuse(other, lag=k, criterion=criterion)
        # the same steps in another summation order (compiled shift) or bit for bit (numpy)
        assert_same_fusion(result, expected, 1e-12)
        np.testing.assert_allclose(kf.x.ravel(), np.ravel(expected.x), rtol=0,
                                   atol=1e-12 * (1 + np.abs(expected.x).max()))


@pytest.mark.skipif(not numba_available(), reason="needs numba")
@settings(max_examples=60, deadline=None)
@given(st.data(), st.sampled_from([1, 2, -1, -2]))
def test_the_compiled_shift_is_the_numpy_shift(data, k):
    """At condition numbers to 1e12 and scales 1e-12..1e12: the kernel's (x, P, alpha)
    against alignment.predicted / retrodicted on LAPACK's factor."""
    P = data.draw(ill_conditioned_spd(4))
    x = data.draw(st.lists(st.floats(-1e3, 1e3), min_size=4, max_size=4))
    x = np.array(x) * np.sqrt(np.diag(P))
    motion = alignment.StepMotion(F_CV.copy(), Q_CV * np.sqrt(P.trace()))
    L = np.linalg.cholesky(P)
    if k > 0:
        M, N = motion.checked(float(k), 4)
        x_ref, P_ref = alignment.predicted(x, L, M, N)
        alpha_ref = None
    else:
        M, N = motion.back(float(-k), 4, "F")
        F, Q = motion.checked(float(-k), 4)
        x_ref, P_ref, alpha_ref = alignment.retrodicted(x, L, F, Q, F_inv=M, Q_back=N)
    x_k, P_k = np.empty(4), np.empty((4, 4))
    status, alpha_k = shift_single(x.copy(), P.copy(), M, N, k < 0, np.empty((4, 4)), x_k,
                                   P_k)
    assert status == 0
    alpha_k = None if k > 0 else alpha_k
    assert (P_k == P_k.T).all()
    # both are n eps |M| |L| |L^T| |M^T| + |N| away from the exact product, entry by entry
    bound = 64 * np.finfo(float).eps * (np.abs(M) @ np.abs(L) @ np.abs(L).T @ np.abs(M).T
                                        + np.abs(N))
    if k < 0:
        bound = bound / min(alpha_k, 1 - alpha_k)
    assert (np.abs(P_k - P_ref) <= bound).all()
    assert (np.abs(x_k - x_ref) <= 64 * np.finfo(float).eps * (np.abs(M) @ np.abs(x))).all()
    if alpha_ref is None:
        assert alpha_k is None
    else:
        assert alpha_k == pytest.approx(alpha_ref, rel=1e-13)


@pytest.mark.skipif(not numba_available(), reason="needs numba")
def test_the_usual_call_takes_the_compiled_shift():
    kf = cv_filter(np.eye(4))
    other = (np.ones(4), 2.0 * np.eye(4))
    with cifilter.use_backend("numba"):
        kf.fuse(other, lag=1)  # (the kernels compile on first use under "numba")
        before = dispatch.report()["kernels"]
        kf.fuse(other, lag=1)
        # one compiled call brings the other track and fuses the pair
        assert dispatch.report()["kernels"] == before + 1
        assert kf.last_fusion.info["solver"] == "diagonalise"


BAD = {
    # not positive definite, but its prediction F P F^T + Q is: the validation must see it
    "indefinite": (np.ones(4), np.diag([1.0, 1.0, 1.0, -1e-4])),
    "nan in P": (np.ones(4), np.where(np.eye(4) == 1, np.nan, 0.0)),
    "nan in x": (np.array([1.0, np.nan, 0.0, 0.0]), np.eye(4)),
    "asymmetric": (np.ones(4), np.eye(4) + np.triu(np.ones((4, 4)), 1)),
    "huge": (np.ones(4), np.diag([1e308, 1.0, 1.0, 1.0]) * 1.7),
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k", [1, -1])
@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_gets_the_usual_error_and_the_filter_is_unchanged(backend, k, case,
                                                                    monkeypatch):
    kf = cv_filter(np.eye(4))
    other = BAD[case]
    if case == "indefinite":  # (the premise: the prediction alone would pass)
        assert np.linalg.eigvalsh(F_CV @ other[1] @ F_CV.T + Q_CV).min() > 0
    with cifilter.use_backend(backend):
        with pytest.raises((ValueError, TypeError)) as usual_error:
            usual(kf, other, monkeypatch, lag=k)
        x, P = kf.x.copy(), kf.P.copy()
        with pytest.raises(type(usual_error.value)) as error:
            kf.fuse(other, lag=k)
    assert str(error.value) == str(usual_error.value)
    np.testing.assert_array_equal(kf.x, x)
    np.testing.assert_array_equal(kf.P, P)


@pytest.mark.parametrize("backend", BACKENDS)
def test_nearly_symmetric_input_goes_the_usual_way_bit_for_bit(backend, monkeypatch):
    P_other = np.array([[2.0, 0.3, 0.0, 0.1], [0.3, 1.0, 0.0, 0.0], [0.0, 0.0, 1.5, 0.2],
                        [0.1, 0.0, 0.2, 1.0]])
    P_other[0, 1] += 1e-15  # within the validation's tolerance: it symmetrises
    other = (np.ones(4), P_other)
    kf = cv_filter(np.eye(4))
    with cifilter.use_backend(backend):
        expected = usual(kf, other, monkeypatch, lag=2)
        result = kf.fuse(other, lag=2)
    np.testing.assert_array_equal(result.P, expected.P)
    np.testing.assert_array_equal(result.x, expected.x)


@pytest.mark.parametrize("backend", BACKENDS)
def test_inputs_are_not_modified_and_the_info_is_read_only(backend):
    other = (np.ones(4), 2.0 * np.eye(4) + 0.1)
    copies = [a.copy() for a in other]
    kf = cv_filter(np.eye(4))
    with cifilter.use_backend(backend):
        result = kf.fuse(other, lag=-1)
    for a, b in zip(other, copies):
        np.testing.assert_array_equal(a, b)
    alpha = result.info["retrodiction_alpha"]
    assert alpha[0] is None and 0.0 < float(alpha[1]) < 1.0
    if isinstance(alpha[1], np.ndarray):
        assert not alpha[1].flags.writeable
    with pytest.raises(TypeError):
        result.info["at"] = 1.0
