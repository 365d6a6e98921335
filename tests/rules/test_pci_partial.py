"""Partial-correlation CI of estimates of parts ``H_i x`` of the state (issue 22, item 1).

``fuse(..., method="pci", H=..., rho=...)``: with ``w_i^-1 = rho_i / delta_i + 1 - rho_i``
(eq. (24) of Wu, Cai & Fu 2018), ``P^-1 = sum_i w_i H_i^T P_i^-1 H_i`` and
``K_i = w_i P H_i^T P_i^-1`` (docs/methods/partial_state.rst, eqs. (H10)-(H12)). Checked
against an independent reference (a bounded scalar search and a Nelder-Mead search of the
same trace, assembled directly from explicit inverses), the full-state rule where every
``H_i`` is None or the identity, a hand-derived case that is tight, the exact worst
direction from the inputs at 50 digits (tests/worst_case.py: every joint covariance whose
normalised cross blocks have norm at most ``rho``) at condition numbers to 1e12 and scales
1e-12..1e12, batches, the errors, and that inputs are not modified.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize, minimize_scalar
from strategies import partial_state_problems
from worst_case import assert_bound_holds, gain_bound_difference, padded, worst_case_variance

import cifilter
from cifilter import fuse, get_method, partial_ci

EPS = np.finfo(float).eps
POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])  # of a 2-D CV state
VELOCITY = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def random_spd(g, n, scale=1.0):
    A = g.standard_normal((n, n))
    return scale * (A @ A.T + 0.3 * np.eye(n))


def full_H(H, n):
    return np.eye(n) if H is None else H


def eq_24(delta, rho):
    """w_i = 1 / (rho_i / delta_i + 1 - rho_i), 1 for rho_i = 0, 0 for delta_i = 0."""
    rho = np.broadcast_to(rho, np.shape(delta))
    return np.array([1.0 if r == 0 else (0.0 if d <= 0 else 1.0 / (r / d + 1.0 - r))
                     for d, r in zip(delta, rho)])


def direct_P(Ps, Hs, delta, rho):
    """(sum_i w_i H_i^T P_i^-1 H_i)^-1 from explicit inverses (the reference's way)."""
    w = eq_24(delta, rho)
    J = sum(wi * H.T @ np.linalg.inv(P) @ H for wi, P, H in zip(w, Ps, Hs))
    return np.linalg.inv(J)


def fused(Ps, Hs, rho, xs=None, **options):
    xs = [np.zeros(P.shape[0]) for P in Ps] if xs is None else xs
    return fuse(list(zip(xs, Ps)), method="pci", H=Hs, rho=rho, **options)


# ------------------------------------------------------------------ independent reference
@pytest.mark.parametrize("rho", [0.1, 0.5, 0.9])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_estimates_equal_a_bounded_scalar_search(rho, seed):
    g = np.random.default_rng(seed)
    Ps = [random_spd(g, 4), random_spd(g, 2, 0.5)]
    Hs = [np.eye(4), POSITION]
    xs = [g.standard_normal(4), g.standard_normal(2)]
    r = fused(Ps, [None, POSITION], rho, xs)
    found = minimize_scalar(lambda t: np.trace(direct_P(Ps, Hs, [t, 1 - t], rho)),
                            bounds=(1e-9, 1 - 1e-9), method="bounded",
                            options={"xatol": 1e-12})
    assert r.info["converged"] and r.info["gap"] <= 1e-10
    assert r.info["delta"][0] == pytest.approx(found.x, abs=1e-5)
    # the optimum: at most the reference's trace, and equal to it
    assert np.trace(r.P) <= found.fun * (1 + 1e-10)
    assert np.trace(r.P) == pytest.approx(found.fun, rel=1e-9)
    np.testing.assert_allclose(r.P, direct_P(Ps, Hs, r.info["delta"], rho), rtol=1e-9)
    np.testing.assert_allclose(r.weights, eq_24(r.info["delta"], rho), rtol=1e-14)
    # x = P sum_i w_i H_i^T P_i^-1 x_i (eq. (H11)), from explicit inverses
    x = r.P @ sum(w * H.T @ np.linalg.solve(P, xi)
                  for w, H, P, xi in zip(r.weights, Hs, Ps, xs))
    np.testing.assert_allclose(r.x, x, rtol=1e-9, atol=1e-12)
    assert r.gains is None and r.info["gains"][1].shape == (4, 2)


@pytest.mark.parametrize("rho", [0.2, [0.1, 0.6, 0.9]])
def test_three_partial_estimates_equal_a_nelder_mead_search(rho):
    g = np.random.default_rng(5)
    Hs = [POSITION, VELOCITY,
          np.array([[1.0, 0.5, 0.0, 0.0], [0.0, 0.0, 1.0, 0.5], [1.0, 0.0, 1.0, 0.0]])]
    Ps = [random_spd(g, H.shape[0]) for H in Hs]
    xs = [g.standard_normal(H.shape[0]) for H in Hs]
    r = fused(Ps, Hs, rho, xs)

    def objective(z):
        d = np.exp(z - z.max())
        return np.trace(direct_P(Ps, Hs, d / d.sum(), rho))

    best = min((minimize(objective, start, method="Nelder-Mead",
                         options={"xatol": 1e-10, "fatol": 1e-15, "maxfev": 6000})
                for start in (np.zeros(3), np.array([1.0, -1.0, 0.0]))),
               key=lambda found: found.fun)
    assert r.info["converged"] and r.info["solver"] == "newton"
    assert np.trace(r.P) <= best.fun * (1 + 1e-10)
    assert np.trace(r.P) == pytest.approx(best.fun, rel=1e-8)
    x = r.P @ sum(w * H.T @ np.linalg.solve(P, xi)
                  for w, H, P, xi in zip(r.weights, Hs, Ps, xs))
    np.testing.assert_allclose(r.x, x, rtol=1e-9, atol=1e-12)
    # the paper's alternating projections reach the same optimum
    alternating = fused(Ps, Hs, rho, xs, solver="alternating", max_iter=5000)
    assert alternating.info["converged"]
    assert np.trace(alternating.P) == pytest.approx(np.trace(r.P), rel=1e-8)


@pytest.mark.parametrize("m", [2, 3, 4])
@pytest.mark.parametrize("rho", [0.0, 0.3, 1.0])
def test_each_estimate_of_one_component_is_tight_by_hand(m, rho):
    """H_i = e_i^T, P_i = 1: P^-1 = diag(w), so Tr P = sum_i (rho / delta_i + 1 - rho),
    least at delta_i = 1/m: P = (1 + (m - 1) rho) I (eq. (37) with q -> infinity), and
    K_i = e_i. The joint with all correlations rho is admissible, and along
    (1, ..., 1) / sqrt(m) its error variance is 1 + (m - 1) rho: the bound is tight."""
    Hs = [np.eye(m)[i:i + 1] for i in range(m)]
    Ps = [np.eye(1)] * m
    xs = [np.array([float(i + 1)]) for i in range(m)]
    r = fused(Ps, Hs, rho, xs)
    assert r.info["converged"]
    if rho > 0:
        np.testing.assert_allclose(r.info["delta"], 1 / m, rtol=1e-9)
    np.testing.assert_allclose(r.P, (1 + (m - 1) * rho) * np.eye(m), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(r.info["gains"]), np.eye(m)[:, :, None], atol=1e-12)
    np.testing.assert_allclose(r.x, np.arange(1.0, m + 1), rtol=1e-12)
    # square gains for tests/worst_case.py: K_i in the first column, zeros elsewhere
    K = np.zeros((m, m, m))
    K[:, :, :1] = np.asarray(r.info["gains"])
    unit = np.broadcast_to(np.eye(m), (m, m, m))
    v = np.ones(m) / np.sqrt(m)
    assert v @ r.P @ v == pytest.approx(worst_case_variance(K, unit, v, rho), rel=1e-12)
    assert_bound_holds(r.P, K, unit, rho=rho)


def test_rho_0_is_the_naive_and_rho_1_the_generalised_ci_fusion():
    g = np.random.default_rng(3)
    Hs = [None, POSITION, VELOCITY]
    Ps = [random_spd(g, 4), random_spd(g, 2), random_spd(g, 2)]
    xs = [g.standard_normal(P.shape[0]) for P in Ps]
    pairs = list(zip(xs, Ps))
    naive = fuse(pairs, method="naive", H=Hs)
    zero = fuse(pairs, method="pci", H=Hs, rho=0.0)
    np.testing.assert_allclose(zero.P, naive.P, rtol=1e-12)
    np.testing.assert_allclose(zero.x, naive.x, rtol=1e-12, atol=1e-14)
    ci = fuse(pairs, method="ci", H=Hs)
    one = fuse(pairs, method="pci", H=Hs, rho=1.0)
    assert one.info["converged"] and ci.info["converged"]
    np.testing.assert_allclose(np.trace(one.P), np.trace(ci.P), rtol=1e-9)
    np.testing.assert_allclose(one.weights, one.info["delta"], atol=1e-15)  # w = delta
    # in between, the trace is monotone in rho (Remark 3)
    traces = [np.trace(fuse(pairs, method="pci", H=Hs, rho=rho).P)
              for rho in (0.0, 0.25, 0.5, 0.75, 1.0)]
    assert np.all(np.diff(traces) >= -1e-12 * traces[-1])


@pytest.mark.parametrize("rho", [0.0, 0.4, 1.0, [0.2, 0.7, 0.5]])
@pytest.mark.parametrize("solver", ["newton", "alternating"])
def test_identity_and_none_H_equal_the_full_state_rule(rho, solver):
    g = np.random.default_rng(11)
    Ps = np.stack([random_spd(g, 3) for _ in range(3)])
    xs = g.standard_normal((3, 3))
    full = partial_ci(xs, Ps, rho, solver=solver, max_iter=5000)
    pairs = list(zip(xs, Ps))
    # every H None: the ordinary estimates, the same call
    none = fuse(pairs, method="pci", H=[None] * 3, rho=rho, solver=solver, max_iter=5000)
    np.testing.assert_array_equal(none.P, full.P)
    np.testing.assert_array_equal(none.x, full.x)
    for Hs in ([np.eye(3)] * 3, [None, np.eye(3), None]):
        r = fuse(pairs, method="pci", H=Hs, rho=rho, solver=solver, max_iter=5000)
        assert r.info["converged"]
        np.testing.assert_allclose(r.P, full.P, rtol=1e-9)
        np.testing.assert_allclose(r.x, full.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r.gains, full.gains, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(r.info["rho"], full.info["rho"])


# ---------------------------------------------------- the exact worst direction, cond 1e12
@st.composite
def partial_problems(draw):
    """:func:`strategies.partial_state_problems` with a common bound rho (0, 1, anything
    between, or tiny)."""
    Hs, Ps, n = draw(partial_state_problems())
    rho = draw(st.one_of(st.sampled_from([0.0, 1.0, 1e-12, 1e-300]), st.floats(0.0, 1.0)))
    return Hs, Ps, n, rho


def assert_valid(P):
    assert np.all(np.isfinite(P))
    np.testing.assert_array_equal(P, P.T)
    np.linalg.cholesky(P)


@settings(max_examples=60)
@given(partial_problems(), st.sampled_from(["newton", "alternating"]))
def test_bound_holds_in_the_exact_worst_direction(problem, solver):
    """Every joint covariance whose normalised cross blocks have norm at most rho (the
    worst one along each direction: tests/worst_case.py), at 50 digits from the inputs,
    to the tolerance of the full-state rule, 64 n N eps ||P|| (P is formed from the
    inputs in compensated arithmetic)."""
    Hs, Ps, n, rho = problem
    r = fused(Ps, Hs, rho, solver=solver)
    assert_valid(r.P)
    gains = r.info["gains"]
    cond = max(np.linalg.cond(P) for P in Ps)
    unbiased = sum(K @ full_H(H, n) for K, H in zip(gains, Hs))
    scale = 1.0 + max(np.abs(K @ full_H(H, n)).max() for K, H in zip(gains, Hs))
    # exact to rounding where a full-state estimate takes the remainder; otherwise to the
    # rounding of the information form (as for generalised CI)
    kept = Hs[0] is None and r.weights[0] > 0.0
    allowed = 64 * n * EPS if kept else (1e3 * n + cond) * EPS
    assert np.abs(unbiased - np.eye(n)).max() <= allowed * scale
    K_pad, P_pad = padded(gains, Ps)
    assert_bound_holds(r.P, K_pad, P_pad, rho=float(r.info["rho"][0]))
    gap = float(r.info["gap"])
    assert np.isfinite(gap) and gap >= 0.0
    assert bool(r.info["converged"]) == (gap <= 1e-10) or solver == "alternating"
    if solver == "newton" and cond <= 1e8:
        assert r.info["converged"], gap


@settings(max_examples=30)
@given(partial_problems(), st.integers(0, 2**32 - 1))
def test_given_delta_is_a_bound_in_the_exact_worst_direction(problem, seed):
    """Lemma 7 holds for every delta on the simplex (a positive one: every estimate kept)."""
    Hs, Ps, _, rho = problem
    delta = np.random.default_rng(seed).dirichlet(np.ones(len(Ps))) * 0.9 + 0.1 / len(Ps)
    r = fused(Ps, Hs, rho, delta=delta)
    assert_valid(r.P)
    assert r.info["rule"] == "fixed"
    np.testing.assert_allclose(r.info["delta"], delta, rtol=1e-15)
    K_pad, P_pad = padded(r.info["gains"], Ps)
    assert_bound_holds(r.P, K_pad, P_pad, rho=float(r.info["rho"][0]))


def test_p_is_the_bound_of_the_returned_gains_from_the_inputs_at_condition_1e12():
    """P = sum_i K_i P_i K_i^T / w_i of the returned gains and the inputs to N eps ||P||,
    against the same sum at 50 digits (as for full states, issue 21 item 2)."""
    rng = np.random.default_rng(4)
    Hs = [None, rng.standard_normal((2, 4)), rng.standard_normal((3, 4))]
    Ps = []
    for m in (4, 2, 3):
        Q, _ = np.linalg.qr(rng.standard_normal((m, m)))
        P = Q @ np.diag(10.0 ** rng.uniform(-6, 6) * np.logspace(0, 12, m)) @ Q.T
        Ps.append(0.5 * (P + P.T))
    for rho in (0.0, 0.5):
        r = fused(Ps, Hs, rho)
        difference = gain_bound_difference(r.P, r.info["gains"], Ps, r.weights)
        assert difference <= 4 * 3 * EPS * np.linalg.norm(r.P, 2)


# ------------------------------------------------------------------------ batches, filters
def test_batched_equals_per_item():
    g = np.random.default_rng(6)
    P1 = random_spd(g, 4)
    P2 = np.stack([random_spd(g, 2) for _ in range(3)])
    x1, x2 = g.standard_normal((3, 4)), g.standard_normal((3, 2))
    rho = np.array([[0.1], [0.5], [0.9]])
    batched = fuse([(x1, P1), (x2, P2)], method="pci", H=[None, POSITION], rho=rho)
    assert batched.P.shape == (3, 4, 4) and batched.info["converged"].all()
    for k in range(3):
        item = fuse([(x1[k], P1), (x2[k], P2[k])], method="pci", H=[None, POSITION],
                    rho=float(rho[k, 0]))
        np.testing.assert_allclose(batched.P[k], item.P, rtol=1e-9)
        np.testing.assert_allclose(batched.x[k], item.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(batched.info["delta"][k], item.info["delta"], atol=1e-7)


def test_filter_fuse_with_H_equals_the_front_door():
    kf = cifilter.KalmanFilter(dim_x=4, dim_z=2)
    g = np.random.default_rng(7)
    kf.x = g.standard_normal((4, 1))
    kf.P = random_spd(g, 4)
    fix = (g.standard_normal(2), random_spd(g, 2))
    direct = fuse([(kf.x, kf.P), fix], method="pci", H=[None, POSITION], rho=0.3)
    kf.fuse(fix, method="pci", H=POSITION, rho=0.3)
    np.testing.assert_array_equal(kf.P, direct.P)
    np.testing.assert_array_equal(kf.x, direct.x)
    assert kf.x.shape == (4, 1)


# -------------------------------------------------------------------- errors and contract
def test_record_declares_H():
    assert "H" in get_method("pci").front_door


def test_unobserved_directions_are_named_as_for_generalised_ci():
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pairs = [(np.zeros(2), np.eye(2)), (np.zeros(2), np.eye(2))]
    with pytest.raises(ValueError) as pci_error:
        fuse(pairs, method="pci", H=[H, H], rho=0.5)
    with pytest.raises(ValueError) as ci_error:
        fuse(pairs, method="ci", H=[H, H])
    assert str(pci_error.value) == str(ci_error.value)
    assert "[0.0, 0.0, 1.0]" in str(pci_error.value)


def test_a_given_delta_that_drops_the_only_estimate_of_a_direction_is_named():
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pairs = [(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))]
    Hs = [H, np.array([[0.0, 0.0, 1.0]])]
    with pytest.raises(ValueError, match=r"given delta.*unobserved.*\[0\.0, 0\.0, 1\.0\]"):
        fuse(pairs, method="pci", H=Hs, rho=0.5, delta=[1.0, 0.0])
    # with rho_2 = 0 the weight is 1 whatever delta_2: nothing is dropped
    r = fuse(pairs, method="pci", H=Hs, rho=[0.5, 0.0], delta=[1.0, 0.0])
    np.testing.assert_allclose(r.P, np.diag([1.0, 1.0, 1.0]), rtol=1e-12)


@pytest.mark.parametrize("options, error, message", [
    ({}, ValueError, "needs a correlation coefficient bound"),
    ({"rho": 1.5}, ValueError, r"rho must lie in \[0, 1\]"),
    ({"rho": [0.1, 0.2, 0.3]}, ValueError, r"shape \(\.\.\., 2\)"),
    ({"rho": 0.5, "delta": [0.3, 0.3]}, ValueError, "delta must lie on the simplex"),
    ({"rho": 0.5, "solver": "bisection"}, ValueError, "solver"),
    ({"rho": 0.5, "omega": 0.5}, TypeError, "does not accept"),
])
def test_bad_options_are_named(options, error, message):
    with pytest.raises(error, match=message):
        fuse([(np.zeros(4), np.eye(4)), (np.zeros(2), np.eye(2))], method="pci",
             H=[None, POSITION], **options)


def test_bad_H_and_other_front_door_options_are_named():
    pairs = [(np.zeros(4), np.eye(4)), (np.zeros(2), np.eye(2))]
    with pytest.raises(ValueError, match=r"H\[1\] has shape \(3, 4\).*needs 2 rows"):
        fuse(pairs, method="pci", H=[None, np.ones((3, 4))], rho=0.5)
    with pytest.raises(ValueError, match=r"does not accept times="):
        fuse(pairs, method="pci", H=[None, POSITION], rho=0.5, times=[0.0, 1.0],
             motion=lambda dt: (np.eye(4), np.eye(4)))
    with pytest.raises(ValueError, match=r"horizon=.*does not support H="):
        fuse(pairs, method="pci", H=[None, POSITION], rho=0.5, horizon=2,
             model=dict(F=np.eye(4), Q=np.eye(4)))


def test_inputs_are_not_modified_and_the_result_is_read_only():
    g = np.random.default_rng(9)
    P1, P2 = random_spd(g, 4), random_spd(g, 2)
    x1, x2, H = g.standard_normal(4), g.standard_normal(2), POSITION.copy()
    rho = np.array([0.3, 0.6])
    copies = [a.copy() for a in (P1, P2, x1, x2, H, rho)]
    for array in (P1, P2, x1, x2, H, rho):
        array.flags.writeable = False
    r = fuse([(x1, P1), (x2, P2)], method="pci", H=[None, H], rho=rho)
    for a, b in zip((P1, P2, x1, x2, H, rho), copies):
        np.testing.assert_array_equal(a, b)
    assert not r.info["gains"][1].flags.writeable
    with pytest.raises(ValueError):
        r.P[0, 0] = 1.0


def test_column_style_of_the_first_estimate_is_kept():
    r = fuse([(np.zeros((4, 1)), np.eye(4)), (np.zeros(2), np.eye(2))], method="pci",
             H=[None, POSITION], rho=0.5)
    assert r.x.shape == (4, 1)


def test_an_ignored_full_state_estimate_leaves_no_unbounded_gain():
    """Found by hypothesis: at rho = 1 the optimum ignores the full-state estimate
    (delta_1 = 0), and generalised CI's assembly gave it the remainder
    I - sum_j K_j H_j, rounding amplified by its condition number 1e6, a gain with no term
    in the bound: the worst direction exceeded P by 1.5e-12 (||P|| = 6.8), twice the
    tolerance. An ignored estimate has a zero gain."""
    Hs = [None,
          np.array([[0.40655813, -0.39477768, -0.1961583], [0.39857089, 1.13968568, -1.08333979],
                    [-0.25871163, -0.7698658, 0.930482]]),
          np.array([[0.27310196, 1.63830555, 1.13237361]])]
    Ps = [np.diag([1e6, 1.0, 1.0]), np.eye(3), np.eye(1)]
    r = fused(Ps, Hs, 1.0)
    assert r.info["converged"] and r.weights[0] == 0.0
    K_pad, P_pad = padded(r.info["gains"], Ps)
    assert_bound_holds(r.P, K_pad, P_pad, rho=1.0)
    assert not r.info["gains"][0].any()


def test_truth_hook_with_blocks_of_unequal_dimensions_gives_a_bound_for_the_joint():
    """Simulations know the joint covariance of estimates of H_i x (blocks m_i x m_j):
    the truth hook takes their dimensions (sizes=), eq. (21) holds tightly for the rho it
    returns, and the fused bound dominates the true error covariance of the gains."""
    g = np.random.default_rng(12)
    Hs = [None, POSITION, g.standard_normal((3, 4))]
    sizes = [4, 2, 3]
    E = np.concatenate([full_H(H, 4) for H in Hs])  # the stacked H_i
    A = g.standard_normal((9, 9))
    joint = A @ A.T + 0.2 * np.eye(9)  # errors e_i of x_i = H_i x + e_i
    hook = get_method("pci").truth_options
    for count, blocks, J in ((3, sizes, joint), (2, sizes[:2], joint[:6, :6])):
        rho = float(hook(J, None, count=count, sizes=blocks)["rho"][0])
        ends = np.cumsum([0] + blocks)
        D = np.zeros_like(J)
        for a, b in zip(ends[:-1], ends[1:]):
            D[a:b, a:b] = J[a:b, a:b]
        assert np.linalg.eigvalsh(J - (1 - rho) * D)[0] > -1e-12 * np.abs(J).max()
        assert np.linalg.eigvalsh(J - (1 - rho + 1e-6) * D)[0] < 0
        Ps = [J[a:b, a:b] for a, b in zip(ends[:-1], ends[1:])]
        r = fused(Ps, Hs[:count], rho)
        K = np.concatenate(r.info["gains"], axis=-1)
        np.testing.assert_allclose(K @ E[:ends[-1]], np.eye(4), atol=1e-12)
        assert np.linalg.eigvalsh(r.P - K @ J @ K.T)[0] >= -1e-12 * np.linalg.norm(r.P, 2)
    with pytest.raises(ValueError, match=r"dimensions \[4, 2\]"):
        hook(joint, None, count=2, sizes=[4, 2])
