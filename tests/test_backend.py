"""The backend switch (cifilter.backend) and the compiled kernels against the numpy path.

The CI-family tests (test_ci.py, test_optimal.py, the CI tests of test_conditioning.py)
run on both backends through the ``ci_backend`` fixture; here: the contract of
``set_backend``/``get_backend``/``backend``, the agreement of the two backends on batches
of the conditioning strategies (condition numbers up to 1e12, scales 1e-12..1e12), the
hand-back of items the kernels cannot certify, errors, and a cifilter without numba.
"""

import subprocess
import sys
import threading

import mpmath as mp
import numpy as np
import pytest
from helpers import fused_bound_tolerance
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets, ill_conditioned_spd
from worst_case import assert_bound_holds

import cifilter
from cifilter import IllConditionedError, covariance_intersection, naive_fusion
from cifilter._kernels.dispatch import THREADED_MIN
from cifilter._numerics.information import reference_estimates
from cifilter.backend import AUTO_MIN_BATCH, BACKENDS, numba_available

needs_numba = pytest.mark.skipif(not numba_available(), reason="numba is not installed")


# ----------------------------------------------------------------- the switch
def test_default_is_auto_and_set_backend_returns_the_previous():
    assert cifilter.get_backend() == "auto"
    previous = cifilter.set_backend("numpy")
    try:
        assert previous == "auto" and cifilter.get_backend() == "numpy"
    finally:
        assert cifilter.set_backend(previous) == "numpy"
    assert cifilter.get_backend() == "auto"


@pytest.mark.parametrize("name", ["NUMPY", "cuda", "", None, 1, "numpy "])
def test_unknown_backends_are_rejected(name):
    with pytest.raises(ValueError, match="backend must be one of 'auto', 'numpy', 'numba'"):
        cifilter.set_backend(name)
    with pytest.raises(ValueError, match="backend must be one of"):
        with cifilter.use_backend(name):
            pass
    assert cifilter.get_backend() == "auto"


def test_context_manager_nests_restores_on_error_and_is_thread_local():
    seen = []
    with cifilter.use_backend("numpy"):
        assert cifilter.get_backend() == "numpy"
        with pytest.raises(RuntimeError), cifilter.use_backend("auto"):
            assert cifilter.get_backend() == "auto"
            raise RuntimeError
        assert cifilter.get_backend() == "numpy"
        thread = threading.Thread(target=lambda: seen.append(cifilter.get_backend()))
        thread.start()
        thread.join()
    assert cifilter.get_backend() == "auto" and seen == ["auto"]
    assert set(BACKENDS) == {"auto", "numpy", "numba"}


def test_importing_cifilter_imports_no_numba():
    code = "import sys, cifilter; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"


def test_cifilter_works_without_numba():
    """numba blocked: the package imports, auto and numpy run, 'numba' is refused."""
    code = """
import sys
sys.modules["numba"] = None  # import numba raises ImportError
import numpy as np
import cifilter
from cifilter.backend import numba_available
assert not numba_available()
rng = np.random.default_rng(0)
A = rng.standard_normal((200, 2, 3, 3))
Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
xs = rng.standard_normal((200, 2, 3))
r = cifilter.covariance_intersection(xs, Ps)
assert r.info["converged"].all() and r.P.shape == (200, 3, 3)
cifilter.covariance_intersection(xs, Ps, omega="fast")
cifilter.naive_fusion(xs, Ps)
try:
    cifilter.set_backend("numba")
except ValueError as error:
    assert "numba" in str(error)
else:
    raise AssertionError("set_backend('numba') accepted without numba")
assert "numba" not in [m for m in sys.modules if sys.modules[m] is not None]
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


# ----------------------------------------------------------------- agreement
def _run(backend, call):
    with cifilter.use_backend(backend):
        return call()


def _assert_same(a, b, rtol=1e-9):
    """Two FusionResults equal to ``rtol``: omega (on the simplex, so absolutely), x and P
    relative to the size of P, per item; the same info keys and flags."""
    np.testing.assert_allclose(a.omega, b.omega, rtol=0, atol=rtol)
    scale = np.abs(b.P).max(axis=(-2, -1))
    np.testing.assert_array_less(np.abs(a.P - b.P).max(axis=(-2, -1)), rtol * scale * (1 + 1e-12))
    sd = np.sqrt(scale)
    np.testing.assert_array_less(np.abs(a.x - b.x).max(axis=-1), rtol * sd * 1e3 + 1e-300)
    np.testing.assert_allclose(a.gains.sum(axis=-3), np.broadcast_to(np.eye(a.P.shape[-1]),
                                                                       a.P.shape), atol=1e-6)
    assert a.info.keys() == b.info.keys()
    for key in ("converged", "solver", "rule", "criterion"):
        if key in b.info:
            np.testing.assert_array_equal(a.info[key], b.info[key])
    if "log_value" in b.info:
        # log det P moves by at most n ||P^-1 (P_a - P_b)||_2 under the difference of P
        # (which is ill-conditioned: cond(P) times the relative difference); and each
        # backend takes it from its own Cholesky factor of P (LAPACK's, the kernel's loop),
        # whose backward error, (n + 1) eps relative to the diagonal, moves log det by up to
        # n (n + 1) eps kappa_s(P) <= n^2 (n + 1) eps cond(P) each
        n = b.P.shape[-1]
        shift = np.linalg.norm(np.linalg.solve(b.P, a.P - b.P), ord=2, axis=(-2, -1))
        factors = 2.0 * n**2 * (n + 1) * np.finfo(float).eps * np.linalg.cond(b.P)
        bound = n * shift * (1 + 1e-6) + 1e-12 + factors
        assert np.all(np.abs(a.info["log_value"] - b.info["log_value"]) <= bound)
    elif "value" in b.info:
        np.testing.assert_allclose(a.info["value"], b.info["value"], rtol=rtol)
    np.testing.assert_array_equal(a.P, np.swapaxes(a.P, -1, -2))


@st.composite
def batches(draw, count, n, size):
    """A batch of ``size`` problems: ill-conditioned sets (up to 1e12, common scales in
    1e-12..1e12) and well-conditioned ones (the kernels' own territory), means of the
    covariances' scale."""
    Ps = []
    for _ in range(size):
        if draw(st.booleans()):
            Ps.append(np.stack(draw(ill_conditioned_sets(count, n))))
        else:
            Ps.append(np.stack(draw(ill_conditioned_sets(count, n, max_condition=1e3))))
    Ps = np.stack(Ps)
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    scale = np.sqrt(np.abs(np.diagonal(Ps, axis1=-2, axis2=-1)))
    return rng.standard_normal(Ps.shape[:-1]) * scale, Ps


criteria = st.sampled_from(["trace", "det", "weighted"])


def _criterion(name, n):
    return np.diag(np.arange(1.0, n + 1)) if name == "weighted" else name


@needs_numba
@settings(max_examples=25)
@given(st.integers(1, 5).flatmap(lambda n: batches(2, n, 6)), criteria)
def test_two_estimate_optimal_ci_agrees_with_numpy(batch, criterion):
    xs, Ps = batch
    criterion = _criterion(criterion, xs.shape[-1])
    a = _run("numba", lambda: covariance_intersection(xs, Ps, criterion))
    b = _run("numpy", lambda: covariance_intersection(xs, Ps, criterion))
    _assert_same(a, b)
    assert a.info["solver"] == "diagonalise"
    assert_bound_holds(a.P[0], a.gains[0], list(Ps[0]), tol=fused_bound_tolerance(Ps[0]))


@needs_numba
@settings(max_examples=15)
@given(st.integers(2, 4).flatmap(lambda count: st.integers(1, 4).flatmap(
    lambda n: batches(count, n, 5))), st.sampled_from(["fast", "improved-fast", "det-ratio",
                                                       "fixed", "optimal"]), criteria)
def test_weights_rules_and_naive_fusion_agree_with_numpy(batch, rule, criterion):
    xs, Ps = batch
    criterion = _criterion(criterion, xs.shape[-1])
    count = Ps.shape[-3]
    omega = {"optimal": None, "fixed": np.full(count, 1.0 / count)}.get(rule, rule)

    def ci():
        return covariance_intersection(xs, Ps, criterion, omega)

    _assert_same(_run("numba", ci), _run("numpy", ci))
    try:
        b = _run("numpy", lambda: naive_fusion(xs, Ps))
    except IllConditionedError as error:  # beyond the contract: both raise alike
        with pytest.raises(IllConditionedError) as raised:
            _run("numba", lambda: naive_fusion(xs, Ps))
        assert str(raised.value) == str(error)
        return
    a = _run("numba", lambda: naive_fusion(xs, Ps))
    scale = np.abs(b.P).max(axis=(-2, -1))
    np.testing.assert_array_less(np.abs(a.P - b.P).max(axis=(-2, -1)), 1e-9 * scale)


@needs_numba
@pytest.mark.parametrize("size", [AUTO_MIN_BATCH, THREADED_MIN + 3])
def test_batches_go_to_the_kernels_under_auto_and_agree(size):
    """Batches above the threshold of auto, on the serial and the threaded kernels."""
    rng = np.random.default_rng(5)
    A = rng.standard_normal((size, 2, 4, 4))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
    xs = rng.standard_normal((size, 2, 4))
    for criterion in ("trace", "det"):
        a = covariance_intersection(xs, Ps, criterion)
        b = _run("numpy", lambda criterion=criterion: covariance_intersection(xs, Ps, criterion))
        _assert_same(a, b, rtol=1e-10)
        np.testing.assert_array_equal(a.info["iterations"], b.info["iterations"])
        assert a.info["converged"].all()
    a = covariance_intersection(xs, Ps, omega="fast")
    _assert_same(a, _run("numpy", lambda: covariance_intersection(xs, Ps, omega="fast")))


@needs_numba
def test_items_the_kernel_cannot_certify_are_solved_by_numpy():
    """Condition 1e10 pairs (not trusted by the diagonalisation) amid ordinary ones: the
    whole batch equals the numpy path, including the re-solved items."""
    rng = np.random.default_rng(11)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    bad = Q @ np.diag([1.0, 1e-5, 1e-10]) @ Q.T
    bad = 0.5 * (bad + bad.T)
    A = rng.standard_normal((8, 2, 3, 3))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    Ps[[1, 5], 0] = bad
    xs = rng.standard_normal((8, 2, 3))
    for criterion in ("trace", "det"):
        a = _run("numba", lambda criterion=criterion: covariance_intersection(xs, Ps, criterion))
        b = _run("numpy", lambda criterion=criterion: covariance_intersection(xs, Ps, criterion))
        _assert_same(a, b)
        np.testing.assert_array_equal(a.info["iterations"], b.info["iterations"])
        for k in (1, 5):
            assert_bound_holds(a.P[k], a.gains[k], list(Ps[k]))


@needs_numba
def test_errors_are_those_of_the_numpy_path():
    """Validation stays at the front door; a kernel that meets a numerically singular
    fused information hands the item back, and the numpy path raises its own error."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((100, 2, 2, 2))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(2)
    xs = np.zeros((100, 2, 2))
    Ps_bad = Ps.copy()
    Ps_bad[7] = np.diag([1.0, 1e-30])
    calls = [
        (IllConditionedError, lambda: covariance_intersection(xs, Ps_bad, omega=0.5)),
        (IllConditionedError, lambda: naive_fusion(xs, Ps_bad)),
        (ValueError, lambda: covariance_intersection(xs, Ps, omega=1.5)),
        (ValueError, lambda: covariance_intersection(xs, Ps, criterion="volume")),
        (ValueError, lambda: covariance_intersection(xs[:, :, :1], Ps)),
    ]
    for kind, call in calls:
        messages = []
        for backend in ("numpy", "numba"):
            with cifilter.use_backend(backend), pytest.raises(kind) as raised:
                call()
            messages.append(str(raised.value))
        assert messages[0] == messages[1]


@needs_numba
def test_inputs_are_not_modified():
    rng = np.random.default_rng(2)
    A = rng.standard_normal((100, 2, 3, 3))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    xs = rng.standard_normal((100, 2, 3))
    copies = xs.copy(), Ps.copy()
    a = covariance_intersection(xs, Ps)
    np.testing.assert_array_equal(xs, copies[0])
    np.testing.assert_array_equal(Ps, copies[1])
    assert a.P.dtype == np.float64 and a.info["converged"].all()


# ----------------------------------------------------------------- agreement at kappa 1e12
_EPS = np.finfo(float).eps


def _exact_fused_condition(Ps, weights):
    """cond_2 of the exact fused information ``sum_i w_i P_i^-1`` (= cond_2 of the exact
    fused covariance), from the inputs in 40-digit arithmetic."""
    with mp.workdps(40):
        J = None
        for P, w in zip(Ps, weights):
            if w > 0.0:
                term = mp.matrix(np.asarray(P).tolist()) ** -1 * mp.mpf(float(w))
                J = term if J is None else J + term
        values = [abs(v) for v in mp.eigsy(0.5 * (J + J.T), eigvals_only=True)]
        return float(max(values) / min(values))


def _assert_within_the_agreement_bound(a, b, xs, Ps, weights):
    """docs/backend.rst, at the same weights: ``||P_numba - P_numpy||_2 <= 4 n eps kappa
    ||P||_2`` with ``kappa = cond(J) + max_i cond(L_i)``, J the exact fused information
    (from the inputs in 40 digits) and L_i the inputs' Cholesky factors (whose triangular
    inverses the two backends compute differently), and the means within
    ``4 eps kappa sum_i w_i ||P|| ||P_i^-1|| ||x_i - x_r||`` (x_r the reference)."""
    n = Ps.shape[-1]
    kappa = (_exact_fused_condition(Ps, weights)
             + float(np.sqrt(np.linalg.cond(Ps).max())))
    norm = np.linalg.norm(b.P, 2)
    assert np.linalg.norm(a.P - b.P, 2) <= 4.0 * n * _EPS * kappa * norm, (
        np.linalg.norm(a.P - b.P, 2) / (n * _EPS * kappa * norm))
    reference = int(reference_estimates(weights, np.linalg.cholesky(Ps)))
    spread = np.linalg.norm(xs - xs[reference], axis=-1)
    inverse_norms = 1.0 / np.linalg.eigvalsh(Ps)[:, 0]
    beta = kappa * float((weights * norm * inverse_norms * spread).sum())
    assert np.linalg.norm(a.x - b.x) <= 4.0 * _EPS * beta + 1e-300


@needs_numba
@settings(max_examples=20)
@given(st.integers(2, 3).flatmap(lambda count: st.integers(2, 4).flatmap(
    lambda n: st.booleans().flatmap(lambda common: st.lists(
        ill_conditioned_sets(count, n, common_scale=common), min_size=3, max_size=3)))),
    st.sampled_from(["fixed", "fast", "optimal", "naive"]), st.integers(0, 2**32 - 1))
def test_backends_agree_to_the_documented_bound_at_condition_1e12(sets, rule, seed):
    """Pairs and N = 3 at condition numbers up to 1e12, each covariance at the set's common
    scale or at its own (mixed scales, where before the two backends differed by up to 4.7
    relative): given, fast and naive weights to the bound of docs/backend.rst; optimal
    weights (whose omega may differ by rounding) to the 1e-9 contract."""
    Ps = np.stack([np.stack(s) for s in sets])
    size, count = Ps.shape[0], Ps.shape[1]
    rng = np.random.default_rng(seed)
    xs = rng.standard_normal(Ps.shape[:-1]) * np.sqrt(np.diagonal(Ps, axis1=-2, axis2=-1))
    omega = {"optimal": None, "fixed": np.full(count, 1.0 / count)}.get(rule, rule)

    def call():
        if rule == "naive":
            return naive_fusion(xs, Ps)
        return covariance_intersection(xs, Ps, "trace", omega)

    try:
        b = _run("numpy", call)
    except IllConditionedError as error:  # beyond the contract: both raise alike
        with pytest.raises(IllConditionedError) as raised:
            _run("numba", call)
        assert str(raised.value) == str(error)
        return
    a = _run("numba", call)
    if rule == "optimal":  # the weights themselves may differ (to 1e-9): that contract
        _assert_same(a, b)
        return
    for i in range(size):
        w = np.ones(count) if rule == "naive" else b.omega[i]
        if rule != "naive":
            np.testing.assert_array_equal(a.omega[i], w)  # numpy computes them for both
        _assert_within_the_agreement_bound(_Item(a, i), _Item(b, i), xs[i], Ps[i], w)


class _Item:
    """Problem ``i`` of a batched FusionResult (x and P)."""

    def __init__(self, result, i):
        self.x, self.P = result.x[i], result.P[i]


@needs_numba
@settings(max_examples=30)
@given(st.integers(2, 4).flatmap(lambda n: ill_conditioned_spd(n, max_condition=1e9)),
       st.sampled_from(["det", "trace"]), st.sampled_from([0, 1, 12]))
def test_a_tied_pair_gets_the_same_weight_on_both_backends(P, criterion, others):
    """P_1 = P_2: every omega is optimal, the end slopes are rounding noise whose sign
    differs between the kernel's Jacobi eigenvalues and LAPACK's (and between LAPACK's
    routes for small and large batches); a tie to rounding gets omega = 1/2 on the numpy
    path, and the kernel hands ties to it, so both backends agree, alone (no batch axes),
    in a batch of one and amid ``others`` ordinary problems (before: 0 on one backend, 1 or
    1/2 on the other for 173 of 3 000 such checks, docs/backend.rst)."""
    n = P.shape[0]
    tied = np.stack([P, P.copy()])
    rng = np.random.default_rng(others)
    A = rng.standard_normal((others, 2, n, n))
    ordinary = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    for Ps in (tied, tied[None], np.concatenate([ordinary, tied[None]])):
        xs = np.zeros(Ps.shape[:-1])
        a = _run("numba", lambda xs=xs, Ps=Ps: covariance_intersection(xs, Ps, criterion))
        b = _run("numpy", lambda xs=xs, Ps=Ps: covariance_intersection(xs, Ps, criterion))
        for r in (a, b):  # the tied problem (the last): exactly 1/2, converged
            assert np.reshape(r.omega, (-1, 2))[-1, 0] == 0.5
            assert np.reshape(r.info["converged"], -1)[-1]
        np.testing.assert_allclose(a.omega, b.omega, rtol=0, atol=1e-9)  # the others
        np.testing.assert_array_equal(a.info["converged"], b.info["converged"])


# Two covariances (condition numbers 1e5 and 4e5) for which the backends broke the tie
# P_1 = P_2 differently under det: omega 1 (numba) against 1/2 and 0 (numpy).
_TIED = [
    [[2166.435495216351, 8150.639721138385, 9393.914671758583],
     [8150.639721138385, 30861.71651617992, 35861.083266424284],
     [9393.914671758583, 35861.083266424284, 42129.84967459925]],
    [[8735.429225295265, 26143.487460834353, 12314.933413289044, -21188.143001050754],
     [26143.487460834353, 78512.20733799967, 36965.77357861948, -63639.42687636755],
     [12314.933413289044, 36965.77357861948, 17885.05535649808, -29008.71796507066],
     [-21188.143001050754, -63639.42687636755, -29008.71796507066, 53485.46408877517]],
]


@needs_numba
@pytest.mark.parametrize("P", _TIED)
def test_ties_the_backends_broke_differently(P):
    """Found by checking 800 tied pairs (condition numbers 1e2..1e9): 38 got different
    weights on the two backends before, none now."""
    Ps = np.array([P, P])[None]
    xs = np.zeros(Ps.shape[:-1])
    a = _run("numba", lambda: covariance_intersection(xs, Ps, "det"))
    b = _run("numpy", lambda: covariance_intersection(xs, Ps, "det"))
    np.testing.assert_array_equal(a.omega, b.omega)
    np.testing.assert_array_equal(a.omega, [[0.5, 0.5]])
    assert a.info["converged"].all() and b.info["converged"].all()


# Four 2x2 covariances of very different scales (condition numbers up to 1e12), the least
# precise first: with equal weights it was the reference estimate of both paths.
_MIXED_SCALES = [
    [[3.534989066812879e+17, -1.466940241298153e+17],
     [-1.466940241298153e+17, 6.0874691007098456e+16]],
    [[22787.418529964, 247003.9399814629], [247003.9399814629, 2677396.1382870832]],
    [[0.0028267688316305248, -520.0249384390224], [-520.0249384390224, 706692207.9076312]],
    [[45.46778626352984, 1095160.0391677758], [1095160.0391677758, 11366946565882.459]],
]


@needs_numba
def test_estimates_of_very_different_scales_agree_to_the_documented_bound():
    """With equal weights the estimate of largest weight (the old reference, whose gain is
    I minus the others) was the least precise one: the backends were 7e-6 apart relative,
    against a bound of 2e-10 (kappa of the fused information 1e5). The reference is now
    the most precise weighted estimate on both paths."""
    Ps = np.array(_MIXED_SCALES)
    xs = np.zeros((4, 2))
    calls = [(np.full(4, 0.25), lambda: covariance_intersection(xs, Ps, omega=np.full(4, 0.25))),
             (np.ones(4), lambda: naive_fusion(xs, Ps))]
    for weights, call in calls:
        a, b = _run("numba", call), _run("numpy", call)
        _assert_within_the_agreement_bound(a, b, xs, Ps, weights)


# ----------------------------------------------------------------- N >= 3 compiled
@needs_numba
@settings(max_examples=25)
@given(st.integers(3, 5).flatmap(lambda count: st.integers(1, 4).flatmap(
    lambda n: st.booleans().flatmap(lambda common: st.tuples(
        batches(count, n, 6), st.just(common))))), criteria)
def test_many_estimate_optimal_ci_agrees_with_numpy(drawn, criterion):
    """N = 3 to 5 at condition numbers up to 1e12 (and well-conditioned sets, which the
    kernel solves itself): the compiled solver and the numpy path give the same weights to
    1e-9 and P to 1e-9 relative, the same flags; every compiled result dominates the error
    covariance of its gains in the exact worst direction (50 digits)."""
    (xs, Ps), _ = drawn
    criterion = _criterion(criterion, xs.shape[-1])
    try:
        b = _run("numpy", lambda: covariance_intersection(xs, Ps, criterion))
    except IllConditionedError as error:  # beyond the contract: both raise alike
        with pytest.raises(IllConditionedError) as raised:
            _run("numba", lambda: covariance_intersection(xs, Ps, criterion))
        assert str(raised.value) == str(error)
        return
    a = _run("numba", lambda: covariance_intersection(xs, Ps, criterion))
    _assert_same(a, b)
    assert a.info["solver"] == "simplex"
    for i in range(Ps.shape[0]):
        assert_bound_holds(a.P[i], a.gains[i], list(Ps[i]), tol=fused_bound_tolerance(Ps[i]))


def _well_conditioned(size, count, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((size, count, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    return rng.standard_normal((size, count, n)), Ps


def _refuse(sub, sub_W):
    raise AssertionError(f"{sub.x.shape[0]} items handed back to numpy")


@needs_numba
@pytest.mark.parametrize("count", [3, 4, 7, 11])
@pytest.mark.parametrize("criterion", ["trace", "det", "weighted"])
def test_the_kernel_solves_well_conditioned_sets_of_three_and_more(count, criterion):
    """Ordinary sets of 3 to 11 estimates are solved and certified by the compiled solver
    itself (nothing is handed back to numpy), with the numpy path's certificate semantics:
    every item converged, the same weights, P, gap flags and a gap within the tolerance."""
    from cifilter._kernels import dispatch
    from cifilter._numerics.criteria import GAP_TOL, parse_criterion
    from cifilter._numerics.validation import as_estimates

    xs, Ps = _well_conditioned(40, count, 3, count)
    kind, W = parse_criterion(_criterion(criterion, 3), 3)
    est = as_estimates(xs, Ps)
    with cifilter.use_backend("numba"):
        weights, info, (x, P, gains), report = dispatch.optimal_many(est, kind, W, _refuse)
    b = _run("numpy", lambda: covariance_intersection(xs, Ps, _criterion(criterion, 3)))
    np.testing.assert_allclose(weights, b.omega, rtol=0, atol=1e-10)
    np.testing.assert_allclose(P, b.P, rtol=1e-10, atol=0)
    np.testing.assert_allclose(x, b.x, rtol=0, atol=1e-9 * np.abs(b.x).max())
    np.testing.assert_allclose(gains.sum(axis=-3), np.broadcast_to(np.eye(3), P.shape),
                               atol=1e-12)
    assert info["converged"].all() and (info["gap"] <= GAP_TOL).all()
    assert (weights >= 0).all() and np.allclose(weights.sum(axis=-1), 1.0, rtol=0, atol=1e-15)
    assert (weights == 0.0).any()  # optima on faces are exact zeros, as numpy's
    np.testing.assert_allclose(report["value"], b.info["value"], rtol=1e-10)


@needs_numba
def test_many_estimates_beyond_the_active_set_range_stay_on_numpy():
    """12 estimates and more: numpy's interior-point phase leads, the kernel is not used."""
    from cifilter._kernels import dispatch
    from cifilter._numerics.validation import as_estimates

    xs, Ps = _well_conditioned(10, 12, 2, 0)
    with cifilter.use_backend("numba"):
        assert dispatch.optimal_many(as_estimates(xs, Ps), "trace", None, _refuse) is None


@needs_numba
def test_sets_the_kernel_cannot_certify_are_solved_by_numpy():
    """Tied estimates (P_1 = P_2: the reduced Hessian is singular, the weights are not
    determined by the gradients) and a set at condition 1e10 amid ordinary sets: the tie
    is handed back under both criteria, the ill-conditioned set under trace (its
    certificate's rounding term, 7e-5, is far above the tolerance; under det its optimum is
    the vertex of the precise estimate, certified by the kernel as by numpy), and the whole
    batch equals the numpy path."""
    xs, Ps = _well_conditioned(10, 3, 3, 21)
    Ps[2, 1] = Ps[2, 0]
    rng = np.random.default_rng(4)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    Ps[6, 2] = Q @ np.diag([1.0, 1e-5, 1e-10]) @ Q.T
    Ps[6, 2] = 0.5 * (Ps[6, 2] + Ps[6, 2].T)
    from cifilter._kernels import dispatch

    for criterion, handed_back in (("trace", 2), ("det", 1)):
        before = dispatch.report()["handed_back"]
        a = _run("numba", lambda criterion=criterion: covariance_intersection(xs, Ps, criterion))
        assert dispatch.report()["handed_back"] - before == handed_back
        b = _run("numpy", lambda criterion=criterion: covariance_intersection(xs, Ps, criterion))
        _assert_same(a, b)
        for k in (2, 6):
            assert_bound_holds(a.P[k], a.gains[k], list(Ps[k]))


# ----------------------------------------------------------------- threads and dimensions
def _pairs(size, n, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((size, 2, n, n))
    return rng.standard_normal((size, 2, n)), A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)


@needs_numba
def test_auto_sends_problems_above_the_crossover_dimension_to_numpy():
    """Under auto, batches of n <= AUTO_MAX_DIM run on the kernels, larger n on numpy
    (LAPACK wins there, benchmarks/bench_many.py --dims); "numba" still forces the kernels."""
    from cifilter._kernels import dispatch

    def kernel_calls(n, backend):
        xs, Ps = _pairs(AUTO_MIN_BATCH + 1, n)
        before = dispatch.report()["kernels"]
        _run(backend, lambda: covariance_intersection(xs, Ps))
        _run(backend, lambda: covariance_intersection(xs, Ps, omega="fast"))
        return dispatch.report()["kernels"] - before

    assert kernel_calls(dispatch.AUTO_MAX_DIM, "auto") == 2
    assert kernel_calls(dispatch.AUTO_MAX_DIM + 1, "auto") == 0
    assert kernel_calls(dispatch.AUTO_MAX_DIM + 1, "numba") == 2


@needs_numba
@pytest.mark.parametrize("size", [THREADED_MIN + 3, AUTO_MIN_BATCH])
def test_blas_is_pinned_to_one_thread_around_the_threaded_kernels(monkeypatch, size):
    """While a threaded kernel runs (numba with more than one thread), BLAS runs one
    thread, and has its previous count again afterwards; around the serial kernels (small
    batches) BLAS is left alone."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    import numba

    from cifilter._kernels import dispatch

    def blas_threads():
        return [pool["num_threads"] for pool in threadpoolctl.threadpool_info()
                if pool["user_api"] == "blas"]

    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        outside = blas_threads()
        if numba.get_num_threads() < 2 or not outside or max(outside) < 2:
            pytest.skip("needs two numba and two BLAS threads")
        seen = []
        kernel = dispatch._kernel

        def recording(name, n):
            real = kernel(name, n)

            def run(*args):
                seen.append(blas_threads())
                return real(*args)
            return run

        monkeypatch.setattr(dispatch, "_kernel", recording)
        xs, Ps = _pairs(size, 3)
        with cifilter.use_backend("numba"):
            covariance_intersection(xs, Ps)
            covariance_intersection(np.concatenate([xs, xs[:, :1]], axis=1),
                                    np.concatenate([Ps, Ps[:, :1] * 2.0], axis=1))
            naive_fusion(xs, Ps)
        assert len(seen) == 3
        expected = [1] * len(outside) if size >= THREADED_MIN else outside
        assert all(threads == expected for threads in seen), seen
        assert blas_threads() == outside
