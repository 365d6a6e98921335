"""The single-call route of ``"ci"`` (issue 24): two single estimates reach one compiled
call (``_kernels.compiled.ci_pair_serial``, which checks and factors the raw input itself)
through the rule's ``pair`` route, under the numba backend and under ``"auto"`` once the
kernels are there.

Checked here: the route is taken (the validation of the usual route is not called), its
result equals the usual route's to rounding on problems of condition number up to 1e12 and
is a bound in the exact worst direction, every bad input gives the usual route's error
(the same type and text), a filter whose fuse raises is left as it was, the caller's
vector style is kept and the inputs are never modified.
"""

import numpy as np
import pytest
from helpers import fused_bound_tolerance
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets
from worst_case import assert_bound_holds

import cifilter
from cifilter import KalmanFilter, get_method
from cifilter._kernels import dispatch
from cifilter._numerics import validation
from cifilter.backend import numba_available

needs_numba = pytest.mark.skipif(not numba_available(), reason="numba is not installed")

CRITERIA = ("trace", "det", "weighted")


def _criterion(name, n):
    return np.diag(np.arange(1.0, n + 1)) if name == "weighted" else name


def _problem(seed=0, n=4):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((2, n, n))
    Ps = A @ A.swapaxes(-1, -2) + 0.5 * np.eye(n)
    return rng.standard_normal((2, n)), Ps


def _usual(pairs, options):
    """The usual route: the validation, then the rule's core (the same backend)."""
    est = validation.as_estimates([p[0] for p in pairs], [p[1] for p in pairs])
    return get_method("ci").core(est, **options)


class _ValidationCalled(AssertionError):
    pass


def _assert_same_optimum(result, usual):
    """``result`` solves the problems of ``usual`` as well: the same info keys and flags,
    omega to 1e-9 or, where the criterion is flat to rounding (ties: the two routes'
    Cholesky factors differ in the last bits, and so may the broken tie), criterion values
    within the two certified gaps; P exactly symmetric."""
    assert result.x.shape == usual.x.shape and result.P.shape == usual.P.shape
    assert list(result.info) == list(usual.info)
    np.testing.assert_array_equal(result.info["converged"], usual.info["converged"])
    np.testing.assert_array_equal(result.P, np.swapaxes(result.P, -1, -2))
    close = np.abs(result.omega - usual.omega).max(axis=-1) <= 1e-9
    gaps = result.info["gap"] + usual.info["gap"]
    if "log_value" in usual.info:
        # log det P from each route's Cholesky factor of P: backward errors of (n + 1) eps
        # move it by up to n (n + 1) eps cond(P) each (as tests/test_backend.py bounds it)
        n = usual.P.shape[-1]
        rounding = 2.0 * n**2 * (n + 1) * np.finfo(float).eps * np.linalg.cond(usual.P)
        same = (np.abs(result.info["log_value"] - usual.info["log_value"])
                <= gaps + rounding + 1e-12)
    else:
        largest = np.maximum(result.info["value"], usual.info["value"])
        same = np.abs(result.info["value"] - usual.info["value"]) <= (gaps + 1e-12) * largest
    assert np.all(close | same), (result.omega, usual.omega, gaps)
    scale = np.abs(usual.P).max(axis=(-2, -1))
    near = np.abs(result.P - usual.P).max(axis=(-2, -1)) <= 1e-9 * scale
    assert np.all(near | ~close)


@needs_numba
@pytest.mark.parametrize("criterion", CRITERIA)
@pytest.mark.parametrize("column", [False, True])
def test_kf_fuse_takes_one_compiled_call_without_the_validation(monkeypatch, criterion,
                                                                column):
    xs, Ps = _problem()
    options = {} if criterion == "trace" else {"criterion": _criterion(criterion, 4)}
    kf = KalmanFilter(dim_x=4, dim_z=1)
    kf.x, kf.P = xs[0].reshape(4, 1), Ps[0]
    other = (xs[1].reshape(4, 1) if column else xs[1], Ps[1])
    with cifilter.use_backend("numba"):
        expected = _usual([(xs[0].reshape(4, 1), Ps[0]), (other[0].reshape(4, 1), Ps[1])],
                          options)

        def refuse(*args, **kwargs):
            raise _ValidationCalled("the usual route's validation ran")

        monkeypatch.setattr("cifilter.registry.as_estimates", refuse)
        before = dispatch.report()["kernels"]
        result = kf.fuse(other, method="ci", **options)
        assert dispatch.report()["kernels"] == before + 1
        front = cifilter.fuse([(xs[0], Ps[0]), (xs[1], Ps[1])], **options)
    # bitwise where the kernel's factors equal LAPACK's (this well-conditioned 4 x 4 pair),
    # else to rounding; the same info, keys, types and flags
    np.testing.assert_allclose(result.omega, expected.omega, rtol=0, atol=1e-13)
    np.testing.assert_allclose(result.P, expected.P, rtol=1e-12, atol=0)
    np.testing.assert_allclose(result.x, expected.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(result.gains, expected.gains, rtol=1e-12, atol=1e-14)
    assert list(result.info) == list(expected.info)
    for key, value in expected.info.items():
        assert type(result.info[key]) is type(value), key
        if key in ("criterion", "rule", "solver", "converged", "iterations"):
            assert np.array_equal(result.info[key], value), key
    assert result.x.shape == expected.x.shape == (4, 1)
    assert kf.x.shape == (4, 1) and np.array_equal(kf.x, result.x)
    assert front.x.shape == (4,)
    for array in (result.x, result.P, result.omega, result.gains, result.info["gap"]):
        assert not array.flags.writeable
    assert result.weights is result.omega


_problems = st.integers(1, 6).flatmap(lambda n: st.tuples(
    st.booleans().flatmap(lambda common: ill_conditioned_sets(2, n, common_scale=common)),
    st.integers(0, 2**32 - 1)))


@needs_numba
@settings(max_examples=60, deadline=None)
@given(_problems, st.sampled_from(CRITERIA), st.booleans())
def test_route_equals_the_usual_route_and_is_a_bound(problem, criterion, column):
    _route_equals_the_usual_route(problem, criterion, column, "numba")


@settings(max_examples=60, deadline=None)
@given(_problems, st.sampled_from(CRITERIA), st.booleans())
def test_numpy_route_equals_the_usual_route_and_is_a_bound(problem, criterion, column):
    _route_equals_the_usual_route(problem, criterion, column, "numpy")


def _route_equals_the_usual_route(problem, criterion, column, backend):
    Ps, seed = problem
    n = Ps[0].shape[0]
    rng = np.random.default_rng(seed)
    xs = [rng.standard_normal(n) * np.sqrt(np.abs(np.diag(P))) for P in Ps]
    if column:
        xs = [x.reshape(n, 1) for x in xs]
    pairs = list(zip(xs, Ps))
    options = {"criterion": _criterion(criterion, n)}
    copies = [(x.copy(), P.copy()) for x, P in pairs]
    with cifilter.use_backend(backend):
        fast = get_method("ci").pair(pairs, options)
        usual = _usual(pairs, options)
    for (x, P), (x0, P0) in zip(pairs, copies):  # inputs never modified
        assert np.array_equal(x, x0) and np.array_equal(P, P0)
    if fast is None:  # handed back (ill-conditioned pairs): the usual route answers
        return
    # the kernel's Cholesky factors against LAPACK's: x, P, omega to rounding (measured on
    # 3 000 problems at condition numbers to 1e12: at most 1e-12 relative to max |P|)
    _assert_same_optimum(fast, usual)
    assert_bound_holds(fast.P, fast.gains, list(Ps), tol=fused_bound_tolerance(np.stack(Ps)))


def _bad_inputs():
    xs, Ps = _problem(3)
    x1, x2 = xs
    P1, P2 = Ps
    nan_x = x2.copy()
    nan_x[1] = np.nan
    inf_P = P2.copy()
    inf_P[0, 0] = np.inf
    nan_off = P2.copy()
    nan_off[0, 1] = nan_off[1, 0] = np.nan
    asymmetric = P2.copy()
    asymmetric[0, 1] += 1e-3
    indefinite = P2.copy()
    indefinite[0, 0] = -1.0
    singular = np.zeros((4, 4))
    huge = P2 / np.abs(P2).max() * 2.0**1023
    rank_one = np.outer(x1, x1)
    return {
        "nan mean": ((x1, P1), (nan_x, P2)),
        "inf covariance": ((x1, P1), (x2, inf_P)),
        "nan off the diagonal": ((x1, P1), (x2, nan_off)),
        "not symmetric": ((x1, P1), (x2, asymmetric)),
        "not symmetric first": ((x1, asymmetric), (x2, P2)),
        "indefinite": ((x1, P1), (x2, indefinite)),
        "zero": ((x1, singular), (x2, P2)),
        "rank one": ((x1, P1), (x2, rank_one)),
        "entries beyond 2**1023": ((x1, huge), (x2, P2)),
        "dimensions differ": ((x1, P1), (x2[:3], P2[:3, :3])),
        "mean of the wrong size": ((x1, P1), (x2[:3], P2)),
        "complex covariance": ((x1, P1), (x2, P2 + 0j)),
        "boolean mean": ((x1, P1), (x2 > 0, P2)),
    }


def _error(call):
    try:
        call()
    except Exception as error:  # (the type and text are compared)
        return type(error), str(error)
    return None


@needs_numba
@pytest.mark.parametrize("case", sorted(_bad_inputs()))
@pytest.mark.parametrize("criterion", ["trace", "det", "bogus"])
def test_bad_input_gives_the_usual_error(case, criterion):
    pairs = _bad_inputs()[case]
    options = {"criterion": criterion}
    with cifilter.use_backend("numpy"):  # the usual route (the route runs the kernel only)
        expected = _error(lambda: cifilter.fuse(list(pairs), **options))
    with cifilter.use_backend("numba"):
        got = _error(lambda: cifilter.fuse(list(pairs), **options))
        kf = KalmanFilter(dim_x=4, dim_z=1)
        x0, P0 = np.array(pairs[0][0], dtype=float).reshape(-1, 1), pairs[0][1]
        if x0.shape[0] == 4 and np.shape(P0) == (4, 4):
            kf.x, kf.P = x0, P0
            with cifilter.use_backend("numpy"):
                filter_expected = _error(lambda: kf.fuse(pairs[1], **options))
            state = (kf.x, kf.P, kf.x_post, kf.P_post, kf.last_fusion)
            filter_got = _error(lambda: kf.fuse(pairs[1], **options))
            assert filter_got == filter_expected
            if filter_got is not None:  # atomic: the very same objects, unchanged
                after = (kf.x, kf.P, kf.x_post, kf.P_post, kf.last_fusion)
                assert all(a is b for a, b in zip(after, state))
    assert expected is not None
    assert got == expected


@needs_numba
def test_a_failing_fuse_leaves_the_filter_as_it_was():
    xs, Ps = _problem(4)
    kf = KalmanFilter(dim_x=4, dim_z=1)
    with cifilter.use_backend("numba"):
        kf.fuse((xs[1], Ps[1]))  # a successful fusion first: last_fusion is set
        state = [np.array(v, copy=True) for v in (kf.x, kf.P, kf.x_post, kf.P_post)]
        objects = (kf.x, kf.P, kf.x_post, kf.P_post, kf.last_fusion)
        bad = Ps[1].copy()
        bad[2, 3] += 1.0
        with pytest.raises(ValueError, match="other's P is not symmetric"):
            kf.fuse((xs[1], bad))
    assert all(a is b for a, b in zip((kf.x, kf.P, kf.x_post, kf.P_post, kf.last_fusion),
                                      objects))
    for value, saved in zip((kf.x, kf.P, kf.x_post, kf.P_post), state):
        assert np.array_equal(value, saved)


@needs_numba
def test_inputs_are_not_modified_nor_aliased():
    xs, Ps = _problem(5)
    P2 = Ps[1].copy()
    P2[0, 1] += 1e-12 * abs(P2[0, 1])  # symmetric within the tolerance: symmetrised copy
    pairs = [(xs[0].copy(), np.asfortranarray(Ps[0])), (xs[1].copy(), P2)]
    saved = [(x.copy(), P.copy()) for x, P in pairs]
    with cifilter.use_backend("numba"):
        result = cifilter.fuse(pairs)
    for (x, P), (x0, P0) in zip(pairs, saved):
        assert np.array_equal(x, x0) and np.array_equal(P, P0)
        assert x.flags.writeable and P.flags.writeable
        assert not np.shares_memory(result.P, P) and not np.shares_memory(result.x, x)


@needs_numba
def test_mixed_vector_styles_keep_the_first_style():
    xs, Ps = _problem(6)
    with cifilter.use_backend("numba"):
        a = cifilter.fuse([(xs[0].reshape(4, 1), Ps[0]), (xs[1], Ps[1])])
        b = cifilter.fuse([(xs[0], Ps[0]), (xs[1].reshape(4, 1), Ps[1])])
    assert a.x.shape == (4, 1) and b.x.shape == (4,)
    np.testing.assert_allclose(a.x[:, 0], b.x, rtol=1e-13)


@pytest.mark.parametrize("criterion", CRITERIA)
def test_numpy_backend_takes_lapack_directly_or_the_usual_route(monkeypatch, criterion):
    """Without the kernels: one pair through LAPACK directly (rules/_ci_lean.py) where it
    answers: omega and the certificate bit for bit the numpy path's, x and P to rounding,
    the same info; no validation of the usual route."""
    xs, Ps = _problem(7)
    pairs = [(xs[0].reshape(4, 1), Ps[0]), (xs[1].reshape(4, 1), Ps[1])]
    options = {"criterion": _criterion(criterion, 4)}
    with cifilter.use_backend("numpy"):
        usual = _usual(pairs, options)
        calls = []
        original = validation.as_estimates

        def counting(*args, **kwargs):
            calls.append(1)
            return original(*args, **kwargs)

        monkeypatch.setattr("cifilter.registry.as_estimates", counting)
        result = cifilter.fuse(pairs, **options)
    from cifilter.rules import ci

    if ci.lean_pair is None:
        assert calls == [1]
        return
    assert calls == []
    np.testing.assert_array_equal(result.omega, usual.omega)
    for key in ("iterations", "converged", "gap", "gap_floor", "solver", "rule"):
        np.testing.assert_array_equal(result.info[key], usual.info[key])
    assert list(result.info) == list(usual.info)
    assert result.x.shape == usual.x.shape == (4, 1)
    np.testing.assert_allclose(result.x, usual.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(result.P, usual.P, rtol=1e-12, atol=0)
    np.testing.assert_allclose(result.gains, usual.gains, rtol=1e-12, atol=1e-14)
    assert not result.P.flags.writeable and not result.gains.flags.writeable


def test_other_options_take_the_usual_route():
    xs, Ps = _problem(8)
    pairs = [(xs[0], Ps[0]), (xs[1], Ps[1])]
    route = get_method("ci").pair
    with cifilter.use_backend("numba" if numba_available() else "numpy"):
        assert route(pairs, {"omega": 0.3}) is None
        assert route(pairs, {"criterion": "trace", "omega": None}) is None
        assert route([(xs[0], Ps[0]), (xs[1], np.stack([Ps[1]] * 2))], {}) is None
        assert route([(list(xs[0]), Ps[0]), (xs[1], Ps[1])], {}) is None


# ------------------------------------------------------------ batches: validation folded in
@st.composite
def _batches(draw, n, size):
    """``size`` pairs: ill-conditioned (to 1e12, common or separate scales) and
    well-conditioned ones, means of the covariances' scale, rows or columns."""
    Ps = np.stack([np.stack(draw(ill_conditioned_sets(
        2, n, max_condition=draw(st.sampled_from([1e3, 1e12])),
        common_scale=draw(st.booleans())))) for _ in range(size)])
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    xs = rng.standard_normal(Ps.shape[:-1]) * np.sqrt(np.abs(np.diagonal(Ps, axis1=-2,
                                                                       axis2=-1)))
    return (xs[..., None] if draw(st.booleans()) else xs), Ps


@needs_numba
@settings(max_examples=30, deadline=None)
@given(st.integers(1, 5).flatmap(lambda n: _batches(n, 7)), st.sampled_from(CRITERIA))
def test_batched_route_equals_the_usual_route(monkeypatch, batch, criterion):
    xs, Ps = batch
    criterion = _criterion(criterion, Ps.shape[-1])
    saved = (xs.copy(), Ps.copy())
    with cifilter.use_backend("numba"):
        usual = get_method("ci").core(validation.as_estimates(xs, Ps), criterion=criterion)

        def refuse(*args, **kwargs):
            raise _ValidationCalled("the usual route's validation ran")

        with monkeypatch.context() as patch:
            patch.setattr("cifilter.rules.ci.as_estimates", refuse)
            fast = cifilter.covariance_intersection(xs, Ps, criterion)
            pairs = [(xs[:, 0], Ps[:, 0]), (xs[:, 1], Ps[:, 1])]
            through_fuse = get_method("ci").pair(pairs, {"criterion": criterion})
    assert np.array_equal(xs, saved[0]) and np.array_equal(Ps, saved[1])
    assert through_fuse is not None
    for result in (fast, through_fuse):
        _assert_same_optimum(result, usual)
    for b in range(Ps.shape[0]):
        assert_bound_holds(fast.P[b], fast.gains[b], list(Ps[b]),
                           tol=fused_bound_tolerance(Ps[b]))


@needs_numba
@pytest.mark.parametrize("case", sorted(_bad_inputs()))
def test_bad_item_of_a_batch_gives_the_usual_error(case):
    (x1, P1), (x2, P2) = _bad_inputs()[case]
    if np.shape(P1) != np.shape(P2) or np.shape(x1) != np.shape(x2):
        pytest.skip("no batch of mismatched shapes")
    good_x, good_P = _problem(9)
    xs = np.stack([good_x, good_x, np.stack([x1, x2]).astype(np.result_type(x1, x2))])
    Ps = np.stack([good_P, good_P, np.stack([P1, P2]).astype(np.result_type(P1, P2))])
    with cifilter.use_backend("numpy"):
        expected = _error(lambda: cifilter.covariance_intersection(xs, Ps))
    with cifilter.use_backend("numba"):
        got = _error(lambda: cifilter.covariance_intersection(xs, Ps))
    assert got == expected


@needs_numba
@pytest.mark.parametrize("lag", [2, -1])
def test_lag_brings_and_fuses_in_one_compiled_call(monkeypatch, lag):
    xs, Ps = _problem(10)
    kf = KalmanFilter(dim_x=4, dim_z=1)
    kf.F = np.eye(4) + np.diag([1.0, 1.0], 2)
    kf.Q = 0.01 * np.eye(4)
    kf.x, kf.P = xs[0].reshape(4, 1), Ps[0]
    calls = []
    route = dispatch.shifted_pair_single

    def counted(*args):
        result = route(*args)
        calls.append(result is not None)
        return result

    with cifilter.use_backend("numba"):
        usual = cifilter.fuse([(xs[0], Ps[0]), (xs[1], Ps[1])], times=[0.0, -float(lag)],
                              at=0.0, motion=lambda dt: (np.linalg.matrix_power(kf.F, int(dt)),
                                                         sum(np.linalg.matrix_power(kf.F, j)
                                                             @ kf.Q @ np.linalg.matrix_power(
                                                                 kf.F, j).T
                                                             for j in range(int(dt)))))
        monkeypatch.setattr(dispatch, "shifted_pair_single", counted)
        monkeypatch.setattr(dispatch, "pair_single", None)  # (not called)
        result = kf.fuse((xs[1], Ps[1]), lag=lag)
    assert calls == [True]
    assert result.info["at"] == 0.0 and result.x.shape == (4, 1)
    np.testing.assert_allclose(result.omega, usual.omega, rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.P, usual.P, rtol=1e-8, atol=0)


@needs_numba
def test_a_batch_of_criterion_matrices_takes_the_usual_route(monkeypatch):
    xs, Ps = _problem(11)
    Ws = np.stack([np.eye(4), np.diag([1.0, 2.0, 3.0, 4.0])])
    pairs = [(xs[0], Ps[0]), (xs[1], Ps[1])]
    with cifilter.use_backend("numba"):
        assert get_method("ci").pair(pairs, {"criterion": Ws}) is None
        monkeypatch.setattr(dispatch, "pair_single", None)  # (not reached: not called)
        with pytest.raises(ValueError):  # (single estimates, a batch of W: refused as before)
            cifilter.fuse(pairs, criterion=Ws)
