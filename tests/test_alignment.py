"""Time alignment (issue 22, item 3): prediction and the retrodiction bound.

An older estimate is predicted (``F x``, ``F P F^T + Q``: exact). A newer one is brought
back with ``F^-1``; its error ``F^-1 (e + w)`` contains the process noise ``w`` in between,
correlated with the estimate's error ``e`` in a way nobody knows, so ``F^-1 (P + Q) F^-T``
is not a bound, and ``F^-1 (P / alpha + Q / (1 - alpha)) F^-T`` is (docs/methods/time.rst,
eqs. (T1)-(T6)). Checked in the exact worst case (a joint of ``(e, w)`` built to attain
``(sqrt(u^T P u) + sqrt(u^T Q u))^2`` along ``u``, in 50 digits from the inputs) and by
Monte Carlo with a newer estimate that is a Kalman filter which saw the process noise
(NEES of the retrodicted estimate and of the fused result within the chi-square bounds;
the plain sum fails the same test).
"""

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from scipy.stats import chi2
from strategies import ill_conditioned_spd

from cifilter import IllConditionedError, fuse, get_method
from cifilter._numerics.alignment import (
    StepMotion,
    added_to_reference,
    check_times,
    motion_matrices,
    predicted,
    residuals_to_reference,
    retrodicted,
    retrodiction_alpha,
)

DIGITS = 50


def mp(A):
    return mpmath.matrix(np.asarray(A, dtype=float).tolist())


def quadratic(M, v):
    vm = mpmath.matrix([mpmath.mpf(float(a)) for a in v])
    return (vm.T * M * vm)[0, 0]


def worst_variance(F, P, Q, v):
    """max over every joint of (e, w) of var(v^T F^-1 (e + w)) at 50 digits from the inputs:
    (sqrt(u^T P u) + sqrt(u^T Q u))^2 with u = F^-T v (eq. (T3))."""
    with mpmath.workdps(DIGITS):
        F_inv = mpmath.inverse(mp(F))
        vm = mpmath.matrix([mpmath.mpf(float(a)) for a in v])
        u = F_inv.T * vm
        p = (u.T * mp(P) * u)[0, 0]
        q = (u.T * mp(Q) * u)[0, 0]
        return (mpmath.sqrt(max(p, 0)) + mpmath.sqrt(max(q, 0))) ** 2


def worst_joint_covariance(F, P, Q, u):
    """cov(F^-1 (e + w)) for the joint of (e, w) that is perfectly correlated along u:
    e = L a, w = D b with cross-covariance L alpha beta^T D^T, alpha = L^T u / |L^T u|,
    beta = D^T u / |D^T u| (a positive semidefinite joint whose marginals are P and Q),
    at 50 digits."""
    with mpmath.workdps(DIGITS):
        Pm, Qm = mp(P), mp(Q)
        L = mpmath.cholesky((Pm + Pm.T) / 2)
        values, vectors = mpmath.eigsy((Qm + Qm.T) / 2)
        D = vectors * mpmath.diag([mpmath.sqrt(max(x, 0)) for x in values])
        um = mpmath.matrix([mpmath.mpf(float(a)) for a in u])
        a = L.T * um
        b = D.T * um
        a = a / mpmath.norm(a)
        b = b / mpmath.norm(b)
        C = L * a * b.T * D.T  # cov(e, w)
        F_inv = mpmath.inverse(mp(F))
        return F_inv * (Pm + Qm + C + C.T) * F_inv.T


def min_eigenvalue(M):
    with mpmath.workdps(DIGITS):
        return float(min(mpmath.eigsy((M + M.T) / 2)[0]))


# --------------------------------------------------------------------------- prediction
def test_prediction_is_F_x_and_F_P_F_T_plus_Q():
    F = np.array([[1.0, 2.0], [0.0, 1.0]])
    P, Q = np.diag([4.0, 1.0]), np.diag([0.5, 0.25])
    x, P_new = predicted(np.array([1.0, 3.0]), np.linalg.cholesky(P), F, Q)
    np.testing.assert_allclose(x, [7.0, 3.0])
    # by hand: F P F^T = [[4 + 4, 2], [2, 1]]
    np.testing.assert_allclose(P_new, [[8.5, 2.0], [2.0, 1.25]], rtol=1e-15)


# ------------------------------------------------------------------------- retrodiction
def test_retrodiction_by_hand():
    """F = 2 I, P = diag(4, 16), Q = diag(4, 0): F^-1 P F^-T = diag(1, 4), F^-1 Q F^-T =
    diag(1, 0), a = 5, b = 1, alpha = sqrt(5) / (sqrt(5) + 1)."""
    F = 2.0 * np.eye(2)
    P, Q = np.diag([4.0, 16.0]), np.diag([4.0, 0.0])
    x, P_new, alpha = retrodicted(np.array([2.0, 4.0]), np.linalg.cholesky(P), F, Q)
    expected = np.sqrt(5.0) / (np.sqrt(5.0) + 1.0)
    assert float(alpha) == pytest.approx(expected, rel=1e-15)
    np.testing.assert_allclose(x, [1.0, 2.0])
    np.testing.assert_allclose(P_new, np.diag([1 / expected + 1 / (1 - expected),
                                               4 / expected]), rtol=1e-14)
    # without process noise the retrodiction is exact
    _, exact, alpha = retrodicted(np.zeros(2), np.linalg.cholesky(P), F, np.zeros((2, 2)))
    assert float(alpha) == 1.0
    np.testing.assert_allclose(exact, np.diag([1.0, 4.0]))


def test_alpha_minimises_the_trace():
    a, b = 3.0, 0.7
    alpha = float(retrodiction_alpha(np.array(a), b))
    trace = a / alpha + b / (1 - alpha)
    assert trace == pytest.approx((np.sqrt(a) + np.sqrt(b)) ** 2, rel=1e-14)
    for other in (alpha - 1e-3, alpha + 1e-3):
        assert a / other + b / (1 - other) > trace


@st.composite
def retrodiction_problems(draw):
    n = draw(st.integers(1, 4))
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    log_scale = draw(st.floats(-12.0, 12.0))
    scales = (10.0**log_scale, 10.0**log_scale)
    F = np.eye(n) + g.standard_normal((n, n)) * draw(st.sampled_from([0.1, 0.5, 1.0]))
    P = draw(ill_conditioned_spd(n, scales=scales))
    Q = draw(ill_conditioned_spd(n, scales=scales))
    if n > 1 and draw(st.booleans()):  # a singular process noise (one driving direction)
        Q = np.outer(Q[0], Q[0]) / Q[0, 0]
    return F, P, Q


@settings(max_examples=60)
@given(retrodiction_problems())
def test_retrodiction_bound_holds_in_the_exact_worst_case(problem):
    """In every direction v, v^T P' v >= (sqrt(u^T P u) + sqrt(u^T Q u))^2 (u = F^-T v),
    the largest error variance of any joint of (e, w); and P' dominates the error
    covariance of the joint built to attain it along u, in every direction."""
    F, P, Q = problem
    n = F.shape[0]
    if np.linalg.cond(F) > 1e6:
        return
    _, P_new, _ = retrodicted(np.zeros(n), np.linalg.cholesky(P), F, Q)
    tol = 64.0 * n * np.finfo(float).eps * (np.linalg.cond(F) ** 2 + np.linalg.cond(P))
    g = np.random.default_rng(0)
    directions = list(np.linalg.eigh(P_new)[1].T) + list(g.standard_normal((4, n)))
    for v in directions:
        worst = float(worst_variance(F, P, Q, v))
        assert v @ P_new @ v >= worst * (1.0 - tol), (v, v @ P_new @ v, worst)
        u = np.linalg.solve(F.T, v)
        if not np.any(Q @ u):  # the noise does not reach this direction
            continue
        with mpmath.workdps(DIGITS):
            C = worst_joint_covariance(F, P, Q, u)
            difference = mp(P_new) - C
        assert min_eigenvalue(difference) >= -tol * np.linalg.norm(P_new, 2)


@settings(max_examples=40)
@given(retrodiction_problems(), st.integers(1, 3))
def test_retrodicted_bound_is_exactly_symmetric_and_the_cached_path_agrees(problem, k):
    """The single-estimate retrodiction forms P without a final symmetrisation: A A^T
    (numpy's syrk) and back_noise's symmetrised F^-1 Q F^-T are exactly symmetric, so P is;
    through lag='s cache (StepMotion.back) it is the same P bit for bit, and it is the
    formula (T5)-(T6) evaluated in 50 digits from the inputs, to rounding."""
    F, P, Q = problem
    n = F.shape[0]
    if np.linalg.cond(F) > 1e3:
        return
    Q = 0.5 * (Q + Q.T)  # (exactly symmetric: the cache's checked copy is the same Q)
    steps = StepMotion(F, Q)
    F_k, Q_k = steps(k)
    L = np.linalg.cholesky(P)
    x = np.arange(1.0, n + 1)
    x_new, P_new, alpha = retrodicted(x, L, F_k, Q_k)
    np.testing.assert_array_equal(P_new, P_new.T)
    F_inv, Q_back = steps.back(k, n, "F")
    np.testing.assert_array_equal(Q_back, Q_back.T)
    cached = retrodicted(x, L, F_k, Q_k, F_inv=F_inv, Q_back=Q_back)
    np.testing.assert_array_equal(cached[0], x_new)
    np.testing.assert_array_equal(cached[1], P_new)
    assert cached[2] == alpha
    with mpmath.workdps(DIGITS):
        Fi = mp(F_k) ** -1
        exact = Fi * (mp(P) / alpha + mp(Q_k) / (1 - alpha)) * Fi.T if alpha < 1 else (
            Fi * mp(P) * Fi.T)
        error = max(abs(float(exact[i, j]) - P_new[i, j]) for i in range(n)
                    for j in range(n))
    bound = 64.0 * n * np.finfo(float).eps * np.linalg.cond(F_k) ** 2
    assert error <= bound * max(np.abs(P_new).max(), 1e-300)


def test_retrodiction_bound_is_tight_in_some_direction():
    """max over v of worst(v) / v^T P' v is 1: the bound cannot be lowered uniformly."""
    F = np.array([[1.0, 0.5], [0.0, 1.0]])
    P, Q = np.array([[2.0, 0.3], [0.3, 0.5]]), np.array([[0.2, 0.1], [0.1, 0.4]])
    _, P_new, _ = retrodicted(np.zeros(2), np.linalg.cholesky(P), F, Q)

    def ratio(angle):
        v = np.array([np.cos(angle[0]), np.sin(angle[0])])
        return -float(worst_variance(F, P, Q, v)) / (v @ P_new @ v)

    best = min((minimize(ratio, [start], method="Nelder-Mead",
                         options={"xatol": 1e-12, "fatol": 1e-15})
                for start in np.linspace(0, np.pi, 7)), key=lambda r: r.fun)
    assert -best.fun <= 1.0 + 1e-12
    assert -best.fun == pytest.approx(1.0, abs=1e-9)


def test_the_plain_sum_is_not_a_bound_in_the_worst_case():
    """F^-1 (P + Q) F^-T misses the worst case along u = F^-T v by 2 sqrt(p q)."""
    F = np.array([[1.0, 0.5], [0.0, 1.0]])
    P, Q = np.array([[2.0, 0.3], [0.3, 0.5]]), np.array([[0.2, 0.1], [0.1, 0.4]])
    F_inv = np.linalg.inv(F)
    plain = F_inv @ (P + Q) @ F_inv.T
    v = np.array([1.0, 0.0])
    assert float(worst_variance(F, P, Q, v)) > 1.2 * (v @ plain @ v)


def test_singular_F_is_refused_with_a_clear_error():
    L = np.eye(2)
    with pytest.raises(IllConditionedError, match=r"F is singular or numerically singular.*"
                                                  r"retrodiction needs F\^-1"):
        retrodicted(np.zeros(2), L, np.array([[1.0, 1.0], [1.0, 1.0]]), np.eye(2))
    with pytest.raises(IllConditionedError, match="numerically singular"):
        retrodicted(np.zeros(2), L, np.diag([1.0, 1e-14]), np.eye(2))

    def motion(dt):
        return np.array([[1.0, dt], [0.0, 0.0]]), np.eye(2)

    with pytest.raises(IllConditionedError, match=r"F of motion\(1\.0\) \(for estimates\[1\], "
                                                  r"newer than at\)"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(2), np.eye(2))], times=[0.0, 1.0], at=0.0,
             motion=motion)


# ---------------------------------------------------------------------------- Monte Carlo
# A constant-velocity model (dt = 0.5) whose process noise is strongly negatively correlated
# between its two states, and a sensor of the difference of the states: the newer Kalman
# filter's error is correlated with the process noise so that F^-1 (P + Q) F^-T is 1.78
# times too small along its worst direction (computed exactly below).
F_MC = np.array([[1.0, 0.5], [0.0, 1.0]])
Q_MC = np.array([[1.0, -0.9], [-0.9, 1.0]])
H_B, R_B = np.array([[1.0, -1.0]]), np.array([[0.01]])
H_A, R_A = np.array([[0.0, 1.0]]), np.array([[1.0]])  # filter A at T: the second state
LAG = 3


def kalman_gains(H, R, steps, P0):
    """The (deterministic) gains and covariances of a Kalman filter on the MC model."""
    P, out = P0, []
    for _ in range(steps):
        P = F_MC @ P @ F_MC.T + Q_MC
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        P = (np.eye(2) - K @ H) @ P
        out.append((K, P.copy()))
    return out


def motion_mc(dt):
    steps = round(float(dt))
    F, Q = np.eye(2), np.zeros((2, 2))
    for _ in range(steps):
        F, Q = F_MC @ F, F_MC @ Q @ F_MC.T + Q_MC
    return F, Q


def exact_retrodicted_covariance(warm):
    """cov(F^-k (e + w)) of the newer filter's retrodicted error, propagated exactly."""
    gains = kalman_gains(H_B, R_B, warm + LAG, 10.0 * np.eye(2))
    J = np.zeros((4, 4))
    J[:2, :2] = gains[warm - 1][1]
    for K, _ in gains[warm:]:
        A = np.eye(2) - K @ H_B
        M = np.block([[A @ F_MC, np.zeros((2, 2))], [np.zeros((2, 2)), F_MC]])
        N = np.vstack([-A, np.eye(2)])
        J = M @ J @ M.T + N @ Q_MC @ N.T
        J[:2, :2] += K @ R_B @ K.T
    F_k, _ = motion_mc(LAG)
    F_inv = np.linalg.inv(F_k)
    e_plus_w = J[:2, :2] + J[2:, 2:] + J[:2, 2:] + J[2:, :2]
    return F_inv @ e_plus_w @ F_inv.T, gains[-1][1]


def simulate(runs, warm, rng):
    """Truth at T = warm and at T + LAG, filter A's estimate at T, filter B's at T + LAG."""
    x = rng.multivariate_normal(np.zeros(2), 10.0 * np.eye(2), size=runs)
    xa = np.zeros((runs, 2))
    xb = np.zeros((runs, 2))
    gains_a = kalman_gains(H_A, R_A, warm, 10.0 * np.eye(2))
    gains_b = kalman_gains(H_B, R_B, warm + LAG, 10.0 * np.eye(2))
    noise = np.linalg.cholesky(Q_MC)
    truth_T = None
    for step in range(warm + LAG):
        x = x @ F_MC.T + rng.standard_normal((runs, 2)) @ noise.T
        for est, gains, H, R in ((xb, gains_b, H_B, R_B), (xa, gains_a, H_A, R_A)):
            if gains is gains_a and step >= warm:
                continue
            K, _ = gains[step]
            z = x @ H.T + rng.standard_normal((runs, 1)) * np.sqrt(R[0, 0])
            predicted_mean = est @ F_MC.T
            est[:] = predicted_mean + (z - predicted_mean @ H.T) @ K.T
        if step == warm - 1:
            truth_T = x.copy()
    return truth_T, xa, gains_a[-1][1], xb, gains_b[-1][1]


def nees(error, P):
    return np.einsum("ki,ij,kj->k", error, np.linalg.inv(P), error)


@pytest.mark.parametrize("seed", [11])
def test_monte_carlo_retrodiction_and_fusion_are_consistent(seed):
    runs, warm = 4000, 30
    truth, xa, Pa, xb, Pb = simulate(runs, warm, np.random.default_rng(seed))
    exact, _ = exact_retrodicted_covariance(warm)
    # the newer filter's retrodicted estimate, bound and plain sum
    x_back, P_back, _ = retrodicted(xb, np.linalg.cholesky(Pb), *motion_mc(LAG))
    F_k, Q_k = motion_mc(LAG)
    F_inv = np.linalg.inv(F_k)
    plain = F_inv @ (Pb + Q_k) @ F_inv.T
    error = x_back - truth
    low, high = chi2.ppf([0.0005, 0.9995], 2 * runs) / runs
    anees_bound = nees(error, P_back).mean()
    assert anees_bound <= high  # (a bound: may be far below n = 2)
    # the worst direction of the plain sum, from the exact covariance: 1-D NEES there
    L = np.linalg.cholesky(plain)
    values, vectors = np.linalg.eigh(np.linalg.solve(L, np.linalg.solve(L, exact).T))
    assert values[-1] > 1.7  # the plain sum is 1.78 times too small along it
    u = np.linalg.solve(L.T, vectors[:, -1])
    _, high1 = chi2.ppf([0.0005, 0.9995], runs) / runs
    plain_nees = ((error @ u) ** 2 / (u @ plain @ u)).mean()
    bound_nees = ((error @ u) ** 2 / (u @ P_back @ u)).mean()
    assert plain_nees > high1  # the plain sum fails
    assert bound_nees <= high1  # the bound does not
    assert np.linalg.eigvalsh(P_back - exact).min() >= -1e-12 * np.abs(P_back).max()
    # fused with filter A at T through the front door
    fused = fuse([(xa, Pa), (xb, Pb)], times=[float(warm), float(warm + LAG)],
                 at=float(warm), motion=motion_mc)
    assert 0.1 < fused.weights[0, 0] < 0.9  # the retrodicted estimate takes part
    anees_fused = nees(fused.x - truth, fused.P[0]).mean()
    assert anees_fused <= high
    np.testing.assert_allclose(fused.P[0], fused.P[-1])
    assert low < 2.0 < high  # (the band is the chi-square one of 2 * runs degrees)


# ------------------------------------------------------------------- the front door's time
def test_fuse_brings_older_and_newer_estimates_to_at():
    def motion(dt):
        return np.array([[1.0, dt], [0.0, 1.0]]), 0.1 * dt * np.eye(2)

    a = (np.array([0.0, 1.0]), np.diag([1.0, 0.5]))
    b = (np.array([2.0, 1.0]), np.diag([2.0, 0.5]))
    r = fuse([a, b], times=[1.0, 3.0], motion=motion)  # at = 3: a is predicted 2 seconds
    assert r.info["at"] == 3.0 and r.info["retrodiction_alpha"] == (None, None)
    F, Q = motion(2.0)
    expected = fuse([(F @ a[0], F @ a[1] @ F.T + Q), b])
    np.testing.assert_allclose(r.x, expected.x, rtol=1e-14)
    np.testing.assert_allclose(r.P, expected.P, rtol=1e-14)
    back = fuse([a, b], times=[1.0, 3.0], at=1.0, motion=motion)  # b is retrodicted
    assert back.info["retrodiction_alpha"][0] is None
    alpha = float(back.info["retrodiction_alpha"][1])
    F_inv = np.linalg.inv(F)
    P_b = F_inv @ (b[1] / alpha + Q / (1 - alpha)) @ F_inv.T
    expected = fuse([a, (F_inv @ b[0], P_b)])
    np.testing.assert_allclose(back.P, expected.P, rtol=1e-12)
    # estimates at the same time need no motion
    same = fuse([a, b], times=[2.0, 2.0])
    np.testing.assert_array_equal(same.P, fuse([a, b]).P)


@pytest.mark.parametrize("kwargs, error, message", [
    ({"times": [0.0]}, ValueError, "times has 1 entries but there are 2 estimates"),
    ({"times": 1.0}, TypeError, "times must be a sequence"),
    ({"times": [0.0, np.nan]}, ValueError, r"times\[1\] must be finite"),
    ({"times": [0.0, "1"]}, TypeError, r"times\[1\] must be a real number"),
    ({"times": [0.0, True]}, TypeError, r"times\[1\] must be a real number"),
    ({"times": [0.0, 1.0], "at": np.inf}, ValueError, "at must be finite"),
    ({"times": [0.0, 1.0]}, ValueError, r"estimates\[0\] is at time 0.*give motion="),
    ({"at": 1.0}, ValueError, "give times="),
    ({"motion": lambda dt: (np.eye(2), np.eye(2))}, ValueError, "give times="),
    ({"times": [0.0, 1.0], "motion": "cv"}, TypeError, "motion must be callable"),
    ({"times": [0.0, 1.0], "motion": lambda dt: np.eye(2)}, TypeError,
     r"motion must return a pair \(F, Q\)"),
    ({"times": [0.0, 1.0], "motion": lambda dt: (np.eye(3), np.eye(2))}, ValueError,
     r"motion\(1\.0\) returned F of shape \(3, 3\)"),
    ({"times": [0.0, 1.0], "motion": lambda dt: (np.eye(2), -np.eye(2))}, ValueError,
     r"Q of motion\(1\.0\) must be positive semidefinite"),
    ({"times": [0.0, 1.0], "motion": lambda dt: (np.eye(2), np.array([[1.0, 2.0], [0, 1]]))},
     ValueError, r"Q of motion\(1\.0\) must be symmetric"),
    ({"times": [0.0, 1.0], "motion": lambda dt: (np.full((2, 2), np.nan), np.eye(2))},
     ValueError, "returned F with non-finite values"),
    ({"times": [0.0, 1.0], "method": "naive"}, ValueError,
     r"method 'naive' does not accept times=; the rules that bring estimates of other "
     r"times to at= \(times=\) are 'ci'"),
])
def test_bad_time_options_are_named(kwargs, error, message):
    pair = [(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))]
    with pytest.raises(error, match=message):
        fuse(pair, **kwargs)


def test_a_partial_estimate_cannot_move_in_time():
    def motion(dt):
        return np.eye(2), np.eye(2)

    with pytest.raises(ValueError, match=r"estimates\[1\] is at time 0.*part of the state"):
        fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))],
             H=[None, np.array([[1.0, 0.0]])], times=[1.0, 0.0], motion=motion)
    r = fuse([(np.zeros(2), np.eye(2)), (np.zeros(1), np.eye(1))],
             H=[None, np.array([[1.0, 0.0]])], times=[0.0, 1.0], motion=motion)
    assert r.info["at"] == 1.0


def test_check_times_and_motion_matrices_copy_and_check():
    times, at = check_times(np.array([1, 2]), 2)
    assert times == (1.0, 2.0) and at == 2.0
    F0, Q0 = np.eye(2), np.eye(2)
    F, Q = motion_matrices(lambda dt: (F0, Q0), 1.0, 2)
    assert F is not F0 and Q is not Q0


# ---------------------------------------------------------------------------- residuals
def wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def heading_residual(a, b):
    d = a - b
    d[0] = wrap(d[0])
    return d


def test_residuals_and_addition_per_batch_item():
    x = [np.array([[np.radians(179), 1.0], [0.0, 2.0]]),
         np.array([[np.radians(-179), 3.0], [0.5, 2.0]])]
    d = residuals_to_reference(x, (None, None), heading_residual)
    np.testing.assert_allclose(d[1], [[np.radians(2), 2.0], [0.5, 0.0]], atol=1e-14)
    np.testing.assert_array_equal(d[0], np.zeros((2, 2)))
    back = added_to_reference(x[0], d[1], lambda a, b: a + b)
    np.testing.assert_allclose(back[0], [np.radians(181), 3.0])


def test_fuse_with_a_wrapping_residual_fuses_across_the_wrap():
    a = (np.array([np.radians(179), 0.0]), np.diag([0.01, 1.0]))
    b = (np.array([np.radians(-179), 0.0]), np.diag([0.01, 1.0]))
    euclidean = fuse([a, b])
    assert abs(euclidean.x[0]) < 1e-12  # the silent failure of issue 22
    r = fuse([a, b], residual=heading_residual, add=lambda x, dx: x + dx)
    assert np.degrees(r.x[0]) == pytest.approx(180.0, abs=1e-9)
    r = fuse([a, b], residual=heading_residual,
             add=lambda x, dx: np.array([wrap(x[0] + dx[0]), x[1] + dx[1]]))
    assert abs(np.degrees(r.x[0])) == pytest.approx(180.0, abs=1e-9)


@pytest.mark.parametrize("kwargs, error, message", [
    ({"residual": "minus"}, TypeError, "residual must be callable"),
    ({"add": 3}, TypeError, "add must be callable"),
    ({"residual": lambda a, b: np.zeros(3)}, ValueError,
     r"residual must return 2 numbers \(shape \(2,\)\), got shape \(3,\)"),
    ({"residual": lambda a, b: [np.nan, 0.0]}, ValueError, "residual returned non-finite"),
    ({"residual": lambda a, b: "x"}, TypeError, r"residual must return 2 numbers, got str"),
    ({"add": lambda a, b: np.zeros((2, 2))}, ValueError, "add must return 2 numbers"),
    ({"residual": lambda a, b: a[5]}, IndexError, "residual failed"),
    ({"residual": np.subtract, "method": "ei"}, ValueError,
     r"method 'ei' does not accept residual=; the rules that accept residual= and add= are "
     r"'ci', 'naive', 'optimal', 'pci', 'split-ci'"),
])
def test_bad_residual_options_are_named(kwargs, error, message):
    pair = [(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))]
    with pytest.raises(error, match=message):
        fuse(pair, **kwargs)


def test_residual_needs_a_full_state_reference():
    with pytest.raises(ValueError, match=r"first estimate, which must estimate the full state"):
        fuse([(np.zeros(1), np.eye(1)), (np.zeros(2), np.eye(2))],
             H=[np.array([[1.0, 0.0]]), None], residual=np.subtract)


def test_residual_is_passed_copies_and_inputs_are_unchanged():
    seen = []

    def mutating(a, b):
        seen.append((a.copy(), b.copy()))
        a[0] = 99.0  # a user's residual that writes into its arguments
        return a - b

    x1, x2 = np.array([1.0, 2.0]), np.array([3.0, 5.0])
    r = fuse([(x1, np.eye(2)), (x2, np.eye(2))], residual=mutating)
    np.testing.assert_array_equal(x1, [1.0, 2.0])
    np.testing.assert_array_equal(x2, [3.0, 5.0])
    assert len(seen) == 1
    np.testing.assert_allclose(r.x, fuse([(x1, np.eye(2)), (x2, np.eye(2))]).x + [48.0, 0.0])


def test_the_front_door_options_are_declared_by_the_records():
    assert get_method("ci").front_door == ("H", "residual", "times")
    assert get_method("naive").front_door == ("H", "residual")
    assert get_method("pci").front_door == ("H", "residual")  # (H=: partial CI of parts)
    assert get_method("ei").front_door == ()


@pytest.mark.parametrize("times, at", [([0.0, 2.0, 1.0], 2.0), ([0.0, 2.0, 1.0], 0.0),
                                       ([1.0, 1.0, 3.0], 1.0)])
def test_times_on_a_batch_equal_the_items_fused_one_by_one(times, at):
    """The batched path of the time alignment (each moved estimate's mean, covariance and
    factor written into the validated stack) gives each item's single fusion."""
    rng = np.random.default_rng(11)

    def motion(dt):
        return np.array([[1.0, dt], [0.0, 1.0]]), 0.1 * dt * np.array([[1.0, 0.3], [0.3, 1.0]])

    xs = rng.standard_normal((3, 4, 2))  # 3 estimates, a batch of 4
    Ps = []
    for _ in range(3):
        A = rng.standard_normal((4, 2, 2))
        Ps.append(A @ A.swapaxes(-1, -2) + 0.3 * np.eye(2))
    batched = fuse([(xs[i], Ps[i]) for i in range(3)], times=times, at=at, motion=motion)
    for b in range(4):
        single = fuse([(xs[i][b], Ps[i][b]) for i in range(3)], times=times, at=at,
                      motion=motion)
        np.testing.assert_allclose(batched.x[b], single.x, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(batched.P[b], single.P, rtol=1e-12)
        for i, alpha in enumerate(single.info["retrodiction_alpha"]):
            if alpha is None:
                assert batched.info["retrodiction_alpha"][i] is None
            else:
                assert batched.info["retrodiction_alpha"][i][b] == pytest.approx(alpha,
                                                                                rel=1e-12)


# ------------------------------------------- the cheap checks of H= (as_partial_estimates)
def _bad(kind, x, P):
    """A copy of the estimate (x, P) spoilt as ``kind`` says."""
    x, P = x.copy(), P.copy()
    if kind == "x nan":
        x[-1] = np.nan
    elif kind == "x inf":
        x[0] = np.inf
    elif kind == "P nan above the diagonal":
        P[0, -1] = np.nan
    elif kind == "P inf on the diagonal":
        P[-1, -1] = np.inf
    elif kind == "P -inf and +inf":
        P[0, 0], P[-1, -1] = np.inf, -np.inf
    elif kind == "P asymmetric":
        P[0, -1] += 1e-6 * P[0, 0]
    elif kind == "P not positive definite":
        P[-1, -1] = -1.0
    return x, P


BAD = ["x nan", "x inf", "P nan above the diagonal", "P inf on the diagonal",
       "P -inf and +inf", "P asymmetric", "P not positive definite"]


@pytest.mark.parametrize("kind", BAD)
@pytest.mark.parametrize("which", [0, 1])
@pytest.mark.parametrize("n, m", [(4, 2), (10, 9)])  # (9 > 8: the checks on numpy arrays)
def test_partial_estimates_give_the_general_validations_errors(kind, which, n, m):
    """Every bad estimate of kf.fuse(other, H=) and fuse(..., H=) is refused with the error
    of the general validation (as_estimates, the same type and text)."""
    from cifilter import KalmanFilter
    from cifilter._numerics.validation import as_estimates

    rng = np.random.default_rng(n)
    A, B = rng.standard_normal((n, n)), rng.standard_normal((m, m))
    good = [(rng.standard_normal(n), A @ A.T + np.eye(n)),
            (rng.standard_normal(m), B @ B.T + np.eye(m))]
    H = rng.standard_normal((m, n))
    estimates = list(good)
    estimates[which] = _bad(kind, *good[which])
    label = ("this filter", "other")[which]
    with pytest.raises((ValueError, TypeError)) as general:
        as_estimates([estimates[which][0]], [estimates[which][1]], min_count=1,
                     names=("x", "P"), labels=(label,))
    kf = KalmanFilter(dim_x=n, dim_z=m)
    kf.x, kf.P = estimates[0][0].copy(), estimates[0][1].copy()
    before = (kf.x.copy(), kf.P.copy())
    with pytest.raises(type(general.value)) as raised:
        kf.fuse(estimates[1], H=H)
    assert str(raised.value) == str(general.value)
    np.testing.assert_array_equal(kf.x, before[0])  # (the filter is left as it was)
    np.testing.assert_array_equal(kf.P, before[1])
    with pytest.raises((ValueError, TypeError)) as general:
        as_estimates([estimates[which][0]], [estimates[which][1]], min_count=1,
                     names=("x", "P"), labels=(f"estimates[{which}]",))
    with pytest.raises(type(general.value)) as raised:
        fuse(estimates, H=[None, H])
    assert str(raised.value) == str(general.value)


@pytest.mark.parametrize("n, m", [(4, 2), (10, 9)])
def test_partial_estimates_in_every_layout_give_the_same_fusion(n, m):
    """Fortran-ordered and column inputs, and a P asymmetric within the tolerance (taken
    as its symmetric part), fuse as the plain symmetric inputs do, bit for bit; the inputs
    are not modified."""
    rng = np.random.default_rng(m)
    A, B = rng.standard_normal((n, n)), rng.standard_normal((m, m))
    P1, P2 = A @ A.T + np.eye(n), B @ B.T + np.eye(m)
    x1, x2 = rng.standard_normal(n), rng.standard_normal(m)
    H = rng.standard_normal((m, n))
    plain = fuse([(x1, P1), (x2, P2)], H=[None, H])
    E = np.zeros((m, m))
    E[0, -1] = 1e-12 * P2[0, 0]
    skew = P2 + E
    inputs = [(x1[:, None], np.asfortranarray(P1)), (x2, skew)]
    copies = [(x.copy(), P.copy()) for x, P in inputs]
    other = fuse(inputs, H=[None, np.asfortranarray(H)])
    symmetric = fuse([(x1, P1), (x2, 0.5 * (skew + skew.T))], H=[None, H])
    np.testing.assert_array_equal(other.x.ravel(), symmetric.x)
    np.testing.assert_array_equal(other.P, symmetric.P)
    np.testing.assert_allclose(other.P, plain.P, rtol=1e-9)
    assert other.x.shape == (n, 1)
    for (x, P), (x0, P0) in zip(inputs, copies):
        np.testing.assert_array_equal(x, x0)
        np.testing.assert_array_equal(P, P0)
