"""The parser of ``python -m cifilter`` and its sub-commands."""

import argparse
import os
import sys
from collections.abc import Sequence
from typing import Optional

from ..registry import available_methods, get_method
from . import args as types
from . import reproduce

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr and exit status 2.

    argparse prints the usage and the error; a first-time user then sees several lines
    for one typo. Here: ``<prog>: error: <message> (see <prog> --help)``. Sub-command
    parsers inherit the class (``add_subparsers`` uses the parent's type).
    """

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _methods(args):
    rows = [(name, get_method(name)) for name in available_methods()]
    header = f"{'method':<10} {'P is':<6} summary / reference"
    print(header)
    print("-" * max(len(header), 60))
    for name, record in rows:
        print(f"{name:<10} {record.guarantee:<6} {record.summary}")
        if record.reference:
            print(f"{'':<17} {record.reference}")
    return 0


def _demo(args):
    from .. import montecarlo
    from .demo import run_demo

    network = dict(nodes=args.nodes, sequential=args.fusion == "sequential",
                   feedback=not args.no_feedback, period=args.period, loss=args.loss,
                   delay=args.delay)
    if args.scenario == "two-tracks":
        changed = [f"--{name.replace('_', '-')}" for name, value in
                   (("nodes", args.nodes), ("fusion", args.fusion != "sequential"),
                    ("no_feedback", args.no_feedback), ("period", args.period != 1),
                    ("loss", args.loss), ("delay", args.delay), ("workers", args.workers),
                    ("scheduler", args.scheduler)) if value]
        if changed:
            verb = "applies" if len(changed) == 1 else "apply"
            _usage_error("demo", f"{', '.join(changed)} {verb} to the network scenarios, "
                         "not to --scenario two-tracks")
        rows = run_demo(seed=args.seed, runs=args.runs, steps=args.steps,
                        methods=args.methods, plot=args.plot, scenario="two-tracks")
    else:
        if args.nodes is not None and args.scenario in ("naveen-taylor", "common-information"):
            _usage_error("demo", "--nodes applies to ring, chain and fully-connected; "
                         f"{args.scenario} has a fixed number of nodes")
        with montecarlo.dask_client(workers=args.workers, scheduler=args.scheduler) as client:
            rows = run_demo(seed=args.seed, runs=args.runs, steps=args.steps,
                            methods=args.methods, plot=args.plot, scenario=args.scenario,
                            client=client, **network)
    return 0 if all("error" not in row for row in rows) or args.methods is None else 1


def _usage_error(command, message):
    prog = f"python -m cifilter {command}"
    print(f"{prog}: error: {message} (see {prog} --help)", file=sys.stderr)
    raise SystemExit(2)


def _build_parser():
    """The argument parser of ``python -m cifilter``."""
    from ..network.graph import scenario_names

    parser = _Parser(
        prog="python -m cifilter",
        description="Fuse estimates with unknown cross-correlation: demo and paper reproductions.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = commands.add_parser(
        "demo", help="a sensor network with feedback, every registered rule",
        description="A decentralised sensor network tracking one target: every node fuses "
                    "its neighbours' estimates and feeds the result back; every registered "
                    "rule is scored (RMSE, ANEES with chi-square bounds, verdict). "
                    "--scenario two-tracks runs the earlier two-track demo (no feedback).")
    demo.add_argument("--scenario", choices=scenario_names(), default="naveen-taylor",
                      help="network (default naveen-taylor: Naveen & Taylor's six nodes) "
                           "or two-tracks")
    demo.add_argument("--nodes", type=types.positive_int, metavar="N",
                      help="number of nodes of a ring, chain or fully-connected network")
    demo.add_argument("--seed", type=types.seed, default=0, help="random seed (default 0)")
    demo.add_argument("--runs", type=types.positive_int, metavar="N",
                      help="Monte Carlo runs (default 10; two-tracks 20)")
    demo.add_argument("--steps", type=types.positive_int, metavar="N",
                      help="time steps per run (default 40; two-tracks 100)")
    demo.add_argument("--methods", type=types.method_list, metavar="A,B",
                      help="comma-separated rules (default: all registered)")
    demo.add_argument("--fusion", choices=("sequential", "all"), default="sequential",
                      help="fuse the received estimates one at a time (default) or all at "
                           "once")
    demo.add_argument("--period", type=types.positive_int, default=1, metavar="K",
                      help="exchange every K steps (default 1)")
    demo.add_argument("--loss", type=types.probability, default=0.0, metavar="P",
                      help="probability that a message is lost (default 0)")
    demo.add_argument("--delay", action="store_true",
                      help="messages arrive one step late")
    demo.add_argument("--no-feedback", action="store_true",
                      help="fuse without writing the result back into the filters")
    demo.add_argument("--plot", type=types.plot_directory, metavar="DIR",
                      help="write the figures (PNG) to DIR (created if missing)")
    types.add_parallel_arguments(demo)
    demo.set_defaults(handler=_demo)

    methods = commands.add_parser("methods", help="list the registered fusion rules",
                                  description="List the registered fusion rules.")
    methods.set_defaults(handler=_methods)

    repro = commands.add_parser("reproduce", help="reproduce a paper's results",
                                description="Reproduce a paper's results.")
    papers = repro.add_subparsers(dest="paper", required=True, metavar="PAPER")
    for name, module in reproduce.available().items():
        sub = papers.add_parser(name, help=module.DESCRIPTION, description=module.DESCRIPTION)
        module.add_arguments(sub)
        sub.set_defaults(handler=module.run)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line; returns the exit status.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success, 1 when a requested rule could not run; bad arguments exit with
        status 2 and a one-line message (``SystemExit``).

    Examples
    --------
    >>> from cifilter.cli.main import main
    >>> main(["methods"])  # doctest: +ELLIPSIS
    method     P is   summary / reference
    ...
    0
    """
    args = _build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return int(args.handler(args) or 0)
    except BrokenPipeError:  # the output went to a command that stopped reading (| head)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
