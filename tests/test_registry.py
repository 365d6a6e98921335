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
    (dict(name="x", function=len, horizon=len), TypeError),  # a horizon hook needs a core
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


# --------------------------------------------------------------------------- the front door
def _pair():
    return [(np.array([1.0, 0.0]), np.diag([1.0, 4.0])),
            (np.array([0.0, 1.0]), np.diag([4.0, 1.0]))]


def _model():
    return dict(F=np.array([[1.0, 1.0], [0.0, 1.0]]), Q=0.1 * np.eye(2),
                H=np.array([[1.0, 0.0]]), R=np.eye(1))


def test_builtin_rules_are_registered_in_their_documented_order():
    assert available_methods()[:7] == ("ci", "naive", "optimal", "pci", "ei", "pcei", "bayes")


def test_fuse_validates_the_estimates_once(monkeypatch):
    """The rule's core gets the validated estimates: no second check of the covariances."""
    import cifilter._numerics.validation as validation

    calls = []
    original = validation.as_estimates

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    rules = cifilter.rules
    for module in (validation, registry_module, rules.ci, rules.pci, rules.optimal, rules.bayes):
        if hasattr(module, "as_estimates"):
            monkeypatch.setattr(module, "as_estimates", counting)
    for method, options in [("ci", {}), ("ci", {"omega": "fast"}), ("naive", {}),
                            ("pci", {"rho": 0.5}), ("bayes", {"samples": 5, "rng": 0})]:
        calls.clear()
        fuse(_pair(), method, **options)
        # plain "ci" of two pairs takes the rule's pair route, whose checks run inside
        # the compiled call or the lean LAPACK path: no Python validation at all there
        assert len(calls) == (0 if (method, options) == ("ci", {}) else 1), method
        calls.clear()
        if get_method(method).horizon is not None and "omega" not in options:
            fuse(_pair(), method, horizon=3, model=_model(), **options)
            assert len(calls) == 1, method


def test_core_receives_factorised_estimates(scratch_registry):
    seen = {}

    def core(estimates):
        seen["estimates"] = estimates
        return FusionResult(estimates.x[..., 0, :], estimates.P[..., 0, :, :], "first")

    register_method("first", lambda xs, Ps: None, core=core)
    fuse(_pair(), "first")
    est = seen["estimates"]
    np.testing.assert_allclose(est.L @ np.swapaxes(est.L, -1, -2), est.P)
    assert est.x.shape == (2, 2) and est.count == 2 and est.dim == 2


@pytest.mark.parametrize("method, options", [
    ("ci", {}), ("ci", {"criterion": "det"}), ("ci", {"omega": "fast"}), ("naive", {}),
    ("pci", {"rho": 0.3}), ("ei", {}), ("pcei", {}), ("bayes", {"samples": 20, "rng": 1}),
])
def test_fuse_equals_the_rule_function(method, options):
    record = get_method(method)
    xs, Ps = [p[0] for p in _pair()], [p[1] for p in _pair()]
    via_fuse = fuse(_pair(), method, **options)
    direct = record.function(xs, Ps, **options)
    np.testing.assert_array_equal(via_fuse.x, direct.x)
    np.testing.assert_array_equal(via_fuse.P, direct.P)


def test_every_result_has_weights_with_one_meaning():
    pair = _pair()
    ci = fuse(pair, "ci")
    np.testing.assert_array_equal(ci.weights, ci.omega)
    assert ci.weights.sum() == pytest.approx(1.0)
    naive = fuse(pair, "naive")
    np.testing.assert_array_equal(naive.weights, [1.0, 1.0])
    pci = fuse(pair, "pci", rho=0.5)
    assert pci.omega is None and pci.weights.sum() > 1.0  # eq. (24): not on the simplex
    d, rho = pci.info["delta"], pci.info["rho"]
    np.testing.assert_allclose(pci.weights, d / (rho + (1 - rho) * d))
    for method in ("ei", "pcei", "bayes"):
        assert fuse(pair, method).weights is None
    for method in ("ci", "naive", "optimal", "pci", "bayes"):
        assert get_method(method).weights  # documented per rule


@pytest.mark.parametrize("method, options, fixed", [
    ("ci", {}, "omega"), ("ci", {"criterion": "det"}, "omega"),
    ("pci", {"rho": 0.5}, "delta"),
])
def test_fuse_with_horizon_nests_the_horizon_diagnostics(method, options, fixed):
    r = fuse(_pair(), method, horizon=4, model=_model(), **options)
    assert r.info["rule"] == "horizon"
    diagnostics = r.info["horizon"]
    assert diagnostics["steps"] == 4
    assert {"criterion", "value", "value_recursive", "weights_recursive", "iterations",
            "converged", "solver"} <= set(diagnostics)
    for key in ("iterations", "converged", "gap"):  # the choice of the weights, not the rule's
        if key in diagnostics:
            np.testing.assert_array_equal(r.info[key], diagnostics[key])
    # the weights are those the horizon chose, applied by the rule
    chosen = r.omega if fixed == "omega" else r.info["delta"]
    again = fuse(_pair(), method, **{fixed: chosen}, **options)
    np.testing.assert_allclose(again.P, r.P, rtol=1e-12)


def test_fuse_with_horizon_zero_is_the_plain_rule():
    for method, options in [("ci", {}), ("pci", {"rho": 0.5})]:
        plain = fuse(_pair(), method, **options)
        zero = fuse(_pair(), method, horizon=0, model=_model(), **options)
        np.testing.assert_allclose(zero.P, plain.P, rtol=1e-9)
        np.testing.assert_allclose(zero.weights, plain.weights, atol=1e-9)


def test_kf_fuse_with_horizon_is_the_front_door_with_the_filters_model():
    kf = cifilter.KalmanFilter(dim_x=2, dim_z=1)
    model = _model()
    kf.F, kf.Q, kf.H, kf.R = model["F"], model["Q"], model["H"], model["R"]
    (x, P), other = _pair()
    kf.x, kf.P = x[:, None], P
    result = kf.fuse(other, horizon=5)
    direct = fuse(_pair(), "ci", horizon=5, model=model)
    np.testing.assert_array_equal(result.P, direct.P)
    assert result.info["horizon"]["steps"] == 5


@pytest.mark.parametrize("kwargs, error, message", [
    ({"method": "ei", "horizon": 3, "model": "m"}, ValueError, "does not support horizon="),
    ({"method": "ci", "horizon": 3}, ValueError, "needs the model"),
    ({"method": "ci", "model": {"F": np.eye(2), "Q": np.eye(2)}}, ValueError,
     "give horizon= too"),
    ({"method": "ci", "horizon": 3, "model": "m", "omega": 0.5}, ValueError,
     "fixes the weights"),
    ({"method": "pci", "horizon": 3, "model": "m"}, ValueError,
     "needs a correlation coefficient bound"),
    ({"method": "ci", "horizon": -1}, ValueError, "horizon"),
    ({"method": "ci", "horizon": 3, "model": {"F": np.eye(2)}}, ValueError, "F and Q"),
])
def test_fuse_horizon_errors_are_named(kwargs, error, message):
    if kwargs.get("model") == "m":
        kwargs["model"] = _model()
    with pytest.raises(error, match=message):
        fuse(_pair(), **kwargs)


@pytest.mark.parametrize("layout", ["empty", "clone"])
def test_a_shadowing_directory_is_named_when_no_rules_are_registered(tmp_path, layout):
    """Issue 21, item 11: run from a folder holding a directory ``cifilter`` without
    ``__init__.py`` (empty, or a clone), ``import cifilter`` is a namespace package and the
    registry is empty; the error says so and names the directory."""
    import os
    import subprocess
    import sys

    shadow = tmp_path / "cifilter"
    shadow.mkdir()
    if layout == "clone":
        (shadow / "pyproject.toml").write_text("[project]\nname = 'cifilter'\n")
        (shadow / "cifilter").mkdir()
        (shadow / "cifilter" / "__init__.py").write_text("")
    code = ("import numpy as np\n"
            "from cifilter.registry import fuse\n"
            "fuse([(np.zeros(2), np.eye(2))] * 2, method='ci')\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 1
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("ValueError: unknown fusion method 'ci': no fusion methods are "
                           "registered;")
    assert "namespace package" in last
    assert repr(str(shadow)) in last
    assert "registered methods are" not in last


def test_an_empty_registry_says_why(monkeypatch):
    monkeypatch.setattr(registry_module, "_REGISTRY", {})
    with pytest.raises(ValueError, match=r"no fusion methods are registered; the built-in "
                                         r"rules are registered when the package is imported"):
        get_method("ci")


# --------------------------------------------------- the front door's options (issue 22)
def test_fuse_and_kf_fuse_have_the_contracted_keywords():
    import inspect

    contract = ["H", "residual", "add", "times", "at", "motion", "horizon", "model"]
    parameters = inspect.signature(fuse).parameters
    assert list(parameters)[:2] == ["estimates", "method"]
    assert list(parameters)[2:10] == contract
    assert all(parameters[name].kind is inspect.Parameter.KEYWORD_ONLY for name in contract)
    assert parameters["method"].default == "ci"
    on_filter = inspect.signature(cifilter.KalmanFilter.fuse).parameters
    assert set(contract + ["lag"]) <= set(on_filter)


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(front_door=("H", "angles")), ValueError, r"front_door may list .* got 'angles'"),
    (dict(front_door=("H",)), TypeError, r"front_door=\('H',\) needs core="),
])
def test_bad_front_door_registrations_are_rejected(scratch_registry, kwargs, error, message):
    with pytest.raises(error, match=message):
        register_method("x", lambda xs, Ps: None, **kwargs)


def test_a_users_rule_gets_the_front_door_options_it_declares(scratch_registry):
    def first(xs, Ps):
        gains = np.zeros(Ps.shape)
        gains[..., 0, :, :] = np.eye(Ps.shape[-1])
        return FusionResult(xs[..., 0, :], Ps[..., 0, :, :], "first", gains=gains)

    def last(xs, Ps):
        return FusionResult(xs[..., -1, :], Ps[..., -1, :, :], "last")

    register_method("first", first, front_door="residual")
    register_method("last", last, front_door=("residual", "times"))
    pair = [(np.array([1.0, 2.0]), np.eye(2)), (np.array([3.0, 5.0]), np.eye(2))]
    r = fuse(pair, "last", residual=lambda a, b: 2.0 * (a - b))
    np.testing.assert_array_equal(r.x, [5.0, 8.0])  # x_1 + residual(x_2, x_1)

    def motion(dt):
        return np.array([[1.0, dt], [0.0, 1.0]]), np.zeros((2, 2))

    r = fuse(pair, "last", times=[1.0, 0.0], motion=motion)  # the last, predicted 1 s
    np.testing.assert_array_equal(r.x, [8.0, 5.0])
    assert r.info["at"] == 1.0
    with pytest.raises(ValueError, match=r"method 'first' does not accept times=; the rules "
                                         r"that bring .* are 'ci', 'last'"):
        fuse(pair, "first", times=[0.0, 0.0])
    # the list of the rules that accept H is the registry's, not a fixed text
    # (the built-in ones, in registration order, then the one registered here, last)
    built_in = [name for name in available_methods() if "H" in get_method(name).front_door]
    assert built_in[:2] == ["ci", "naive"] and "first" not in built_in
    register_method("partial", first, core=lambda est: None, front_door=("H",))
    listed = ", ".join(map(repr, built_in + ["partial"]))
    with pytest.raises(ValueError, match=rf"the rules that accept H are {listed}$"):
        fuse([pair[0], (np.zeros(1), np.eye(1))], "first", H=[None, np.eye(1, 2)])
