"""Inverse Covariance Intersection: hand-derived values, special cases, the bound under the
common-information model in the worst direction, failure outside that model, optimality of
omega against a 30-digit reference, conditioning, conventions."""

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import solve_triangular
from strategies import covariance_sets, ill_conditioned_sets
from worst_case import assert_bound_holds, worst_case_variance

from cifilter import (
    IllConditionedError,
    KalmanFilter,
    covariance_intersection,
    fuse,
    get_method,
    inverse_covariance_intersection,
    naive_fusion,
)

rng = np.random.default_rng(20261201)
EPS = np.finfo(float).eps


def random_spd(n, seed):
    g = np.random.default_rng(seed)
    A = g.standard_normal((n, n))
    return A @ A.T + 0.1 * np.eye(n)


def ici_reference(Pa, Pb, omega):
    """The paper's equations, written out with explicit inverses (well-conditioned tests)."""
    Ia, Ib = np.linalg.inv(Pa), np.linalg.inv(Pb)
    G_inv = np.linalg.inv(omega * Pa + (1 - omega) * Pb)
    P = np.linalg.inv(Ia + Ib - G_inv)
    return P, P @ (Ia - omega * G_inv), P @ (Ib - (1 - omega) * G_inv)


# ----------------------------------------------------------------- worst common information
def _symmetric_basis(n):
    """(n*n, m) matrix whose columns are the vectorised symmetric basis matrices."""
    columns = []
    for i in range(n):
        for j in range(i, n):
            E = np.zeros((n, n))
            E[i, j] = E[j, i] = 1.0
            columns.append(E.ravel())
    return np.array(columns).T


def worst_common_information(a, b, Ia, Ib, t_final=1e10):
    """A feasible C near the maximiser of ``2 a^T C b`` over ``{0 <= C <= Ia, C <= Ib}``.

    A log-barrier interior-point method (damped Newton with feasibility backtracking):
    after centring at barrier parameter t the objective is within ``3 n / t`` (relative to
    its scale) of the maximum (three n x n constraints). Every returned C is admissible
    (checked by Cholesky), so a violation found with it is a real one.
    """
    n = len(a)
    E = _symmetric_basis(n)
    S0 = np.outer(a, b) + np.outer(b, a)
    scale = max(np.abs(S0).max(), 1e-300)
    c = E.T @ (S0.ravel() / scale)
    C = 0.5 * min(np.linalg.eigvalsh(Ia)[0], np.linalg.eigvalsh(Ib)[0]) * np.eye(n)
    signs = (1.0, -1.0, -1.0)

    def constraints(C):
        return (C, Ia - C, Ib - C)

    def barrier(C, t):
        total = -t * (c @ E.T @ C.ravel())
        for X in constraints(C):
            try:
                L = np.linalg.cholesky(X)
            except np.linalg.LinAlgError:
                return np.inf
            total -= 2.0 * np.log(np.diag(L)).sum()
        return total

    t = 1.0
    while t <= t_final:
        for _ in range(20):
            inverses = [np.linalg.inv(X) for X in constraints(C)]
            grad = -t * c - E.T @ sum(s * Xi.ravel() for s, Xi in zip(signs, inverses))
            H = E.T @ sum(np.kron(Xi, Xi) for Xi in inverses) @ E
            step = np.linalg.lstsq(H, -grad, rcond=1e-14)[0]
            decrement = -grad @ step
            if not np.isfinite(decrement) or decrement < 1e-10:
                break
            D = (E @ step).reshape(n, n)
            # the longest step that keeps every constraint positive definite
            limit = np.inf
            for X, dX in zip(constraints(C), (D, -D, -D)):
                Li = np.linalg.inv(np.linalg.cholesky(X))
                top = np.linalg.eigvalsh(-Li @ dX @ Li.T)[-1]
                if top > 0:
                    limit = min(limit, 1.0 / top)
            length, value = min(1.0, 0.95 * limit), barrier(C, t)
            while length > 1e-10:
                trial = C + length * D
                if barrier(trial, t) <= value - 0.25 * length * decrement:
                    break
                length *= 0.5
            if length <= 1e-10:
                break
            C = trial
        t *= 30.0
    return C


def common_information_error(Ka, Kb, Pa, Pb, C):
    """Fused error covariance when ``Pab = Pa C Pb``."""
    cross = Ka @ Pa @ C @ Pb @ Kb.T
    return Ka @ Pa @ Ka.T + Kb @ Pb @ Kb.T + cross + cross.T


def worst_common_excess(P, Ka, Kb, Pa, Pb, rounds=4):
    """Largest ``v^T (E(C) - P) v / v^T P v`` found over the worst common information C of
    each direction v: the eigenvectors of P, each improved by alternating the worst C for
    v and the top generalised eigenvector of (E(C), P)."""
    Ia, Ib = np.linalg.inv(Pa), np.linalg.inv(Pb)
    worst = -np.inf
    for v in np.linalg.eigh(P)[1].T:
        for _ in range(rounds):
            C = worst_common_information(Pa @ Ka.T @ v, Pb @ Kb.T @ v, Ia, Ib)
            E = common_information_error(Ka, Kb, Pa, Pb, C)
            worst = max(worst, (v @ E @ v - v @ P @ v) / (v @ P @ v))
            L = np.linalg.cholesky(P)
            Li = np.linalg.inv(L)
            w = np.linalg.eigh(Li @ E @ Li.T)[1][:, -1]
            v = np.linalg.solve(L.T, w)
            v /= np.linalg.norm(v)
    return worst


def test_worst_common_information_checker_can_fail():
    """The checker finds the overconfidence of the naive fusion under common information."""
    Pa, Pb = random_spd(2, 1), random_spd(2, 2)
    r = naive_fusion([np.zeros(2)] * 2, [Pa, Pb])
    assert worst_common_excess(r.P, r.gains[0], r.gains[1], Pa, Pb, rounds=1) > 0.05


def test_worst_common_information_is_tight_for_equal_estimates():
    """Pa = Pb: the common information may be all of it (C = Pa^-1), and ICI's P = Pa is
    attained: the worst direction is found and the bound is tight."""
    Pa = random_spd(2, 3)
    r = inverse_covariance_intersection([np.zeros(2)] * 2, [Pa, Pa], omega=0.3)
    np.testing.assert_allclose(r.P, Pa, rtol=1e-12)
    excess = worst_common_excess(r.P, r.gains[0], r.gains[1], Pa, Pa, rounds=1)
    assert -1e-8 <= excess <= 1e-9


@pytest.mark.parametrize(("seed", "criterion"), [(0, "trace"), (1, "det"), (1, "fixed")])
def test_bound_under_common_information_in_the_worst_direction(seed, criterion):
    n = 2 + seed % 2
    Pa, Pb = random_spd(n, 10 + seed), random_spd(n, 20 + seed)
    if criterion == "fixed":
        r = inverse_covariance_intersection([np.zeros(n)] * 2, [Pa, Pb], omega=0.25)
    else:
        r = inverse_covariance_intersection([np.zeros(n)] * 2, [Pa, Pb], criterion=criterion)
    excess = worst_common_excess(r.P, r.gains[0], r.gains[1], Pa, Pb, rounds=3)
    assert excess <= 1e-9


def test_not_conservative_outside_the_common_information_model():
    """Pa = diag(1, 4), Pb = diag(4, 1): ICI's P = (20/17) I with omega = 1/2. A joint that
    correlates the first component of one error with the second of the other (the worst
    arbitrary correlation of ICI's gains; it is no common information) gives the direction
    (1, 1)/sqrt(2) a variance of about 1.80 > 20/17. CI's bound holds for it, as for every
    joint."""
    Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    r = inverse_covariance_intersection([np.zeros(2)] * 2, [Pa, Pb])
    np.testing.assert_allclose(r.P, 20 / 17 * np.eye(2), rtol=1e-12)
    v = np.array([1.0, 1.0]) / np.sqrt(2.0)
    assert worst_case_variance(r.gains, [Pa, Pb], v, rho=1.0) == pytest.approx(
        (2 * np.sqrt(260) / (17 * np.sqrt(2))) ** 2, rel=1e-12)  # about 1.799
    # the violating joint written out: C_ab = u_a u_b^T in whitened coordinates
    La, Lb = np.linalg.cholesky(Pa), np.linalg.cholesky(Pb)
    ua, ub = La.T @ r.gains[0].T @ v, Lb.T @ r.gains[1].T @ v
    ua, ub = ua / np.linalg.norm(ua), ub / np.linalg.norm(ub)
    Pab = La @ np.outer(ua, ub) @ Lb.T
    joint = np.block([[Pa, Pab], [Pab.T, Pb]])
    assert np.linalg.eigvalsh(joint)[0] >= -1e-12  # an admissible joint covariance
    K = np.concatenate(list(r.gains), axis=-1)
    assert v @ K @ joint @ K.T @ v > v @ r.P @ v + 0.5
    ci = covariance_intersection([np.zeros(2)] * 2, [Pa, Pb])
    assert_bound_holds(ci.P, ci.gains, [Pa, Pb], rho=1.0)
    Kci = np.concatenate(list(ci.gains), axis=-1)
    assert v @ Kci @ joint @ Kci.T @ v <= v @ ci.P @ v * (1 + 1e-12)


# ----------------------------------------------------------------- values and special cases
def test_hand_derived_example():
    """Pa = diag(1, 4), Pb = diag(4, 1): by symmetry the trace optimum is omega = 1/2, and
    in the basis of the coordinates each variance is
    lam (omega + (1 - omega) lam) / (omega + (1 - omega) lam^2) times Pa's, lam = 4 or 1/4,
    i.e. 20/17; the gains are diag(16/17, 1/17) and diag(1/17, 16/17)."""
    Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    r = inverse_covariance_intersection([np.array([1.0, 0.0]), np.array([0.0, 1.0])],
                                        [Pa, Pb])
    assert r.weights[0] == pytest.approx(0.5, abs=1e-12)
    np.testing.assert_allclose(r.P, 20 / 17 * np.eye(2), rtol=1e-13)
    np.testing.assert_allclose(r.gains[0], np.diag([16 / 17, 1 / 17]), atol=1e-13)
    np.testing.assert_allclose(r.gains[1], np.diag([1 / 17, 16 / 17]), atol=1e-13)
    np.testing.assert_allclose(r.x, [16 / 17, 16 / 17], rtol=1e-13)
    assert r.info["converged"] and r.info["rule"] == "optimal"
    assert np.trace(r.P) < np.trace(covariance_intersection([np.zeros(2)] * 2, [Pa, Pb]).P)


@pytest.mark.parametrize("omega", [0.0, 0.2, 0.5, 0.9, 1.0])
def test_matches_the_paper_equations(omega):
    Pa, Pb = random_spd(3, 5), random_spd(3, 6)
    r = inverse_covariance_intersection([np.zeros(3)] * 2, [Pa, Pb], omega=omega)
    P, Ka, Kb = ici_reference(Pa, Pb, omega)
    np.testing.assert_allclose(r.P, P, rtol=1e-10, atol=1e-12 * np.abs(P).max())
    np.testing.assert_allclose(r.gains[0], Ka, atol=1e-10)
    np.testing.assert_allclose(r.gains[1], Kb, atol=1e-10)
    np.testing.assert_array_equal(r.weights, [omega, 1 - omega])
    assert r.info["rule"] == "fixed"


def test_ends_and_equal_estimates():
    Pa, Pb = random_spd(2, 7), random_spd(2, 8)
    xa, xb = np.array([1.0, 2.0]), np.array([-1.0, 0.5])
    r0 = inverse_covariance_intersection([xa, xb], [Pa, Pb], omega=0.0)
    r1 = inverse_covariance_intersection([xa, xb], [Pa, Pb], omega=1.0)
    np.testing.assert_allclose(r0.P, Pa, rtol=1e-12)
    np.testing.assert_allclose(r0.x, xa, rtol=1e-12)
    np.testing.assert_array_equal(r0.gains[1], np.zeros((2, 2)))
    np.testing.assert_allclose(r1.P, Pb, rtol=1e-12)
    np.testing.assert_allclose(r1.x, xb, rtol=1e-12)
    # equal covariances: all common information; ICI returns the common covariance
    r = inverse_covariance_intersection([xa, xb], [Pa, Pa])
    np.testing.assert_allclose(r.P, Pa, rtol=1e-12)


def test_scalar_keeps_the_better_estimate():
    """n = 1: P(omega) = pa pb g / (omega pa^2 + (1 - omega) pb^2) ... is smallest at the
    end that keeps the smaller variance (a boundary optimum, exactly)."""
    r = inverse_covariance_intersection([np.zeros(1), np.ones(1)], [np.eye(1), 3 * np.eye(1)])
    assert r.weights[0] == 0.0 and r.P[0, 0] == pytest.approx(1.0, rel=1e-14)
    r = inverse_covariance_intersection([np.zeros(1), np.ones(1)], [3 * np.eye(1), np.eye(1)])
    assert r.weights[0] == 1.0 and r.x[0] == pytest.approx(1.0, rel=1e-14)


def test_p_is_the_common_information_bound_of_the_returned_gains():
    """P = Ka Pa Ka^T + Kb Pb Kb^T + t Ka Pa Pb^-1 Pa Ka^T + Kb Pb Pa^-1 Pb Kb^T / t."""
    for seed in range(5):
        Pa, Pb = random_spd(3, 30 + seed), random_spd(3, 40 + seed)
        r = inverse_covariance_intersection([np.zeros(3)] * 2, [Pa, Pb], criterion="det")
        w = r.weights[0]
        t = w / (1 - w)
        Ka, Kb = (r.gains[k].astype(np.longdouble) for k in range(2))
        A, B = Pa.astype(np.longdouble), Pb.astype(np.longdouble)
        bound = (Ka @ A @ Ka.T + Kb @ B @ Kb.T + t * Ka @ A @ np.linalg.inv(Pb) @ A @ Ka.T
                 + Kb @ B @ np.linalg.inv(Pa) @ B @ Kb.T / t)
        np.testing.assert_allclose(r.P, np.asarray(bound, dtype=float), rtol=1e-11)
        np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3), atol=1e-13)


# ----------------------------------------------------------------- optimality
def _reference_optimum(Pa, Pb, criterion):
    """omega* to about 1e-14: the criterion in 30-digit mpmath on a grid of 101 points,
    then a golden-section search of the bracket around the best point."""
    mpmath.mp.dps = 30
    A, B = mpmath.matrix(Pa.tolist()), mpmath.matrix(Pb.tolist())
    W = None if isinstance(criterion, str) else mpmath.matrix(criterion.tolist())

    def f(w):
        P = (A**-1 + B**-1 - (w * A + (1 - w) * B) ** -1) ** -1
        if isinstance(criterion, str) and criterion == "det":
            return mpmath.log(mpmath.det(P))
        M = P if W is None else W * P
        return sum(M[i, i] for i in range(M.rows))

    grid = [mpmath.mpf(k) / 100 for k in range(101)]
    values = [f(w) for w in grid]
    k = min(range(101), key=lambda i: values[i])
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, 100)]
    for _ in range(64):  # golden-section on the convex criterion (bracket below 1e-15)
        a, b = lo + (hi - lo) * 0.382, lo + (hi - lo) * 0.618
        if f(a) < f(b):
            hi = b
        else:
            lo = a
    best = (lo + hi) / 2
    return float(best), float(f(best))


@pytest.mark.parametrize(("seed", "criterion"), [(0, "trace"), (1, "det"), (2, "weighted")])
def test_omega_is_optimal_against_a_high_precision_reference(seed, criterion):
    Pa, Pb = random_spd(3, 50 + seed), random_spd(3, 60 + seed)
    crit = np.diag([1.0, 0.1, 0.0]) if criterion == "weighted" else criterion
    r = inverse_covariance_intersection([np.zeros(3)] * 2, [Pa, Pb], criterion=crit)
    omega, value = _reference_optimum(Pa, Pb, crit)
    assert r.info["converged"] and r.info["gap"] <= 1e-9
    if 0.0 < omega < 1.0:
        assert r.weights[0] == pytest.approx(omega, abs=1e-6)
    mine = np.log(r.info["value"]) if criterion == "det" else r.info["value"]
    assert mine <= value + 1e-9 * abs(value) + 1e-12


# ----------------------------------------------------------------- conditioning
@settings(max_examples=25)
@given(ill_conditioned_sets(2, 3), st.sampled_from(["trace", "det"]))
def test_conditioning_contract(Ps, criterion):
    Pa, Pb = Ps
    try:
        r = inverse_covariance_intersection([np.zeros(3)] * 2, Ps, criterion=criterion)
    except IllConditionedError:  # allowed only beyond what float64 resolves
        assert max(np.linalg.cond(Pa), np.linalg.cond(Pb)) > 1e10
        return
    assert np.all(np.isfinite(r.P)) and np.array_equal(r.P, r.P.T)
    np.linalg.cholesky(r.P)
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3),
                               atol=1e-9 * max(1.0, np.abs(r.gains).max()))
    # P dominates the common-information bound B_t(K) of the returned gains, in the
    # directions of P's eigenvectors, up to cond * eps (the square roots of the terms
    # from triangular solves, their products in extended precision)
    w = r.weights[0]
    La, Lb = np.linalg.cholesky(Pa), np.linalg.cholesky(Pb)
    Ka, Kb = r.gains
    terms = [Ka @ La, Kb @ Lb]
    if 0 < w < 1:
        terms.append(np.sqrt(w / (1 - w)) * solve_triangular(Lb, (Ka @ Pa).T, lower=True).T)
        terms.append(np.sqrt((1 - w) / w) * solve_triangular(La, (Kb @ Pb).T, lower=True).T)
    terms = [T.astype(np.longdouble) for T in terms]
    bound = sum(T @ T.T for T in terms)
    tol = 64 * EPS * max(np.linalg.cond(Pa), np.linalg.cond(Pb))
    for v in np.linalg.eigh(r.P)[1].T:
        assert float(v @ bound @ v) <= (v @ r.P @ v) * (1 + tol) + tol * np.abs(r.P).max()
    # converged: optimal to the precision the inputs allow (docs/conventions.rst), with a
    # rounding floor of order kappa eps
    floor = float(r.info["gap_floor"])
    assert 0.0 < floor <= 64 * 27 * EPS * (np.linalg.cond(r.P) + max(np.linalg.cond(Pa),
                                                                     np.linalg.cond(Pb)))
    assert r.info["gap"] > 0.0
    if r.info["converged"]:
        assert r.info["gap"] <= max(1e-9, 2.0 * floor)


# ----------------------------------------------------------------- N estimates
def test_sequential_n_estimates_depend_on_the_order():
    Ps = [random_spd(3, 170 + k) for k in range(3)]
    xs = [rng.standard_normal(3) for _ in range(3)]
    r = inverse_covariance_intersection(xs, Ps)
    assert r.weights is None and r.info["rule"] == "sequential"
    assert r.info["omegas"].shape == (2,)
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.einsum("kij,kj->i", r.gains, np.array(xs)), r.x, atol=1e-12)
    # step by step
    first = inverse_covariance_intersection(xs[:2], Ps[:2])
    second = inverse_covariance_intersection([first.x, xs[2]], [first.P, Ps[2]])
    np.testing.assert_allclose(r.P, second.P, rtol=1e-12)
    order = [2, 0, 1]
    reordered = inverse_covariance_intersection([xs[k] for k in order], [Ps[k] for k in order])
    assert not np.allclose(reordered.P, r.P, rtol=1e-6)  # order dependence, documented


# ----------------------------------------------------------------- conventions
def test_batched_equals_one_at_a_time_and_column_style():
    Ps = np.stack([[random_spd(3, 100 + 2 * k), random_spd(3, 101 + 2 * k)] for k in range(6)])
    xs = rng.standard_normal((6, 2, 3))
    batch = inverse_covariance_intersection(xs, Ps, criterion="det")
    for k in range(6):
        one = inverse_covariance_intersection(list(xs[k][..., None]), list(Ps[k]),
                                              criterion="det")
        assert one.x.shape == (3, 1)
        np.testing.assert_allclose(batch.P[k], one.P, rtol=1e-10)
        np.testing.assert_allclose(batch.x[k], one.x[:, 0], rtol=1e-9, atol=1e-12)
    assert batch.info["converged"].shape == (6,)


def test_swapping_the_estimates_swaps_omega():
    Pa, Pb = random_spd(3, 80), random_spd(3, 81)
    r = inverse_covariance_intersection([np.zeros(3)] * 2, [Pa, Pb])
    s = inverse_covariance_intersection([np.zeros(3)] * 2, [Pb, Pa])
    assert s.weights[0] == pytest.approx(r.weights[1], abs=1e-8)
    np.testing.assert_allclose(s.P, r.P, rtol=1e-9)


def test_front_door_registry_and_filter():
    record = get_method("ici")
    assert record.guarantee == "bound" and "common information" in record.summary
    Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    r = fuse([(np.zeros(2), Pa), (np.ones(2), Pb)], method="ici", criterion="det")
    direct = inverse_covariance_intersection([np.zeros(2), np.ones(2)], [Pa, Pb],
                                             criterion="det")
    np.testing.assert_array_equal(r.P, direct.P)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.P = Pa.copy()
    kf.fuse((np.ones(2), Pb), method="ici")
    np.testing.assert_allclose(kf.P, 20 / 17 * np.eye(2), rtol=1e-12)
    assert kf.x.shape == (2, 1)
    with pytest.raises(ValueError, match="horizon"):
        fuse([(np.zeros(2), Pa), (np.ones(2), Pb)], method="ici", horizon=2,
             model=dict(F=np.eye(2), Q=np.eye(2)))


def test_errors_and_inputs_unchanged():
    Pa, Pb = random_spd(2, 90), random_spd(2, 91)
    xs, Ps = [np.zeros(2), np.ones(2)], [Pa, Pb]
    copies = [p.copy() for p in Ps]
    inverse_covariance_intersection(xs, Ps)
    for p, c in zip(Ps, copies):
        np.testing.assert_array_equal(p, c)
    with pytest.raises(ValueError, match="omega"):
        inverse_covariance_intersection(xs, Ps, omega=1.5)
    with pytest.raises(ValueError, match="two estimates"):
        inverse_covariance_intersection(xs + [np.zeros(2)], Ps + [Pa], omega=0.5)
    with pytest.raises(ValueError, match="criterion"):
        inverse_covariance_intersection(xs, Ps, criterion="volume")
    with pytest.raises(ValueError, match="positive definite"):
        inverse_covariance_intersection(xs, [Pa, -Pb])
    with pytest.raises(TypeError):
        inverse_covariance_intersection(xs, Ps, omega="fast")


@settings(max_examples=5)
@given(covariance_sets(2, 2))
def test_property_bound_in_worst_common_direction(Ps):
    Pa, Pb = Ps
    r = inverse_covariance_intersection([np.zeros(2)] * 2, Ps)
    assert worst_common_excess(r.P, r.gains[0], r.gains[1], Pa, Pb, rounds=2) <= 1e-9


def test_weight_matrices_per_problem_of_a_batch():
    Ps = np.stack([[[random_spd(3, 200 + 6 * i + 2 * j), random_spd(3, 201 + 6 * i + 2 * j)]
                    for j in range(3)] for i in range(2)])
    W = np.stack([[np.diag([1.0, float(i + j), 0.0]) for j in range(3)] for i in range(2)])
    r = inverse_covariance_intersection(np.zeros((2, 3, 2, 3)), Ps, criterion=W)
    for i in range(2):
        for j in range(3):
            one = inverse_covariance_intersection([np.zeros(3)] * 2, list(Ps[i, j]),
                                                  criterion=W[i, j])
            np.testing.assert_allclose(r.P[i, j], one.P, rtol=1e-10)
