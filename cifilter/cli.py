"""Command line: ``python -m cifilter {demo, methods, reproduce}``."""

import argparse
import sys

from . import reproduce
from .registry import available_methods, get_method

__all__ = ["main"]


def _methods(args):
    for name in available_methods():
        record = get_method(name)
        print(f"{name:<10} {record.guarantee:<6} {record.summary}")
        if record.reference:
            print(f"{'':<17} {record.reference}")
    return 0


def _demo(args):
    from .demo import run_demo

    methods = None if args.methods is None else [m.strip() for m in args.methods.split(",")]
    rows = run_demo(seed=args.seed, runs=args.runs, steps=args.steps, methods=methods,
                    plot=args.plot)
    return 1 if any("error" in row for row in rows) else 0


def _build_parser():
    """The argument parser of ``python -m cifilter``."""
    parser = argparse.ArgumentParser(
        prog="python -m cifilter",
        description="Fuse estimates with unknown cross-correlation: demo and paper reproductions.",
    )
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser("demo", help="two trackers fused by every registered rule")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--runs", type=int, default=20, help="Monte Carlo runs (default 20)")
    demo.add_argument("--steps", type=int, default=100, help="time steps per run (default 100)")
    demo.add_argument("--methods", help="comma-separated methods (default: all registered)")
    demo.add_argument("--plot", metavar="FILE.png", help="draw tracks and fused error ellipses")
    demo.set_defaults(handler=_demo)

    methods = commands.add_parser("methods", help="list the registered fusion rules")
    methods.set_defaults(handler=_methods)

    repro = commands.add_parser("reproduce", help="reproduce a paper's results")
    papers = repro.add_subparsers(dest="paper", required=True, metavar="PAPER")
    for name, module in reproduce.available().items():
        sub = papers.add_parser(name, help=module.DESCRIPTION, description=module.DESCRIPTION)
        module.add_arguments(sub)
        sub.set_defaults(handler=module.run)
    return parser


def main(argv=None):
    """Run the command line; returns the exit status.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success.

    Examples
    --------
    >>> from cifilter.cli import main
    >>> main(["methods"])  # doctest: +ELLIPSIS
    ci ...
    0
    """
    args = _build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    return int(args.handler(args) or 0)
