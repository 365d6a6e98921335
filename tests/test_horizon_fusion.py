"""cifilter.fuse(..., horizon=, model=): the hooks of cifilter.horizon.fusion."""

import numpy as np
import pytest
from test_horizon import F_DYN, H_A, Q_DYN, R_A, dynamic_filter, local_bounds_at_zero

from cifilter import covariance_intersection, fuse, partial_ci
from cifilter.horizon import horizon_weights, optimal_omega

MODEL = dict(F=F_DYN, Q=Q_DYN, H=H_A, R=R_A)


def estimates():
    PA, PB = local_bounds_at_zero()
    return [(np.array([1.0, 2.0]), PA), (np.array([0.0, 1.0]), PB)]


@pytest.mark.parametrize("method, options", [("ci", {}), ("pci", {"rho": 0.5})])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_fuse_with_horizon_equals_the_filter_and_nests_the_diagnostics(method, options,
                                                                       criterion):
    r = fuse(estimates(), method=method, horizon=7, model=MODEL, criterion=criterion,
             **options)
    kf = dynamic_filter("A")
    kf.x, kf.P = np.array([[1.0], [2.0]]), estimates()[0][1]
    rk = kf.fuse(estimates()[1], method, horizon=7, criterion=criterion, **options)
    np.testing.assert_array_equal(r.P, rk.P)
    np.testing.assert_array_equal(r.weights, rk.weights)
    chosen = r.info["horizon"]
    assert r.info["rule"] == "horizon" and chosen["steps"] == 7
    assert set(chosen) >= {"steps", "criterion", "value", "value_recursive",
                           "weights_recursive", "iterations", "converged", "gap", "solver"}
    expected = optimal_omega([p for _, p in estimates()], F_DYN, Q_DYN, H_A, R_A, 7,
                             criterion, rho=options.get("rho"))
    for key in ("converged", "gap", "iterations"):
        np.testing.assert_array_equal(r.info[key], chosen[key])
        np.testing.assert_array_equal(chosen[key], expected.info[key])
    assert chosen["value"] == expected.value
    assert chosen["value_recursive"] >= chosen["value"]


def test_horizon_zero_is_the_plain_rule_bit_for_bit():
    xs = [x for x, _ in estimates()]
    Ps = [P for _, P in estimates()]
    for criterion in ("trace", "det"):
        r = fuse(estimates(), method="ci", horizon=0, model=MODEL, criterion=criterion)
        plain = covariance_intersection(xs, Ps, criterion)
        np.testing.assert_array_equal(r.omega, plain.omega)
        np.testing.assert_allclose(r.P, plain.P, rtol=1e-14)  # assembled from fixed weights
        h = horizon_weights(Ps, F_DYN, Q_DYN, H_A, R_A, 0, criterion)
        np.testing.assert_array_equal(h.omega, plain.omega)
    r = fuse(estimates(), method="pci", rho=0.4, horizon=0, model=MODEL)
    plain = partial_ci(xs, Ps, 0.4)
    np.testing.assert_array_equal(r.info["delta"], plain.info["delta"])
    h = horizon_weights(Ps, F_DYN, Q_DYN, H_A, R_A, 0, rho=0.4)
    np.testing.assert_array_equal(h.omega, plain.info["delta"])


def test_three_estimates_and_batches():
    Ps = [np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.diag([1.5, 1.5])]
    pairs = [(np.zeros(2), P) for P in Ps]
    r = fuse(pairs, method="ci", horizon=4, model=MODEL)
    np.testing.assert_allclose(r.omega, horizon_weights(Ps, F_DYN, Q_DYN, H_A, R_A, 4).omega,
                               atol=0)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(method="ei", horizon=2, model=MODEL), ValueError, "does not support horizon="),
    (dict(method="ci", horizon=2), ValueError, "needs the model"),
    (dict(method="ci", model=MODEL), ValueError, "give horizon="),
    (dict(method="ci", horizon=2, model=MODEL, omega=0.5), ValueError, "give one"),
    (dict(method="pci", horizon=2, model=MODEL), ValueError, "correlation coefficient bound"),
    (dict(method="ci", horizon=2, model=MODEL, tol=1.0), TypeError, "accepts the option"),
])
def test_front_door_errors(kwargs, error, match):
    with pytest.raises(error, match=match):
        fuse(estimates(), **kwargs)
