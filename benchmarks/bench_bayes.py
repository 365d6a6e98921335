"""Sampled joint covariances per second: vectorised sampler against a per-sample loop.

Two 2-D estimates (a 4x4 joint covariance), prior dof 5. The vectorised call is
cifilter.sample_joint_covariances([P1, P2], 5, size). The baseline draws one sample at a time
the way Theorem 1 of Weng & Djurić is written: S from scipy.stats.wishart(df=dof - n), X
standard normal, A_12^T = A_22^1/2 (S + X X^T)^-1/2 X A_11^1/2 with symmetric square roots
(eigendecompositions), and the joint assembled with numpy.block. Both run in the same process;
the script prints the rates, their ratio, the issue's targets (>= 1e6 samples/s, >= 100x) and
a check that both draw the same law (the mean of tr(R R^T) for the normalised cross block R,
which is n^2 / dof = 0.8).

It then times the batched fusion, cifilter.bayesian_fusion on --problems independent problems
(the same two covariances, random means) with --fusion-samples samples each, and reports the
joint-covariance samples fused per second; with --memory it also measures, with tracemalloc,
the peak memory of one fusion of two 4-D estimates with 1e6 samples (the issue's bound:
under 500 MB). The machine is shared: the CPU times (process time, best of 3) are the
robust comparison; run with OPENBLAS_NUM_THREADS=1 so that they count one thread.

    python benchmarks/bench_bayes.py                      # 1e6 vectorised, 5000 in the loop
    python benchmarks/bench_bayes.py --size 200000 --loop-size 2000
    python benchmarks/bench_bayes.py --memory             # also the peak memory at 1e6 samples
"""

import argparse
import os
import platform
import time
import tracemalloc

import numpy as np
from bench_ci import best_of  # the benchmarks' directory is on the path of a script
from scipy import stats

import cifilter

P1 = np.array([[1.0, 0.3], [0.3, 4.0]])
P2 = np.array([[2.0, -0.5], [-0.5, 1.0]])
DOF = 5.0


def symmetric_power(S, power):
    w, V = np.linalg.eigh(S)
    return (V * w**power) @ V.T


def loop_samples(size, seed):
    """One scipy.stats.wishart draw and one Theorem-1 transform per sample: the baseline."""
    rng = np.random.default_rng(seed)
    n = P1.shape[0]
    wishart = stats.wishart(df=DOF - n, scale=np.eye(n))
    root1, root2 = symmetric_power(P1, 0.5), symmetric_power(P2, 0.5)
    out = np.empty((size, 2 * n, 2 * n))
    for m in range(size):
        S = wishart.rvs(random_state=rng)
        X = rng.standard_normal((n, n))
        A12T = root2 @ symmetric_power(S + X @ X.T, -0.5) @ X @ root1
        out[m] = np.block([[P1, A12T.T], [A12T, P2]])
    return out


def mean_trace_RRT(A):
    n = P1.shape[0]
    R = symmetric_power(P1, -0.5) @ A[:, :n, n:] @ symmetric_power(P2, -0.5)
    return float(np.mean(np.einsum("mij,mij->m", R, R)))


def cpu_best_of(repeats, function):
    """Smallest process CPU time of ``repeats`` calls: robust on a shared, loaded machine."""
    times = []
    for _ in range(repeats):
        start = time.process_time()
        function()
        times.append(time.process_time() - start)
    return min(times)


def fusion_problems(problems, seed):
    g = np.random.default_rng(seed)
    xs = g.standard_normal((problems, 2, 2))
    Ps = np.broadcast_to(np.stack([P1, P2]), (problems, 2, 2, 2))
    return xs, Ps


def peak_memory_of_large_fusion(samples=1_000_000):
    """Peak traced memory (bytes) and time of one fusion of two 4-D estimates."""
    Ps = [np.kron(np.eye(2), P1), np.kron(np.eye(2), P2)]
    tracemalloc.start()
    start = time.perf_counter()
    cifilter.bayesian_fusion([np.zeros(4), np.ones(4)], Ps, samples=samples, rng=0)
    elapsed = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak, elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1_000_000, help="vectorised samples")
    parser.add_argument("--loop-size", type=int, default=5000, help="samples in the loop")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--problems", type=int, default=2000, help="batched fusion problems")
    parser.add_argument("--fusion-samples", type=int, default=100,
                        help="samples per batched fusion problem")
    parser.add_argument("--memory", action="store_true",
                        help="also measure the peak memory of a fusion with 1e6 samples")
    args = parser.parse_args()

    vector_time, A = best_of(
        3, lambda: cifilter.sample_joint_covariances([P1, P2], DOF, args.size, rng=args.seed))
    vector_cpu = cpu_best_of(3, lambda: cifilter.sample_joint_covariances(
        [P1, P2], DOF, args.size, rng=args.seed))
    loop_time, B = best_of(1, lambda: loop_samples(args.loop_size, args.seed))
    vector_rate, loop_rate = args.size / vector_time, args.loop_size / loop_time
    speedup = vector_rate / loop_rate

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}")
    print("two 2-D estimates (4x4 joint covariances), prior dof 5")
    print(f"vectorised sample_joint_covariances: {args.size} samples in {vector_time:.3f} s "
          f"(best of 3) = {vector_rate:,.0f} samples/s; CPU time "
          f"{vector_cpu / args.size * 1e6:.3f} us per sample")
    print(f"loop with scipy.stats.wishart:       {args.loop_size} samples in {loop_time:.3f} s "
          f"= {loop_rate:,.0f} samples/s")
    print(f"speed-up: {speedup:.0f}x")
    print(f"targets: >= 1,000,000 samples/s: {'met' if vector_rate >= 1e6 else 'NOT met'}; "
          f">= 100x: {'met' if speedup >= 100 else 'NOT met'}")
    print(f"same law: mean tr(R R^T) = {mean_trace_RRT(A):.4f} (vectorised), "
          f"{mean_trace_RRT(B):.4f} (loop), exact {P1.shape[0] ** 2 / DOF:.4f}")

    xs, Ps = fusion_problems(args.problems, args.seed)
    fusion_time, _ = best_of(3, lambda: cifilter.bayesian_fusion(
        xs, Ps, samples=args.fusion_samples, rng=args.seed))
    fusion_cpu = cpu_best_of(3, lambda: cifilter.bayesian_fusion(
        xs, Ps, samples=args.fusion_samples, rng=args.seed))
    fused = args.problems * args.fusion_samples
    print(f"batched bayesian_fusion: {args.problems} problems x {args.fusion_samples} samples "
          f"in {fusion_time:.3f} s (best of 3) = {fused / fusion_time:,.0f} samples/s; CPU time "
          f"{fusion_cpu / fused * 1e6:.3f} us per sample")
    if args.memory:
        peak, elapsed = peak_memory_of_large_fusion()
        print(f"bayesian_fusion, two 4-D estimates, 1e6 samples: peak traced memory "
              f"{peak / 1e6:,.0f} MB (bound 500 MB: {'met' if peak < 500e6 else 'NOT met'}), "
              f"{elapsed:.1f} s")


if __name__ == "__main__":
    main()
