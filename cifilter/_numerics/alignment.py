"""Bringing estimates to one state space and one time (private).

The front door (:func:`cifilter.fuse`) uses these helpers for its options ``H=``,
``residual=``/``add=`` and ``times=``/``at=``/``motion=`` before a rule runs:

* **Partial estimates.** Estimate ``i`` estimates ``H_i x`` of the common state ``x``
  (``H_i`` of shape (m_i, n)); :class:`PartialEstimates` holds such estimates validated,
  each with its own dimension m_i, and :func:`as_partial_estimates` builds it.
  :func:`unobserved_directions` names the state directions that no estimate observes.
* **Time.** Estimate ``i`` describes the state at ``times[i]``; :func:`align_in_time`
  brings it to ``at`` with ``(F, Q) = motion(dt)`` (:class:`StepMotion`: whole steps of a
  filter's ``F`` and ``Q``, checked once per ``(F, Q, k)``): older estimates are predicted
  (``F x``, ``F P F^T + Q``, exact), newer ones retrodicted with the bound
  ``F^-1 (P / alpha + Q / (1 - alpha)) F^-T`` (:func:`retrodicted`; derivation and proof in
  ``docs/methods/time.rst``).
* **Residuals.** :func:`residuals_to_reference` and :func:`added_to_reference` apply a
  user's ``residual(a, b)`` and ``add(x, dx)`` (angles and other non-Euclidean states;
  ``docs/methods/partial_state.rst``).

Everything returns new arrays; inputs (and the arrays handed to user callables, which
get copies) are never modified.
"""

import math
import numbers
from collections.abc import Sequence
from typing import Any, Callable, NamedTuple, Optional

import numpy as np
from scipy.linalg import lapack

from .linalg import MAX_CONDITION, cholesky, cholesky_single, ill_conditioned, symmetrize
from .validation import (
    PSD_RTOL,
    SYMMETRY_RTOL,
    Estimates,
    as_estimates,
    as_float_array,
    check_psd,
)

__all__ = [
    "PartialEstimates",
    "StepMotion",
    "added_to_reference",
    "align_estimates",
    "align_in_time",
    "aligned_pair",
    "as_partial_estimates",
    "back_noise",
    "check_observation_matrices",
    "check_times",
    "finite_real",
    "motion_matrices",
    "pair_step",
    "predicted",
    "residuals_to_reference",
    "retrodicted",
    "retrodiction_alpha",
    "unobserved_directions",
]


# --------------------------------------------------------------------- partial estimates
class PartialEstimates(NamedTuple):
    """Validated estimates of parts ``H_i x`` of one state ``x`` (each of its own dimension).

    The counterpart of :class:`cifilter._numerics.validation.Estimates` for ``H=``: the
    estimates cannot be stacked (their dimensions m_i differ), so each field is a tuple of
    N arrays with one common batch shape.
    """

    x: tuple  # N arrays (..., m_i)
    P: tuple  # N arrays (..., m_i, m_i), symmetric positive definite
    L: tuple  # N arrays (..., m_i, m_i), their lower Cholesky factors
    H: tuple  # N entries: None (the full state, m_i = n) or an (m_i, n) float array
    dim: int  # n, the dimension of the common state
    column: bool  # the first input was a column vector

    @property
    def count(self):
        return len(self.x)

    @property
    def batch_shape(self):
        return self.x[0].shape[:-1]

    @property
    def full(self):
        """Indices of the estimates of the full state (``H_i`` None)."""
        return tuple(i for i, H in enumerate(self.H) if H is None)

    def observation(self, i):
        """``H_i`` as a matrix (the identity for a full-state estimate)."""
        return np.eye(self.dim) if self.H[i] is None else self.H[i]


def check_observation_matrices(H: Any, count: int) -> Optional[tuple]:
    """``H=`` of the front door: one entry per estimate, None or an (m_i, n) matrix.

    Returns a tuple of None and finite float matrices (copies), or None when ``H`` is
    None or every entry is None (then the estimates are ordinary full-state ones). Shapes
    against the estimates are checked by :func:`as_partial_estimates`.
    """
    if H is None:
        return None
    if isinstance(H, np.ndarray) and H.ndim != 3 and H.dtype != object:
        raise ValueError(
            f"H must be a sequence of {count} entries, one per estimate (None for an "
            f"estimate of the full state, or an (m_i, n) matrix), got an array of shape "
            f"{H.shape}"
        )
    if isinstance(H, (str, bytes)) or not hasattr(H, "__len__"):
        raise TypeError(
            f"H must be a sequence of {count} entries (None or an (m_i, n) matrix), got "
            f"{type(H).__name__}"
        )
    if len(H) != count:
        raise ValueError(
            f"H has {len(H)} entries but there are {count} estimates; give one per "
            "estimate (None for an estimate of the full state)"
        )
    out: list[Any] = []
    partial = False  # (some entry is a matrix)
    for i, entry in enumerate(H):
        if entry is None:
            out.append(None)
            continue
        partial = True
        if (type(entry) is np.ndarray and entry.dtype == np.float64 and entry.ndim == 2
                and entry.size and math.isfinite(sum(entry.ravel().tolist())
                                                 if entry.size <= _SMALL * _SMALL
                                                 else float(entry.sum()))):
            out.append(entry.copy())  # the usual matrix: the checks below pass; a copy
            continue
        matrix = as_float_array(entry, f"H[{i}]")
        if matrix.ndim != 2 or 0 in matrix.shape:
            raise ValueError(
                f"H[{i}] must be None or a matrix of shape (m_{i}, n), got shape {matrix.shape}"
            )
        if not np.all(np.isfinite(matrix)):
            raise ValueError(f"H[{i}] contains non-finite values (NaN or inf)")
        out.append(matrix)
    return tuple(out) if partial else None


class _Single(NamedTuple):
    """One validated estimate (the fields :func:`as_partial_estimates` uses)."""

    x: np.ndarray  # (..., m)
    P: np.ndarray  # (..., m, m)
    L: np.ndarray  # (..., m, m)
    column: bool

    @property
    def dim(self):
        return self.x.shape[-1]

    @property
    def batch_shape(self):
        return self.x.shape[:-1]


def _usual_single(x, P):
    """One unbatched float64 estimate, finite, symmetric and factorisable, checked cheaply
    (the filters' single call); None sends it the long way, whose messages explain."""
    if not (isinstance(x, np.ndarray) and isinstance(P, np.ndarray)
            and x.dtype == np.float64 and P.dtype == np.float64 and P.ndim == 2):
        return None
    m = P.shape[0]
    if m == 0 or P.shape != (m, m) or x.shape not in ((m,), (m, 1)):
        return None
    if m <= _SMALL:
        # (Python floats: for a few entries, faster than numpy's reductions; the sum of
        # the entries is finite only if every entry is)
        values = P.ravel().tolist()
        if not math.isfinite(sum(values) + sum(x.ravel().tolist())):
            return None
        symmetric = values == P.T.ravel().tolist()
    else:
        with np.errstate(invalid="ignore", over="ignore"):  # (inf - inf: not finite)
            if not math.isfinite(float(P.sum()) + float(x.sum())):
                return None
        symmetric = bool((P == P.T).all())
    if symmetric:
        P = P.copy()  # (0.5 (P + P^T) is P: the symmetrisation below, without its sums)
    else:
        P_T = P.T
        asymmetry = float(np.abs(P - P_T).max())
        if asymmetry > SYMMETRY_RTOL * float(np.abs(P.diagonal()).max()):
            return None
        P = 0.5 * (P + P_T)
    # (cholesky_single: LAPACK's factor, None unless it succeeds and is finite)
    L, failed = lapack.dpotrf(P, lower=1, clean=1)
    if failed or not math.isfinite(sum(L.diagonal().tolist())):
        return None
    return _Single(x.reshape(m).copy(), P, L, x.ndim == 2)


# Below this dimension the cheap checks run on Python floats (a list of at most 64 entries).
_SMALL = 8


def _single(estimates):
    """The one estimate of validated :class:`Estimates` (N = 1) as a :class:`_Single`."""
    return _Single(estimates.x[..., 0, :], estimates.P[..., 0, :, :],
                   estimates.L[..., 0, :, :], estimates.column)


def as_partial_estimates(pairs: list, H: tuple, labels: Optional[Sequence[str]] = None
                         ) -> PartialEstimates:
    """Validate N ``(x, P)`` pairs, estimate ``i`` of ``H_i x``, into :class:`PartialEstimates`.

    Each estimate is validated on its own (shape, finiteness, symmetry, positive
    definiteness, Cholesky factor); ``H_i`` must have as many rows as estimate ``i`` has
    dimensions and as many columns as the state (the dimension of the full-state estimates,
    or of ``H``'s first matrix when there is none). Batch axes broadcast.
    """
    count = len(pairs)
    validated = []
    for i, (x, P) in enumerate(pairs):
        usual = _usual_single(x, P)
        if usual is None:
            label = f"estimates[{i}]" if labels is None else labels[i]
            usual = _single(as_estimates([x], [P], min_count=1, names=("x", "P"),
                                         labels=(label,)))
        validated.append(usual)
    dims = [est.x.shape[-1] for est in validated]
    full = [i for i in range(count) if H[i] is None]
    n = dims[full[0]] if full else next(h for h in H if h is not None).shape[1]
    if not all(dims[i] == n if H[i] is None else H[i].shape == (dims[i], n)
               for i in range(count)):
        _raise_dimensions(dims, H, n, full, labels)
    if all(est.x.ndim == 1 for est in validated):  # no batch axes: nothing to broadcast
        return PartialEstimates(tuple(est.x for est in validated),
                                tuple(est.P for est in validated),
                                tuple(est.L for est in validated), tuple(H), n,
                                validated[0].column)
    try:
        batch = np.broadcast_shapes(*(est.batch_shape for est in validated))
    except ValueError:
        shapes = ", ".join(str(est.batch_shape) for est in validated)
        raise ValueError(f"the estimates' batch shapes {shapes} do not broadcast") from None

    def broadcast(array, tail):
        shape = batch + array.shape[array.ndim - tail:]
        return array if array.shape == shape else np.array(np.broadcast_to(array, shape))

    xs = tuple(broadcast(est.x, 1) for est in validated)
    Ps = tuple(broadcast(est.P, 2) for est in validated)
    Ls = tuple(broadcast(est.L, 2) for est in validated)
    return PartialEstimates(xs, Ps, Ls, tuple(H), n, validated[0].column)


def _raise_dimensions(dims, H, n, full, labels):
    """The error for estimates whose dimensions do not match ``H`` and the state."""
    where = [f"estimates[{i}]" if labels is None else labels[i] for i in range(len(dims))]
    if full:
        source = f"{where[full[0]]} estimates the full state"
    else:
        first = next(i for i in range(len(dims)) if H[i] is not None)
        source = f"H[{first}] has {H[first].shape[1]} columns"
    for i in range(len(dims)):
        if H[i] is None:
            if dims[i] != n:
                raise ValueError(
                    f"{where[i]}'s P is {dims[i]}x{dims[i]}, but the state has dimension {n} "
                    f"({source}); an estimate of part of the state needs its H[{i}]"
                )
            continue
        rows, columns = H[i].shape
        if rows != dims[i]:
            raise ValueError(
                f"H[{i}] has shape {H[i].shape}, but {where[i]}'s P is {dims[i]}x{dims[i]}: "
                f"estimate {i} estimates H[{i}] x, so H[{i}] needs {dims[i]} rows"
            )
        if columns != n:
            raise ValueError(
                f"H[{i}] has shape {H[i].shape}, but the state has dimension {n} ({source}); "
                f"H[{i}] needs {n} columns"
            )


def unobserved_directions(G: np.ndarray, n_digits: int = 3) -> list:
    """A basis of the state directions that the stacked square roots ``G`` do not observe.

    ``G`` (M, n) stacks ``L_i^-1 H_i`` of every estimate (one problem): the fused
    information ``G^T G = sum_i H_i^T P_i^-1 H_i`` is numerically singular along the right
    singular vectors whose squared singular value is below ``n eps`` times the largest
    (the threshold of the fused information's Cholesky test). Returned rounded to
    ``n_digits`` as lists (for messages), each with its largest entry positive.
    """
    n = G.shape[-1]
    _, s, Vt = np.linalg.svd(G, full_matrices=True)
    s = np.concatenate([s, np.zeros(n - s.size)]) if s.size < n else s
    top = s.max() if s.size else 0.0
    null = [k for k in range(n) if not s[k] ** 2 > n * np.finfo(float).eps * top**2]
    out = []
    for k in null:
        v = Vt[k]
        v = v * np.sign(v[np.argmax(np.abs(v))])
        out.append([round(float(a), n_digits) + 0.0 for a in v])
    return out


# ------------------------------------------------------------------------------------ time
def check_times(times: Any, count: int, at: Any = None) -> tuple:
    """``times=`` (N finite reals) and ``at=`` (a finite real; default ``max(times)``).

    Returns ``(times, at)`` as a tuple of floats and a float.
    """
    if (type(times) is tuple and len(times) == count
            and (at is None or (type(at) is float and math.isfinite(at)))):
        for t in times:  # (kf.fuse(lag=)'s finite floats, as they are)
            if type(t) is not float or not math.isfinite(t):
                break
        else:
            return times, (max(times) if at is None else at)
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        raise TypeError(
            f"times must be a sequence of {count} numbers (the time of each estimate), got "
            f"{type(times).__name__}"
        )
    if len(times) != count:
        raise ValueError(f"times has {len(times)} entries but there are {count} estimates")
    out = []
    for i, t in enumerate(times):
        out.append(finite_real(t, f"times[{i}]"))
    at = max(out) if at is None else finite_real(at, "at")
    return tuple(out), at


def finite_real(value: Any, name: str) -> float:
    """``value`` as a finite float, or a TypeError (not a real number) / ValueError (not
    finite) naming it as ``name``."""
    if type(value) is float or type(value) is int:  # the common case, without the ABC test
        value = float(value)
        if math.isfinite(value):
            return value
    if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf":
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def motion_matrices(motion: Callable[..., Any], dt: float, n: int) -> tuple:
    """``(F, Q) = motion(dt)``, checked: F (n, n) finite, Q (n, n) symmetric PSD (copies)."""
    try:
        returned = motion(dt)
    except (TypeError, ValueError) as exc:
        raise type(exc)(f"motion({dt!r}) failed: {exc}") from exc
    if (type(returned) is tuple and len(returned) == 2 and _plain(returned[0], n)
            and _plain(returned[1], n) and math.isfinite(float(returned[0].sum()))):
        # (float64 n x n matrices, F finite: the checks below on copies, without conversion)
        Q = _psd(returned[1].copy(), n, f"Q of motion({dt!r})")
        return returned[0].copy(), Q
    call = f"motion({dt!r})"
    if not (isinstance(returned, (tuple, list)) and len(returned) == 2):
        raise TypeError(
            f"motion must return a pair (F, Q) of n x n matrices; {call} returned "
            f"{type(returned).__name__}"
        )
    F, Q = returned
    F = F.copy() if _plain(F, n) else as_float_array(F, f"F of {call}")
    if F.shape != (n, n):
        raise ValueError(f"{call} returned F of shape {F.shape}; the state needs ({n}, {n})")
    if not math.isfinite(float(F.sum())) and not np.all(np.isfinite(F)):
        raise ValueError(f"{call} returned F with non-finite values (NaN or inf)")
    Q = Q.copy() if _plain(Q, n) else as_float_array(Q, f"Q of {call}")
    if Q.shape != (n, n):
        raise ValueError(f"{call} returned Q of shape {Q.shape}; the state needs ({n}, {n})")
    return F, _psd(Q, n, f"Q of {call}")


def _plain(A, n):
    """A float64 (n, n) array (copied as it is; anything else is converted and checked)."""
    return isinstance(A, np.ndarray) and A.dtype == np.float64 and A.shape == (n, n)


_IDENTITIES: dict = {}


def _psd(Q, n, name):
    """:func:`cifilter._numerics.validation.check_psd` for one matrix, its success path with
    LAPACK called directly: symmetric (exactly, or within ``SYMMETRY_RTOL``) and a Cholesky
    factor of ``Q + PSD_RTOL s I``. ``s`` is the largest diagonal entry, which is
    ``max |Q_ij|`` for a positive semidefinite ``Q`` and smaller otherwise, so this accepts
    no matrix that the general check rejects; the general check decides (and explains)
    everything else."""
    if Q.ndim == 2 and math.isfinite(float(Q.sum())):
        scale = float(Q.diagonal().max())
        if not (Q == Q.T).all():
            if not float(np.abs(Q - Q.T).max()) <= SYMMETRY_RTOL * scale:
                return check_psd(Q, n, name)
            Q = 0.5 * (Q + Q.T)
        eye = _IDENTITIES.get(n)
        if eye is None:
            eye = _IDENTITIES[n] = np.eye(n)
        if scale == 0.0 and not Q.any():
            return Q
        if scale > 0.0 and cholesky_single(Q + (PSD_RTOL * scale) * eye) is not None:
            return Q
    return check_psd(Q, n, name)


def predicted(x: np.ndarray, L: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple:
    """An older estimate brought forward: ``F x`` and ``(F L)(F L)^T + Q`` (exact).

    ``x`` (..., n), ``L`` (..., n, n) the Cholesky factor of its covariance. The process
    noise between the two times is independent of the estimate's error, so this is the
    error covariance of ``F x``, not a bound (``docs/methods/time.rst``).
    """
    FL = F @ L
    P = FL @ FL.swapaxes(-1, -2) + Q
    return x @ F.T, 0.5 * (P + P.swapaxes(-1, -2))


def retrodiction_alpha(a: np.ndarray, b: float) -> np.ndarray:
    """``alpha = sqrt(a) / (sqrt(a) + sqrt(b))``, the trace-minimising split (1 when b = 0)."""
    root_a, root_b = np.sqrt(a), math.sqrt(b)
    if root_b == 0.0:
        return np.ones_like(root_a)
    return root_a / (root_a + root_b)


def _inverse_by_lu(F, name):
    """``F^-1`` from its LU factorisation (LAPACK ``getrf``, ``getri``), refused where ``F``
    is singular or its estimated 1-norm condition number (``gecon``) exceeds 1e12."""
    lu, pivots, info = lapack.dgetrf(F)
    what = ("is singular or numerically singular, so a newer estimate cannot be brought "
            "back in time (retrodiction needs F^-1)")
    if info > 0:
        raise ill_conditioned(name, np.inf, what=what)
    reciprocal, _ = lapack.dgecon(lu, float(np.abs(F).sum(axis=0).max()), norm="1")
    if not reciprocal * MAX_CONDITION >= 1.0:
        raise ill_conditioned(name, np.inf if reciprocal == 0 else 1.0 / reciprocal,
                              what=what)
    F_inv, _ = lapack.dgetri(lu, pivots)
    return F_inv


def retrodicted(x: np.ndarray, L: np.ndarray, F: np.ndarray, Q: np.ndarray,
                name: str = "F", F_inv: Optional[np.ndarray] = None,
                Q_back: Optional[np.ndarray] = None) -> tuple:
    """A newer estimate brought back: ``F^-1 x`` and the bound
    ``F^-1 (P / alpha + Q / (1 - alpha)) F^-T`` (eqs. (T5)-(T6) of ``docs/methods/time.rst``,
    a bound by (T3)).

    The estimate's error and the process noise in between are correlated in an unknown
    way, so ``F^-1 (P + Q) F^-T`` is not a bound; for every ``alpha`` in (0, 1) this is,
    and it is tight direction by direction. ``alpha`` minimises the trace:
    ``sqrt(a) / (sqrt(a) + sqrt(b))`` with ``a = tr(F^-1 P F^-T)``, ``b = tr(F^-1 Q F^-T)``
    (1 when ``Q`` is zero: then ``F^-1 P F^-T`` is exact). ``F^-1`` comes from an LU
    factorisation; a singular or numerically singular ``F`` (estimated condition number
    above 1e12) raises
    :class:`~cifilter._numerics.linalg.IllConditionedError`. Returns ``(x, P, alpha)``.
    ``F_inv``, when given, is that inverse already computed (:meth:`StepMotion.inverse`),
    and ``Q_back``, when given with it, ``F_inv @ Q @ F_inv.T`` already computed and
    exactly symmetric (:func:`back_noise`; :meth:`StepMotion.back`).
    """
    if F_inv is None:
        F_inv = _inverse_by_lu(F, name)
    A = F_inv @ L  # F^-1 L: F^-1 P F^-T = A A^T
    if Q_back is None:
        Q_back = back_noise(F_inv, Q)
    b = float(Q_back.trace())
    if A.ndim == 2:  # one estimate: Python floats
        a = float(np.square(A).sum())
        share = 1.0 if b == 0.0 else math.sqrt(a) / (math.sqrt(a) + math.sqrt(b))
        # A @ A.T is exactly symmetric (numpy's syrk) and so is Q_back (back_noise's):
        # so is P, without a symmetrisation
        P = (A @ A.T) / share
        if b > 0.0:
            P += Q_back / (1.0 - share)
        return x @ F_inv.T, P, share
    alpha = retrodiction_alpha(np.square(A).sum(axis=(-2, -1)), b)
    P = A @ A.swapaxes(-1, -2) / alpha[..., None, None]
    if b > 0.0:
        P = P + Q_back / (1.0 - alpha)[..., None, None]
    return x @ F_inv.T, symmetrize(P), alpha


def back_noise(F_inv: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``F^-1 Q F^-T``, the process noise brought back by :func:`retrodicted`, exactly
    symmetric (symmetrised here, once, so that the sum it enters is symmetric)."""
    Q_back = F_inv @ Q @ F_inv.T
    return 0.5 * (Q_back + Q_back.swapaxes(-1, -2))


# (k, F's shape and bytes, Q's shape and bytes) -> [F^k, Q_k, F^-k or None, F^-k Q_k F^-kT
# or None], as checked by motion_matrices and computed by retrodicted; the least recently
# used entry goes first beyond _STEP_CACHE_SIZE
_STEP_CACHE: dict = {}
_STEP_CACHE_SIZE = 64


class StepMotion:
    """``motion(k) -> (F^k, Q_k)`` for ``k`` whole steps of a discrete model (``lag=``).

    ``Q_k = sum_{j<k} F^j Q F^jT``, accumulated as ``Q_k = F Q_{k-1} F^T + Q``.
    :func:`align_in_time` asks :meth:`checked` instead of calling it: the pair checked by
    :func:`motion_matrices` (and, for a retrodiction, ``F^-k``) is computed once per
    ``(F, Q, k)`` and kept in a small cache keyed by ``k`` and the *bytes* (and shapes) of
    ``F`` and ``Q`` as they are at the call, so a model changed in place, or another
    model, never meets an entry of the old one. Cached arrays are read-only.

    Parameters
    ----------
    F, Q : ndarray, shape (n, n)
        The state transition of one step and its process noise covariance (float64; not
        copied, not modified).

    Examples
    --------
    >>> import numpy as np
    >>> motion = StepMotion(np.array([[1.0, 1.0], [0.0, 1.0]]), np.eye(2))
    >>> F_2, Q_2 = motion(2)
    >>> F_2.tolist(), Q_2.tolist()
    ([[1.0, 2.0], [0.0, 1.0]], [[3.0, 1.0], [1.0, 2.0]])
    """

    def __init__(self, F: np.ndarray, Q: np.ndarray) -> None:
        self.F, self.Q = F, Q

    def __call__(self, steps: float) -> tuple:
        """``(F^k, Q_k)`` for ``k = steps`` whole steps (a ValueError otherwise)."""
        k = round(float(steps))
        if k != steps or k < 1:
            raise ValueError(f"lag= shifts by whole steps of the filter, got {steps}")
        F_k, Q_k = self.F, self.Q
        for _ in range(k - 1):
            Q_k = self.F @ Q_k @ self.F.T + self.Q
            F_k = self.F @ F_k
        return F_k, (Q_k if k == 1 else 0.5 * (Q_k + Q_k.T))

    def _entry(self, steps: float, n: int) -> list:
        F, Q = self.F, self.Q
        key = (steps, n, F.shape, F.tobytes(), Q.shape, Q.tobytes())
        entry = _STEP_CACHE.pop(key, None)
        if entry is None:
            F_k, Q_k = motion_matrices(self, steps, n)
            F_k.flags.writeable = Q_k.flags.writeable = False
            entry = [F_k, Q_k, None, None]
            if len(_STEP_CACHE) >= _STEP_CACHE_SIZE:
                del _STEP_CACHE[next(iter(_STEP_CACHE))]
        _STEP_CACHE[key] = entry  # (re)inserted last: the most recently used
        return entry

    def checked(self, steps: float, n: int) -> tuple:
        """:func:`motion_matrices` of this motion (read-only arrays, cached).

        Parameters
        ----------
        steps : float
            The whole number of steps ``k``.
        n : int
            The state dimension.

        Returns
        -------
        tuple of ndarray
            ``(F^k, Q_k)``, as :func:`motion_matrices` returns them.
        """
        entry = self._entry(steps, n)
        return entry[0], entry[1]

    def inverse(self, steps: float, n: int, name: str) -> np.ndarray:
        """``F^-k`` as :func:`retrodicted` computes it (read-only, cached on success).

        Parameters
        ----------
        steps : float
            The whole number of steps ``k``.
        n : int
            The state dimension.
        name : str
            The matrix's name in the error for a singular ``F^k``.

        Returns
        -------
        ndarray
            ``F^-k`` from the LU factorisation of ``F^k``.
        """
        entry = self._entry(steps, n)
        if entry[2] is None:
            F_inv = _inverse_by_lu(entry[0], name)
            F_inv.flags.writeable = False
            entry[2] = F_inv
        return entry[2]

    def back(self, steps: float, n: int, name: str) -> tuple:
        """``F^-k`` and ``F^-k Q_k F^-kT`` as :func:`retrodicted` computes them (read-only,
        cached on success).

        Parameters
        ----------
        steps : float
            The whole number of steps ``k``.
        n : int
            The state dimension.
        name : str
            The matrix's name in the error for a singular ``F^k``.

        Returns
        -------
        tuple of ndarray
            ``(F^-k, F^-k Q_k F^-kT)``.
        """
        entry = self._entry(steps, n)
        if entry[3] is None:
            if entry[2] is None:
                F_inv = _inverse_by_lu(entry[0], name)
                F_inv.flags.writeable = False
                entry[2] = F_inv
            Q_back = back_noise(entry[2], entry[1])
            Q_back.flags.writeable = False
            entry[3] = Q_back
        return entry[2], entry[3]


def align_in_time(x: list, L: list, movable: list, times: tuple, at: float,
                  motion: Optional[Callable[..., Any]], n: int, where: list) -> tuple:
    """Bring the estimates ``movable`` from ``times[i]`` to ``at`` (the rest must be at ``at``).

    ``x`` and ``L`` are lists of the estimates' means (..., n) and Cholesky factors; the
    others' entries are passed through. Returns ``(x, P, alpha, changed)``: new lists (P
    None where unchanged), ``alpha`` per estimate (None unless retrodicted) and the indices
    of the estimates that moved.
    """
    x, P = list(x), [None] * len(x)
    alpha: list = [None] * len(x)
    changed = []
    for i, t in enumerate(times):
        if t == at:
            continue
        x[i], P[i], alpha[i] = _brought(x[i], L[i], movable[i], i, t, at, motion, n, where[i])
        changed.append(i)
    return x, P, alpha, changed


def align_estimates(estimates: Estimates, times: Sequence[float], at: float,
                    motion: Optional[Callable[..., Any]],
                    labels: Optional[Sequence[str]] = None) -> tuple:
    """Bring validated estimates of the full state from ``times[i]`` to ``at``, in place.

    ``estimates`` (:class:`~cifilter._numerics.validation.Estimates`, the validation's own
    copies) get, for each estimate that moves, its new mean, covariance and the Cholesky
    factor of that covariance (a failure names ``"<estimate>'s P brought to at=..."``):
    the numbers and errors of :func:`align_in_time` followed by those factors, without
    the lists. ``labels`` name the estimates (``estimates[i]`` without). Returns ``alpha``
    per estimate (None unless retrodicted).
    """
    x, P, L = estimates.x, estimates.P, estimates.L
    single = x.ndim == 2  # one problem: plain indexing
    n = x.shape[-1]
    moved = []
    for i, t in enumerate(times):
        if t == at:
            continue
        where = f"estimates[{i}]" if labels is None else labels[i]
        x_i, L_i = (x[i], L[i]) if single else (x[..., i, :], L[..., i, :, :])
        moved.append((i, where) + _brought(x_i, L_i, True, i, t, at, motion, n, where))
    alpha: list = [None] * len(times)
    for i, where, x_i, P_i, alpha_i in moved:
        L_i = cholesky_single(P_i) if single else None  # (what cholesky does first)
        if L_i is None:
            L_i = cholesky(P_i, f"{where}'s P brought to at={at:g}")
        if single:
            x[i], P[i], L[i] = x_i, P_i, L_i
        else:
            x[..., i, :], P[..., i, :, :], L[..., i, :, :] = x_i, P_i, L_i
        alpha[i] = alpha_i
    return tuple(alpha)


# Entries of at least 2**1023 overflow when a covariance is symmetrised; the validation
# refuses them, so the short way below leaves them to it.
_LARGEST_ENTRY = 2.0 ** 1023


def aligned_pair(pairs: Sequence[Any], times: Any, at: Any,
                 motion: Optional[Callable[..., Any]],
                 labels: Optional[Sequence[str]] = None) -> Optional[tuple]:
    """Two single estimates brought to one time the short way, or None.

    The front door's ``times=`` for the commonest call, ``kf.fuse(other, lag=k)``: two
    ``(x, P)`` pairs of float64 arrays (``P`` (n, n), ``x`` (n,) or (n, 1) alike). Each
    estimate that moves is checked as the validation checks it (finite, entries below
    ``2**1023``, and here *exactly* symmetric, factored by LAPACK) and brought to ``at`` by
    the same steps as :func:`align_estimates` (:func:`predicted` or the retrodiction bound),
    so its mean and covariance are bit for bit the usual path's. Returns ``(pairs, at,
    alpha)`` with the brought pairs (the one that stays is passed on as given: the rule's
    route checks it), ``at`` as :func:`check_times` gives it, and ``alpha`` per estimate
    (None unless retrodicted). Anything else, and every failure, returns None, and the usual
    path validates, aligns and explains its errors in its order. (A caller that brings and
    fuses in one compiled call asks :func:`pair_step` instead.)
    """
    try:
        if len(pairs) != 2:
            return None
        (x0, P0), (x1, P1) = pairs
        for a in (x0, P0, x1, P1):
            if type(a) is not np.ndarray or a.dtype.char != "d":
                return None
        n = P0.shape[-1]
        if (P0.shape != (n, n) or P1.shape != (n, n) or x1.shape != x0.shape
                or x0.shape not in ((n,), (n, 1)) or n == 0):
            return None
        times, at = check_times(times, 2, at)
        out: list = [pairs[0], pairs[1]]
        alpha: list = [None, None]
        for i, t in enumerate(times):
            if t == at:
                continue
            x, P = pairs[i]
            # Exact symmetry also fails for a NaN anywhere (NaN != NaN); an infinity makes
            # LAPACK fail or the factor's trace infinite (cholesky_single's None). A finite
            # trace below 2**1023 bounds every entry of a positive definite matrix by it.
            # A non-finite x goes on to the route, whose check sends it the usual way.
            if not (P == P.T).all():
                return None
            L = cholesky_single(P)
            if L is None or not float(P.trace()) < _LARGEST_ENTRY:
                return None
            where = f"estimates[{i}]" if labels is None else labels[i]
            x_i, P_i, alpha[i] = _brought(x.reshape(n), L, True, i, t, at, motion, n, where)
            out[i] = (x_i.reshape(x.shape), P_i)
        return out, at, tuple(alpha)
    except (TypeError, ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None


def pair_step(times: Any, at: Any, motion: Any, n: int) -> Optional[tuple]:
    """The one step of :func:`aligned_pair` for a caller that brings the estimate itself.

    For two estimates of dimension ``n`` of which exactly one is away from ``at`` and
    ``motion`` is a :class:`StepMotion` (``kf.fuse(other, lag=k)``): ``(moved, M, N,
    backward, at)``, where estimate ``moved`` is brought by ``x -> M x``, ``P -> M P M^T +
    N`` forward (``backward`` False: ``M, N = F^k, Q_k``, as :func:`predicted`) or by the
    retrodiction bound of :func:`retrodicted` back (``M, N = F^-k, F^-k Q_k F^-kT``), and
    ``at`` is :func:`check_times`'s. The matrices are the motion's cached, checked,
    read-only ones. The caller checks the moved covariance as :func:`aligned_pair` does.
    Anything else, and every failure, returns None (the usual path explains).
    """
    if type(motion) is not StepMotion:
        return None
    try:
        (t0, t1), at = check_times(times, 2, at)
        if t0 == at and t1 != at:
            t = t1
            moved = 1
        elif t1 == at and t0 != at:
            t = t0
            moved = 0
        else:
            return None
        dt = abs(at - t)
        backward = t > at
        M, N = (motion.back(dt, n, f"F of motion({dt!r})") if backward
                else motion.checked(dt, n))
        return moved, M, N, backward, at
    except (TypeError, ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None


def _brought(x, L, movable, i, t, at, motion, n, where):
    """Estimate ``i`` (mean ``x``, factor ``L``) brought from ``t`` to ``at``: ``(x, P,
    alpha)``, alpha None unless retrodicted."""
    if not movable:
        raise ValueError(
            f"{where} is at time {t:g} and estimates part of the state (H[{i}] is "
            f"given); only estimates of the full state can be brought to at={at:g}"
        )
    if motion is None:
        raise ValueError(
            f"{where} is at time {t:g}, not at={at:g}: give motion= (dt -> (F, Q)) "
            "to bring it there"
        )
    if not callable(motion):
        raise TypeError(f"motion must be callable (dt -> (F, Q)), got "
                        f"{type(motion).__name__}")
    dt = abs(at - t)
    steps = motion if isinstance(motion, StepMotion) else None
    F, Q = steps.checked(dt, n) if steps is not None else motion_matrices(motion, dt, n)
    if t < at:
        x, P = predicted(x, L, F, Q)
        return x, P, None
    name = f"F of motion({dt!r}) (for {where}, newer than at)"
    if steps is None:
        return retrodicted(x, L, F, Q, name=name)
    F_inv, Q_back = steps.back(dt, n, name)
    return retrodicted(x, L, F, Q, name=name, F_inv=F_inv, Q_back=Q_back)


# ------------------------------------------------------------------------------- residuals
def _call_vector(function, name, args, n):
    """``function(*args)`` on 1-D float copies, checked to give n finite numbers."""
    try:
        value = function(*[np.array(a, dtype=float) for a in args])
    except (TypeError, ValueError, IndexError) as exc:
        raise type(exc)(f"{name} failed: {exc}") from exc
    if (type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (n,)
            and math.isfinite(float(value.sum()))):
        return value.copy()  # the usual answer (copied: the function may keep it)
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must return {n} numbers, got {type(value).__name__}") from None
    if array.size != n or array.ndim > 2 or (array.ndim == 2 and 1 not in array.shape):
        raise ValueError(f"{name} must return {n} numbers (shape ({n},)), got shape "
                         f"{array.shape}")
    array = array.reshape(n)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} returned non-finite values (NaN or inf)")
    return array


def residuals_to_reference(x: list, H: tuple, residual: Callable[..., Any]) -> list:
    """Means relative to the reference (the first estimate, of the full state).

    Full-state estimate ``i``: ``residual(x_i, x_ref)``, called per batch item on 1-D
    copies; an estimate of ``H_i x``: ``x_i - H_i x_ref`` (its residual is plain
    subtraction in its own space). The reference gets zeros. Returns new arrays.
    """
    reference = x[0]
    n = reference.shape[-1]
    batch = reference.shape[:-1]
    out = [np.zeros(reference.shape)]
    for i in range(1, len(x)):
        if H[i] is not None:
            out.append(x[i] - reference @ H[i].T)
        elif not batch:
            out.append(_call_vector(residual, "residual", (x[i], reference), n))
        else:
            d = np.empty(batch + (n,))
            for index in np.ndindex(batch):
                d[index] = _call_vector(residual, "residual", (x[i][index], reference[index]),
                                        n)
            out.append(d)
    return out


def added_to_reference(reference: np.ndarray, d: np.ndarray,
                       add: Callable[..., Any]) -> np.ndarray:
    """``add(x_ref, d)`` per batch item on 1-D copies (a new array (..., n))."""
    n = reference.shape[-1]
    if reference.ndim == 1 and d.ndim == 1:
        return _call_vector(add, "add", (reference, d), n)
    batch = np.broadcast_shapes(reference.shape[:-1], d.shape[:-1])
    reference = np.broadcast_to(reference, batch + (n,))
    d = np.broadcast_to(d, batch + (n,))
    out = np.empty(batch + (n,))
    for index in np.ndindex(batch):
        out[index] = _call_vector(add, "add", (reference[index], d[index]), n)
    return out
