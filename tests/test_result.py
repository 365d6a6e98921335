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
