"""Mutation testing of the numerical core: hand-made mutations, one at a time.

Each mutation is a (file, exact source snippet, replacement, tests) record. The script copies
the working tree once to a scratch directory (``--scratch``, default a new ``/tmp`` folder;
the tree it reads, ``--source``, is never written), and for each mutation in turn writes the
mutated file into the copy, runs the mutation's tests there with ``pytest -x`` under a time
limit, and restores the file. A mutation is

* ``killed``    the tests failed (or errored) on the mutant;
* ``survived``  the tests passed on the mutant: a wrong result the tests let through
  (unless the mutation is marked ``equivalent``: no observable behaviour changes);
* ``timeout``   the tests did not finish within ``--timeout`` seconds (counted as killed: a
  hang is observable, but it is listed apart);
* ``stale``     the snippet is no longer in the file (the code changed): update or drop it.

Before the mutants, every test file used is run once on the unmutated copy; a mutant whose
selection holds a file that fails there is ``baseline-failed`` (not counted). For each
mutant the new contract tests (``FIRST``) run first and the older files only if those pass.

The kill rate is ``(killed + timeout) / (killed + timeout + survived)`` over the mutations
not marked equivalent. Hypothesis runs with the derandomised ``ci`` profile (``CI=true``) so
that two runs of the script agree.

Usage::

    python tools/mutate.py                    # every mutation
    python tools/mutate.py --list             # the mutations, and whether each snippet is found
    python tools/mutate.py -k gap -k pci      # the mutations whose name contains a word
    python tools/mutate.py --timeout 240 --total 1500 --json /tmp/mutation.json

Run it from any directory; ``--source`` defaults to the repository holding this script.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from typing import NamedTuple, Optional

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class Mutation(NamedTuple):
    name: str
    path: str  # relative to the repository root
    old: str  # exact snippet (its first occurrence is replaced)
    new: str
    tests: tuple[str, ...]  # test paths (relative), run with -x
    equivalent: bool = False  # no observable change expected (reported apart)
    note: str = ""


# ------------------------------------------------------------------------ test selections
GAPS = "tests/rules/test_mutation_gaps.py"
MEANS = "tests/rules/test_fused_means.py"
NUM_GAPS = "tests/numerics/test_mutation_gaps_numerics.py"
HSCALE = "tests/horizon/test_horizon_scales.py"
FIRST = (GAPS, MEANS, NUM_GAPS, HSCALE)  # fast contract tests: run before the others

LINALG = ("tests/numerics/test_linalg.py", NUM_GAPS)
VALIDATION = ("tests/numerics/test_validation.py", NUM_GAPS)
CI = (GAPS, MEANS, "tests/rules/test_ci.py")
ICI = (GAPS, "tests/rules/test_ici.py")
PCI = (GAPS, MEANS, "tests/rules/test_pci.py")
OPT = (NUM_GAPS, GAPS, "tests/numerics/test_optimize.py")
CRIT = (GAPS, NUM_GAPS, "tests/numerics/test_criteria.py")
UNION = (GAPS, "tests/rules/test_union.py")
HORIZON = (HSCALE, "tests/horizon/test_horizon_model.py")
OPTIMAL = (MEANS, "tests/rules/test_optimal.py")
INFO = (MEANS, GAPS)

L = "cifilter/_numerics/linalg.py"
V = "cifilter/_numerics/validation.py"
C = "cifilter/_numerics/criteria.py"
O = "cifilter/_numerics/optimize.py"
I = "cifilter/_numerics/information.py"
W = "cifilter/rules/_ci_weights.py"
IC = "cifilter/rules/_inverse_ci.py"
PC = "cifilter/rules/pci.py"
PR = "cifilter/rules/_partial_correlation.py"
U = "cifilter/rules/_union.py"
HM = "cifilter/horizon/_model.py"
OP = "cifilter/rules/optimal.py"

MUTATIONS: list[Mutation] = [
    # ---------------------------------------------------------------- linear algebra
    Mutation("cholesky_single accepts everything", L,
             "if info != 0 or not math.isfinite(float(L.trace())):\n        return None",
             "if False:\n        return None", LINALG),
    Mutation("cholesky: ill-conditioned/indefinite threshold sign", L,
             "if smallest >= -EIGENVALUE_RTOL * A.shape[-1] * largest:",
             "if smallest >= EIGENVALUE_RTOL * A.shape[-1] * largest:", LINALG),
    Mutation("EIGENVALUE_RTOL 1e6 times larger", L,
             "EIGENVALUE_RTOL = 8 * np.finfo(float).eps",
             "EIGENVALUE_RTOL = 8e6 * np.finfo(float).eps", LINALG),
    Mutation("symmetrize drops the transpose", L,
             "return 0.5 * (A + A.swapaxes(-1, -2))", "return 0.5 * (A + A)",
             LINALG + ("tests/numerics/test_validation.py",) + CI),
    Mutation("solve_lower: off-diagonal sign", L,
             "row = row - (L[..., i:i + 1, :i] @ X[..., :i, :])[..., 0, :]",
             "row = row + (L[..., i:i + 1, :i] @ X[..., :i, :])[..., 0, :]", LINALG),
    Mutation("cho_solve: second solve untransposed", L,
             "X = np.linalg.solve(L.swapaxes(-1, -2), Y)", "X = np.linalg.solve(L, Y)",
             LINALG),
    Mutation("logdet_from_cholesky without the factor 2", L,
             "return 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)",
             "return np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)", LINALG),
    # ---------------------------------------------------------------- validation
    Mutation("SYMMETRY_RTOL 1e-8 -> 1e-6", V, "SYMMETRY_RTOL = 1e-8", "SYMMETRY_RTOL = 1e-6",
             VALIDATION),
    Mutation("SYMMETRY_RTOL 1e-8 -> 1e-10", V, "SYMMETRY_RTOL = 1e-8", "SYMMETRY_RTOL = 1e-10",
             VALIDATION),
    Mutation("symmetry scale: smallest diagonal entry", V,
             "scale = np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(axis=-1)",
             "scale = np.abs(np.diagonal(P, axis1=-2, axis2=-1)).min(axis=-1)", VALIDATION),
    Mutation("fast path skips the symmetry check", V,
             'exact = _check_symmetric(P, "Ps", None)', "exact = False", VALIDATION),
    Mutation("fast path skips the finiteness check", V,
             "    if not np.isfinite(x).all():\n        return None\n    try:",
             "    if False:\n        return None\n    try:", VALIDATION),
    Mutation("PSD_RTOL 1e-10 -> 1e-6", V, "PSD_RTOL = 1e-10", "PSD_RTOL = 1e-6", VALIDATION),
    # ---------------------------------------------------------------- criteria
    Mutation("certified_gap not relative (N > 2)", C,
             'return gap if kind == "det" else gap / value', "return gap", CRIT),
    Mutation("GAP_TOL 1e-9 -> 1e-3", C, "GAP_TOL = 1e-9", "GAP_TOL = 1e-3", CRIT),
    Mutation("trace gradient from the wrong factors", C,
             'if kind == "trace":\n        return squared_norms(factors.B)',
             'if kind == "trace":\n        return squared_norms(factors.C)', CRIT),
    Mutation("log det of a factor without the factor 2", C,
             "return 2.0 * np.log(np.abs(np.diagonal(R_inv, axis1=-2, axis2=-1))).sum(axis=-1)",
             "return np.log(np.abs(np.diagonal(R_inv, axis1=-2, axis2=-1))).sum(axis=-1)",
             CRIT),
    # ---------------------------------------------------------------- optimisation
    Mutation("frank_wolfe_gap against the largest gradient", O,
             "return np.maximum(along - gradient.min(axis=-1), 0.0)",
             "return np.maximum(along - gradient.max(axis=-1), 0.0)", OPT),
    Mutation("interval_gap sign", O,
             "return 0.5 * (abs(slope) + (2.0 * t - 1.0) * slope)",
             "return 0.5 * (abs(slope) - (2.0 * t - 1.0) * slope)", OPT + CI),
    Mutation("interval bracket: lower end on the wrong side", O,
             "lo_i = np.where(g < 0, wi, lo_i)", "lo_i = np.where(g > 0, wi, lo_i)", OPT),
    Mutation("scalar interval: minimum at 1 reported at 0", O,
             "if g1 <= 0:\n        return 1.0, 0, True", "if g1 <= 0:\n        return 0.0, 0, True",
             OPT + CI),
    Mutation("scalar interval: never reports non-convergence", O,
             "return w, max_iter, False", "return w, max_iter, True", OPT),
    Mutation("line search: no descent check", O,
             "f_trial <= f + 1e-4 * t * slope + 1e-15 * np.abs(f))", "f_trial <= np.inf)",
             OPT),
    Mutation("line search: no backtracking", O,
             "t = np.where(failed, 0.5 * t, t)", "t = np.where(failed, 1.0 * t, t)", OPT),
    Mutation("active set: never release a weight", O,
             "release_any = (deficit < -1e-12 * g_scale[..., None]).any(axis=-1)",
             "release_any = np.zeros(shape, dtype=bool)", OPT),
    Mutation("active set: blocked weight not fixed at zero", O,
             "new_w = np.where(hit, 0.0, np.clip(new_w, 0.0, None))",
             "new_w = np.clip(new_w, 0.0, None)", OPT),
    Mutation("simplex: gap test 1e6 times looser", O,
             "certified = active & (gap <= gtol * (1.0 if absolute_gap else np.abs(f)))",
             "certified = active & (gap <= 1e6 * gtol * (1.0 if absolute_gap else np.abs(f)))",
             OPT),
    Mutation("simplex: never stuck (no Frank-Wolfe fallback)", O,
             "if stuck.any():\n            d, slope, free = _towards_best_vertices(",
             "if False:\n            d, slope, free = _towards_best_vertices(", OPT),
    # ---------------------------------------------------------------- information fusion
    Mutation("weighted_fusion (batched): mean update sign", I,
             "x_fused += (gains[..., k, :, :] @ (x[..., k, :] - x_ref)[..., None])[..., 0] * (",
             "x_fused -= (gains[..., k, :, :] @ (x[..., k, :] - x_ref)[..., None])[..., 0] * (",
             INFO),
    Mutation("weighted_fusion (single): mean about the wrong point", I,
             "x_fused += K @ (x[k] - x_ref)", "x_fused += K @ (x[k] + x_ref)", INFO),
    Mutation("weighted_fusion (single): bound multiplies by sqrt(w)", I,
             "M = (gains[k] @ L[k]) / math.sqrt(w[k])", "M = (gains[k] @ L[k]) * math.sqrt(w[k])",
             INFO),
    Mutation("weighted_fusion (batched): bound multiplies by sqrt(w)", I,
             "(gains[..., k, :, :] @ L[..., k, :, :]) / np.sqrt(w), 0.0)",
             "(gains[..., k, :, :] @ L[..., k, :, :]) * np.sqrt(w), 0.0)", INFO),
    Mutation("information_factors ignores the weights", I,
             "term = weights[..., k, None, None] * (Lk.swapaxes(-1, -2) @ Lk)",
             "term = (Lk.swapaxes(-1, -2) @ Lk)", INFO),
    Mutation("DIAGONAL_TRUST 1e6 -> 1e12", I, "DIAGONAL_TRUST = 1e6", "DIAGONAL_TRUST = 1e12",
             (GAPS,)),
    Mutation("single diagonalisation trusts any factor spread", I,
             "if max(d) ** 2 > DIAGONAL_TRUST * min(d) ** 2:\n            return False",
             "if False:\n            return False", (GAPS,)),
    # ---------------------------------------------------------------- CI weights
    Mutation("two-estimate CI (batched diagonal): gap not relative", W,
             "(c * (a + 1.0) / (1.0 + omega[:, None] * a)).sum(axis=-1))",
             "1.0)", CI),
    Mutation("two-estimate CI (single diagonal): gap not relative", W,
             "else sum(ck * (ak + 1.0) / (1.0 + omega * ak) for ck, ak in zip(c, a)))",
             "else 1.0)", CI),
    Mutation("CI: converged whatever the gap", W,
             '"converged": gap_converged(*cert),', '"converged": cert.gap == cert.gap,', CI),
    Mutation("CI (batched diagonal): trust any eigenvalue spread", W,
             "spread = lam_flat.max(axis=-1) / lam_flat.min(axis=-1)",
             "spread = lam_flat.min(axis=-1) / lam_flat.max(axis=-1)", CI),
    Mutation("CI (single diagonal): always trusted", W,
             "if not single_diagonalisation_trusted(lam_list, (L1, L2)):\n        return None",
             "if False:\n        return None", CI),
    # ---------------------------------------------------------------- inverse CI
    Mutation("ICI diagonal path: gap not relative", IC,
             'None if kind == "det" else value(omega))', "None)", ICI),
    Mutation("ICI robust path: gap not relative", IC,
             'cert = pair_certificate(omega, slope, error, None if kind == "det" else f)',
             "cert = pair_certificate(omega, slope, error, None)", ICI),
    Mutation("ICI diagonal path: trusted whatever the spread", IC,
             "trusted = (usable & (spread <= DIAGONAL_TRUST) & (conditioning <= DIAGONAL_TRUST)",
             "trusted = (usable", ICI),
    # ---------------------------------------------------------------- partial CI
    Mutation("partial CI Newton: never reports non-convergence", PC,
             'info["converged"] = (gap <= tol) if converged is None else converged',
             'info["converged"] = (gap == gap) if converged is None else converged', PCI),
    Mutation("partial CI: no repair below the rho floor", PR,
             "redo = (relative_gap(delta, true_rho, trace, spread) > tol).reshape(-1)",
             "redo = (relative_gap(delta, true_rho, trace, spread) > np.inf).reshape(-1)", PCI),
    Mutation("partial CI: NEWTON_RHO_FLOOR 1e-8 -> 1e-4", PR,
             "NEWTON_RHO_FLOOR = 1e-8", "NEWTON_RHO_FLOOR = 1e-4", PCI, equivalent=True,
             note="the repair by Algorithm 2 under the true bounds restores the optimum: "
                  "only the iteration count changes (performance, not results)"),
    Mutation("partial CI: relative gap not relative", PR,
             "return np.maximum(along.sum(axis=-1) - g.min(axis=-1), 0.0) / trace",
             "return np.maximum(along.sum(axis=-1) - g.min(axis=-1), 0.0)", PCI),
    Mutation("Algorithm 2: converged without the gap test", PR,
             "converged[active] = (change <= tol) & (gap <= tol)",
             "converged[active] = (change <= tol)", PCI),
    Mutation("Algorithm 2: eq. (25) without the square root of rho", PR,
             "root = np.sqrt(r) * w * np.sqrt(spread)", "root = r * w * np.sqrt(spread)", PCI),
    Mutation("eq. (24) derivative: one power of the base", PR,
             "first = rho / (base * base)", "first = rho / base", PCI),
    Mutation("eq. (24): weights without rho", PR,
             "denominator = np.where(positive, rho + (1.0 - rho) * delta, 1.0)",
             "denominator = np.where(positive, 1.0, 1.0)", PCI),
    # ---------------------------------------------------------------- covariance union
    Mutation("union dual bound: twice the mean term", U,
             "return ((1.0 - s) * p1 + s * p2 + s * (1.0 - s) * beta**2).sum(axis=-1)",
             "return ((1.0 - s) * p1 + s * p2 + 2.0 * s * (1.0 - s) * beta**2).sum(axis=-1)",
             UNION),
    Mutation("union dual bound: without the mean term", U,
             "return ((1.0 - s) * p1 + s * p2 + s * (1.0 - s) * beta**2).sum(axis=-1)",
             "return ((1.0 - s) * p1 + s * p2).sum(axis=-1)", UNION),
    Mutation("union dual bound: multiplier not clipped to [0, 1]", U,
             "s = np.clip(s, 0.0, 1.0)\n", "s = np.clip(s, -1.0, 2.0)\n", UNION),
    # ---------------------------------------------------------------- horizon recursion
    Mutation("single-model horizon: Joseph form sign", HM,
             "P_c = A @ M @ A.T + K @ R @ K.T", "P_c = A @ M @ A.T - K @ R @ K.T", HORIZON),
    Mutation("single-model horizon: Gamma weight exponent sign", HM,
             "weight = math.exp(2.0 * log_scale - _LN2 * e)",
             "weight = math.exp(2.0 * log_scale + _LN2 * e)", HORIZON),
    Mutation("single-model horizon: prediction transposed", HM,
             "M = F @ P_c @ FT + noise", "M = FT @ P_c @ F + noise", HORIZON),
    Mutation("single-model horizon: R rescaled the wrong way", HM,
             "R = np.ldexp(R, -e)", "R = np.ldexp(R, e)", HORIZON),
    Mutation("batched horizon: Joseph form sign", HM,
             "P = A @ M @ A.swapaxes(-1, -2) + K @ R @ K.swapaxes(-1, -2)",
             "P = A @ M @ A.swapaxes(-1, -2) - K @ R @ K.swapaxes(-1, -2)", HORIZON),
    Mutation("batched horizon: prediction transposed", HM,
             "return symmetrize(model.F @ P @ model.F.swapaxes(-1, -2) + noise)",
             "return symmetrize(model.F.swapaxes(-1, -2) @ P @ model.F + noise)", HORIZON),
    # ---------------------------------------------------------------- optimal (BLUE)
    Mutation("BLUE gains transposed", OP,
             "gains = P[..., None, :, :] @ np.swapaxes(blocks, -1, -2)  # K_i = P A_i^T",
             "gains = P[..., None, :, :] @ blocks", OPTIMAL),
    Mutation("BLUE information from the wrong side", OP,
             "information = symmetrize(np.swapaxes(A, -1, -2) @ E)  # E^T P_x^-1 E",
             "information = symmetrize(np.swapaxes(E, -1, -2) @ E)  # E^T P_x^-1 E", OPTIMAL),
]


# ------------------------------------------------------------------------ machinery
def copy_tree(source, scratch):
    """The working tree without .git and caches (rsync when available, else shutil)."""
    excludes = [".git", "__pycache__", ".hypothesis", ".pytest_cache", "*.egg-info",
                "docs/_build", ".mypy_cache", ".ruff_cache"]
    os.makedirs(scratch, exist_ok=True)
    if shutil.which("rsync"):
        args = ["rsync", "-a", "--delete"] + [f"--exclude={e}" for e in excludes]
        subprocess.run(args + [source.rstrip("/") + "/", scratch.rstrip("/") + "/"], check=True)
    else:
        shutil.rmtree(scratch)
        shutil.copytree(source, scratch, ignore=shutil.ignore_patterns(*excludes))


def environment(scratch):
    env = dict(os.environ)
    env["PYTHONPATH"] = scratch + os.pathsep + os.path.join(scratch, "tests")
    env["CI"] = "true"  # the derandomised hypothesis profile
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    env.setdefault("NUMBA_CACHE_DIR", os.path.join(scratch, ".numba_cache"))
    return env


def check_import(scratch, env):
    """The copy, not the editable install, must be what the tests import."""
    out = subprocess.run([sys.executable, "-c", "import cifilter; print(cifilter.__file__)"],
                         cwd=scratch, env=env, capture_output=True, text=True)
    where = out.stdout.strip()
    if not where.startswith(os.path.realpath(scratch)) and not where.startswith(scratch):
        sys.exit(f"the scratch copy is not the imported package (got {where!r}); stopping")


def _pytest(scratch, env, tests, timeout, extra=()):
    command = [sys.executable, "-m", "pytest", "-o", "addopts=", "-p", "no:cacheprovider",
               "-q", "-m", "not slow", "-W", "ignore::DeprecationWarning", *extra, *tests]
    try:
        out = subprocess.run(command, cwd=scratch, env=env, capture_output=True, text=True,
                             timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, ""
    return out.returncode, out.stdout + out.stderr


def baseline_failures(scratch, env, files, timeout):
    """The test files (of ``files``) with a failing test on the unmutated copy: one run."""
    code, output = _pytest(scratch, env, files, timeout, extra=("-rf",))
    if code is None:
        return set(files)
    failed = set()
    for line in output.splitlines():
        if line.startswith(("FAILED ", "ERROR ")):
            failed.add(line.split()[1].split("::")[0])
    if code not in (0, 1) and not failed:  # collection error, internal error
        failed = set(files)
    return failed


def run_tests(scratch, env, tests, timeout):
    """'passed', 'failed' or 'timeout', and the tail of the output.

    The new contract tests (``FIRST``) run first; the rest only if they pass, so that a
    mutant they kill costs one short run. ``timeout`` bounds the whole.
    """
    tests = [t for t in tests if os.path.exists(os.path.join(scratch, t))]
    stages = [[t for t in tests if t in FIRST], [t for t in tests if t not in FIRST]]
    began = time.monotonic()
    for stage in stages:
        if not stage:
            continue
        left = timeout - (time.monotonic() - began)
        if left <= 0:
            return "timeout", ""
        code, output = _pytest(scratch, env, stage, left, extra=("-x",))
        if code is None:
            return "timeout", ""
        if code != 0:
            return "failed", "\n".join(output.strip().splitlines()[-3:])
    return "passed", ""


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=ROOT, help="the tree to copy (not modified)")
    parser.add_argument("--scratch", default=None, help="scratch directory (default: new /tmp)")
    parser.add_argument("--timeout", type=float, default=240.0, help="seconds per mutant")
    parser.add_argument("--total", type=float, default=None,
                        help="stop starting new mutants after this many seconds")
    parser.add_argument("-k", action="append", default=[], help="name filter (any matches)")
    parser.add_argument("--list", action="store_true", help="list the mutations and exit")
    parser.add_argument("--json", default=None, help="write the results to this file")
    args = parser.parse_args(argv)

    chosen = [m for m in MUTATIONS
              if not args.k or any(k.lower() in m.name.lower() for k in args.k)]
    if args.list:
        for m in chosen:
            text = open(os.path.join(args.source, m.path)).read()
            found = "found" if m.old in text else "STALE"
            print(f"{found:6} {m.path}: {m.name}{' (equivalent)' if m.equivalent else ''}")
        return 0

    scratch = args.scratch or tempfile.mkdtemp(prefix="cifilter-mutate-")
    copy_tree(args.source, scratch)
    env = environment(scratch)
    check_import(scratch, env)
    start = time.monotonic()

    files = sorted({t for m in chosen for t in m.tests
                    if os.path.exists(os.path.join(scratch, t))})
    broken = baseline_failures(scratch, env, files, 4 * args.timeout)
    for name in sorted(broken):
        print(f"baseline failed: {name} (its mutants are not run)", flush=True)
    print(f"baseline: {len(files) - len(broken)} of {len(files)} test files pass "
          f"({time.monotonic() - start:.0f} s)", flush=True)

    results = []
    for m in chosen:
        if args.total is not None and time.monotonic() - start > args.total:
            results.append((m, "not run", ""))
            continue
        target = os.path.join(scratch, m.path)
        if not os.path.exists(target):
            results.append((m, "stale", "file missing"))
            print(f"stale      {m.name}", flush=True)
            continue
        original = open(target).read()
        if m.old not in original:
            results.append((m, "stale", "snippet not found"))
            print(f"stale      {m.name}", flush=True)
            continue
        if broken & set(m.tests):
            results.append((m, "baseline-failed", ""))
            print(f"baseline-failed {m.name}", flush=True)
            continue
        began = time.monotonic()
        try:
            with open(target, "w") as handle:
                handle.write(original.replace(m.old, m.new, 1))
            status, tail = run_tests(scratch, env, m.tests, args.timeout)
        finally:
            with open(target, "w") as handle:
                handle.write(original)
        outcome = {"failed": "killed", "passed": "survived", "timeout": "timeout"}[status]
        results.append((m, outcome, tail))
        mark = " (marked equivalent)" if m.equivalent else ""
        print(f"{outcome:10} {m.name}{mark}  [{time.monotonic() - began:.0f} s]", flush=True)

    counted = [(m, o) for m, o, _ in results
               if not m.equivalent and o in ("killed", "survived", "timeout")]
    killed = sum(o in ("killed", "timeout") for _, o in counted)
    print()
    for label in ("killed", "timeout", "survived", "stale", "baseline-failed", "not run"):
        names = [m.name + (" (equivalent)" if m.equivalent else "")
                 for m, o, _ in results if o == label]
        print(f"{label}: {len(names)}")
        if label in ("survived", "stale", "baseline-failed", "timeout"):
            for name in names:
                print(f"    {name}")
    equivalent = sum(m.equivalent for m, _, _ in results)
    rate = killed / len(counted) if counted else float("nan")
    print(f"marked equivalent: {equivalent}")
    print(f"kill rate: {killed}/{len(counted)} = {rate:.1%} of the non-equivalent mutants run "
          f"({time.monotonic() - start:.0f} s)")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump([dict(name=m.name, path=m.path, outcome=o, equivalent=m.equivalent)
                       for m, o, _ in results], handle, indent=1)
    if args.scratch is None:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0 if all(o != "survived" or m.equivalent for m, o, _ in results) else 1


if __name__ == "__main__":
    sys.exit(main())
