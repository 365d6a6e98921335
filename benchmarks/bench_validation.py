"""Input validation (``as_estimates``) before and after its lean version, in one run.

``before`` is a verbatim copy (docstrings dropped) of the functions of
``cifilter/_numerics/validation.py`` and the Cholesky helpers of ``linalg.py`` at commit
7eb31611 (the tree issue 24 measured: "validation costs 15 us of an 86 us kf.fuse and 36% of
batched CI"); ``after`` is the package's current ``as_estimates``. Both run on the same data,
interleaved (each round times a block of calls of ``before`` then of ``after``; many short
rounds, so that the minimum finds the machine's quiet moments), and the minimum over the
rounds is reported with the ratio. Every case also checks that both return the same
``Estimates`` bit for bit. The cases:

* one pair of 4-D estimates, rows ``(4,)`` and filterpy columns ``(4, 1)`` (what
  ``kf.fuse(other)`` validates);
* a batch of 30 pairs given as two arrays (30, 4) / (30, 4, 4) (what the network demo's
  fusions validate, 3120 times per demo);
* 100 000 pairs as one array (100000, 2, 4, 4) and as a sequence of two (100000, 4, 4)
  (batched CI's input), exactly symmetric and not (the symmetrised copy is then formed);
* 20 000 sets of N = 4 estimates of 6x6.

    python benchmarks/bench_validation.py
    python benchmarks/bench_validation.py --repeats 9
"""

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cifilter._numerics.linalg import ill_conditioned  # noqa: E402
from cifilter._numerics.validation import Estimates, as_estimates  # noqa: E402


# ------------------------------------------------------------------ before (commit 7eb31611)
def symmetrize(A):
    A = np.asarray(A)
    return 0.5 * (A + A.swapaxes(-1, -2))


EIGENVALUE_RTOL = 8 * np.finfo(float).eps


def cholesky_failures(A):
    flat = A.reshape((-1,) + A.shape[-2:])
    failed = np.zeros(len(flat), dtype=bool)

    def visit(lo, hi):
        try:
            if np.isfinite(np.linalg.cholesky(flat[lo:hi])).all():
                return
        except np.linalg.LinAlgError:
            pass
        if hi - lo == 1:
            failed[lo] = True
            return
        middle = (lo + hi) // 2
        visit(lo, middle)
        visit(middle, hi)

    if len(flat):
        visit(0, len(flat))
    return failed.reshape(A.shape[:-2])


def cholesky(A, name="matrix"):
    A = np.asarray(A, dtype=float)
    if A.ndim == 2 and A.shape[0] == A.shape[1]:  # one matrix: LAPACK directly
        L = cholesky_single(A)
        if L is not None:  # (a finite diagonal: finite input gives a finite factor)
            return L
    try:
        L = np.linalg.cholesky(A)
        if np.isfinite(L).all():  # LAPACK passes NaN through instead of failing
            return L
    except np.linalg.LinAlgError:
        pass
    failed = cholesky_failures(A)
    index = np.unravel_index(int(np.argmax(failed.ravel())), A.shape[:-2])
    index = tuple(int(i) for i in index)
    where = f"{name}[{', '.join(map(str, index))}]" if index else name
    matrix = A[index]
    smallest = largest = np.nan
    if np.isfinite(matrix).all():
        eigenvalues = np.linalg.eigvalsh(matrix)
        smallest, largest = float(eigenvalues[0]), float(np.abs(eigenvalues).max())
    if np.isnan(smallest):
        raise ValueError(
            f"{where} is not positive definite: it has non-finite entries (NaN or inf)"
        )
    if smallest >= -EIGENVALUE_RTOL * A.shape[-1] * largest:
        cond = largest / smallest if smallest > 0 else np.inf
        raise ill_conditioned(
            where, cond, what="is too ill-conditioned for a Cholesky factorisation"
        )
    raise ValueError(f"{where} is not positive definite (smallest eigenvalue {smallest:.3g})")


def cholesky_single(A):
    L, info = lapack.dpotrf(A, lower=1, clean=1)
    if info != 0 or not math.isfinite(float(L.trace())):
        return None
    return L


SYMMETRY_RTOL = 1e-8


_NUMERIC_KINDS = frozenset("iuf")


def as_float_array(value: Any, name: str) -> NDArray[np.float64]:
    if isinstance(value, (str, bytes)) or value is None:
        raise TypeError(f"{name} must be a numeric array, got {type(value).__name__}")
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nested sequences
        raise TypeError(f"{name} must be a numeric array, got a ragged sequence ({exc})") from None
    kind = array.dtype.kind
    if kind == "c":
        raise TypeError(
            f"{name} must be real, got complex values (dtype {array.dtype}); pass the real "
            "part explicitly if that is what you mean"
        )
    if kind == "b":
        raise TypeError(f"{name} must be a numeric array, got booleans (dtype {array.dtype})")
    if kind not in _NUMERIC_KINDS and kind != "O":
        raise TypeError(f"{name} must be a numeric array, got dtype {array.dtype}")
    try:
        array = np.array(array, dtype=float)  # a copy: inputs are never aliased
    except (TypeError, ValueError) as exc:  # object arrays of non-numbers or complex
        raise TypeError(f"{name} must be a numeric array of real numbers ({exc})") from None
    return array


def _item_name(name, index, labels=None):
    if labels is None:
        return f"{name}[{index}]"
    return f"{labels[index]}'s {name}"


def _stack(items, axis, name, labels=None, matrices=False):
    names = [_item_name(name, i, labels) for i in range(len(items))]
    arrays = [as_float_array(item, names[i]) for i, item in enumerate(items)]
    if matrices:
        for array, item_name in zip(arrays, names):
            if array.ndim < 2 or array.shape[-1] != array.shape[-2]:
                raise ValueError(
                    f"{item_name} must be a square matrix (..., n, n), got shape {array.shape}"
                )
    for i, array in enumerate(arrays[1:], start=1):
        if array.shape != arrays[0].shape:
            raise ValueError(
                f"{names[i]} has shape {array.shape}, but {names[0]} has shape "
                f"{arrays[0].shape} (estimates given as a sequence must have equal shapes)"
            )
    return np.stack(arrays, axis=axis)


def _is_sequence(value):
    return isinstance(value, (list, tuple))


def _where(name, index, labels=None):
    if labels is None:
        return f"{name}[{', '.join(map(str, index))}]" if index else name
    where = _item_name(name, index[-1], labels)
    return f"{where}[{', '.join(map(str, index[:-1]))}]" if len(index) > 1 else where


def check_symmetric(P, name="Ps", *, labels=None):
    if P.ndim < 2 or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"{name} must hold square matrices (..., n, n), got shape {P.shape}")
    if P.shape[-1] == 0:
        raise ValueError(f"{name} must hold matrices of dimension n >= 1, got shape {P.shape}")
    if P.size == 0:
        raise ValueError(f"{name} is empty (shape {P.shape})")
    if not np.all(np.isfinite(P)):
        finite = np.isfinite(P).all(axis=(-2, -1))
        index = np.unravel_index(int(np.argmin(finite.ravel())), finite.shape)
        raise ValueError(
            f"{_where(name, tuple(int(i) for i in index), labels)} contains non-finite values "
            "(NaN or inf)"
        )
    asymmetry = np.abs(P - np.swapaxes(P, -1, -2)).max(axis=(-2, -1))
    # The largest entry of a positive semidefinite matrix lies on its diagonal (and a
    # matrix that is not PSD fails the Cholesky test anyway).
    scale = np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(axis=-1)
    bad = asymmetry > SYMMETRY_RTOL * scale
    if np.any(bad):
        index = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
        where = _where(name, tuple(int(i) for i in index), labels)
        raise ValueError(
            f"{where} is not symmetric (max |P - P^T| = {float(asymmetry[index]):.3g})"
        )
    return symmetrize(P)


def check_covariances(P, name="Ps", L=None, *, labels=None):
    P = check_symmetric(P, name, labels=labels)
    if L is not None:
        return P, L
    if labels is None:
        return P, cholesky(P, name)
    try:
        return P, cholesky(P, name)
    except ValueError:  # failure path: find the estimate and name it by its label
        for i in range(P.shape[-3]):
            cholesky(P[..., i, :, :], _item_name(name, i, labels))
        raise


def as_covariance_stack(Ps, name="Ps", *, labels=None):
    if _is_sequence(Ps):
        if len(Ps) == 0:
            raise ValueError(f"{name} is empty")
        P = _stack(Ps, axis=-3, name=name, labels=labels, matrices=True)
    else:
        P = as_float_array(Ps, name)
        if P.ndim < 3:
            raise ValueError(
                f"{name} must be a sequence of covariance matrices or an array of shape "
                f"(..., N, n, n), got shape {P.shape}"
            )
    if P.shape[-1] == 0:
        raise ValueError(f"{name} must hold matrices of dimension n >= 1, got shape {P.shape}")
    return P


def vector_style(x, n):
    if x.ndim >= 2 and x.shape[-1] == 1 and x.shape[-2] == n:
        return "column"
    if x.ndim >= 1 and x.shape[-1] == n:
        return "row"
    return None


def as_mean_stack(xs, n, count, name="xs", *, labels=None):
    if _is_sequence(xs):
        if len(xs) != count:
            raise ValueError(f"{name} has {len(xs)} estimates but the covariances have {count}")
        rows, column = [], None
        for i, item in enumerate(xs):
            item_name = _item_name(name, i, labels)
            x = as_float_array(item, item_name)
            style = vector_style(x, n)
            if style is None:
                raise ValueError(
                    f"{item_name} must have shape (..., {n}) or (..., {n}, 1) to match its "
                    f"{n}x{n} covariance, got shape {x.shape}"
                )
            rows.append(x[..., 0] if style == "column" else x)
            column = (style == "column") if column is None else column
        return _stack(rows, axis=-2, name=name, labels=labels), column
    x = as_float_array(xs, name)
    style = vector_style(x, n)
    if style == "column":
        x = x[..., 0]
    if style is None or x.ndim < 2 or x.shape[-2] != count:
        raise ValueError(
            f"{name} must be a sequence of {count} vectors or an array of shape "
            f"(..., {count}, {n}) (or (..., {count}, {n}, 1)), got shape {np.shape(xs)}"
        )
    return x, style == "column"


def _usual_single_estimates(xs, Ps):
    if not (_is_sequence(xs) and _is_sequence(Ps)) or len(xs) != len(Ps) or len(Ps) < 2:
        return None
    first = Ps[0]
    if not isinstance(first, np.ndarray) or first.ndim != 2 or first.dtype != np.float64:
        return None
    n = first.shape[0]
    if n == 0 or first.shape != (n, n):
        return None
    count = len(Ps)
    P = np.empty((count, n, n))
    x = np.empty((count, n))
    column = None
    for i, (xi, Pi) in enumerate(zip(xs, Ps)):
        if not (isinstance(Pi, np.ndarray) and isinstance(xi, np.ndarray)
                and Pi.dtype == np.float64 and xi.dtype == np.float64 and Pi.shape == (n, n)):
            return None
        if xi.shape == (n,):
            style = False
        elif xi.shape == (n, 1):
            style = True
        else:
            return None
        column = style if column is None else column
        P[i] = Pi
        x[i] = xi.reshape(n)
    # NaN and inf propagate through sums (a finite overflow only sends us the long way)
    if not math.isfinite(float(P.sum()) + float(x.sum())):
        return None
    difference = P - P.transpose(0, 2, 1)
    asymmetry = np.abs(difference).max(axis=(1, 2)).tolist()
    scale = np.abs(P.diagonal(axis1=1, axis2=2)).max(axis=1).tolist()
    if any(a > SYMMETRY_RTOL * b for a, b in zip(asymmetry, scale)):
        return None
    P = 0.5 * (P + P.transpose(0, 2, 1))  # exactly symmetric, as symmetrize
    L = np.empty((count, n, n))
    for i in range(count):
        factor = cholesky_single(P[i])
        if factor is None:
            return None
        L[i] = factor
    return Estimates(x, P, L, bool(column))


def as_estimates_before(xs, Ps, *, min_count=2, names=("xs", "Ps"), labels=None):
    if min_count <= 2:
        fast = _usual_single_estimates(xs, Ps)
        if fast is not None:
            return fast
    x_name, P_name = names
    P = as_covariance_stack(Ps, P_name, labels=labels)
    count, n = P.shape[-3], P.shape[-1]
    if count < min_count:
        raise ValueError(f"at least {min_count} estimates are needed, got {count}")
    x, column = as_mean_stack(xs, n, count, x_name, labels=labels)
    if not np.all(np.isfinite(x)):
        finite = np.isfinite(x).all(axis=-1)
        index = np.unravel_index(int(np.argmin(finite.ravel())), finite.shape)
        where = _where(x_name, tuple(int(i) for i in index), labels)
        raise ValueError(f"{where} contains non-finite values (NaN or inf)")
    P, L = check_covariances(P, P_name, labels=labels)
    try:
        batch = np.broadcast_shapes(x.shape[:-2], P.shape[:-3])
    except ValueError:
        raise ValueError(
            f"batch shapes of {x_name} {x.shape[:-2]} and {P_name} {P.shape[:-3]} "
            "do not broadcast"
        ) from None
    if x.shape[:-2] != batch:  # x is already a private copy; only broadcasting copies again
        x = np.array(np.broadcast_to(x, batch + x.shape[-2:]))
    if P.shape[:-3] != batch:
        P = np.array(np.broadcast_to(P, batch + P.shape[-3:]))
        L = np.array(np.broadcast_to(L, batch + L.shape[-3:]))
    return Estimates(x, P, L, bool(column))



# ------------------------------------------------------------------ the benchmark
def spd(rng, shape, n, asymmetry=0.0):
    A = rng.standard_normal(shape + (n, n))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    if asymmetry:  # a filterpy-style rounding asymmetry, well inside SYMMETRY_RTOL
        P = P + asymmetry * np.triu(np.ones((n, n)), 1)
    return P


def cases(rng):
    n = 4
    single = spd(rng, (2,), n)
    yield ("one pair, rows (4,)", [rng.standard_normal(n) for _ in range(2)],
           [single[0].copy(), single[1].copy()], 500)
    yield ("one pair, filterpy columns (4, 1)", [rng.standard_normal((n, 1)) for _ in range(2)],
           [single[0].copy(), single[1].copy()], 500)
    batch = spd(rng, (30, 2), n)
    yield ("30 pairs as two arrays (the demo's calls)",
           [rng.standard_normal((30, n)) for _ in range(2)],
           [batch[:, 0].copy(), batch[:, 1].copy()], 200)
    big = spd(rng, (100000, 2), n)
    xs = rng.standard_normal((100000, 2, n))
    yield "1e5 pairs, one array (1e5, 2, 4, 4)", xs, big, 1
    yield ("1e5 pairs, two arrays (1e5, 4, 4)", [xs[:, 0].copy(), xs[:, 1].copy()],
           [big[:, 0].copy(), big[:, 1].copy()], 1)
    yield "1e5 pairs, one array, asymmetric by 1e-13", xs, spd(rng, (100000, 2), n, 1e-13), 1
    yield ("2e4 sets of N = 4 of 6x6, one array", rng.standard_normal((20000, 4, 6)),
           spd(rng, (20000, 4), 6), 1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=21,
                        help="interleaved rounds; each times a block of calls per version")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"numpy {np.__version__}; minimum over {args.repeats} interleaved repetitions")
    rng = np.random.default_rng(args.seed)
    for label, xs, Ps, calls in cases(rng):  # calls: per timed block
        old, new = as_estimates_before(xs, Ps), as_estimates(xs, Ps)
        same = (all(np.array_equal(a, b) for a, b in zip(old[:3], new[:3]))
                and old.column == new.column)
        best = {"before": np.inf, "after": np.inf}
        for _ in range(args.repeats):
            for key, function in (("before", as_estimates_before), ("after", as_estimates)):
                start = time.perf_counter()
                for _ in range(calls):
                    function(xs, Ps)
                best[key] = min(best[key], (time.perf_counter() - start) / calls)
        unit, scale = ("us", 1e6) if best["before"] < 1e-3 else ("ms", 1e3)
        print(f"  {label:44s} before {best['before'] * scale:8.1f} {unit}  after "
              f"{best['after'] * scale:8.1f} {unit}  {best['before'] / best['after']:4.2f}x"
              f"  {'identical' if same else 'DIFFERENT RESULTS'}")


if __name__ == "__main__":
    main()
