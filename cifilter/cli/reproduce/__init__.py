"""Reproductions of the papers' results: ``python -m cifilter reproduce NAME``.

Every module of this package is one reproduction; the command line finds them by name.
A module defines ``DESCRIPTION`` (one line), ``add_arguments(parser)`` and ``run(args)``
(returns the exit status), and prints each reproduced number next to the paper's.
"""

import importlib
import pkgutil
from types import ModuleType

__all__ = ["available"]


def available() -> dict[str, ModuleType]:
    """The reproduction modules by name.

    Returns
    -------
    dict
        ``{name: module}`` for every module of :mod:`cifilter.cli.reproduce`.

    Examples
    --------
    >>> from cifilter.cli import reproduce
    >>> all(hasattr(module, "run") for module in reproduce.available().values())
    True
    """
    return {
        info.name: importlib.import_module(f"{__name__}.{info.name}")
        for info in pkgutil.iter_modules(__path__)
        if not info.name.startswith("_")
    }
