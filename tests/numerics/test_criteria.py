"""Criteria of a fused covariance bound (cifilter._numerics.criteria)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.optimize import minimize
from strategies import covariance_sets

from cifilter._numerics.criteria import (
    certified_gap,
    criterion_gradient,
    criterion_of_factor,
    criterion_report,
    criterion_value,
    parse_criterion,
)
from cifilter._numerics.information import information_factors, lower_inverse_stack
from cifilter._numerics.linalg import IllConditionedError

rng = np.random.default_rng(12)
W2 = np.array([[2.0, 0.5], [0.5, 1.0]])


def spd(shape, n):
    A = rng.standard_normal(shape + (n, n))
    return A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(n)


# ------------------------------------------------------------------ parse_criterion
def test_parse_criterion_names():
    assert parse_criterion("trace", 3) == ("trace", None)
    assert parse_criterion("det", 3) == ("det", None)
    kind, W = parse_criterion(W2.tolist(), 2)
    assert kind == "weighted-trace" and isinstance(W, np.ndarray)
    np.testing.assert_array_equal(W, W2)
    kind, W = parse_criterion(np.diag([1.0, 0.0]), 2)  # semidefinite is enough
    assert kind == "weighted-trace"


@pytest.mark.parametrize("criterion, error, message", [
    ("Trace", ValueError, r"^criterion must be 'trace', 'det' or a positive semidefinite 2x2 "
                          r"weight matrix, got 'Trace'"),
    ("logdet", ValueError, r"got 'logdet'"),
    (np.eye(3), ValueError, r"^criterion must be a 2x2 weight matrix, got shape \(3, 3\)"),
    (np.zeros((2, 2)), ValueError, r"^criterion must not be the zero matrix"),
    (-np.eye(2), ValueError, r"^criterion must be positive semidefinite"),
    (np.array([[1.0, 1.0], [0.0, 1.0]]), ValueError, r"^criterion must be symmetric"),
    (np.diag([1.0, np.nan]), ValueError, r"^criterion contains non-finite"),
    (None, TypeError, r"^criterion must be a numeric array"),
    (np.eye(2, dtype=bool), TypeError, r"^criterion must be a numeric array, got booleans"),
])
def test_parse_criterion_rejects_bad_values_naming_the_criterion(criterion, error, message):
    with pytest.raises(error, match=message):
        parse_criterion(criterion, 2)


# ------------------------------------------------------------------ values and gradients
def test_criterion_value_and_of_factor():
    P = spd((4,), 2)
    np.testing.assert_allclose(criterion_value(P, "det", None), np.linalg.det(P), rtol=1e-12)
    np.testing.assert_allclose(criterion_value(P, "trace", None), P[:, 0, 0] + P[:, 1, 1])
    np.testing.assert_allclose(criterion_value(P, "weighted-trace", W2),
                               [np.trace(W2 @ p) for p in P], rtol=1e-12)
    R_inv = np.linalg.cholesky(P).swapaxes(-1, -2)  # P = R_inv^T R_inv
    np.testing.assert_allclose(criterion_of_factor(R_inv, "trace", None),
                               criterion_value(P, "trace", None), rtol=1e-12)
    np.testing.assert_allclose(criterion_of_factor(R_inv, "det", None),
                               np.linalg.slogdet(P)[1], rtol=1e-12)
    np.testing.assert_allclose(criterion_of_factor(R_inv, "weighted-trace", W2),
                               criterion_value(P, "weighted-trace", W2), rtol=1e-12)


def objective(L_inv, w, kind, W):
    return criterion_of_factor(information_factors(L_inv, w).R_inv, kind, W)


@pytest.mark.parametrize("kind, W", [("trace", None), ("det", None), ("weighted-trace", W2)])
def test_criterion_gradient_is_minus_the_derivative_in_the_weights(kind, W):
    Ps = spd((3,), 2)
    L_inv = lower_inverse_stack(np.linalg.cholesky(Ps))
    w = np.array([0.2, 0.5, 0.3])
    g = criterion_gradient(information_factors(L_inv, w), kind, W)
    h = 1e-6
    numeric = np.array([
        (objective(L_inv, w + h * e, kind, W) - objective(L_inv, w - h * e, kind, W)) / (2 * h)
        for e in np.eye(3)
    ])
    np.testing.assert_allclose(g, -numeric, rtol=1e-6)
    assert (g > 0).all()


# ------------------------------------------------------------------ certified gap
def reference_minimum(L_inv, kind, W):
    """min over the simplex: a grid of step 1/60 polished by SLSQP from its best points."""
    count = L_inv.shape[0]
    ticks = np.arange(61) / 60.0
    grid = np.array([w for w in np.stack(np.meshgrid(*[ticks] * (count - 1)), -1).reshape(
        -1, count - 1) if w.sum() <= 1.0 + 1e-12])
    grid = np.concatenate([grid, 1.0 - grid.sum(axis=-1, keepdims=True)], axis=-1)
    grid = np.clip(grid, 0.0, None)
    factors = information_factors(np.broadcast_to(L_inv, (len(grid),) + L_inv.shape), grid,
                                  failures="nan")
    values = criterion_of_factor(factors.R_inv, kind, W)
    ok = np.isfinite(values)
    best = values[ok].min()

    def f(w):
        w = np.clip(w, 0.0, None)
        w = w / w.sum()
        return float(objective(L_inv, w, kind, W))

    for start in grid[ok][np.argsort(values[ok])[:2]]:
        result = minimize(f, start, method="SLSQP", bounds=[(0.0, 1.0)] * count,
                          constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1.0}],
                          options={"ftol": 1e-15, "maxiter": 300})
        best = min(best, f(result.x))
    return best


@given(
    covariance_sets(3, 2),
    arrays(float, (3,), elements=st.floats(0.0, 1.0)),
    st.sampled_from([("trace", None), ("det", None), ("weighted-trace", W2)]),
)
def test_certified_gap_bounds_the_excess_over_the_minimum(Ps, raw, criterion):
    kind, W = criterion
    if raw.sum() == 0.0:
        raw = np.ones(3)
    w = raw / raw.sum()
    L_inv = lower_inverse_stack(np.linalg.cholesky(np.stack(Ps)))
    factors = information_factors(L_inv, w)
    value = criterion_of_factor(factors.R_inv, kind, W)
    g = criterion_gradient(factors, kind, W)
    gap = certified_gap(w, g, value, kind)
    assert gap >= 0.0
    best = reference_minimum(L_inv, kind, W)
    excess = value - best  # log det units for det, else relative to f(w) like the gap
    if kind != "det":
        excess = excess / value
    assert excess <= gap + 1e-12 * (1.0 + abs(value))
    assert best <= value + 1e-12 * (1.0 + abs(value))


def test_certified_gap_is_zero_at_a_vertex_that_is_optimal_and_positive_elsewhere():
    # the first estimate is better in every direction: w = e_1 is optimal
    Ps = np.stack([np.eye(2), 4.0 * np.eye(2), np.diag([9.0, 2.0])])
    L_inv = lower_inverse_stack(np.linalg.cholesky(Ps))
    for kind in ("trace", "det"):
        w = np.array([1.0, 0.0, 0.0])
        factors = information_factors(L_inv, w)
        value = criterion_of_factor(factors.R_inv, kind, None)
        assert certified_gap(w, criterion_gradient(factors, kind, None), value, kind) == 0.0
        w = np.full(3, 1 / 3)
        factors = information_factors(L_inv, w)
        value = criterion_of_factor(factors.R_inv, kind, None)
        assert certified_gap(w, criterion_gradient(factors, kind, None), value, kind) > 0.1


def test_certified_gap_relative_for_traces_absolute_for_det():
    w, g = np.array([0.5, 0.5]), np.array([3.0, 1.0])  # max g - w.g = 1
    assert certified_gap(w, g, 4.0, "trace") == 0.25
    assert certified_gap(w, g, 4.0, "weighted-trace") == 0.25
    assert certified_gap(w, g, 4.0, "det") == 1.0
    batch = certified_gap(np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([[3.0, 1.0]] * 2),
                          np.array([2.0, 2.0]), "trace")
    np.testing.assert_array_equal(batch, [0.0, 1.0])


# ------------------------------------------------------------------ criterion_report
def test_criterion_report_values():
    P = np.diag([2.0, 3.0])
    report = criterion_report(P, "det", None)
    assert report["value"] == pytest.approx(6.0) and report["log_value"] == pytest.approx(
        np.log(6.0))
    assert criterion_report(P, "trace", None) == {"value": 5.0}
    assert criterion_report(P, "weighted-trace", W2)["value"] == pytest.approx(7.0)
    tiny = criterion_report(1e-200 * np.eye(3), "det", None)  # det underflows, log does not
    assert tiny["value"] == 0.0 and tiny["log_value"] == pytest.approx(-600 * np.log(10))


@pytest.mark.parametrize("P", [
    np.diag([1.0, 0.0]), np.diag([1.0, 1e-17]), np.ones((2, 2)), np.diag([1.0, np.nan]),
    np.diag([1.0, -1.0]),
])
@pytest.mark.parametrize("kind", ["trace", "det"])
def test_criterion_report_rejects_a_singular_fused_covariance(P, kind):
    with pytest.raises(IllConditionedError, match=r"^the fused covariance is too "
                                                   r"ill-conditioned"):
        criterion_report(np.stack([np.eye(2), P]), kind, None)
