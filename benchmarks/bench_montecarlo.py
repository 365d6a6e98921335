"""The Weng & Djurić reproduction (reduced size) on one Dask worker against two.

``python -m cifilter reproduce weng`` runs its Monte Carlo through
:func:`cifilter.montecarlo.run`; this benchmark times the whole reproduction, in the same
run, three ways:

* in process (no Dask; the baseline of the ratios);
* on a local Dask cluster of 1 worker process (one thread);
* on a local Dask cluster of 2 worker processes (one thread each);

the clusters being started before the clock starts (their start-up time is printed
separately). The reports of the three runs must be identical apart from timings (same
seed, same chunk size), which the benchmark checks. Run it with

    python benchmarks/bench_montecarlo.py               # --runs 200, every section
    python benchmarks/bench_montecarlo.py --runs 1000 --only model1,model2,nodes

On a 2-core machine the ideal ratio of 1 to 2 workers is 2; chunks that do not divide
evenly between the workers (``--runs 200`` makes two chunks per journal study, one for the
repeated-fusion study) and the other processes on the machine lower it.
"""

import argparse
import io
import re
import time

from cifilter import montecarlo
from cifilter.cli.reproduce import weng


def _report_without_timings(text):
    text = re.sub(r"\d+\.\d+ to \d+\.\d+ s of compute each \(median [\d.]+ s\)", "", text)
    text = re.sub(r"total \d+ s", "", text)
    return re.sub(r"(?m)^(\s+\d+ .*?)\s+[\d.]+$", r"\1", text)  # Fig. 10's time column


def _cpu_seconds(client):
    """CPU seconds of this process plus those of every worker process so far."""
    workers = 0.0 if client is None else sum(client.run(time.process_time).values())
    return time.process_time() + workers


def _run(args, client):
    """Wall seconds, CPU seconds (all processes) and the report of one reproduction."""
    namespace = weng_arguments(args)
    out = io.StringIO()
    if client is not None:
        namespace.scheduler = client.cluster.scheduler_address
    cpu = _cpu_seconds(client)
    start = time.perf_counter()
    weng.run(namespace, out=out)
    wall = time.perf_counter() - start
    return wall, _cpu_seconds(client) - cpu, out.getvalue()


def weng_arguments(args):
    parser = argparse.ArgumentParser()
    weng.add_arguments(parser)
    return parser.parse_args(["--runs", str(args.runs), "--only", args.only,
                              "--seed", str(args.seed)])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200,
                        help="runs per journal configuration (default 200)")
    parser.add_argument("--only", default=",".join(weng.SECTIONS),
                        help="sections of the reproduction (default all)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    print(f"Weng & Djurić reproduction, --runs {args.runs}, sections {args.only}; "
          f"chunks of {montecarlo.DEFAULT_CHUNK_SIZE} runs")
    timings, cpu, reports = {}, {}, {}
    timings["in process"], cpu["in process"], reports["in process"] = _run(args, None)
    for workers in (1, 2):
        start = time.perf_counter()
        with montecarlo.dask_client(workers=workers) as client:
            started = time.perf_counter() - start
            label = f"{workers} worker{'s' if workers > 1 else ''}"
            timings[label], cpu[label], reports[label] = _run(args, client)
        print(f"  (local cluster of {workers} started in {started:.1f} s, not counted)")
    baseline = _report_without_timings(reports["in process"])
    for label, report in reports.items():
        if _report_without_timings(report) != baseline:
            raise SystemExit(f"the report on {label} differs from the in-process report")
    print(f"\n{'run':<12} {'wall [s]':>8} {'vs in process':>14} {'CPU [s]':>8}")
    for label, seconds in timings.items():
        print(f"{label:<12} {seconds:>8.1f} {timings['in process'] / seconds:>13.2f}x "
              f"{cpu[label]:>8.1f}")
    print("(CPU: this process and the worker processes; the scheduler's and nannies' are "
          "not counted. Wall time depends on what else runs on the machine.)")
    ratio = timings["1 worker"] / timings["2 workers"]
    print(f"\n1 worker / 2 workers: {ratio:.2f}x (identical reports: yes)")
    return ratio


if __name__ == "__main__":
    main()
