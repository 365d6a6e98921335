"""The default demo before and after a change: wall time, the demo's own time, per-rule time.

Runs ``python -m cifilter demo`` (and any demo arguments after ``--``) in fresh processes
for two trees, alternating before/after so that both see the same machine load, and prints
every wall time and CPU time (user + system of the process: less sensitive to other jobs on
a shared machine), the minimum of each and their ratios. ``before`` is a directory holding a
``cifilter`` package or a git revision of this repository (extracted with ``git archive``
into a temporary directory, which changes nothing in the repository); ``after`` is this
tree unless ``--after`` says otherwise. Each process runs with ``PYTHONPATH`` set to its
tree, from a temporary working directory, with one BLAS thread (``OMP_NUM_THREADS=1``).

It also checks that the two demos print the same table (every column but the time) and,
with ``--rules``, runs each tree ``--repeats`` more times through a driver that times
every rule's fusions (``registry.fuse_estimates``: validation and the rule) and the rest of
the demo (the minimum of each entry over the runs).

    python benchmarks/bench_demo.py --before HEAD                # 3 repeats each
    python benchmarks/bench_demo.py --before /path/to/old/tree --repeats 5 --rules
    python benchmarks/bench_demo.py --before HEAD -- --runs 4 --steps 20
"""

import argparse
import os
import re
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# the demo's summary line: "12.3 s (13 rules)"
_DEMO_TIME = re.compile(r"^([0-9.]+) s \((\d+) rules?\)$")

_RULE_TIMES = """
import contextlib, io, sys, time
start = time.perf_counter()
import cifilter
from cifilter import registry
from cifilter.cli.main import main
imported = time.perf_counter() - start
seconds = {}
original = registry.fuse_estimates
def timed(estimates, method, options, **kwargs):
    t = time.perf_counter()
    try:
        return original(estimates, method, options, **kwargs)
    finally:
        seconds[method] = seconds.get(method, 0.0) + time.perf_counter() - t
registry.fuse_estimates = timed
with contextlib.redirect_stdout(io.StringIO()):
    t = time.perf_counter()
    main(["demo"] + sys.argv[1:])
    total = time.perf_counter() - t
print(f"import={imported}")
print(f"demo={total}")
for method, value in seconds.items():
    print(f"rule:{method}={value}")
"""


def extract_revision(revision, into):
    """``git archive`` of ``revision`` unpacked into ``into``; returns the tree's path."""
    archive = Path(into) / "tree.tar"
    with open(archive, "wb") as out:
        subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", revision],
                       stdout=out, check=True)
    tree = Path(into) / "tree"
    tree.mkdir()
    safe = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}
    with tarfile.open(archive) as tar:
        tar.extractall(tree, **safe)
    return tree


def environment(tree):
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    env.pop("PYTHONHASHSEED", None)
    return env


def children_cpu():
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_demo(tree, demo_args, workdir):
    """Wall seconds, CPU seconds (user + system), the demo's own seconds and its output."""
    cpu = children_cpu()
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "cifilter", "demo", *demo_args],
                          env=environment(tree), cwd=workdir, capture_output=True, text=True)
    wall = time.perf_counter() - start
    cpu = children_cpu() - cpu
    if done.returncode:
        raise SystemExit(f"the demo failed in {tree}:\n{done.stderr[-3000:]}")
    own = None
    for line in done.stdout.splitlines():
        match = _DEMO_TIME.match(line.strip())
        if match:
            own = float(match.group(1))
    return wall, cpu, own, done.stdout


def table_without_times(output):
    """The demo's output without the time column and the time line (what must not change)."""
    lines = []
    for line in output.splitlines():
        if _DEMO_TIME.match(line.strip()):
            continue
        # the last column of a rule's row is its time per fusion (a number or '-')
        lines.append(re.sub(r"\s+(\d+|-)\s*$", "", line))
    return lines


def rule_times(tree, demo_args, workdir):
    done = subprocess.run([sys.executable, "-c", _RULE_TIMES, *demo_args],
                          env=environment(tree), cwd=workdir, capture_output=True, text=True,
                          check=True)
    values = {}
    for line in done.stdout.splitlines():
        key, _, value = line.partition("=")
        values[key] = float(value)
    return values


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True,
                        help="a directory with the cifilter package, or a git revision")
    parser.add_argument("--after", default=str(ROOT),
                        help="a directory with the cifilter package (default: this tree)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rules", action="store_true",
                        help="also time every rule's fusions (one more run per tree)")
    parser.add_argument("demo_args", nargs="*", help="arguments of the demo (after --)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as scratch:
        before = Path(args.before)
        if not (before / "cifilter" / "__init__.py").exists():
            before = extract_revision(args.before, scratch)
        trees = {"before": before, "after": Path(args.after)}
        workdir = Path(scratch) / "work"
        workdir.mkdir()
        print(f"demo arguments: {' '.join(args.demo_args) or '(defaults)'}; "
              f"before = {args.before}, after = {args.after}; {os.cpu_count()} cores, "
              f"OMP_NUM_THREADS=1")
        walls = {"before": [], "after": []}
        cpus = {"before": [], "after": []}
        owns = {"before": [], "after": []}
        outputs = {}
        for repeat in range(args.repeats):
            order = ("before", "after") if repeat % 2 == 0 else ("after", "before")
            for label in order:
                wall, cpu, own, output = run_demo(trees[label], args.demo_args, workdir)
                walls[label].append(wall)
                cpus[label].append(cpu)
                owns[label].append(own)
                outputs[label] = output
        for label in ("before", "after"):
            shown = ", ".join(f"{w:.2f}" for w in walls[label])
            cpu = ", ".join(f"{c:.2f}" for c in cpus[label])
            own = ", ".join("?" if o is None else f"{o:.1f}" for o in owns[label])
            print(f"{label:6s} wall s: {shown}  (min {min(walls[label]):.2f})")
            print(f"{'':6s} CPU s:  {cpu}  (min {min(cpus[label]):.2f}); the demo's own s: {own}")
        print(f"speed-up of the wall time (min before / min after): "
              f"{min(walls['before']) / min(walls['after']):.2f}x; of the CPU time: "
              f"{min(cpus['before']) / min(cpus['after']):.2f}x")
        valid = [o for o in owns["before"] + owns["after"] if o is not None]
        if len(valid) == 2 * args.repeats:
            print(f"speed-up of the demo's own time: "
                  f"{min(owns['before']) / min(owns['after']):.2f}x")
        old, new = (table_without_times(outputs[k]) for k in ("before", "after"))
        if old == new:
            print("tables: identical apart from the time column")
        else:
            print("tables differ (besides the time column):")
            for a, b in zip(old, new):
                if a != b:
                    print(f"  before: {a}\n  after:  {b}")
        if args.rules:
            times = {"before": {}, "after": {}}
            for repeat in range(args.repeats):  # alternating; the minimum of each entry
                order = ("before", "after") if repeat % 2 == 0 else ("after", "before")
                for label in order:
                    for key, value in rule_times(trees[label], args.demo_args, workdir).items():
                        times[label][key] = min(times[label].get(key, float("inf")), value)
            print(f"through the timing driver, minimum of {args.repeats} runs each, seconds "
                  "(import, demo, each rule's fusions with their validation):")
            keys = ["import", "demo"] + sorted(
                (k for k in times["before"] if k.startswith("rule:")),
                key=lambda k: -times["before"][k])
            for key in keys:
                a, b = times["before"].get(key, float("nan")), times["after"].get(key, float("nan"))
                print(f"  {key.replace('rule:', ''):12s} {a:7.2f} -> {b:7.2f}  ({a / b:4.1f}x)")
            for label in ("before", "after"):
                fusion = sum(v for k, v in times[label].items() if k.startswith("rule:"))
                print(f"  {label}: fusions {fusion:.2f} s, rest of the demo "
                      f"{times[label]['demo'] - fusion:.2f} s")


if __name__ == "__main__":
    main()
