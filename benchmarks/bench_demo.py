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
the demo (the minimum of each entry over the runs), in wall seconds and in CPU seconds of the
demo's thread (``time.thread_time``: a background compilation of the numba kernels in the
same process, which the trees started in a fresh directory may run, is not counted, and
other processes on a shared machine disturb it less).

``--also REVISION`` (repeatable) adds further baselines (directories or git revisions),
measured in the same alternating rounds, each compared with ``after``: for instance the
commit a target was set against and the current HEAD, both against the working tree.

    python benchmarks/bench_demo.py --before HEAD                # 3 repeats each
    python benchmarks/bench_demo.py --before /path/to/old/tree --repeats 5 --rules
    python benchmarks/bench_demo.py --before HEAD -- --runs 4 --steps 20
    python benchmarks/bench_demo.py --before 7eb3161 --also HEAD --repeats 3 --rules
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
seconds, cpu = {}, {}
original = registry.fuse_estimates
def timed(estimates, method, options, **kwargs):
    t, c = time.perf_counter(), time.thread_time()
    try:
        return original(estimates, method, options, **kwargs)
    finally:
        seconds[method] = seconds.get(method, 0.0) + time.perf_counter() - t
        cpu[method] = cpu.get(method, 0.0) + time.thread_time() - c
registry.fuse_estimates = timed
with contextlib.redirect_stdout(io.StringIO()):
    t, c = time.perf_counter(), time.thread_time()
    main(["demo"] + sys.argv[1:])
    total, total_cpu = time.perf_counter() - t, time.thread_time() - c
print(f"import={imported}")
print(f"demo={total}")
print(f"cpu-demo={total_cpu}")
for method, value in seconds.items():
    print(f"rule:{method}={value}")
    print(f"cpu-rule:{method}={cpu[method]}")
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


def _order(labels, repeat):
    """The labels in order on even rounds, reversed on odd ones (both see the same load)."""
    return labels if repeat % 2 == 0 else labels[::-1]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True,
                        help="a directory with the cifilter package, or a git revision")
    parser.add_argument("--also", action="append", default=[], metavar="REVISION",
                        help="a further baseline (directory or git revision), repeatable")
    parser.add_argument("--after", default=str(ROOT),
                        help="a directory with the cifilter package (default: this tree)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rules", action="store_true",
                        help="also time every rule's fusions (one more run per tree)")
    parser.add_argument("demo_args", nargs="*", help="arguments of the demo (after --)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as scratch:
        trees = {}
        names = {}
        for k, source in enumerate([args.before] + args.also):
            label = "before" if k == 0 else f"also{k}"  # (named by source below)
            tree = Path(source)
            if not (tree / "cifilter" / "__init__.py").exists():
                into = Path(scratch) / label
                into.mkdir()
                tree = extract_revision(source, into)
            trees[label], names[label] = tree, source
        trees["after"], names["after"] = Path(args.after), args.after
        labels = list(trees)
        baselines = labels[:-1]
        workdir = Path(scratch) / "work"
        workdir.mkdir()
        print(f"demo arguments: {' '.join(args.demo_args) or '(defaults)'}; "
              + "; ".join(f"{label} = {names[label]}" for label in labels)
              + f"; {os.cpu_count()} cores, OMP_NUM_THREADS=1")
        walls = {label: [] for label in labels}
        cpus = {label: [] for label in labels}
        owns = {label: [] for label in labels}
        outputs = {}
        for repeat in range(args.repeats):
            for label in _order(labels, repeat):
                wall, cpu, own, output = run_demo(trees[label], args.demo_args, workdir)
                walls[label].append(wall)
                cpus[label].append(cpu)
                owns[label].append(own)
                outputs[label] = output
        width = max(len(label) for label in labels)
        for label in labels:
            shown = ", ".join(f"{w:.2f}" for w in walls[label])
            cpu = ", ".join(f"{c:.2f}" for c in cpus[label])
            own = ", ".join("?" if o is None else f"{o:.1f}" for o in owns[label])
            print(f"{label:{width}s} wall s: {shown}  (min {min(walls[label]):.2f})")
            print(f"{'':{width}s} CPU s:  {cpu}  (min {min(cpus[label]):.2f}); "
                  f"the demo's own s: {own}")
        for base in baselines:
            tag = "" if len(baselines) == 1 else f" ({base} / after)"
            print(f"speed-up of the wall time{tag} (min {base} / min after): "
                  f"{min(walls[base]) / min(walls['after']):.2f}x; of the CPU time: "
                  f"{min(cpus[base]) / min(cpus['after']):.2f}x")
            valid = [o for o in owns[base] + owns["after"] if o is not None]
            if len(valid) == 2 * args.repeats:
                print(f"speed-up of the demo's own time{tag}: "
                      f"{min(owns[base]) / min(owns['after']):.2f}x")
            old, new = (table_without_times(outputs[k]) for k in (base, "after"))
            if old == new:
                print(f"tables{tag}: identical apart from the time column")
            else:
                print(f"tables differ{tag} (besides the time column):")
                for a, b in zip(old, new):
                    if a != b:
                        print(f"  {base}: {a}\n  after:  {b}")
        if args.rules:
            times = {label: {} for label in labels}
            for repeat in range(args.repeats):  # alternating; the minimum of each entry
                for label in _order(labels, repeat):
                    for key, value in rule_times(trees[label], args.demo_args, workdir).items():
                        times[label][key] = min(times[label].get(key, float("inf")), value)
            _print_rule_times(times, labels, baselines, args.repeats, "")
            _print_rule_times(times, labels, baselines, args.repeats, "cpu-")


def _print_rule_times(times, labels, baselines, repeats, prefix):
    """The timing driver's table: wall seconds (``prefix=""``) or the CPU seconds of the
    demo's own thread (``"cpu-"``: insensitive to other threads of the process, such as a
    background compilation, and less sensitive than the wall time to other processes)."""
    what = "CPU seconds of the demo's thread" if prefix else "wall seconds"
    print(f"through the timing driver, minimum of {repeats} runs each, {what} "
          "(import, demo, each rule's fusions with their validation):")
    print(f"  {'':12s} " + " ".join(f"{label:>8s}" for label in labels)
          + "  " + " ".join(f"{base + '/after':>13s}" for base in baselines))
    rules = sorted((k[len(prefix):] for k in times["before"]
                    if k.startswith(prefix + "rule:")),
                   key=lambda k: -times["before"][prefix + k])
    keys = (["import"] if not prefix else []) + ["demo"] + rules
    for key in keys:
        name = key if key == "import" else prefix + key
        values = [times[label].get(name, float("nan")) for label in labels]
        ratios = [times[base].get(name, float("nan")) / values[-1] for base in baselines]
        print(f"  {key.replace('rule:', ''):12s} "
              + " ".join(f"{v:8.2f}" for v in values) + "  "
              + " ".join(f"{r:12.2f}x" for r in ratios))
    fusions = {}
    for label in labels:
        fusions[label] = sum(v for k, v in times[label].items()
                             if k.startswith(prefix + "rule:"))
        print(f"  {label}: fusions {fusions[label]:.2f} s, rest of the demo "
              f"{times[label][prefix + 'demo'] - fusions[label]:.2f} s")
    for base in baselines:
        print(f"  fusions, {base} / after: {fusions[base] / fusions['after']:.2f}x")


if __name__ == "__main__":
    main()
