"""The compiled generalised-CI pair (``cifilter._kernels.generalised``, issue 22's ``H=``
latency): one full-state and one partial estimate, the pair ``kf.fuse(other, H=H)`` makes.

Checked here: under the numba backend a single ``H=`` pair runs the kernel (its result is
the kernel's, bit for bit); where the kernel decides, it agrees with the numpy path's
diagonalised pair (weights to 1e-10, x and P to 1e-10 of their scale, the same
certificate) on problems of condition number up to 1e12 at scales 1e-12..1e12, and where it
does not (m > n, an untrusted diagonalisation) the numpy path's result is returned
unchanged; a hand-derived optimum; the exact worst-direction bound of the kernel's own
gains. (The tests of ``test_generalised_ci.py`` on the pair path also run under both
backends.)
"""

import numpy as np
import pytest
from hypothesis import given, note, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_spd
from worst_case import assert_bound_holds, gain_bound_difference, padded

import cifilter
from cifilter import KalmanFilter, fuse
from cifilter.backend import numba_available
from cifilter.registry import get_method

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not installed")

EPS = np.finfo(float).eps
KINDS = ("trace", "det", "weighted")


def _criterion(kind, n):
    return np.diag(np.arange(1.0, n + 1)) if kind == "weighted" else kind


def _kernel(a, b, H, kind):
    """The kernel on a pair's validated arrays (None where it does not decide)."""
    from cifilter._kernels.generalised import partial_pair
    from cifilter._numerics.alignment import as_partial_estimates
    from cifilter._numerics.criteria import parse_criterion

    est = as_partial_estimates([a, b], (None, H))
    name, W = parse_criterion(_criterion(kind, H.shape[1]), H.shape[1])
    return partial_pair(est.x[0], est.P[0], est.x[1], est.P[1], H, name, W,
                        factors=(est.L[0], est.L[1]))


@st.composite
def pairs(draw, max_condition=1e12, ratios=(1e-3, 1e3)):
    """A full-state estimate (n = 1..5) and one of ``H x`` (m = 1..n + 1 rows, random H),
    covariances of condition number up to ``max_condition`` at one scale in 1e-12..1e12
    (the partial one's within ``ratios`` of it), means of their standard deviations."""
    n = draw(st.integers(1, 5))
    m = draw(st.integers(1, n + 1))
    log_scale = draw(st.floats(-12.0, 12.0))
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    P1 = draw(ill_conditioned_spd(n, max_condition, scales=(10.0**log_scale,) * 2))
    ratio = draw(st.floats(np.log10(ratios[0]), np.log10(ratios[1])))
    scale = 10.0 ** (log_scale + ratio)
    P2 = draw(ill_conditioned_spd(m, max_condition, scales=(scale, scale)))
    H = g.standard_normal((m, n))
    x1 = g.standard_normal(n) * np.sqrt(np.diag(P1))
    x2 = g.standard_normal(m) * np.sqrt(np.diag(P2))
    return (x1, P1), (x2, P2), H


def _both(a, b, H, kind):
    crit = _criterion(kind, H.shape[1])
    with cifilter.use_backend("numpy"):
        r0 = fuse([a, b], H=[None, H], criterion=crit)
    with cifilter.use_backend("numba"):
        r1 = fuse([a, b], H=[None, H], criterion=crit)
    return r0, r1


def _assert_same_result(r0, r1):
    np.testing.assert_array_equal(r0.x, r1.x)
    np.testing.assert_array_equal(r0.P, r1.P)
    np.testing.assert_array_equal(r0.weights, r1.weights)
    assert r0.info.keys() == r1.info.keys()


def _assert_agree(r0, r1, kind):
    """The kernel's result r1 against the numpy path's diagonalised r0."""
    assert r0.info.keys() == r1.info.keys()
    assert abs(r0.weights[0] - r1.weights[0]) <= 1e-10
    assert r1.weights[0] + r1.weights[1] == 1.0
    scale_P = np.abs(r0.P).max()
    assert np.abs(r0.P - r1.P).max() <= 1e-10 * scale_P
    scale_x = max(np.abs(r0.x).max(), np.sqrt(np.abs(np.diag(r0.P)).max()))
    assert np.abs(r0.x.ravel() - r1.x.ravel()).max() <= 1e-10 * scale_x
    for K0, K1 in zip(r0.info["gains"], r1.info["gains"]):
        assert K0.shape == K1.shape
    # the same certificate: gaps of the same meaning, both certified or neither
    assert float(r1.info["gap"]) >= 0.0
    if max(float(r0.info["gap"]), float(r1.info["gap"])) < 0.5e-9:
        assert bool(r0.info["converged"]) and bool(r1.info["converged"])
    assert int(r1.info["iterations"]) <= 100
    if kind == "det":
        assert abs(float(r0.info["log_value"]) - float(r1.info["log_value"])) <= 1e-9 * (
            1.0 + abs(float(r0.info["log_value"])))
    else:
        assert float(r1.info["value"]) == pytest.approx(float(r0.info["value"]), rel=1e-10)


# ----------------------------------------------------------------------------- the route
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("column", [False, True])
def test_kf_fuse_with_H_runs_the_kernel_under_numba(kind, column):
    rng = np.random.default_rng(7)
    A = rng.standard_normal((4, 4))
    P1 = A @ A.T + 0.5 * np.eye(4)
    B = rng.standard_normal((2, 2))
    P2 = B @ B.T + 0.5 * np.eye(2)
    x1, x2 = rng.standard_normal(4), rng.standard_normal(2)
    H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    kernel = _kernel((x1, P1), (x2, P2), H, kind)
    assert kernel is not None
    x, P, omega, info = kernel
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P = (x1[:, None] if column else x1.copy()), P1.copy()
    with cifilter.use_backend("numba"):
        r = kf.fuse((x2, P2), H=H, criterion=_criterion(kind, 4))
    # bit for bit the kernel's answer
    np.testing.assert_array_equal(r.x.ravel(), x)
    np.testing.assert_array_equal(r.P, P)
    assert r.weights.tolist() == [omega, 1.0 - omega]
    for K_r, K in zip(r.info["gains"], info["gains"]):
        np.testing.assert_array_equal(K_r, K)
    assert r.info["solver"] == "diagonalise" and r.info["converged"]
    assert kf.x.shape == ((4, 1) if column else (4,))
    # and the numpy path's to rounding
    with cifilter.use_backend("numpy"):
        r0 = fuse([(x1, P1), (x2, P2)], H=[None, H], criterion=_criterion(kind, 4))
    _assert_agree(r0, r, kind)


def test_the_partial_estimate_first_is_the_same_pair():
    rng = np.random.default_rng(2)
    A = rng.standard_normal((3, 3))
    a = (rng.standard_normal(3), A @ A.T + np.eye(3))
    b = (rng.standard_normal(1), np.array([[0.3]]))
    H = np.array([[1.0, -1.0, 0.5]])
    with cifilter.use_backend("numba"):
        first = fuse([a, b], H=[None, H])
        second = fuse([b, a], H=[H, None])
    np.testing.assert_array_equal(first.x, second.x)
    np.testing.assert_array_equal(first.P, second.P)
    assert first.weights.tolist() == second.weights[::-1].tolist()
    assert [K.shape for K in second.info["gains"]] == [(3, 1), (3, 3)]


# ------------------------------------------------------------------------------ agreement
@settings(max_examples=120)
@given(pairs(), st.sampled_from(KINDS))
def test_kernel_agrees_with_the_numpy_path(problem, kind):
    a, b, H = problem
    kernel = _kernel(a, b, H, kind)
    r0, r1 = _both(a, b, H, kind)
    note(f"kernel decided: {kernel is not None}, numpy path: {r0.info['solver']}")
    if kernel is None:  # the numpy path answers, unchanged
        _assert_same_result(r0, r1)
        return
    assert H.shape[0] <= H.shape[1]
    np.testing.assert_array_equal(r1.x, kernel[0])
    np.testing.assert_array_equal(r1.P, kernel[1])
    if r0.info["solver"] == "diagonalise":
        _assert_agree(r0, r1, kind)
    else:  # (the numpy path did not trust its SVD: its simplex optimum, to its tolerance)
        assert r1.info["converged"] and r0.info["converged"]
        assert abs(r0.weights[0] - r1.weights[0]) <= 1e-6


def test_problems_the_kernel_leaves_to_the_numpy_path():
    """m > n (the numpy path's QR route) and a diagonalisation that is not trusted (the
    factor's squared diagonal spread above 1e6): None, and fuse answers as numpy."""
    rng = np.random.default_rng(5)
    a = (np.zeros(2), np.eye(2))
    b = (np.zeros(3), np.eye(3))
    H = rng.standard_normal((3, 2))
    assert _kernel(a, b, H, "trace") is None
    _assert_same_result(*_both(a, b, H, "trace"))
    graded = (np.zeros(2), np.diag([1.0, 1e-8]))
    H = np.array([[1.0, 1.0]])
    assert _kernel(graded, (np.zeros(1), np.eye(1)), H, "trace") is None
    _assert_same_result(*_both(graded, (np.zeros(1), np.eye(1)), H, "trace"))


# -------------------------------------------------------------------------- hand-derived
def test_kernel_hand_derived_trace_optimum_with_a_direction_beyond_the_rank():
    """P_a = diag(1, 1, 9), the fix measures the first two states with P_b = diag(1/4, 4).
    In the full state's coordinates mu = (4, 1/4, 0) with c = (1, 1, 9), so
    tr P(w) = 1/(4 - 3w) + 4/(1 + 3w) + 9/w, f'(w) = 3/(4-3w)^2 - 12/(1+3w)^2 - 9/w^2 < 0 on
    (0, 1]: w = 1 and P = P_a, K_b = 0 (the fix cannot pay for the third state's 9 / w)."""
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pair = [(np.zeros(3), np.diag([1.0, 1.0, 9.0])), (np.ones(2), np.diag([0.25, 4.0]))]
    x, P, omega, info = _kernel(pair[0], pair[1], H, "trace")
    assert omega == 1.0 and float(info["gap"]) == 0.0 and info["converged"]
    np.testing.assert_array_equal(P, np.diag([1.0, 1.0, 9.0]))
    np.testing.assert_array_equal(info["gains"][1], np.zeros((3, 2)))
    np.testing.assert_array_equal(x, np.zeros(3))
    assert float(info["value"]) == 11.0


def test_kernel_hand_derived_det_optimum_with_a_direction_beyond_the_rank():
    """P_a = diag(4, 1), the fix measures the first state with variance 1 (mu = 4, and
    mu = 0 beyond the rank): log det P(w) = -log(4 - 3w) - log(w) + log 4, so
    f'(w) = 3/(4 - 3w) - 1/w = 0 at w = 2/3, P = diag(2, 3/2) (as the numpy path's
    test_det_optimal_weight_of_a_position_fix_by_hand)."""
    H = np.array([[1.0, 0.0]])
    x, P, omega, info = _kernel((np.array([0.0, 1.0]), np.diag([4.0, 1.0])),
                                (np.array([3.0]), np.eye(1)), H, "det")
    assert omega == pytest.approx(2.0 / 3.0, abs=4 * EPS)
    np.testing.assert_allclose(P, np.diag([2.0, 1.5]), rtol=8 * EPS, atol=8 * EPS)
    np.testing.assert_allclose(info["gains"][1], [[2.0 / 3.0], [0.0]], rtol=0, atol=8 * EPS)
    np.testing.assert_allclose(x, [2.0, 1.0], rtol=0, atol=8 * EPS)
    assert float(info["log_value"]) == pytest.approx(np.log(3.0), rel=8 * EPS)


# ---------------------------------------------------------------------- the exact bound
@settings(max_examples=60)
@given(pairs(ratios=(1e-2, 1e2)), st.sampled_from(KINDS))
def test_kernel_result_is_a_bound_in_the_exact_worst_direction(problem, kind):
    """The kernel's P dominates the worst-case error covariance of its own gains over every
    correlation (50 digits, from the inputs), it is the bound of those gains (eq. (H4)),
    and the gains are unbiased: K_a + K_b H = I."""
    a, b, H = problem
    kernel = _kernel(a, b, H, kind)
    note(f"kernel decided: {kernel is not None}")
    if kernel is None:
        return
    x, P, omega, info = kernel
    n = H.shape[1]
    assert np.all(np.isfinite(P))
    np.testing.assert_array_equal(P, P.T)
    np.linalg.cholesky(P)
    Ka, Kb = info["gains"]
    Ps = [a[1], b[1]]
    cond = max(np.linalg.cond(a[1]), np.linalg.cond(b[1]))
    K_pad, P_pad = padded([Ka, Kb], Ps)
    assert_bound_holds(P, K_pad, P_pad, tol=(64.0 * n * 2 + cond) * EPS)
    weights = (omega, 1.0 - omega)
    difference = gain_bound_difference(P, [Ka, Kb], Ps, weights)
    # (P is formed from K_i L_i: its rounding is that of the terms' scale
    # ||K_i||^2 ||P_i|| / w_i, which exceeds ||P|| where the gains amplify)
    terms = sum(np.linalg.norm(K, 2) ** 2 * np.linalg.norm(Pi, 2) / w
                for K, Pi, w in zip((Ka, Kb), Ps, weights) if w > 0.0)
    assert difference <= 64.0 * n * EPS * terms
    if omega > 0.0:
        assert np.abs(Ka + Kb @ H - np.eye(n)).max() <= 1e3 * EPS * (1 + np.abs(Kb @ H).max())
        np.testing.assert_allclose(x, a[0] + Kb @ (b[0] - H @ a[0]), rtol=1e-12,
                                   atol=1e-12 * np.abs(x).max())


# ------------------------------------------- the route from the raw arrays (kf.fuse(H=))
def _route(pairs, H, **options):
    """The ``"ci"`` record's short route with ``H=`` (``rules/ci.py`` checks the options,
    ``partial_pair_route`` the rest)."""
    with cifilter.use_backend("numba"):
        return get_method("ci").pair(pairs, options, tuple(H))


@settings(max_examples=80)
@given(pairs(), st.sampled_from(KINDS), st.booleans(), st.booleans())
def test_route_from_raw_arrays_equals_the_usual_route(problem, kind, swap, column):
    """The route factors the raw covariances by LAPACK as the validation does and the
    kernel checks the rest; where it answers, its result is the usual route's (validation,
    then the kernel) bit for bit, with the same info, the weights in the given order and
    the first estimate's vector style."""
    a, b, H = problem
    n = H.shape[1]
    if column:
        a = (a[0][:, None], a[1])
    given_pairs, Hs = ([b, a], [H, None]) if swap else ([a, b], [None, H])
    crit = _criterion(kind, n)
    r = _route(given_pairs, Hs, criterion=crit)
    with cifilter.use_backend("numba"):
        usual = fuse(given_pairs, H=Hs, criterion=crit)
    note(f"route answered: {r is not None}")
    if r is None:
        return
    assert r.x.shape == usual.x.shape == ((n, 1) if column and not swap else (n,))
    _assert_same_result(r, usual)
    assert list(r.info.keys()) == list(usual.info.keys())
    for key in ("iterations", "converged", "gap", "solver", "value", "criterion", "rule"):
        assert r.info[key] == usual.info[key]
    for K_r, K in zip(r.info["gains"], usual.info["gains"]):
        np.testing.assert_array_equal(K_r, K)
        assert not K_r.flags.writeable


@pytest.mark.parametrize("spoil", ["x nan", "P nan above", "P inf", "P huge", "P asymmetric",
                                   "P not positive definite"])
@pytest.mark.parametrize("which", [0, 1])
def test_route_leaves_every_bad_estimate_to_the_validation(spoil, which):
    """A bad estimate is never answered by the route (the usual route then raises the
    validation's error: tests/test_alignment.py), nor one asymmetric within the tolerance
    (the validation symmetrises it)."""
    rng = np.random.default_rng(11)
    A, B = rng.standard_normal((3, 3)), rng.standard_normal((2, 2))
    good = [[rng.standard_normal(3), A @ A.T + np.eye(3)],
            [rng.standard_normal(2), B @ B.T + np.eye(2)]]
    H = rng.standard_normal((2, 3))
    assert _route([tuple(p) for p in good], [None, H]) is not None
    x, P = good[which][0].copy(), good[which][1].copy()
    if spoil == "x nan":
        x[0] = np.nan
    elif spoil == "P nan above":
        P[0, 1] = np.nan
    elif spoil == "P inf":
        P[1, 1] = np.inf
    elif spoil == "P huge":
        P[0, 0] = 2.0**1023
    elif spoil == "P asymmetric":
        P[0, 1] += 1e-7 * P[0, 0]
    else:
        P[1, 1] = -P[1, 1]
    pairs_ = [tuple(p) for p in good]
    pairs_[which] = (x, P)
    assert _route(pairs_, [None, H]) is None
    if spoil != "P huge":  # (entries of 2**1023 and more: the validation decides)
        with pytest.raises((ValueError, TypeError)):
            fuse(pairs_, H=[None, H])
    if spoil == "P asymmetric":  # within the tolerance: left to the validation, which
        P[0, 1] = P[1, 0] + 1e-10 * P[0, 0]  # takes its symmetric part
        pairs_[which] = (x, P)
        copies = [(xi.copy(), Pi.copy()) for xi, Pi in pairs_]
        assert _route(pairs_, [None, H]) is None
        symmetric = list(pairs_)
        symmetric[which] = (x, 0.5 * (P + P.T))
        with cifilter.use_backend("numba"):
            np.testing.assert_array_equal(fuse(pairs_, H=[None, H]).P,
                                          _route(symmetric, [None, H]).P)
        for (xi, Pi), (x0, P0) in zip(pairs_, copies):  # (not modified)
            np.testing.assert_array_equal(xi, x0)
            np.testing.assert_array_equal(Pi, P0)


def test_route_declines_what_it_does_not_handle():
    rng = np.random.default_rng(4)
    A = rng.standard_normal((3, 3))
    a = (rng.standard_normal(3), A @ A.T + np.eye(3))
    b = (rng.standard_normal(2), np.eye(2))
    H = rng.standard_normal((2, 3))
    assert _route([a, b], [None, H]) is not None
    assert _route([a, b], [None, H], omega=[0.5, 0.5]) is None  # (given weights)
    assert _route([a, b], [H.T @ H, H]) is None  # (no full-state estimate)
    assert _route([a, (np.zeros(4), np.eye(4))], [None, rng.standard_normal((4, 3))]) is None
    assert _route([a, (b[0].astype(np.float32), b[1])], [None, H]) is None
    assert _route([a, ([0.0, 0.0], b[1])], [None, H]) is None  # (not an array)
    assert _route([a, b], [None, H], criterion="volume") is None  # (the usual route raises)
    with cifilter.use_backend("numpy"):
        from cifilter.rules._generalised_ci import partial_pair_route

        assert partial_pair_route([a, b], (None, H), "trace") is None


def test_one_compiled_signature_for_every_layout():
    """Fortran-ordered, read-only and column inputs are brought to one layout: the kernel
    is compiled once."""
    from cifilter._kernels.generalised import generalised_pair

    rng = np.random.default_rng(9)
    A = rng.standard_normal((4, 4))
    P1 = A @ A.T + np.eye(4)
    H = rng.standard_normal((2, 4))
    read_only = np.eye(2)
    read_only.setflags(write=False)
    for pairs_ in ([(np.zeros(4), P1), (np.ones(2), np.eye(2))],
                   [(np.zeros((4, 1)), np.asfortranarray(P1)), (np.ones(2), read_only)]):
        assert _route(pairs_, [None, np.asfortranarray(H)]) is not None
        with cifilter.use_backend("numba"):
            fuse(pairs_, H=[None, H], criterion="det")
    assert len(generalised_pair.signatures) == 1


def test_auto_runs_the_kernel_only_once_it_is_compiled_with_the_others():
    """Under "auto" a single H= call never starts or waits for a compile: the kernel runs
    only when the background compilation includes it and the kernels are there; otherwise
    the numpy path answers (bit for bit the numpy backend's result)."""
    from cifilter._kernels import background

    rng = np.random.default_rng(8)
    A = rng.standard_normal((4, 4))
    pair = [(rng.standard_normal(4), A @ A.T + np.eye(4)), (rng.standard_normal(2), np.eye(2))]
    H = [None, rng.standard_normal((2, 4))]
    with cifilter.use_backend("auto"):
        auto = fuse(pair, H=H)
    with cifilter.use_backend("numpy"):
        numpy_result = fuse(pair, H=H)
    with cifilter.use_backend("numba"):
        compiled = fuse(pair, H=H)
    assert not np.array_equal(numpy_result.P, compiled.P)  # (the two paths round apart)
    ready = "generalised_pair" in background.KERNELS and background.status()["ready"]
    _assert_same_result(auto, compiled if ready else numpy_result)
