"""Command line: ``python -m cifilter {demo, methods, reproduce}``.

Bad arguments are reported on one line (``python -m cifilter demo: error: ...``) with exit
status 2 and no traceback; every argument is checked while parsing (by the types of
:mod:`cifilter.cli.args`), so a bad ``--plot`` directory fails before a long run starts.

The command line sits on top of the package: nothing below imports it. Its modules:
:mod:`~cifilter.cli.main` (the parser and sub-commands), :mod:`~cifilter.cli.args`
(argument types), :mod:`~cifilter.cli.demo` (the main job), :mod:`~cifilter.cli.plotting`
(figures) and :mod:`~cifilter.cli.reproduce` (the papers' experiments).
"""

from .main import main

__all__ = ["main"]
