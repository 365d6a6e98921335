"""Contracts of the shared numerics that mutation testing (tools/mutate.py) found untested.

* The convex minimisers report ``converged = False`` when the iteration limit stops them
  short, and True only at a minimiser.
* The simplex minimiser's line search makes every step a descent: on a function whose full
  Newton steps overshoot (pseudo-Huber terms), the iterates' values never increase, and a
  problem it calls converged has a Frank-Wolfe gap (recomputed here) within ``gtol``.
* Tied and nearly tied inputs (a Hessian singular along the ties) converge with equal
  weights.
"""

import numpy as np
import pytest

from cifilter import covariance_intersection
from cifilter._numerics.optimize import (
    minimize_convex_interval,
    minimize_convex_scalar,
    minimize_convex_simplex,
)

# f(w) = log cosh(a (w - c)) / a: convex, f' = tanh(a (w - c)); Newton from afar overshoots.
A, C = 40.0, 0.3


def tanh_derivative(w):
    t = np.tanh(A * (w - C))
    return t, A * (1.0 - t * t)


def test_scalar_minimiser_reports_the_iteration_limit():
    w, iterations, converged = minimize_convex_scalar(
        lambda w: tuple(map(float, tanh_derivative(w))), scale=1.0, max_iter=2)
    assert not converged and iterations == 2
    w, iterations, converged = minimize_convex_scalar(
        lambda w: tuple(map(float, tanh_derivative(w))), scale=1.0)
    assert converged and w == pytest.approx(C, abs=1e-12)


def test_interval_minimiser_reports_the_iteration_limit():
    def derivatives(w, index):
        return tanh_derivative(w)

    w, _, converged = minimize_convex_interval(derivatives, 3, scale=np.ones(3), max_iter=2)
    assert not converged.any()
    w, _, converged = minimize_convex_interval(derivatives, 3, scale=np.ones(3))
    assert converged.all()
    np.testing.assert_allclose(w, C, atol=1e-12)


def test_interval_minimiser_ends_exactly_at_the_end_where_the_minimum_is():
    def derivatives(w, index):  # f = (w - centre)^2 / 2 with centres beyond the ends
        centre = np.array([-0.5, 1.5, 0.25])[index]
        return w - centre, np.ones_like(w)

    w, _, converged = minimize_convex_interval(derivatives, 3, scale=np.ones(3))
    assert converged.all()
    assert w[0] == 0.0 and w[1] == 1.0 and w[2] == pytest.approx(0.25, abs=1e-13)
    for centre, end in ((-0.5, 0.0), (1.5, 1.0)):
        w, _, ok = minimize_convex_scalar(lambda t, c=centre: (t - c, 1.0), scale=1.0)
        assert ok and w == end


# ------------------------------------------------------------------ the simplex
TARGET = np.array([0.72, 0.2, 0.08, 0.0])
SLOPE = np.array([30.0, 60.0, 45.0, 80.0])


def huber(w):
    """sum_i sqrt(1 + (a_i (w_i - c_i))^2) / a_i, with its gradient and Hessian."""
    z = SLOPE * (w - TARGET)
    root = np.sqrt(1.0 + z * z)
    f = (root / SLOPE).sum(axis=-1)
    g = z / root
    h = SLOPE / root**3
    H = h[..., :, None] * np.eye(w.shape[-1])
    return f, g, H


class Recorded:
    def __init__(self):
        self.values = []

    def evaluate(self, w):
        f, g, H = huber(w)
        self.values.append(f.copy())
        return f, g, H

    def objective(self, w):
        return huber(w)[0]


@pytest.mark.parametrize("gtol", [0.0, 1e-12])
def test_every_simplex_step_is_a_descent_and_ends_at_the_minimum(gtol):
    record = Recorded()
    w, _, converged = minimize_convex_simplex(
        record.evaluate, record.objective, 4, (1,), gtol=gtol, max_iter=200)
    values = np.array(record.values)[:, 0]
    rise = np.diff(values)
    assert rise.max() <= 1e-12 * values[0], (values, rise.max())
    assert converged.all()
    f, g, _ = huber(w)
    gap = (w * g).sum(axis=-1) - g.min(axis=-1)
    assert gap[0] <= max(gtol, 1e-12) * f[0] * 10
    # the minimiser of this separable problem on the simplex: w_i = c_i + s_i with a common
    # multiplier; the answer is within 1e-6 of the target, which is on the simplex
    np.testing.assert_allclose(w[0], TARGET, atol=1e-6)


def test_a_converged_simplex_problem_has_its_gap_within_gtol():
    rng = np.random.default_rng(5)
    centres = rng.dirichlet(np.ones(4), size=6)
    curvature = rng.uniform(0.5, 50.0, size=(6, 4))

    def evaluate(w):
        d = w - centres
        f = 0.5 * (curvature * d * d).sum(axis=-1) + 1.0
        return f, curvature * d, curvature[..., :, None] * np.eye(4)

    def objective(w):
        return evaluate(w)[0]

    gtol = 1e-10
    w, _, converged = minimize_convex_simplex(evaluate, objective, 4, (6,), gtol=gtol)
    assert converged.all()
    f, g, _ = evaluate(w)
    gap = (w * g).sum(axis=-1) - g.min(axis=-1)
    assert (gap <= gtol * np.abs(f)).all(), gap / f


@pytest.mark.parametrize("perturbation", [0.0, 1e-12, 1e-9])
def test_tied_inputs_converge_with_equal_weights(perturbation):
    rng = np.random.default_rng(1)
    B = rng.standard_normal((3, 3))
    P = B @ B.T + np.eye(3)
    Ps = [P, P * (1 + perturbation), P * (1 - perturbation)]
    for criterion in ("trace", "det"):
        r = covariance_intersection(np.zeros((3, 3)), Ps, criterion)
        assert r.info["converged"]
        if perturbation == 0.0:
            np.testing.assert_allclose(r.omega, 1 / 3, rtol=1e-12)
        np.testing.assert_allclose(r.P, P, rtol=1e-8)
