"""The horizon recursion with measurements at large and small scales, against a Kalman filter
written out in the test (prediction (16), gain (32), Joseph form (33)) and a bounded scalar
search for the weight: an independent reference, not the package's recursion.

Where the prior bound is much larger than the measurement noise, the Joseph form's
``K R K^T`` term is a small part of the posterior (a sign error in it changed the result by
4.6e-6 and passed every earlier test); these tests compare to 1e-9.
"""

import mpmath
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from cifilter import fuse, propagate_bound
from cifilter.horizon import optimal_omega

F = np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.5], [0.0, 0.0, 0.9]])
Q = np.array([[0.2, 0.05, 0.0], [0.05, 0.3, 0.02], [0.0, 0.02, 0.1]])
H = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
R = np.array([[0.5, 0.1], [0.1, 0.8]])
PA = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
PB = np.array([[2.0, -0.3, 0.0], [-0.3, 5.0, 1.0], [0.0, 1.0, 1.5]])


def kalman_steps(P, F, Q, H, R, steps, digits=40):
    """Prediction and Joseph-form update with the optimal gain, ``steps`` times, in
    ``digits``-digit arithmetic from the float64 inputs; rounded to float64 at the end."""
    with mpmath.workdps(digits):
        P, F, Q, H, R = (mpmath.matrix(np.asarray(A, dtype=float).tolist())
                         for A in (P, F, Q, H, R))
        eye = mpmath.eye(P.rows)
        for _ in range(steps):
            M = F * P * F.T + Q
            S = H * M * H.T + R
            K = M * H.T * mpmath.inverse(S)
            A = eye - K * H
            P = A * M * A.T + K * R * K.T
            P = (P + P.T) / 2
        return np.array(P.tolist(), dtype=float)


def tolerance(prior):
    """Rounding of order cond * eps: the bound's condition relative to the noise is about
    ``prior`` (or its inverse), plus a floor."""
    return 1e-10 + 16 * np.finfo(float).eps * max(prior, 1.0 / prior)


def ci(omega, Pa, Pb):
    return np.linalg.inv(omega * np.linalg.inv(Pa) + (1 - omega) * np.linalg.inv(Pb))


# prior scale relative to the noise, and the overall scale of everything
CASES = [(1.0, 1.0), (1e8, 1.0), (1e8, 1e-12), (1e8, 1e12), (1e-6, 1e6), (1.0, 1e12)]


@pytest.mark.parametrize("prior, scale", CASES)
@pytest.mark.parametrize("steps", [1, 3, 12])
def test_propagated_bound_matches_a_kalman_filter_at_every_scale(prior, scale, steps):
    P0 = prior * scale * PA
    expected = kalman_steps(P0, F, scale * Q, H, scale * R, steps)
    got = propagate_bound(P0, F, scale * Q, H, scale * R, steps)
    np.testing.assert_allclose(got, expected, rtol=tolerance(prior), atol=0)


@pytest.mark.parametrize("prior, scale", CASES)
@pytest.mark.parametrize("steps", [1, 4])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_horizon_ci_value_and_weight_match_an_independent_search(prior, scale, steps, criterion):
    Pa, Pb = prior * scale * PA, prior * scale * PB
    q, r = scale * Q, scale * R

    def value(omega):
        P = kalman_steps(ci(omega, Pa, Pb), F, q, H, r, steps)
        if criterion == "trace":
            return np.trace(P) / scale
        return np.linalg.slogdet(P / scale)[1]

    result = optimal_omega(Pa, Pb, F, q, H, r, steps, criterion)
    omega = float(result.omega)
    # the value the package reports is the criterion of the bound at its weight
    P = kalman_steps(ci(omega, Pa, Pb), F, q, H, r, steps)
    tol = tolerance(prior)
    np.testing.assert_allclose(result.P, P, rtol=tol)
    if criterion == "trace":
        np.testing.assert_allclose(result.value, np.trace(P), rtol=tol)
    else:
        np.testing.assert_allclose(np.log(result.value), np.linalg.slogdet(P)[1],
                                   rtol=tol, atol=tol)
    # and its weight is the minimiser (to the flatness of the criterion near it)
    best = minimize_scalar(value, bounds=(0.0, 1.0), method="bounded",
                           options={"xatol": 1e-12})
    assert value(omega) <= min(best.fun, value(0.0), value(1.0)) + tol * abs(best.fun)
    # fuse(..., horizon=) gives the same bound
    fused = fuse([(np.zeros(3), Pa), (np.ones(3), Pb)], method="ci", horizon=steps,
                 model=dict(F=F, Q=q, H=H, R=r), criterion=criterion)
    np.testing.assert_allclose(fused.weights[0], omega, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("prior", [1.0, 1e8])
def test_horizon_weights_of_three_estimates_and_a_batch(prior):
    """Three estimates (the weights minimise the propagated trace over the simplex, checked
    against a grid refined around the answer) and a batch of two problems equal to the
    problems one at a time (supersedes test_horizon_fusion.py::
    test_three_estimates_and_batches, which had no batch and compared the code path with
    itself)."""
    Ps = [prior * PA, prior * PB, prior * np.diag([3.0, 1.0, 2.5])]
    steps = 3
    r = fuse([(np.zeros(3), P) for P in Ps], method="ci", horizon=steps,
             model=dict(F=F, Q=Q, H=H, R=R))
    w = np.asarray(r.weights)
    assert w.shape == (3,) and abs(w.sum() - 1) < 1e-12 and (w >= 0).all()

    def value(weights):
        info = sum(wi * np.linalg.inv(P) for wi, P in zip(weights, Ps))
        return np.trace(kalman_steps(np.linalg.inv(info), F, Q, H, R, steps))

    here = value(w)
    np.testing.assert_allclose(r.info["horizon"]["value"], here, rtol=tolerance(prior))
    rng = np.random.default_rng(0)
    for radius in (1e-1, 1e-2, 1e-3):
        for _ in range(30):
            other = np.clip(w + radius * rng.standard_normal(3), 0.0, None)
            if other.sum() == 0:
                continue
            assert here <= value(other / other.sum()) * (1 + tolerance(prior))
    # a batch: the two problems stacked give each one's answer
    Ps2 = [prior * PB, prior * PA, prior * np.diag([1.0, 2.0, 1.0])]
    r2 = fuse([(np.zeros(3), P) for P in Ps2], method="ci", horizon=steps,
              model=dict(F=F, Q=Q, H=H, R=R))
    batch = fuse([(np.zeros((2, 3)), np.stack([P1, P2])) for P1, P2 in zip(Ps, Ps2)],
                 method="ci", horizon=steps, model=dict(F=F, Q=Q, H=H, R=R))
    np.testing.assert_allclose(batch.weights[0], r.weights, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(batch.weights[1], r2.weights, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(batch.P[1], r2.P, rtol=tolerance(prior))


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_study_values_against_an_independent_filter_and_its_plot(criterion):
    """Every field of horizon_study checked against the test's own Kalman filter and scalar
    search, and the plot drawing those numbers (supersedes test_horizon_study.py::
    test_study_result_fields_and_plot, which checked only shapes)."""
    import matplotlib.pyplot as plt

    from cifilter.horizon import horizon_study

    horizons = [0, 1, 3, 6]
    s = horizon_study(PA, PB, F, Q, H, R, horizons, criterion)
    assert s.horizons.tolist() == horizons and s.criterion == criterion

    def crit(P):
        return np.trace(P) if criterion == "trace" else np.linalg.det(P)

    def value(omega, steps):
        return crit(kalman_steps(ci(omega, PA, PB), F, Q, H, R, steps, digits=30))

    w0 = minimize_scalar(lambda w: value(w, 0), bounds=(0, 1), method="bounded",
                         options={"xatol": 1e-12}).x
    assert float(s.omega_recursive) == pytest.approx(w0, abs=1e-6)
    for k, steps in enumerate(horizons):
        P_batch = kalman_steps(ci(s.omega[k], PA, PB), F, Q, H, R, steps)
        np.testing.assert_allclose(s.P_batch[k], P_batch, rtol=1e-9)
        np.testing.assert_allclose(s.batch[k], crit(P_batch), rtol=1e-9)
        P_rec = kalman_steps(ci(float(s.omega_recursive), PA, PB), F, Q, H, R, steps)
        np.testing.assert_allclose(s.P_recursive[k], P_rec, rtol=1e-9)
        np.testing.assert_allclose(s.recursive[k], crit(P_rec), rtol=1e-9)
        best = minimize_scalar(value, bounds=(0, 1), args=(steps,), method="bounded",
                               options={"xatol": 1e-12})
        assert s.batch[k] <= min(best.fun, value(0.0, steps), value(1.0, steps)) * (1 + 1e-9)
        assert s.batch[k] <= s.recursive[k] * (1 + 1e-12)
    # the steady state: a fixed point of the filter's step
    steady = kalman_steps(s.steady_P, F, Q, H, R, 1)
    np.testing.assert_allclose(steady, s.steady_P, rtol=1e-9)
    np.testing.assert_allclose(s.steady_value, crit(s.steady_P), rtol=1e-9)
    fig = s.plot(label="A")
    try:
        ax_omega, ax_value = fig.axes
        np.testing.assert_array_equal(ax_omega.lines[0].get_ydata(), s.omega)
        np.testing.assert_array_equal(ax_value.lines[0].get_ydata(), s.batch)
        np.testing.assert_array_equal(ax_value.lines[1].get_ydata(), s.recursive)
        np.testing.assert_array_equal(ax_omega.lines[0].get_xdata(), horizons)
    finally:
        plt.close(fig)


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_horizon_beyond_the_float_range_of_the_recursion_scale(criterion):
    """An unstable mode that no sensor sees grows the bound past 2^200 within the horizon,
    where the recursion moves its scale into an exponent, while the measured mode keeps
    adding information: the value and the weight still match the test's own filter in
    40 digits."""
    F2 = np.array([[2.0, 0.3], [0.0, 0.8]])
    Q2 = np.array([[0.1, 0.02], [0.02, 0.2]])
    H2, R2 = np.array([[0.0, 1.0]]), np.array([[0.5]])
    Pa = np.array([[2.0, 0.3], [0.3, 1.0]])
    Pb = np.array([[1.0, -0.2], [-0.2, 3.0]])
    steps = 130  # 2^260 > 2^200
    result = optimal_omega(Pa, Pb, F2, Q2, H2, R2, steps, criterion)
    omega = float(result.omega)

    def value(w):
        P = kalman_steps(ci(w, Pa, Pb), F2, Q2, H2, R2, steps, digits=30)
        return np.log(np.trace(P)) if criterion == "trace" else np.linalg.slogdet(P)[1]

    expected = value(omega)
    got = np.log(float(result.value))
    assert np.isfinite(got) and got > np.log(2.0) * 200
    np.testing.assert_allclose(got, expected, rtol=1e-10)
    # a minimum: no better value at the ends or a little to either side
    for other in (0.0, 1.0, max(omega - 1e-4, 0.0), min(omega + 1e-4, 1.0)):
        assert expected <= value(other) + 1e-12
