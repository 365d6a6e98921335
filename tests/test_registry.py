"""The registry, fuse() and FusionResult."""

import dataclasses
import types

import numpy as np
import pytest

import cifilter
from cifilter import FusionResult, available_methods, fuse, get_method, register_method
from cifilter import registry as registry_module


@pytest.fixture
def scratch_registry(monkeypatch):
    """Register test rules in a copy of the registry that is restored afterwards."""
    monkeypatch.setattr(registry_module, "_REGISTRY", dict(registry_module._REGISTRY))


def test_builtin_methods_are_registered():
    assert {"ci", "naive", "optimal"} <= set(available_methods())
    assert get_method("ci").guarantee == "bound"
    assert get_method("optimal").guarantee == "exact"
    assert get_method("naive").guarantee == "none"


def test_unknown_method_lists_registered_names():
    with pytest.raises(ValueError, match=r"unknown fusion method 'nope'.*'ci'.*'naive'"):
        fuse([(np.zeros(2), np.eye(2))] * 2, method="nope")


def test_user_rule_can_be_registered_and_used(scratch_registry):
    calls = []

    def average(xs, Ps, scale=1.0):
        calls.append((xs.shape, Ps.shape))
        n, count = xs.shape[-1], xs.shape[-2]
        gains = np.broadcast_to(np.eye(n) / count, Ps.shape).copy()
        return FusionResult(xs.mean(axis=-2), scale * Ps.mean(axis=-3), "average", gains=gains)

    register_method("average", average, summary="mean of the inputs")
    r = fuse([(np.zeros((2, 1)), np.eye(2)), (np.ones(2), np.eye(2))], "average", scale=2.0)
    assert calls == [((2, 2), (2, 2, 2))]  # the rule sees validated row-style arrays
    assert r.x.shape == (2, 1)  # the caller sees its own style
    np.testing.assert_allclose(r.P, 2 * np.eye(2))
    with pytest.raises(ValueError, match="already registered"):
        register_method("average", average)
    register_method("average", average, replace=True)


def test_unknown_option_names_the_option_and_the_accepted_ones():
    with pytest.raises(TypeError, match=r"'ci' does not accept option.*'weights'.*'criterion'"):
        fuse([(np.zeros(2), np.eye(2))] * 2, method="ci", weights=[0.5, 0.5])


def test_rule_returning_something_else_is_a_type_error(scratch_registry):
    register_method("broken", lambda xs, Ps: (xs, Ps))
    with pytest.raises(TypeError, match="not FusionResult"):
        fuse([(np.zeros(2), np.eye(2))] * 2, method="broken")


@pytest.mark.parametrize("kwargs, error", [
    (dict(name=3, function=len), TypeError),
    (dict(name="", function=len), ValueError),
    (dict(name="x", function=3), TypeError),
    (dict(name="x", function=len, guarantee="maybe"), ValueError),
    (dict(name="x", function=len, truth_options=3), TypeError),
])
def test_bad_registrations_are_rejected(scratch_registry, kwargs, error):
    with pytest.raises(error):
        register_method(**kwargs)


def test_estimates_may_be_filters_pairs_and_batches():
    kf = cifilter.KalmanFilter(dim_x=2, dim_z=1)
    kf.P = np.diag([1.0, 4.0])
    r = fuse([kf, (np.ones(2), np.diag([4.0, 1.0]))])
    assert r.x.shape == (2, 1)  # the filter's column style
    batch = fuse([(np.zeros((5, 2)), np.eye(2)), (np.ones((5, 2)), 2 * np.eye(2))], "naive")
    assert batch.x.shape == (5, 2) and batch.P.shape == (5, 2, 2)


@pytest.mark.parametrize("estimates, error, message", [
    ([(np.zeros(2), np.eye(2))], ValueError, "at least 2"),
    ([(np.zeros(2), np.eye(2)), 3], TypeError, r"estimates\[1\]"),
    ("ab", TypeError, "sequence"),
    (None, TypeError, "sequence"),
])
def test_bad_estimates_are_named(estimates, error, message):
    with pytest.raises(error, match=message):
        fuse(estimates)


def test_fusion_result_is_immutable():
    r = fuse([(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))])
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.x = np.zeros(2)
    for array in (r.x, r.P, r.omega, r.gains):
        with pytest.raises(ValueError, match="read-only"):
            array[...] = 0
    assert isinstance(r.info, types.MappingProxyType)
    with pytest.raises(TypeError):
        r.info["value"] = 0
    assert "FusionResult(method='ci'" in repr(r)


def test_replace_returns_a_new_result():
    r = fuse([(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))])
    s = r.replace(method="other")
    assert s.method == "other" and r.method == "ci"
    np.testing.assert_array_equal(s.P, r.P)


def test_missing_required_option_names_the_option_and_the_method():
    with pytest.raises(TypeError, match=r"method 'optimal' needs the option\(s\) 'joint'"):
        fuse([(np.zeros(2), np.eye(2))] * 2, method="optimal")


def test_required_options_of_user_rules_are_checked_generically(scratch_registry):
    def scaled(xs, Ps, scale, *, offset, shift=0.0):
        return FusionResult(xs[..., 0, :] + offset + shift, scale * Ps[..., 0, :, :], "scaled")

    register_method("scaled", scaled)
    expected = (r"method 'scaled' needs the option\(s\) 'scale', 'offset': "
                r"fuse\(estimates, method='scaled', scale=\.\.\., offset=\.\.\.\)")
    with pytest.raises(TypeError, match=expected):
        fuse([(np.zeros(2), np.eye(2))] * 2, method="scaled")
    with pytest.raises(TypeError, match=r"needs the option\(s\) 'offset'"):
        fuse([(np.zeros(2), np.eye(2))] * 2, method="scaled", scale=2.0)
    r = fuse([(np.zeros(2), np.eye(2))] * 2, method="scaled", scale=2.0, offset=1.0)
    np.testing.assert_array_equal(r.x, [1.0, 1.0])


def test_option_errors_come_before_the_validation_of_the_estimates():
    # The option is the first thing wrong that the caller can see without computing.
    with pytest.raises(TypeError, match="does not accept"):
        fuse([(np.zeros(2), -np.eye(2))] * 2, method="ci", weights=1)


@pytest.mark.parametrize("estimates, error, message", [
    ([(np.array([1 + 5j, 0.0]), np.eye(2)), (np.zeros(2), np.eye(2))], TypeError,
     r"estimates' x\[0\] must be real"),
    ([(np.zeros(2), np.ones(2)), (np.zeros(2), np.ones(2))], ValueError,
     r"estimates' P\[0\] must be a square matrix"),
    ([(np.zeros(2), np.ones((2, 2))), (np.zeros(2), np.eye(2))], ValueError,
     r"estimates' P\[0\] is too ill-conditioned.*condition number infinite"),
    ([(np.zeros(2), np.eye(2, dtype=bool)), (np.zeros(2), np.eye(2))], TypeError,
     r"estimates' P\[0\] must be a numeric array, got booleans"),
])
def test_bad_values_through_fuse_are_named(estimates, error, message):
    with pytest.raises(error, match=message):
        fuse(estimates)
