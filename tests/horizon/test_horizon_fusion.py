"""cifilter.fuse(..., horizon=, model=): the hooks of cifilter.horizon.fusion; the filters'
``kf.fuse(..., horizon=)`` with their own model or another one."""

import copy

import numpy as np
import pytest
from helpers import F_DYN, H_A, H_B, Q_DYN, R_A, R_B, dynamic_filter, local_bounds_at_zero

from cifilter import ExtendedKalmanFilter, covariance_intersection, fuse, partial_ci
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




# ----------------------------------------------------------------- filters: kf.fuse(horizon=)
@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_filter_fuse_with_horizon_uses_its_own_model(criterion):
    PA, PB = local_bounds_at_zero()
    kf = dynamic_filter("A")
    kf.x, kf.P = np.array([[1.0], [2.0]]), PA.copy()
    other = (np.array([0.0, 1.0]), PB.copy())
    other_copy = copy.deepcopy(other)
    result = kf.fuse(other, horizon=10, criterion=criterion)
    expected = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 10, criterion)
    assert result.omega[0] == pytest.approx(float(expected.omega), abs=1e-12)
    assert kf.last_fusion is result
    chosen = result.info["horizon"]
    assert result.info["rule"] == "horizon" and chosen["steps"] == 10
    assert chosen["criterion"] == criterion
    assert chosen["value"] == pytest.approx(float(expected.value), rel=1e-12)
    assert chosen["value_recursive"] >= chosen["value"]
    assert result.info["converged"] == chosen["converged"] and result.info["gap"] == chosen["gap"]
    plain = covariance_intersection([np.array([1.0, 2.0]), other[0]], [PA, PB],
                                    omega=float(expected.omega))
    np.testing.assert_allclose(kf.x[:, 0], plain.x, rtol=1e-12)
    np.testing.assert_allclose(kf.P, plain.P, rtol=1e-12)
    np.testing.assert_array_equal(kf.P_post, kf.P)
    np.testing.assert_array_equal(other[0], other_copy[0])
    np.testing.assert_array_equal(other[1], other_copy[1])


def test_filter_fuse_horizon_zero_equals_plain_ci_and_model_overrides():
    PA, PB = local_bounds_at_zero()
    kf, plain = dynamic_filter("A"), dynamic_filter("A")
    kf.P, plain.P = PA.copy(), PA.copy()
    r0 = kf.fuse((np.zeros(2), PB), horizon=0, criterion="det")
    rp = plain.fuse((np.zeros(2), PB), criterion="det")
    np.testing.assert_array_equal(r0.omega, rp.omega)
    # filter A fusing as if it were filter B (the model) picks B's omega
    kf.P = PA.copy()
    model = dict(F=F_DYN, Q=Q_DYN, H=H_B, R=R_B)
    r = kf.fuse((np.zeros(2), PB), horizon=30, model=model, criterion="det")
    assert r.omega[0] == pytest.approx(0.853, abs=1e-3)
    kf.P = PA.copy()
    r_obj = kf.fuse((np.zeros(2), PB), horizon=30, model=dynamic_filter("B"), criterion="det")
    assert r_obj.omega[0] == pytest.approx(r.omega[0], abs=1e-12)
    kf.P = PA.copy()
    with pytest.warns(DeprecationWarning, match="model="):
        r_old = kf.fuse((np.zeros(2), PB), horizon=30, future=model, criterion="det")
    np.testing.assert_array_equal(r_old.omega, r.omega)


def test_filter_fuse_with_horizon_and_several_estimates():
    kf = dynamic_filter("A")
    kf.P = np.diag([1.0, 2.0])
    others = [(np.zeros(2), np.diag([2.0, 1.0])), (np.ones(2), np.diag([1.5, 1.5]))]
    r = kf.fuse(others, horizon=4)
    expected = horizon_weights([np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.diag([1.5, 1.5])],
                               F_DYN, Q_DYN, H_A, R_A, 4)
    np.testing.assert_allclose(r.omega, expected.omega, atol=1e-10)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(horizon=2, method="naive"), ValueError, "does not support horizon="),
    (dict(horizon=2, omega=0.3), ValueError, "give one"),
    (dict(model=dict(F=F_DYN, Q=Q_DYN)), ValueError, "give horizon="),
    (dict(horizon=2, model=dict(F=F_DYN)), ValueError, "at least F and Q"),
    (dict(horizon=2, model=dict(F=F_DYN, Q=Q_DYN, X=1)), ValueError, "unknown entries"),
    (dict(horizon=-1), ValueError, "horizon must be >= 0"),
    (dict(horizon=2, model=dict(F=np.eye(3), Q=Q_DYN)), ValueError, "F must have shape"),
    (dict(horizon=2, criterion="max"), ValueError, "criterion"),
    # partial-correlation CI (tests/horizon/test_horizon_pci.py)
    (dict(method="pci", horizon=2), ValueError, "needs a correlation coefficient bound"),
    (dict(method="pci", rho=0.5, delta=[0.5, 0.5], horizon=2), ValueError, "give one"),
    (dict(method="pci", rho=0.5, horizon=2, tol=1e-3), TypeError, "accepts the option"),
    (dict(method="pci", rho=1.5, horizon=2), ValueError, "rho must lie"),
    (dict(method="pci", rho=[0.1, 0.2, 0.3], horizon=2), ValueError, "rho must be a scalar"),
    (dict(method="pci", rho=0.5, horizon=2, criterion="max"), ValueError, "criterion"),
    (dict(method="pci", rho=0.5, horizon=-1), ValueError, "horizon must be >= 0"),
    (dict(method="pci", rho=0.5, model=dict(F=F_DYN, Q=Q_DYN)), ValueError, "give horizon="),
    (dict(method="naive", horizon=2), ValueError, "'ci', 'pci'"),
])
def test_filter_fuse_with_horizon_is_atomic_on_bad_input(kwargs, error, match):
    kf = dynamic_filter("A")
    kf.x, kf.P = np.array([[1.0], [2.0]]), np.diag([1.0, 2.0])
    before = copy.deepcopy(kf.__dict__)
    with pytest.raises(error, match=match):
        kf.fuse((np.zeros(2), np.eye(2)), **kwargs)
    np.testing.assert_array_equal(kf.x, before["x"])
    np.testing.assert_array_equal(kf.P, before["P"])
    assert kf.last_fusion is None


def test_extended_filter_needs_a_model():
    ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    ekf.P = np.diag([1.0, 2.0])
    with pytest.raises(ValueError, match="no matrix H"):
        ekf.fuse((np.zeros(2), np.eye(2)), horizon=3)
    assert ekf.last_fusion is None
    r = ekf.fuse((np.zeros(2), np.eye(2)), horizon=3,
                 model=dict(F=ekf.F, Q=ekf.Q, H=np.array([[1.0, 0.0]]), R=ekf.R))
    assert r.info["horizon"]["steps"] == 3 and ekf.last_fusion is r
