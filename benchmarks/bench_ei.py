"""Batched EI and PC-EI against per-pair Python loops of the same computations.

EI: cifilter.ellipsoidal_intersection on (pairs, 4) / (pairs, 4, 4) arrays against a loop
that evaluates eqs. (11)-(13) and (7)-(8) of Naveen & Taylor for one pair at a time with
numpy (eigendecompositions and inverses, as printed).

PC-EI: cifilter.pc_ellipsoidal_intersection (eq. (13) as printed, alpha = 0.05, where the
constraint is active in every pair) against a loop that solves eq. (19) for one pair at a
time the way the paper describes it: SciPy's SLSQP over the lower triangular S of
C_c = C_EI + S S^T, minimising log det C_c subject to psi <= gamma, started from a
multiple of the identity. The loop's time is scaled to all pairs; the script also prints
how the two optima compare. The default-mean PC-EI is timed on the demo's batch.

    python benchmarks/bench_ei.py                  # 2000 pairs, 40 looped for PC-EI
    python benchmarks/bench_ei.py --pairs 500 --loop-pairs 20
"""

import argparse
import os
import platform

import numpy as np
from bench_ci import best_of  # the same timing helper (run as a script from benchmarks/)
from scipy import optimize, stats

import cifilter
from cifilter.cli.demo import simulate

inv = np.linalg.inv


def make_pairs(pairs, n, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((pairs, 2, n, n))
    Ps = A @ np.swapaxes(A, -1, -2) / n + 0.2 * np.eye(n)
    xs = 0.5 * rng.standard_normal((pairs, 2, n))
    return xs, Ps


def ill_conditioned_pairs(pairs, n, cond, seed):
    """Rotated log-spaced spectra from 1 to ``cond`` (the construction of issue 9)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((pairs, 2, n, n)))
    P = (Q * np.logspace(0, np.log10(cond), n)) @ np.swapaxes(Q, -1, -2)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    return P[:, 0], P[:, 1]


def literal_ei(xa, Pa, xb, Pb):
    """Eqs. (11)-(13), (7)-(8) for one pair (eps = 0.01 as in the paper)."""
    d_a, E_a = np.linalg.eigh(Pa)
    root = np.diag(np.sqrt(d_a))
    d_b, Q_b = np.linalg.eigh(inv(root) @ E_a.T @ Pb @ E_a @ inv(root))
    Cc = E_a @ root @ Q_b @ np.diag(np.maximum(d_b, 1.0)) @ Q_b.T @ root @ E_a.T
    Cc = Cc + 0.01 * np.eye(len(xa))
    Ia, Ib, Ic = inv(Pa) - inv(Cc), inv(Pb) - inv(Cc), inv(Cc)
    mc = inv(Ia + Ib) @ (Ia @ xa + Ib @ xb)
    P = inv(inv(Pa) + inv(Pb) - Ic)
    return P @ (inv(Pa) @ xa + inv(Pb) @ xb - Ic @ mc), P, Cc


def psi(xa, Pa, xb, Pb, Cc):
    """Eq. (17) with eq. (13) as printed."""
    Ia, Ib = inv(Pa) - inv(Cc), inv(Pb) - inv(Cc)
    mc = inv(Ia + Ib) @ (Ia @ xa + Ib @ xb)
    ma = inv(Ia) @ (inv(Pa) @ xa - inv(Cc) @ mc)
    mb = inv(Ib) @ (inv(Pb) @ xb - inv(Cc) @ mc)
    return (ma - mb) @ inv(inv(Ia) + inv(Ib)) @ (ma - mb)


def slsqp_pc(xa, Pa, xb, Pb, gamma):
    """Eq. (19) with SLSQP over S for one pair; returns log det C_c (inf if it failed)."""
    n = len(xa)
    C_ei = literal_ei(xa, Pa, xb, Pb)[2] - 0.01 * np.eye(n)
    tril = np.tril_indices(n)

    def common(s):
        S = np.zeros((n, n))
        S[tril] = s
        return C_ei + S @ S.T

    def constraint(s):
        value = psi(xa, Pa, xb, Pb, common(s))
        return np.log(gamma) - np.log(value) if np.isfinite(value) and value > 0 else -1e3

    start = np.eye(n)[tril]
    result = optimize.minimize(lambda s: np.linalg.slogdet(common(s))[1], start,
                               method="SLSQP", constraints={"type": "ineq", "fun": constraint},
                               options={"ftol": 1e-12, "maxiter": 500})
    ok = constraint(result.x) >= -1e-8
    return result.fun if ok else np.inf


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--loop-pairs", type=int, default=40,
                        help="pairs solved by the SLSQP loop (its time is scaled)")
    parser.add_argument("--dim", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    xs, Ps = make_pairs(args.pairs, args.dim, args.seed)
    xa, xb, Pa, Pb = xs[:, 0], xs[:, 1], Ps[:, 0], Ps[:, 1]
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}; {args.pairs} pairs of {args.dim}x{args.dim} covariances")

    t_ei, _ = best_of(3, lambda: cifilter.ellipsoidal_intersection(
        xa, Pa, xb, Pb, eps=0.01, regularizer="covariance", mutual_mean="as-printed"))
    t_loop, _ = best_of(1, lambda: [literal_ei(xa[k], Pa[k], xb[k], Pb[k])
                                    for k in range(args.pairs)])
    print(f"EI    batched {t_ei:8.3f} s   loop of eqs. (11)-(13) {t_loop:8.3f} s   "
          f"speed-up {t_loop / t_ei:6.1f}x")
    t_default, _ = best_of(3, lambda: cifilter.ellipsoidal_intersection(xa, Pa, xb, Pb))
    print(f"EI    batched, default options (information regulariser): {t_default:8.3f} s")
    Pa_ill, Pb_ill = ill_conditioned_pairs(args.pairs, args.dim, 1e9, args.seed)
    P_ill = cifilter.ellipsoidal_intersection(np.zeros(args.dim), Pa_ill, np.zeros(args.dim),
                                              Pb_ill).P
    smallest = np.linalg.eigvalsh(P_ill)[:, 0]
    print(f"EI    on {args.pairs} random pairs with condition number 1e9: "
          f"{np.mean(smallest <= 0):.1%} not positive definite")

    data = simulate(20, 100, rng=0)
    t_demo, r = best_of(3, lambda: cifilter.pc_ellipsoidal_intersection(
        data.x_a, data.P_a, data.x_b, data.P_b))
    print(f"PC-EI (Sijs & Lazar mean) on the demo's 2000 problems: {t_demo:.3f} s "
          f"(solvers: {dict(zip(*np.unique(r.info['solver'], return_counts=True)))})")

    t_pc, r = best_of(1, lambda: cifilter.pc_ellipsoidal_intersection(
        xa, Pa, xb, Pb, mutual_mean="as-printed"))
    info = r.info
    ok = info["feasible"]
    print(f"PC-EI (printed mean) batched {t_pc:8.3f} s: Newton iterations mean "
          f"{info['iterations'][ok].mean():.1f} max {info['iterations'].max()}, converged "
          f"{info['converged'][ok].mean():.4f}, max KKT residual "
          f"{np.nanmax(info['kkt_residual'][ok]):.1e}, starts agreeing "
          f"{dict(zip(*np.unique(info['starts_agree'][ok], return_counts=True)))}")

    loop = min(args.loop_pairs, args.pairs)
    gamma = stats.chi2.ppf(0.95, args.dim)
    t_slsqp, values = best_of(1, lambda: np.array([slsqp_pc(xa[k], Pa[k], xb[k], Pb[k], gamma)
                                                   for k in range(loop)]))
    ours = np.linalg.slogdet(info["common_P"][:loop])[1]
    found = np.isfinite(values) & ok[:loop]
    scaled = t_slsqp * args.pairs / loop
    print(f"SLSQP loop (paper's parameterisation, one start): {t_slsqp:.2f} s for {loop} pairs,"
          f" {scaled:.1f} s scaled to {args.pairs}; speed-up {scaled / t_pc:.1f}x")
    print(f"  SLSQP met the constraint in {found.sum()} of {ok[:loop].sum()} feasible pairs; "
          f"log det C_c ours - SLSQP: min {np.min(ours[found] - values[found]):.2e}, "
          f"max {np.max(ours[found] - values[found]):.2e} (negative: ours smaller)")


if __name__ == "__main__":
    main()
