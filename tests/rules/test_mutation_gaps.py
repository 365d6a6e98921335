"""Contracts that mutation testing (tools/mutate.py) found untested in the rules.

* The certified gap and ``converged`` are relative: they do not change when every
  covariance is multiplied by the same scale (CI, inverse CI, partial CI; N = 2 and N > 2).
* ``converged`` is checked against a gap recomputed from the *inputs* in 40-digit
  arithmetic (never from the rule's own factors).
* Pairs whose generalised eigenvalues spread between 1e6 and 1e9 (beyond the trust of the
  diagonalised solvers, within the conditioning contract) are solved, certified and bounded.
* Partial CI: ``converged`` is False when the iteration limit stops the Newton solver short;
  bounds below the Newton phase's floor of rho are repaired to the true optimum; the sweeps
  of Algorithm 2 are the paper's (an independent implementation of eqs. (24), (33), (25))
  and never increase the trace (supersedes ``test_pci.py::test_each_iteration_lowers_the_trace``,
  which ran the Newton solver).
* Covariance union of two estimates: the certified gap is a true bound (no other mean gives
  a smaller trace than ``value (1 - gap)``) and is tight (converged on ordinary problems).
"""

import mpmath
import numpy as np
import pytest
from helpers import fused_bound_tolerance
from worst_case import assert_bound_holds

from cifilter import (
    covariance_intersection,
    covariance_union,
    inverse_covariance_intersection,
    partial_ci,
    use_backend,
)

BACKENDS = ["numpy", "numba"]
SCALES = [1e-12, 1e-6, 1e6, 1e8, 1e12]
GAP = 1e-9


def spd(rng, n, cond, scale=1.0):
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    P = Q @ np.diag(scale * np.logspace(0, np.log10(cond), n)) @ Q.T
    return 0.5 * (P + P.T)


def problems(count, n, cond, seeds):
    """Sets of ``count`` covariances with condition numbers ``cond`` and mixed scales."""
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        out.append([spd(rng, n, cond, 10.0 ** rng.uniform(-1, 1)) for _ in range(count)])
    return out


# ------------------------------------------------------------------ high-precision gaps
def _mp(A):
    return mpmath.matrix(np.asarray(A, dtype=float).tolist())


def mp_information_gap(Ps, w, kind, rho=None):
    """Frank-Wolfe gap of ``trace P`` (relative) or ``log det P`` at the weights ``w`` of the
    information fusion ``P^-1 = sum_i a_i P_i^-1``, from the inputs in 40 digits.

    CI: ``a_i = w_i``. Partial CI (``rho``): ``w`` is delta and ``a_i`` is eq. (24).
    """
    with mpmath.workdps(40):
        infos = [mpmath.inverse(_mp(P)) for P in Ps]
        w = [mpmath.mpf(float(v)) for v in w]
        if rho is None:
            a, da = w, [mpmath.mpf(1)] * len(w)
        else:
            r = [mpmath.mpf(float(v)) for v in np.broadcast_to(rho, len(w))]
            a = [wi / (ri + (1 - ri) * wi) for wi, ri in zip(w, r)]
            da = [ri / (ri + (1 - ri) * wi) ** 2 for wi, ri in zip(w, r)]
        J = infos[0] * a[0]
        for k in range(1, len(infos)):
            J += infos[k] * a[k]
        P = mpmath.inverse(J)
        n = P.rows
        if kind == "det":
            g = [sum((P * I)[i, i] for i in range(n)) * d for I, d in zip(infos, da)]
            value = mpmath.mpf(1)
        else:
            g = [sum((P * I * P)[i, i] for i in range(n)) * d for I, d in zip(infos, da)]
            value = sum(P[i, i] for i in range(n))
        gap = (max(g) - sum(wi * gi for wi, gi in zip(w, g))) / value
        return float(gap)


# ------------------------------------------------------------------ scale invariance
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("criterion", ["trace", "det", "weighted"])
def test_two_estimate_ci_gap_and_converged_do_not_depend_on_the_scale(backend, criterion):
    W = np.diag([1.0, 2.0, 3.0])
    crit = W if criterion == "weighted" else criterion
    for Ps in problems(2, 3, 1e3, range(6)):
        xs = [np.zeros(3), np.ones(3)]
        with use_backend(backend):
            base = covariance_intersection(xs, Ps, crit)
            assert base.info["converged"]
            assert base.info["gap"] <= max(GAP, 2 * base.info["gap_floor"])
            for s in SCALES:
                r = covariance_intersection(xs, [s * P for P in Ps], crit)
                assert r.info["converged"], (s, r.info["gap"])
                assert r.info["gap"] <= GAP
                np.testing.assert_allclose(r.omega, base.omega, rtol=1e-6, atol=1e-9)
                np.testing.assert_allclose(r.P / s, base.P, rtol=1e-6)
            # the batched path: every scale at once
            batch = covariance_intersection(
                np.zeros((len(SCALES), 2, 3)), np.stack([[s * P for P in Ps] for s in SCALES]),
                crit)
            assert batch.info["converged"].all(), batch.info["gap"]
            assert (batch.info["gap"] <= GAP).all()
            np.testing.assert_allclose(batch.omega, np.broadcast_to(base.omega, batch.omega.shape),
                                       rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_of_many_estimates_gap_and_converged_do_not_depend_on_the_scale(criterion):
    for Ps in problems(4, 3, 1e3, range(4)):
        xs = np.zeros((4, 3))
        base = covariance_intersection(xs, Ps, criterion)
        assert base.info["converged"]
        for s in SCALES:
            r = covariance_intersection(xs, [s * P for P in Ps], criterion)
            assert r.info["converged"], (s, r.info["gap"])
            assert r.info["gap"] <= GAP
            np.testing.assert_allclose(r.P / s, base.P, rtol=1e-6)


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_inverse_ci_gap_and_converged_do_not_depend_on_the_scale(criterion):
    cases = problems(2, 3, 1e3, range(6)) + problems(2, 3, 1e8, range(6, 10))
    for Ps in cases:
        xs = [np.zeros(3), np.ones(3)]
        base = inverse_covariance_intersection(xs, Ps, criterion)
        assert base.info["converged"] and base.info["gap"] <= max(GAP, 2 * base.info["gap_floor"])
        for s in SCALES:
            r = inverse_covariance_intersection(xs, [s * P for P in Ps], criterion)
            assert r.info["converged"], (s, r.info["gap"])
            assert r.info["gap"] <= max(GAP, 2 * r.info["gap_floor"])
            np.testing.assert_allclose(r.weights, base.weights, rtol=1e-6, atol=1e-9)


def test_partial_ci_gap_and_converged_do_not_depend_on_the_scale():
    for count in (2, 3):
        for Ps in problems(count, 3, 1e3, range(4)):
            xs = np.zeros((count, 3))
            base = partial_ci(xs, Ps, 0.6)
            assert base.info["converged"]
            for s in SCALES:
                r = partial_ci(xs, [s * P for P in Ps], 0.6)
                assert r.info["converged"], (s, r.info["gap"])
                assert r.info["gap"] <= 1e-10
                np.testing.assert_allclose(r.P / s, base.P, rtol=1e-6)


# ------------------------------------------------------------------ converged, checked
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("count", [2, 3, 5])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_converged_means_optimal_in_high_precision(backend, count, criterion):
    """Ordinary problems (condition numbers up to 1e4) converge, and the optimality gap
    recomputed from the inputs in 40 digits is within the tolerance."""
    for Ps in problems(count, 3, 1e4, range(5)):
        with use_backend(backend):
            r = covariance_intersection(np.zeros((count, 3)), Ps, criterion)
        assert r.info["converged"]
        assert mp_information_gap(Ps, r.omega, criterion) <= 2 * GAP


def test_ci_with_an_optimum_on_a_face_releases_the_weights_it_needs():
    """Three estimates where the optimum has one weight at zero and two inside: a solver
    that fixes a weight at zero on the way must release it again."""
    Ps = [np.diag([1.0, 100.0]), np.diag([100.0, 1.0]), np.diag([3.0, 3.0])]
    for order in ([0, 1, 2], [2, 0, 1], [1, 2, 0]):
        Qs = [Ps[i] for i in order]
        r = covariance_intersection(np.zeros((3, 2)), Qs, "trace")
        assert r.info["converged"]
        assert mp_information_gap(Qs, r.omega, "trace") <= 2 * GAP


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("spread", [3e6, 1e7, 1e8, 1e9])
def test_pairs_with_eigenvalue_spread_between_1e6_and_1e9(backend, spread):
    """Beyond the diagonalised solver's trust (1e6), within the conditioning contract: the
    weights are optimal to the rounding level of the inputs (true gap from the inputs in 40
    digits), and the bound holds against the inputs in the exact worst direction.

    (That ``converged`` implies a true gap within 1e-9 here is issue 21, item 3: at HEAD
    bc582ac it fails at spreads 1e8 and 1e9, true gaps 4.5e-9 and 2.1e-9.)"""
    eps = np.finfo(float).eps
    for seed in range(2):
        rng = np.random.default_rng(100 + seed)
        Pa = spd(rng, 3, spread, 1.0)
        Pb = spd(rng, 3, 10.0, 30.0)
        for criterion in ("trace", "det"):
            with use_backend(backend):
                r = covariance_intersection([np.zeros(3), np.ones(3)], [Pa, Pb], criterion)
            true_gap = mp_information_gap([Pa, Pb], r.omega, criterion)
            assert true_gap <= max(GAP, 64 * spread * eps)
            assert_bound_holds(r.P, r.gains, [Pa, Pb], tol=fused_bound_tolerance([Pa, Pb]))


def similar_pair(rng, cond):
    """``P_a`` of condition number ``cond`` and ``P_b = P_a^1/2 D P_a^1/2`` with
    ``D = diag(1/2, 2, 1)``: each ill-conditioned, their generalised eigenvalues
    (1/2, 2, 1) close together, the optimum inside (0, 1)."""
    Pa = spd(rng, 3, cond, 1.0)
    lam, V = np.linalg.eigh(Pa)
    root = V @ np.diag(np.sqrt(lam)) @ V.T
    Pb = root @ np.diag([0.5, 2.0, 1.0]) @ root
    return Pa, 0.5 * (Pb + Pb.T)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("cond", [1e8, 1e10, 1e12])
def test_similar_ill_conditioned_pairs(backend, cond):
    """Small spread of the generalised eigenvalues, ill-conditioned factors (only their
    conditioning says the diagonal form is not to be trusted): converged implies optimal
    in 40 digits, optimal to the rounding level of the inputs, the bound held against the
    inputs."""
    eps = np.finfo(float).eps
    for seed in range(3):
        Pa, Pb = similar_pair(np.random.default_rng(200 + seed), cond)
        for criterion in ("trace", "det"):
            with use_backend(backend):
                r = covariance_intersection([np.zeros(3), np.ones(3)], [Pa, Pb], criterion)
            true_gap = mp_information_gap([Pa, Pb], r.omega, criterion)
            assert true_gap <= max(GAP, 64 * cond * eps)
            assert_bound_holds(r.P, r.gains, [Pa, Pb], tol=fused_bound_tolerance([Pa, Pb]))
    # (That converged implies a true gap within 1e-9 is issue 21, item 3: at HEAD bc582ac
    # it fails here at cond 1e10 and 1e12, true gaps 3.2e-9 to 3.6e-9 with converged True.)


def dominated_pair(rng, cond):
    """``P_b = 2 P_a + (a small PSD term)``: the optimum is exactly omega = 1."""
    Pa = spd(rng, 3, cond, 1.0)
    E = rng.standard_normal((3, 3))
    Pb = 2.0 * Pa + 1e-3 * np.sqrt(cond) * (E @ E.T)
    return Pa, 0.5 * (Pb + Pb.T)


@pytest.mark.parametrize("backend", BACKENDS)
def test_converged_is_the_documented_gap_test_on_every_path(backend):
    """``converged`` is ``gap <= 1e-9``, item by item, on the single and the batched path,
    including ill-conditioned items whose certificate is above the tolerance."""
    rng = np.random.default_rng(9)
    pairs = [similar_pair(rng, cond) for cond in (1e2, 1e8, 1e12)]
    pairs += [(spd(rng, 3, cond, 1.0), 2.5 * spd(rng, 3, 1e10, 1.0)) for cond in (1e4, 1e11)]
    pairs += [dominated_pair(rng, cond) for cond in (1e8, 1e10)]
    xs = np.zeros((len(pairs), 2, 3))
    for criterion in ("trace", "det"):
        with use_backend(backend):
            batch = covariance_intersection(xs, np.array(pairs), criterion)
            singles = [covariance_intersection(x, np.array(p), criterion)
                       for x, p in zip(xs, pairs)]
        for info in [batch.info] + [r.info for r in singles]:
            np.testing.assert_array_equal(
                info["converged"],
                np.asarray(info["gap"]) <= np.maximum(GAP, 2.0 * np.asarray(info["gap_floor"])))


# ------------------------------------------------------------------ partial CI
def test_partial_ci_newton_reports_non_convergence_at_the_iteration_limit():
    for Ps in problems(4, 3, 1e2, range(3)):
        xs = np.zeros((4, 3))
        best = partial_ci(xs, Ps, 0.7)
        assert best.info["converged"]
        short = partial_ci(xs, Ps, 0.7, max_iter=1)
        excess = np.trace(short.P) / np.trace(best.P) - 1.0
        assert excess > 1e-6  # one step is not enough here
        assert not short.info["converged"]
        assert short.info["gap"] >= excess * (1 - 1e-6)  # the gap bounds the excess


@pytest.mark.parametrize("rho", [1e-9, 1e-12, [1e-12, 0.5], [1e-10, 1e-9, 0.3]])
def test_partial_ci_below_the_newton_floor_of_rho_reaches_the_true_optimum(rho):
    count = np.size(rho) if np.ndim(rho) else 3
    for Ps in problems(count, 2, 1e2, range(3)):
        r = partial_ci(np.zeros((count, 2)), Ps, rho)
        assert r.info["converged"]
        assert r.info["gap"] <= 1e-10
        # two estimates: the common bound sqrt(rho_1 rho_2) of Definition 2 / Lemma 3
        used = np.sqrt(np.prod(rho)) if count == 2 else rho
        assert mp_information_gap(Ps, r.info["delta"], "trace", used) <= 2e-10


def algorithm_2(Ps, rho, sweeps):
    """Wu, Cai & Fu (2018), Algorithm 2, written from the paper: delta after ``sweeps``."""
    infos = [np.linalg.inv(P) for P in Ps]
    delta = np.full(len(Ps), 1.0 / len(Ps))
    for _ in range(sweeps):
        w = delta / (rho + (1 - rho) * delta)  # (24)
        P = np.linalg.inv(sum(wi * I for wi, I in zip(w, infos)))  # (33)
        K = [wi * P @ I for wi, I in zip(w, infos)]  # (34)
        root = np.sqrt([rho * np.trace(Ki @ Pi @ Ki.T) for Ki, Pi in zip(K, Ps)])
        delta = root / root.sum()  # (25)
    return delta


def test_algorithm_2_sweeps_are_the_papers_and_never_increase_the_trace():
    for Ps in problems(4, 3, 1e2, [11, 12]):
        traces = []
        for k in range(1, 25):
            r = partial_ci(np.zeros((4, 3)), Ps, 0.8, tol=1e-300, max_iter=k,
                           solver="alternating")
            np.testing.assert_allclose(r.info["delta"], algorithm_2(Ps, 0.8, k), rtol=1e-9)
            traces.append(np.trace(r.P))
        assert np.all(np.diff(traces) <= 1e-12 * traces[0])
        assert traces[-1] < traces[0]
        best = partial_ci(np.zeros((4, 3)), Ps, 0.8)
        assert traces[-1] >= np.trace(best.P) * (1 - 1e-12)


def test_algorithm_2_converged_needs_the_gap_not_only_a_resting_delta():
    """Near rho = 1 the sweeps creep (delta moves less than tol per sweep long before the
    trace is optimal): converged must wait for the certified gap."""
    Ps = [np.diag([1.0, 2.0]), np.diag([3.0, 5.0])]
    r = partial_ci([np.zeros(2)] * 2, Ps, 1.0, tol=1e-6, max_iter=5000, solver="alternating")
    if r.info["converged"]:
        assert np.trace(r.P) <= 3.0 * (1 + 1e-6)
    best = partial_ci([np.zeros(2)] * 2, Ps, 1.0)
    assert best.info["converged"] and np.trace(best.P) == pytest.approx(3.0, rel=1e-12)
    for Ps in problems(3, 3, 1e2, [5, 6]):
        r = partial_ci(np.zeros((3, 3)), Ps, 0.9, tol=1e-8, solver="alternating",
                       max_iter=10000)
        if r.info["converged"]:
            assert mp_information_gap(Ps, r.info["delta"], "trace", 0.9) <= 1.01e-8


# ------------------------------------------------------------------ covariance union
def test_union_gap_bounds_the_excess_over_every_mean_and_is_tight():
    rng = np.random.default_rng(3)
    for _ in range(4):
        Pa, Pb = spd(rng, 2, 10.0, 1.0), spd(rng, 2, 30.0, 2.0)
        xs = [np.zeros(2), rng.standard_normal(2) * 3]
        r = covariance_union(xs, [Pa, Pb])
        assert r.info["converged"] and r.info["gap"] <= GAP
        value = np.trace(r.P)
        lower = value * (1 - r.info["gap"])
        u = np.ravel(r.x)
        for step in (1e-1, 1e-2, 1e-3, 1e-4):
            for direction in rng.standard_normal((8, 2)):
                other = covariance_union(xs, [Pa, Pb], mean=u + step * direction)
                assert np.trace(other.P) >= lower - 1e-12 * value
