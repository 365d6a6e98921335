"""Batched paths of two source trees of cifilter, timed alternately (CPU time, best of 5).

Each case runs in a fresh process that imports cifilter from the given tree, so two
versions can be compared on the same data in the same conditions, for instance the code
before and after a change (``git archive REV | tar -x -C /tmp/old``):

    python benchmarks/bench_versions.py /tmp/old .
    python benchmarks/bench_versions.py /tmp/old . --cases ci,ei --rounds 3
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

CASES = ("ci", "ci3", "pci2", "pci3", "ei", "pcei", "sampler", "bayes")

CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
import cifilter

def pairs(count, N, n, seed):
    r = np.random.default_rng(seed)
    A = r.standard_normal((count, N, n, n))
    return r.standard_normal((count, N, n)), A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)

case = sys.argv[2]
if case == "ci":
    xs, Ps = pairs(100000, 2, 4, 0)
    run = lambda: cifilter.covariance_intersection(xs, Ps)
elif case == "ci3":
    xs, Ps = pairs(20000, 3, 4, 1)
    run = lambda: cifilter.covariance_intersection(xs, Ps)
elif case in ("pci2", "pci3"):
    xs, Ps = pairs(20000, int(case[-1]), 4, 0)
    run = lambda: cifilter.partial_ci(xs, Ps, 0.5)
elif case in ("ei", "pcei"):
    xs, Ps = pairs(2000, 2, 4, 3)
    rule = (cifilter.ellipsoidal_intersection if case == "ei"
            else cifilter.pc_ellipsoidal_intersection)
    run = lambda: rule(xs[:, 0], Ps[:, 0], xs[:, 1], Ps[:, 1])
elif case == "sampler":
    Pb = np.array([[[2.0, 0.3], [0.3, 1.0]], [[1.0, -0.2], [-0.2, 3.0]]])
    run = lambda: cifilter.sample_joint_covariances(Pb, 5, 1_000_000, rng=0)
else:
    xs, Ps = pairs(2000, 2, 2, 4)
    run = lambda: cifilter.bayesian_fusion(xs, Ps, samples=100, rng=0)
run()
times = []
for _ in range(5):
    start = time.process_time()
    run()
    times.append(time.process_time() - start)
print(json.dumps(min(times)))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path, help="source tree of the baseline version")
    parser.add_argument("after", type=Path, help="source tree of the version to compare")
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    cases = args.cases.split(",")
    best = {case: {"before": float("inf"), "after": float("inf")} for case in cases}
    for _ in range(args.rounds):
        for case in cases:
            for label, root in (("before", args.before), ("after", args.after)):
                out = subprocess.run([sys.executable, "-c", CHILD, str(root.resolve()), case],
                                     capture_output=True, text=True, check=True, cwd="/")
                best[case][label] = min(best[case][label], json.loads(out.stdout.split()[-1]))
    print(f"{'case':8} {'before [s]':>11} {'after [s]':>10} {'after/before':>13}")
    for case in cases:
        b, a = best[case]["before"], best[case]["after"]
        print(f"{case:8} {b:11.3f} {a:10.3f} {a / b:13.2f}")


if __name__ == "__main__":
    main()
