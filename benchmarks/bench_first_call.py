"""The first batched call in a fresh process with an empty numba cache (issue 24).

Each measurement is a new Python process with ``NUMBA_CACHE_DIR`` set to a new empty
directory; it imports cifilter, builds 1000 pairs of 4x4 covariances (``--size``) and times
its *first* ``covariance_intersection`` call (the import is timed apart), then reads
where the call went from ``cifilter._kernels.dispatch.report()``. Backends, measured in
one run, interleaved, ``--repeats`` times each:

* ``numpy``: the numpy backend (the baseline);
* ``auto``: the default; with an empty cache numpy answers and the kernels compile in a
  background thread (the process exits without waiting for it);
* ``auto, cached``: the same after ``python -m cifilter compile`` filled the cache (timed
  too, once): the kernels are loaded from the cache in the first call;
* ``numba``: the explicit numba backend with an empty cache, which compiles in the
  foreground (what ``"auto"`` did before; skipped with ``--no-foreground``).

The ratios are against the minimum of the ``numpy`` runs of the same run.

    python benchmarks/bench_first_call.py
    python benchmarks/bench_first_call.py --repeats 5 --no-foreground
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import time
began = time.perf_counter()
import json, sys, warnings
import numpy as np
sys.path.insert(0, {root!r})
import cifilter
imported = time.perf_counter() - began
from cifilter._kernels import dispatch

warnings.simplefilter("ignore", cifilter.backend.CompileNotice)
rng = np.random.default_rng(0)
A = rng.standard_normal(({size}, 2, 4, 4))
Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
xs = rng.standard_normal(({size}, 2, 4))
cifilter.set_backend({backend!r})
start = time.perf_counter()
cifilter.covariance_intersection(xs, Ps)
seconds = time.perf_counter() - start
report = dispatch.report()
print(json.dumps({{"seconds": seconds, "import": imported, "kernels": report["kernels"],
                  "numpy_while_compiling": report["numpy_while_compiling"]}}))
"""


def first_call(backend: str, size: int, cache: str) -> dict:
    """Time the first call of a fresh process on ``backend`` with ``NUMBA_CACHE_DIR=cache``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    code = CHILD.format(root=str(ROOT), size=size, backend=backend)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1000, help="pairs (default 1000)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per backend (default 3)")
    parser.add_argument("--no-foreground", action="store_true",
                        help="skip the explicit numba backend (a 10-40 s compile)")
    args = parser.parse_args()

    rows: dict[str, list[dict]] = {"numpy": [], "auto": []}
    with tempfile.TemporaryDirectory() as scratch:
        for _ in range(args.repeats):
            for backend in ("numpy", "auto"):
                cache = tempfile.mkdtemp(dir=scratch)
                rows[backend].append(first_call(backend, args.size, cache))
        cache = tempfile.mkdtemp(dir=scratch)
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "cifilter", "compile"], cwd=ROOT, check=True,
                       env=dict(os.environ, NUMBA_CACHE_DIR=cache), capture_output=True)
        compile_seconds = time.perf_counter() - start
        rows["auto, cached"] = [first_call("auto", args.size, cache)
                                for _ in range(args.repeats)]
        if not args.no_foreground:
            rows["numba"] = [first_call("numba", args.size, tempfile.mkdtemp(dir=scratch))]

    base = min(row["seconds"] for row in rows["numpy"])
    print(f"first covariance_intersection call on {args.size} pairs of 4x4, fresh process, "
          f"empty numba cache (python {sys.version.split()[0]}, {os.cpu_count()} cpus)")
    print(f"{'backend':<14} {'runs':>4} {'min s':>8} {'max s':>8} {'x numpy':>8} "
          f"{'import+1st':>10}  where   (import+1st: import cifilter and first call, min s)")
    for name, runs in rows.items():
        seconds = [row["seconds"] for row in runs]
        where = sorted({"kernels" if row["kernels"] else "numpy" for row in runs})
        print(f"{name:<14} {len(runs):>4} {min(seconds):8.3f} {max(seconds):8.3f} "
              f"{min(seconds) / base:8.2f} "
              f"{min(row['seconds'] + row['import'] for row in runs):10.3f}  {'/'.join(where)}")
    print(f"python -m cifilter compile (whole process): {compile_seconds:.1f} s")


if __name__ == "__main__":
    main()
