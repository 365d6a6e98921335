"""Typing of the public API: every public function, method and class of a public module is
annotated (parameters and return), the package ships ``py.typed``, and mypy finds no error
in the package (configured in ``setup.cfg``)."""

import importlib
import inspect
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import cifilter

ROOT = Path(__file__).resolve().parents[1]


def public_callables():
    """(dotted path, function) of every public function and method defined in a public
    module: names without a leading underscore, in modules and packages without one.
    ``__init__`` counts as public (it is the class's signature)."""
    found = {}
    for info in pkgutil.walk_packages(cifilter.__path__, prefix="cifilter."):
        if any(part.startswith("_") for part in info.name.split(".")):
            continue
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            if inspect.isfunction(obj):
                found[f"{module.__name__}.{name}"] = obj
            elif inspect.isclass(obj):
                for member_name, member in vars(obj).items():
                    if isinstance(member, (staticmethod, classmethod)):
                        member = member.__func__
                    elif isinstance(member, property):
                        member = member.fget
                    if inspect.isfunction(member) and (
                            not member_name.startswith("_") or member_name == "__init__"):
                        found[f"{module.__name__}.{name}.{member_name}"] = member
    return sorted(found.items())


def missing_annotations(function):
    """Names of the parameters (and 'return') of ``function`` without an annotation (of the
    function a decorator such as ``contextlib.contextmanager`` wraps: ``functools.wraps``
    copies its annotations)."""
    missing = []
    parameters = list(inspect.signature(function).parameters.values())
    for index, parameter in enumerate(parameters):
        if index == 0 and parameter.name in ("self", "cls"):
            continue
        if parameter.annotation is inspect.Parameter.empty:
            missing.append(parameter.name)
    if "return" not in function.__annotations__:
        missing.append("return")
    return missing


PUBLIC = public_callables()


def test_the_public_api_is_found():
    names = {path for path, _ in PUBLIC}
    assert "cifilter.registry.fuse" in names
    assert "cifilter.filters.kalman.FusionMixin.fuse" in names
    assert "cifilter.result.FusionResult.replace" in names
    assert len(PUBLIC) > 100


@pytest.mark.parametrize("path, function", PUBLIC, ids=[path for path, _ in PUBLIC])
def test_public_function_is_annotated(path, function):
    assert not missing_annotations(function), f"{path}: {missing_annotations(function)}"


def test_fusion_result_fields_are_typed():
    fields = cifilter.FusionResult.__dataclass_fields__
    assert all(field.type not in (None, inspect.Parameter.empty) for field in fields.values())


def test_package_is_marked_typed():
    assert (Path(cifilter.__file__).parent / "py.typed").is_file()


def test_mypy_is_clean():
    completed = subprocess.run(
        [sys.executable, "-m", "mypy", "--no-incremental", "--cache-dir", "/dev/null",
         "-p", "cifilter"],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )
    assert completed.returncode == 0, completed.stdout + completed.stderr
