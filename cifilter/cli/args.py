"""Argument types and shared options of the command line (``python -m cifilter``).

Every check runs while the arguments are parsed, before any work starts, and a failure is
an :class:`argparse.ArgumentTypeError`: the parser prints one line naming the option and
the problem and exits with status 2 (no traceback).
"""

import argparse
import math
import os
from pathlib import Path

__all__ = []


def _converted(text, convert, expected):
    """``convert(text)``, or the one-line error "expected <expected>, got <text>"."""
    try:
        return convert(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None


def positive_int(text: str) -> int:
    """An integer >= 1 (``--runs``, ``--steps``, ``--workers``)."""
    value = _converted(text, int, "a positive integer")
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def seed(text: str) -> int:
    """A non-negative integer (``--seed``; the root of numpy's ``SeedSequence``)."""
    value = _converted(text, int, "a non-negative integer")
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be non-negative, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite float > 0."""
    value = _converted(text, float, "a positive number")
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def probability(text: str) -> float:
    """A float in [0, 1] (e.g. a packet loss probability)."""
    value = _converted(text, float, "a number in [0, 1]")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value}")
    return value


def plot_directory(text: str) -> Path:
    """A directory for figures: created if missing, and it must be writable.

    Checked when the arguments are parsed, so an unwritable path fails before a long run.
    """
    path = Path(text)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise argparse.ArgumentTypeError(
            f"cannot create directory {text!r}: {error.strerror or error}") from None
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is not a directory")
    if not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"directory {text!r} is not writable")
    return path


def method_list(text: str) -> list[str]:
    """Comma-separated names of registered fusion rules, checked against the registry."""
    from ..registry import available_methods

    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise argparse.ArgumentTypeError("expected at least one method name")
    known = available_methods()
    unknown = [name for name in names if name not in known]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown method(s) {', '.join(map(repr, unknown))}; "
            f"available: {', '.join(known)}")
    return names


def add_parallel_arguments(
        parser: argparse.ArgumentParser) -> argparse._MutuallyExclusiveGroup:
    """``--workers N`` (a local Dask cluster) and ``--scheduler ADDRESS`` (an existing one).

    Both absent: the Monte Carlo runs in this process. See :func:`cifilter.montecarlo.run`.
    """
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--workers", type=positive_int, metavar="N",
                       help="run the Monte Carlo on a local Dask cluster of N workers "
                            "(needs Dask: pip install \".[distributed]\" from a clone)")
    group.add_argument("--scheduler", metavar="ADDRESS",
                       help="run the Monte Carlo on an existing Dask scheduler "
                            "(needs Dask: pip install \".[distributed]\" from a clone)")
    return group
