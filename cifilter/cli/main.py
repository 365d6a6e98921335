"""The parser of ``python -m cifilter`` and its sub-commands."""

import argparse
import contextlib
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


def _compile(args):
    """Compile and cache every kernel in the foreground, printing each and its time."""
    import time

    from .. import backend

    if not backend.numba_available():
        print("python -m cifilter compile: numba is not installed (pip install \".[fast]\" "
              "from a clone); cifilter runs on numpy", file=sys.stderr)
        return 1

    def progress(name, seconds, how):
        print(f"{name:<26} {how:<18} {seconds:7.2f} s", flush=True)

    print("compiling the numba kernels (cached on disk for later processes)", flush=True)
    start = time.perf_counter()
    done = backend.compile_kernels(progress)
    print(f"{len(done)} kernels ready in {time.perf_counter() - start:.2f} s")
    return 0


def _demo(args):
    from .. import montecarlo
    from .demo import run_demo

    network = dict(nodes=args.nodes, sequential=args.fusion == "sequential",
                   feedback=not args.no_feedback, period=args.period, loss=args.loss,
                   delay=args.delay)
    if args.scenario in ("multi-target", "two-tracks"):
        _refuse_network_options(args)
    if args.scenario == "multi-target":
        if args.steps is not None and args.steps < 8:
            _usage_error("demo", f"--steps: the multi-target scenario needs at least 8 "
                         f"scans, got {args.steps}")
        rows = run_demo(seed=args.seed, runs=args.runs, steps=args.steps,
                        methods=args.methods, plot=args.plot, scenario="multi-target")
        return 0 if all("error" not in row for row in rows) or args.methods is None else 1
    if args.scenario == "two-tracks":
        rows = run_demo(seed=args.seed, runs=args.runs, steps=args.steps,
                        methods=args.methods, plot=args.plot, scenario="two-tracks")
    else:
        if args.nodes is not None and args.scenario in ("naveen-taylor", "common-information"):
            _usage_error("demo", "--nodes applies to ring, chain and fully-connected; "
                         f"{args.scenario} has a fixed number of nodes")
        if args.nodes is not None:  # a small network of the same kind checks --nodes and
            small = _scenario(args, min(args.nodes, 8))  # gives the state dimension;
            _check_memory(args.nodes, small.dim, args)  # the network itself may be too big
        scenario = _scenario(args, args.nodes)
        if args.nodes is None:
            _check_memory(scenario.nodes, scenario.dim, args)
        del network["nodes"]  # the scenario is built
        with contextlib.ExitStack() as stack:
            client = _enter_client(stack, args, montecarlo)
            rows = run_demo(seed=args.seed, runs=args.runs, steps=args.steps,
                            methods=args.methods, plot=args.plot, scenario=scenario,
                            client=client, **network)
    return 0 if all("error" not in row for row in rows) or args.methods is None else 1


def _refuse_network_options(args):
    """A one-line usage error for the options of the network scenarios given to a scenario
    without a network (two-tracks, multi-target)."""
    changed = [f"--{name.replace('_', '-')}" for name, value in
               (("nodes", args.nodes), ("fusion", args.fusion != "sequential"),
                ("no_feedback", args.no_feedback), ("period", args.period != 1),
                ("loss", args.loss), ("delay", args.delay), ("workers", args.workers),
                ("scheduler", args.scheduler)) if value]
    if changed:
        verb = "applies" if len(changed) == 1 else "apply"
        _usage_error("demo", f"{', '.join(changed)} {verb} to the network scenarios, "
                     f"not to --scenario {args.scenario}")


def _scenario(args, nodes):
    """The network of ``--scenario`` with ``nodes`` nodes (None: its own number), or a
    one-line error (``--nodes 1``)."""
    from ..network.graph import get_scenario

    try:
        return get_scenario(args.scenario, **({} if nodes is None else {"nodes": nodes}))
    except (TypeError, ValueError) as error:
        option = "--nodes" if args.nodes is not None else "--scenario"
        _usage_error("demo", f"{option}: {error}")


def _check_memory(nodes, dim, args):
    """Refuse a network too large for this machine's memory before any work starts."""
    from .demo import DEMO_CHUNK_SIZE, NETWORK_DEFAULTS, network_memory_estimate

    steps = NETWORK_DEFAULTS["steps"] if args.steps is None else args.steps
    methods = available_methods() if args.methods is None else args.methods
    need = network_memory_estimate(nodes, dim, steps,
                                   min(DEMO_CHUNK_SIZE, args.runs or NETWORK_DEFAULTS["runs"]),
                                   estimators=len(methods) + 2)
    have = _available_memory()
    if have is not None and need > have:
        _usage_error("demo", f"--nodes {nodes}: the study would need about "
                     f"{_bytes(need)} of memory (an estimate made before starting: the "
                     f"network's joint covariances grow as the square of the nodes), "
                     f"{_bytes(have)} are available; use fewer nodes")


def _available_memory():
    """Bytes of memory available to a new allocation (Linux: MemAvailable), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def _bytes(count):
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if count < 1000 or unit == "TB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1000
    return f"{count:.1f} PB"  # pragma: no cover - the loop returns


SCHEDULER_TIMEOUT = 5
"""Seconds the command line waits for a ``--scheduler`` to answer before it gives up."""


def _enter_client(stack, args, montecarlo):
    """The Dask client of ``--workers``/``--scheduler`` (None for neither), entered in
    ``stack``; an unreachable scheduler or a missing Dask is a one-line error, and a
    scheduler that does not answer is given up after :data:`SCHEDULER_TIMEOUT` seconds."""
    if args.workers is None and args.scheduler is None:
        return None
    try:
        if args.scheduler is None:
            return stack.enter_context(montecarlo.dask_client(workers=args.workers))
        _check_reachable(args.scheduler)
        import dask

        # The connect timeout of the client, only while it connects (default 30 s).
        with dask.config.set({"distributed.comm.timeouts.connect": f"{SCHEDULER_TIMEOUT}s"}):
            return stack.enter_context(montecarlo.dask_client(scheduler=args.scheduler))
    except ImportError as error:
        _usage_error("demo", str(error))
    except (OSError, TimeoutError) as error:  # asyncio's and distributed's timeouts too
        if args.scheduler is None:
            raise
        _usage_error("demo", f"--scheduler: cannot connect to {args.scheduler!r} within "
                     f"{SCHEDULER_TIMEOUT} s ({_reason(error)})")
    return None  # pragma: no cover - _usage_error exits


def _reason(error):
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _check_reachable(address):
    """For a ``tcp://host:port`` address, a TCP connection within the timeout (fast
    refusal of a closed port); other protocols are left to Dask."""
    import socket
    from urllib.parse import urlsplit

    if "://" not in address:
        address = f"tcp://{address}"
    parts = urlsplit(address)
    if parts.scheme != "tcp" or parts.hostname is None or parts.port is None:
        return
    with socket.create_connection((parts.hostname, parts.port), timeout=SCHEDULER_TIMEOUT):
        pass


def _usage_error(command, message):
    prog = f"python -m cifilter {command}"
    print(f"{prog}: error: {message} (see {prog} --help)", file=sys.stderr)
    raise SystemExit(2)


def _build_parser():
    """The argument parser of ``python -m cifilter``."""
    from ..network.graph import scenario_names

    parser = _Parser(
        prog="python -m cifilter",
        description="Fuse estimates with unknown cross-correlation: demo, paper reproductions, "
                    "compiling the kernels.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = commands.add_parser(
        "demo", help="a sensor network with feedback, every registered rule",
        description="A decentralised sensor network tracking one target: every node fuses "
                    "its neighbours' estimates and feeds the result back; every registered "
                    "rule is scored (RMSE, ANEES with chi-square bounds, verdict). "
                    "--scenario two-tracks runs the earlier two-track demo (no feedback).")
    demo.add_argument("--scenario", choices=(*scenario_names(), "multi-target"),
                      default="naveen-taylor",
                      help="network (default naveen-taylor: Naveen & Taylor's six nodes), "
                           "two-tracks, or multi-target (a track-to-track fusion centre)")
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

    compile_ = commands.add_parser(
        "compile", help="compile and cache the numba kernels now",
        description="Compile every numba kernel in the foreground and cache it on disk, so "
                    "that later processes load the kernels instead of answering on numpy "
                    "while they compile in the background. Needs numba.")
    compile_.set_defaults(handler=_compile)

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
