"""Input checking and the array conventions shared by every fusion function.

Conventions
-----------
* A state vector is ``(n,)`` or filterpy's column ``(n, 1)``; answers come back in
  the style of the first input.
* Several estimates are either a sequence of N vectors (each with optional leading
  batch axes) or one array ``(..., N, n)`` (or ``(..., N, n, 1)``); their
  covariances a sequence of N matrices or one array ``(..., N, n, n)``.
* Batch axes of the means and the covariances broadcast against each other.
* Inputs are copied, never modified; covariances are symmetrised after the check.
"""

import numbers
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

from .linalg import cholesky, symmetrize

# Relative tolerance for the symmetry check of a covariance: filterpy's Joseph-form
# updates leave asymmetries of order 1e-16 relative, user typos are of order 1.
SYMMETRY_RTOL = 1e-8
# Tolerance of the positive semidefiniteness check of weight and model matrices: smallest
# eigenvalue >= -PSD_RTOL * max|M_ij|.
PSD_RTOL = 1e-10


class Estimates(NamedTuple):
    """Validated estimates in the canonical row layout."""

    x: np.ndarray  # (..., N, n)
    P: np.ndarray  # (..., N, n, n), symmetric positive definite
    L: np.ndarray  # (..., N, n, n), lower Cholesky factors of P
    column: bool  # the first input was a filterpy column vector

    @property
    def count(self):
        return self.x.shape[-2]

    @property
    def dim(self):
        return self.x.shape[-1]

    @property
    def batch_shape(self):
        return self.x.shape[:-2]


# dtype kinds that convert to float without losing anything a caller meant: bool ("b"),
# complex ("c"), strings ("U", "S"), dates ("M", "m") and records ("V") are rejected.
_NUMERIC_KINDS = frozenset("iuf")


def as_float_array(value: Any, name: str) -> NDArray[np.float64]:
    """A float copy of ``value`` with a ``TypeError`` naming ``name`` for non-real input.

    Parameters
    ----------
    value : array_like
        Real numbers: a number, a nested sequence or an array of integer or float dtype
        (object arrays of real numbers are converted too).
    name : str
        Argument name for the error messages.

    Returns
    -------
    ndarray
        A new float64 array (inputs are never aliased, so never modified).

    Raises
    ------
    TypeError
        ``None``, strings, booleans, complex numbers (their imaginary part would be
        discarded silently), dates, ragged nested sequences or anything else that is not
        an array of real numbers.
    """
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


def check_finite(array, name):
    """Raise ``ValueError`` if ``array`` has NaN or infinite entries."""
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")


def _item_name(name, index, labels=None):
    """``name[index]``, or ``"<label>'s <name>"`` when the estimates have labels."""
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
    """Name of the matrix at ``index`` of a stack (..., N, n, n) of labelled estimates."""
    if labels is None:
        return f"{name}[{', '.join(map(str, index))}]" if index else name
    where = _item_name(name, index[-1], labels)
    return f"{where}[{', '.join(map(str, index[:-1]))}]" if len(index) > 1 else where


def check_symmetric(P, name="Ps", *, labels=None):
    """Check a stack of matrices: square, at least 1x1, finite and symmetric.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
        Float array (for instance from :func:`as_float_array`); not modified.
    name : str, optional
        Argument name for the messages.
    labels : sequence of str, optional
        Names of the estimates along axis -3 (then ``P`` is a stack (..., N, n, n)).

    Returns
    -------
    ndarray
        ``(P + P^T) / 2``, a new array.

    Raises
    ------
    ValueError
        Not square, n = 0, non-finite entries, or ``|P - P^T| > SYMMETRY_RTOL * max|P_ii|``
        (the message names the first offending matrix).
    """
    _check_symmetric(P, name, labels)
    return _symmetrized(P)


def _check_symmetric(P, name, labels):
    """:func:`check_symmetric`'s tests. Returns True when ``P`` is exactly symmetric and its
    symmetrised copy ``(P + P^T) / 2`` equals ``P`` bit for bit, for sure or (on the long
    stacks tested column by column) whenever ``P`` passes a Cholesky factorisation."""
    if P.ndim < 2 or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"{name} must hold square matrices (..., n, n), got shape {P.shape}")
    if P.shape[-1] == 0:
        raise ValueError(f"{name} must hold matrices of dimension n >= 1, got shape {P.shape}")
    if P.size == 0:
        raise ValueError(f"{name} is empty (shape {P.shape})")
    n = P.shape[-1]
    count = P.size // (n * n)
    if 1 < n <= _COLUMN_DIM and count >= _COLUMN_STACK and P.flags.c_contiguous:
        asymmetry, scale = _symmetry_by_columns(P.reshape(count, n * n), n)
        asymmetry, scale = asymmetry.reshape(P.shape[:-2]), scale.reshape(P.shape[:-2])
    else:
        with np.errstate(invalid="ignore", over="ignore"):  # inf - inf, inf - x: flagged below
            difference = np.subtract(P, np.swapaxes(P, -1, -2))
        if not difference.any():  # exactly symmetric, hence finite (inf - inf is NaN)
            return bool(np.abs(P).max() < _NO_OVERFLOW)  # then P + P^T = 2 P exactly
        np.abs(difference, out=difference)
        asymmetry = difference.max(axis=(-2, -1))
        scale = np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(axis=-1)
    # One pass serves both tests: an entry that is not finite makes its matrix's asymmetry
    # (off the diagonal: inf - inf and NaN give NaN, inf - x inf) or its scale (on the
    # diagonal) NaN or inf; only then are the entries looked at one by one
    if not (np.isfinite(asymmetry).all() and np.isfinite(scale).all()):
        finite = np.isfinite(P).all(axis=(-2, -1))
        if not finite.all():
            index = np.unravel_index(int(np.argmin(finite.ravel())), finite.shape)
            raise ValueError(
                f"{_where(name, tuple(int(i) for i in index), labels)} contains non-finite "
                "values (NaN or inf)"
            )
    # The largest entry of a positive semidefinite matrix lies on its diagonal (and a
    # matrix that is not PSD fails the Cholesky test anyway).
    bad = asymmetry > SYMMETRY_RTOL * scale
    if np.any(bad):
        index = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
        where = _where(name, tuple(int(i) for i in index), labels)
        raise ValueError(
            f"{where} is not symmetric (max |P - P^T| = {float(asymmetry[index]):.3g})"
        )
    # a matrix that factorises has no entry above its largest diagonal one (to rounding)
    return not asymmetry.any() and bool(scale.max() < _NO_OVERFLOW / 2)


# 2 P overflows exactly for entries of at least this size.
_NO_OVERFLOW = 2.0**1023
# Stacks of at least this many matrices of dimension at most _COLUMN_DIM are tested column
# by column (a pass over the stack per pair of entries: strided but long) rather than with
# P - P^T (a transposed operand and a reduction over each small matrix, both slow on long
# stacks; 5x slower for 2e5 matrices 4 x 4).
_COLUMN_STACK = 256
_COLUMN_DIM = 8


def _symmetry_by_columns(flat, n):
    """``max |P_ij - P_ji|`` and ``max |P_ii|`` per row of ``flat`` (count, n * n), the
    matrices flattened; NaN or inf for a matrix with a non-finite entry (as in
    :func:`_check_symmetric`)."""
    asymmetry = None
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf, inf - x: NaN and inf
        for i in range(1, n):
            for j in range(i):
                difference = np.subtract(flat[:, i * n + j], flat[:, j * n + i])
                np.abs(difference, out=difference)
                asymmetry = (difference if asymmetry is None
                             else np.maximum(asymmetry, difference, out=asymmetry))
    scale = np.abs(flat[:, 0])
    for i in range(1, n):
        np.maximum(scale, np.abs(flat[:, i * (n + 1)]), out=scale)
    return asymmetry, scale


def _symmetrized(P):
    """``(P + P^T) / 2`` (bitwise what :func:`symmetrize` gives), one temporary fewer.

    Entries of at least ``2**1023`` overflow to infinity here, silently: the caller's
    finiteness check then refuses the matrix with its message (no RuntimeWarning first)."""
    with np.errstate(over="ignore"):
        S = np.add(P, np.swapaxes(P, -1, -2))
    S *= 0.5
    return S


def check_covariances(P, name="Ps", L=None, *, labels=None):
    """Check a stack of covariances: square, finite, symmetric, positive definite.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
        Float array; not modified.
    name : str, optional
        Argument name for the messages.
    L : ndarray, optional
        Cholesky factors if already known (then positive definiteness is not re-checked).
    labels : sequence of str, optional
        Names of the estimates along axis -3, used instead of ``name[i]`` in messages.

    Returns
    -------
    P : ndarray
        The symmetrised copy.
    L : ndarray
        Its lower Cholesky factors.

    Raises
    ------
    ValueError
        As :func:`check_symmetric`; or a matrix that is not positive definite (the message
        gives its smallest eigenvalue).
    IllConditionedError
        A matrix that is positive semidefinite up to rounding but numerically singular (the
        message gives its condition number).

    Notes
    -----
    The success path costs one symmetry test and one batched Cholesky factorisation;
    eigenvalues are computed only for the message of a failure.
    """
    return _checked_covariances(P, name, L, labels, owned=False)


def _checked_covariances(P, name, L=None, labels=None, owned=False):
    """:func:`check_covariances`; with ``owned`` (``P`` is a private copy of the caller's
    input) an exactly symmetric ``P`` is returned as it is when it factorises: it equals its
    symmetrised copy bit for bit."""
    exact = _check_symmetric(P, name, labels)
    if L is not None:
        return _symmetrized(P), L
    if P.ndim > 2:
        # P itself is finite (tested), so LAPACK either fails on it or gives a finite factor;
        # a symmetrised copy may have overflowed, and then its factor is tested as always
        as_is = exact and owned
        S = P if as_is else _symmetrized(P)
        try:
            L = np.linalg.cholesky(S)
            if as_is or np.isfinite(L).all():
                return S, L
        except np.linalg.LinAlgError:
            pass  # the messages below
    P = _symmetrized(P)
    if labels is None:
        return P, cholesky(P, name)
    try:
        return P, cholesky(P, name)
    except ValueError:  # failure path: find the estimate and name it by its label
        for i in range(P.shape[-3]):
            cholesky(P[..., i, :, :], _item_name(name, i, labels))
        raise


def as_covariance_stack(Ps, name="Ps", *, labels=None):
    """Convert a sequence of N covariances or an array (..., N, n, n) to an array."""
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
    """'column' if x ends in (n, 1), 'row' if it ends in (n,), else None."""
    if x.ndim >= 2 and x.shape[-1] == 1 and x.shape[-2] == n:
        return "column"
    if x.ndim >= 1 and x.shape[-1] == n:
        return "row"
    return None


def as_mean_stack(xs, n, count, name="xs", *, labels=None):
    """Convert N means (sequence or array) to an array (..., N, n) and report their style."""
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


def _usual_estimates(xs, Ps):
    """The common case of :func:`as_estimates` done cheaply, or None.

    Sequences of N >= 2 float64 arrays (exactly ``numpy.ndarray``) of equal shapes:
    covariances (..., n, n) and means (..., n) or (..., n, 1) with the same batch axes (no
    broadcasting), finite, symmetric within ``SYMMETRY_RTOL`` and Cholesky-factorisable.
    The result is exactly the general path's (the same copies, symmetrisation and factors;
    one pair without batch axes is factorised matrix by matrix by LAPACK, as it always
    was). Anything else, including every failure, returns None and the general path
    decides (and explains). A single fusion of two tracks is the call a tracker makes
    hundreds of times per scan, and a batch of them the call of a simulation; the general
    path's per-item generality costs more than the fusion.
    """
    if not (_is_sequence(xs) and _is_sequence(Ps)) or len(xs) != len(Ps) or len(Ps) < 2:
        return None
    first, x_first = Ps[0], xs[0]
    if type(first) is not np.ndarray or type(x_first) is not np.ndarray:
        return None
    shape, x_shape = first.shape, x_first.shape
    if len(shape) < 2 or shape[-1] != shape[-2] or shape[-1] == 0:
        return None
    n, batch = shape[-1], shape[:-2]
    if x_shape == batch + (n,):
        column = False
    elif x_shape == batch + (n, 1):
        column = True
    else:
        return None
    for xi, Pi in zip(xs, Ps):
        if (type(Pi) is not np.ndarray or type(xi) is not np.ndarray or Pi.shape != shape
                or xi.shape != x_shape or Pi.dtype != np.float64 or xi.dtype != np.float64):
            return None
    if not batch:
        return _usual_single_problem(xs, Ps, n, column)
    # new arrays: the inputs are never aliased
    P = np.stack(Ps, axis=-3)
    x = np.stack([xi[..., 0] for xi in xs] if column else xs, axis=-2)
    if not np.isfinite(x).all():
        return None
    try:
        exact = _check_symmetric(P, "Ps", None)
    except ValueError:
        return None
    if not exact:
        P = _symmetrized(P)
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return None
    # the input itself is finite (tested), so its factor is; a symmetrised copy may have
    # overflowed (entries near the largest float), and LAPACK passes inf and NaN through
    if not exact and not np.isfinite(L).all():
        return None
    return Estimates(x, P, L, column)


def _usual_single_problem(xs, Ps, n, column):
    """:func:`_usual_estimates` for N checked float64 estimates without batch axes (the
    single fusion of a tracker): the same arrays, bit for bit, in fewer passes.

    The largest magnitude of the covariances' entries tests their finiteness (NaN or
    infinite: the test below fails) and sends entries of at least ``2**1023`` (whose
    symmetrised copy overflows; the general path refuses them) the long way; below it
    neither ``P - P^T`` nor ``P + P^T`` overflows. An exact comparison with the transpose
    tests the symmetry (no subtraction, so no floating-point warning to silence); a matrix
    that is not exactly symmetric is tested as :func:`_check_symmetric` tests it and
    symmetrised by :func:`_symmetrized`. Each matrix is factorised by LAPACK, as it always
    was (the general path's batched factorisation may differ in the last bits, so this path
    accepts exactly what the fast path always accepted). None whenever a test fails: the
    general path decides and explains.
    """
    P = np.array(Ps)
    x = np.array(xs).reshape(len(xs), n)
    # (a NaN or an infinity in P makes its largest magnitude fail the test too)
    if not (float(np.abs(P).max()) < _NO_OVERFLOW and np.isfinite(x).all()):
        return None
    P_T = P.swapaxes(-1, -2)
    exact = bool((P == P_T).all())
    if not exact:  # (finite, below 2**1023: the difference neither overflows nor is NaN)
        asymmetry = np.abs(P - P_T).max(axis=(-2, -1))
        scale = np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(axis=-1)
        if (asymmetry > SYMMETRY_RTOL * scale).any():
            return None
        P = _symmetrized(P)
    L = np.empty(P.shape)
    for i in range(len(P)):  # LAPACK directly
        factor, info = lapack.dpotrf(P[i], lower=1, clean=1)
        if info:
            return None
        L[i] = factor
    if not exact and not np.isfinite(L).all():
        return None
    return Estimates(x, P, L, column)


def as_estimates(xs, Ps, *, min_count=2, names=("xs", "Ps"), labels=None):
    """Validate N estimates and bring them to the canonical layout.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N means, each (..., n) or (..., n, 1); or one array (..., N, n) / (..., N, n, 1).
    Ps : sequence of array_like or array_like
        N covariances (..., n, n); or one array (..., N, n, n).
    min_count : int
        Smallest admissible N.
    names : tuple of str
        Argument names for the error messages.
    labels : sequence of str, optional
        Names of the N estimates (for instance ``("this filter", "other")``); messages
        then say ``"other's P"`` instead of ``"Ps[1]"``.

    Returns
    -------
    Estimates
        ``x`` (..., N, n) and ``P`` (..., N, n, n) broadcast to a common batch shape,
        Cholesky factors ``L`` and the vector style of the first input. All new arrays:
        the inputs are never modified or aliased.

    Raises
    ------
    TypeError
        Non-numeric, boolean or complex input.
    ValueError
        Fewer than ``min_count`` estimates, shapes that do not match, non-finite values,
        covariances that are not symmetric or not positive definite (an
        :class:`~cifilter._numerics.linalg.IllConditionedError` for numerically singular ones),
        batch shapes that do not broadcast.
    """
    if min_count <= 2:
        fast = _usual_estimates(xs, Ps)
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
    P, L = _checked_covariances(P, P_name, labels=labels, owned=True)
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


def as_covariances(Ps, *, min_count=2, name="Ps"):
    """Validate N covariances alone; the returned Estimates have zero means."""
    P = as_covariance_stack(Ps, name)
    if P.shape[-3] < min_count:
        raise ValueError(f"at least {min_count} estimates are needed, got {P.shape[-3]}")
    P, L = _checked_covariances(P, name, owned=True)
    return Estimates(np.zeros(P.shape[:-1]), P, L, False)


def restore_style(x, column):
    """Give a fused mean (..., n) the caller's vector style."""
    return x[..., None] if column else x


def check_weights(omega, count, name="omega", *, batch_shape=None):
    """Check weights on the probability simplex; a number means (omega, 1 - omega).

    Parameters
    ----------
    omega : float or array_like, shape (..., N)
        The weights; a real number (or 0-d array) only for two estimates.
    count : int
        The number N of estimates.
    name : str, optional
        Argument name for the messages.
    batch_shape : tuple of int, optional
        Batch shape of the estimates. When given, the weights' batch axes must broadcast
        to it (they cannot add batch axes of their own) and the weights are returned
        broadcast to ``batch_shape + (N,)``.

    Returns
    -------
    ndarray, shape (..., N)
        A new array of nonnegative weights that sum to one along the last axis.

    Raises
    ------
    TypeError
        Non-numeric, boolean or complex weights.
    ValueError
        Wrong last axis, non-finite values, weights off the simplex (beyond 1e-9), a
        scalar for N != 2, batch axes that do not broadcast to ``batch_shape``.
    """
    scalar = (isinstance(omega, numbers.Real) and not isinstance(omega, bool)) or (
        isinstance(omega, np.ndarray) and omega.ndim == 0 and omega.dtype.kind in "iuf"
    )
    if scalar:
        if count != 2:
            raise ValueError(
                f"a scalar {name} is only defined for two estimates; "
                f"give an array of {count} weights"
            )
        value = float(omega)
        omega = [value, 1.0 - value]
    w = as_float_array(omega, name)
    if w.ndim == 0 or w.shape[-1] != count:
        raise ValueError(f"{name} must have shape (..., {count}), got shape {w.shape}")
    check_finite(w, name)
    tol = 1e-9
    bad = (w < -tol).any(axis=-1) | (np.abs(w.sum(axis=-1) - 1.0) > tol)
    if np.any(bad):
        index = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
        where = f"{name}[{', '.join(map(str, index))}]" if index else name
        raise ValueError(
            f"{where} must lie on the simplex (w_i >= 0, sum w_i = 1), got {w[index]}"
        )
    if batch_shape is not None:
        batch_shape = tuple(batch_shape)
        try:
            ok = np.broadcast_shapes(w.shape[:-1], batch_shape) == batch_shape
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"{name} has shape {w.shape}, whose batch axes {w.shape[:-1]} do not "
                f"broadcast to the estimates' batch shape {batch_shape}; give shape "
                f"({count},) or (..., {count}) with batch axes matching {batch_shape}"
            )
    w = np.clip(w, 0.0, None)
    w = w / w.sum(axis=-1, keepdims=True)
    if batch_shape is not None and w.shape[:-1] != batch_shape:
        w = np.array(np.broadcast_to(w, batch_shape + (count,)))
    return w


def check_scalar(value, name, *, low=None, high=None, low_open=False, high_open=False):
    """Check a real scalar against an interval and return it as float.

    ``value`` is a real number or a 0-d integer or float array (not a bool); the
    ``TypeError`` or ``ValueError`` names ``name`` and, for the interval, its bounds.
    """
    if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf":
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    value = float(value)
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    below = low is not None and (value <= low if low_open else value < low)
    above = high is not None and (value >= high if high_open else value > high)
    if below or above:
        left = "(" if low_open or low is None else "["  # an unbounded side is open
        right = ")" if high_open or high is None else "]"
        lower = "-inf" if low is None else low
        upper = "inf" if high is None else high
        interval = f"{left}{lower}, {upper}{right}"
        raise ValueError(f"{name} must lie in {interval}, got {value}")
    return value


def check_int(value, name, *, low=None):
    """Check an integer (not bool) with an optional lower bound and return it."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be >= {low}, got {value}")
    return int(value)


def as_rng(rng: Any) -> np.random.Generator:
    """A ``numpy.random.Generator`` from a Generator, a seed or None."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, np.random.SeedSequence):
        return np.random.default_rng(rng)
    if isinstance(rng, numbers.Integral):  # int(): the same seed, in a type numpy declares
        return np.random.default_rng(int(rng))
    raise TypeError(
        f"rng must be a numpy.random.Generator, an integer seed or None, got {type(rng).__name__}"
    )


def as_matrix(value, name, shape=None):
    """A finite numeric array (..., rows, columns), optionally of a given trailing shape."""
    array = as_float_array(value, name)
    if array.ndim < 2:
        raise ValueError(f"{name} must be a matrix (..., rows, columns), got shape {array.shape}")
    check_finite(array, name)
    if shape is not None:
        rows, columns = shape
        if (rows is not None and array.shape[-2] != rows) or array.shape[-1] != columns:
            want = f"({'p' if rows is None else rows}, {columns})"
            raise ValueError(f"{name} must have shape (..., {want[1:-1]}), got shape {array.shape}")
    return array


def check_psd(value, size, name):
    """A symmetric positive semidefinite (..., size, size) matrix; a number means value * I."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        value = float(value) * np.eye(size)
    M = as_matrix(value, name, (size, size))
    scale = np.abs(M).max(axis=(-2, -1), keepdims=True)
    if np.any(np.abs(M - np.swapaxes(M, -1, -2)) > SYMMETRY_RTOL * scale):
        raise ValueError(f"{name} must be symmetric")
    M = symmetrize(M)
    # PSD up to -PSD_RTOL * max|M_ij| in the smallest eigenvalue. Success path: one
    # Cholesky factorisation of the shifted matrix; eigenvalues only when it fails.
    try:
        np.linalg.cholesky(M + (PSD_RTOL * scale) * np.eye(size))
        return M
    except np.linalg.LinAlgError:
        pass
    smallest = np.linalg.eigvalsh(M)[..., 0]
    if np.any(smallest < -PSD_RTOL * scale[..., 0, 0]):
        raise ValueError(
            f"{name} must be positive semidefinite (smallest eigenvalue {smallest.min():.3g})"
        )
    return M


def check_psd_weight_matrix(W, n, name="criterion"):
    """Check a symmetric positive semidefinite, nonzero weight matrix (..., n, n)."""
    W = as_float_array(W, name)
    if W.ndim < 2 or W.shape[-2:] != (n, n):
        raise ValueError(f"{name} must be a {n}x{n} weight matrix, got shape {W.shape}")
    W = check_psd(W, n, name)
    if np.any(np.abs(W).max(axis=(-2, -1)) == 0):
        raise ValueError(f"{name} must not be the zero matrix")
    return W
