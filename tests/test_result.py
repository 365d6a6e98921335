"""FusionResult: immutable, including every array inside info; pickles and copies."""

import copy
import pickle

import numpy as np
import pytest

from cifilter import FusionResult, covariance_intersection, fuse


def nested_info():
    return {
        "value": np.array([1.0, 2.0]),
        "scalar": 3,
        "trace": {"P": np.eye(2), "deeper": {"w": np.ones(3)}},
        "history": [np.zeros(2), {"step": np.arange(3.0)}],
        "pair": (np.ones(1), "label"),
    }


def arrays_in(value):
    if isinstance(value, np.ndarray):
        yield value
    elif hasattr(value, "items"):
        for item in value.values():
            yield from arrays_in(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from arrays_in(item)


def test_every_array_in_info_is_read_only():
    r = FusionResult(np.zeros(2), np.eye(2), "mine", info=nested_info())
    found = list(arrays_in(r.info))
    assert len(found) == 6
    for array in found:
        assert not array.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            array[...] = 7.0


def test_nested_containers_in_info_cannot_be_changed():
    r = FusionResult(np.zeros(2), np.eye(2), "mine", info=nested_info())
    with pytest.raises(TypeError):
        r.info["trace"]["P"] = 0
    with pytest.raises(TypeError):
        r.info["trace"]["deeper"]["w"] = 0
    with pytest.raises(TypeError):
        r.info["history"].append(1)
    with pytest.raises(TypeError):
        r.info["history"][0] = 1
    with pytest.raises(TypeError):
        r.info["history"][1]["step"] = 1
    # Containers still compare equal to what was given.
    assert r.info["history"][1].keys() == {"step"}
    assert r.info["pair"][1] == "label" and r.info["scalar"] == 3
    assert isinstance(r.info["history"], list) and r.info["history"][0].tolist() == [0.0, 0.0]


def test_the_callers_info_is_not_frozen_or_shared_in_its_containers():
    info = nested_info()
    r = FusionResult(np.zeros(2), np.eye(2), "mine", info=info)
    info["trace"]["new"] = 1  # the caller's dict stays a dict
    info["history"].append(2)
    assert "new" not in r.info["trace"] and len(r.info["history"]) == 2
    assert info["value"].flags.writeable  # the caller's arrays stay writable


@pytest.mark.parametrize("clone", [
    lambda r: pickle.loads(pickle.dumps(r)),
    copy.copy,
    copy.deepcopy,
])
def test_results_with_nested_info_pickle_and_copy_and_stay_read_only(clone):
    r = FusionResult(np.zeros(2), np.eye(2), "mine", omega=np.array([0.5, 0.5]),
                     gains=np.stack([0.5 * np.eye(2)] * 2), info=nested_info())
    c = clone(r)
    assert isinstance(c, FusionResult) and c.method == "mine"
    np.testing.assert_array_equal(c.info["trace"]["deeper"]["w"], np.ones(3))
    np.testing.assert_array_equal(c.info["history"][1]["step"], np.arange(3.0))
    assert c.info["pair"][1] == "label"
    for array in list(arrays_in(c.info)) + [c.x, c.P, c.omega, c.gains]:
        assert not array.flags.writeable
    with pytest.raises(TypeError):
        c.info["history"].append(1)


def test_rule_results_have_read_only_info_arrays():
    r = covariance_intersection([np.zeros(2), np.ones(2)], [np.diag([1.0, 4.0]), np.eye(2)])
    assert isinstance(r.info["iterations"], np.ndarray)
    for array in arrays_in(r.info):
        assert not array.flags.writeable
    s = fuse([(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))]).replace(method="renamed")
    for array in arrays_in(s.info):
        assert not array.flags.writeable


def _plain(value):
    """Plain, comparable structure: mapping and list types, and arrays as their bytes."""
    if isinstance(value, np.ndarray):
        return ("array", value.shape, value.tobytes())
    if hasattr(value, "items"):
        return (type(value).__name__, [(key, _plain(item)) for key, item in value.items()])
    if isinstance(value, (list, tuple)):
        return (type(value).__name__, [_plain(item) for item in value])
    return value


def _fields(r):
    return dict(x=r.x, P=r.P, method=r.method, omega=r.omega, gains=r.gains, info=r.info,
                weights=r.weights)


@pytest.mark.parametrize("changes", [
    {},
    {"method": "renamed"},
    {"x": np.array([5.0, 6.0])},
    {"omega": np.array([0.2, 0.8])},  # the weights stay those of the result, as given
    {"weights": None},  # the weights become omega
    {"info": "added"},
    {"info": "dropped"},
    {"info": "changed"},
    {"info": [("pairs", 1)]},
])
def test_replace_is_the_constructor_on_the_merged_fields(changes):
    """``replace`` reuses what it can of the frozen result, with the constructor's
    meaning: an info entry given is the new one (frozen), one left out is gone, the rest
    (the same objects) stay frozen; the caller's containers are neither frozen nor
    shared."""
    r = FusionResult(np.zeros(2), np.eye(2), "mine", omega=np.array([0.5, 0.5]),
                     weights=np.array([1.0, 3.0]), info=nested_info())
    history = [np.ones(2), {"step": np.arange(2.0)}]
    if changes.get("info") == "added":
        changes = {"info": dict(r.info, added=history, at=0.0)}
    elif changes.get("info") == "dropped":
        changes = {"info": {key: item for key, item in r.info.items() if key != "trace"}}
    elif changes.get("info") == "changed":
        changes = {"info": dict(r.info, history=history, value=np.array([7.0]))}
    expected = FusionResult(**dict(_fields(r), **changes))
    new = r.replace(**changes)
    assert isinstance(new, FusionResult) and new.method == expected.method
    for name in ("x", "P", "omega", "gains", "weights"):
        a, b = getattr(new, name), getattr(expected, name)
        assert (a is None) == (b is None)
        if a is not None:
            assert a.tobytes() == b.tobytes() and a.shape == b.shape
            assert not a.flags.writeable
    assert list(new.info) == list(expected.info)
    assert _plain(new.info) == _plain(expected.info)
    for array in arrays_in(new.info):
        assert not array.flags.writeable
    if "history" in new.info:
        with pytest.raises(TypeError):
            new.info["history"].append(1)
    with pytest.raises(TypeError):
        new.info["x"] = 1
    assert history[1].keys() == {"step"} and isinstance(history, list)
    history.append(3)  # the caller's list stays the caller's
    if "history" in changes.get("info", {}):
        assert len(new.info["history"]) == 2
    assert history[0].flags.writeable  # and its arrays writable
    if "info" in changes and "trace" not in changes["info"]:
        assert "trace" not in new.info
    assert r.info.keys() == nested_info().keys()  # r itself unchanged


def test_replace_with_an_unknown_field_is_the_constructors_error():
    r = FusionResult(np.zeros(1), np.eye(1), "mine")
    with pytest.raises(TypeError, match="unexpected keyword argument 'omgea'"):
        r.replace(omgea=np.ones(2))
