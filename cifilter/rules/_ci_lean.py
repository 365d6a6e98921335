"""Optimal Covariance Intersection of one pair of estimates through LAPACK directly.

The single call of a tracker (one fusion of two tracks) without numba: the numpy path's
method for one problem (``optimal_weights`` of ``rules/_ci_weights.py`` on one pair: the
simultaneous diagonalisation ``P_1 = T T^T``, ``P_2 = T diag(lam) T^T`` from the Cholesky
factor of ``P_1`` (whitening, no condition number squared), the safeguarded Newton iteration
on omega in Python floats, its certified gap, the fused covariance as the bound of its
gains, the criterion report of the result), with the validation of the inputs folded in
(finiteness, the symmetry tolerance, the Cholesky factors), LAPACK called directly and as
few numpy calls as the formulas allow. Up to omega and its certificate the formulas and
LAPACK calls are the numpy path's, so omega, ``iterations``, ``gap`` and ``gap_floor`` are
its own (bit for bit wherever numpy's and scipy's LAPACK agree, as they do on the reference
install); ``x`` and ``P`` are assembled with fewer calls and agree to rounding.

:func:`lean_pair` answers only where that path takes its single-pair route and certifies
there; everywhere else it declines with None and the caller runs the numpy path, which
raises its usual error or solves the hard case (from Cholesky factors).
"""

import math
from typing import Any, Optional

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

from .._numerics.criteria import (
    GAP_TOL,
    gap_converged,
    pair_certificate,
    slope_rounding_single,
)
from .._numerics.information import DIAGONAL_TRUST
from .._numerics.optimize import minimize_convex_scalar
from .._numerics.validation import SYMMETRY_RTOL
from ._ci_weights import cached_identity, pair_derivative

__all__ = ["lean_pair"]

_EPS = float(np.finfo(float).eps)
# The lean path declines entries of at least this magnitude (and Cholesky factors with a
# squared diagonal entry below _TINY times the largest entry): within these bounds none of
# its products overflows and no slope term underflows to a division by zero, so it needs no
# floating-point error state; the numpy path handles the extreme scales.
_HUGE = 1e100
_TINY = 1e-100

_dpotrf = lapack.dpotrf
_dtrtri = lapack.dtrtri
_dsyevd = lapack.dsyevd
_vdot = np.vdot
_add_reduce = np.add.reduce
_concatenate = np.concatenate


def _checked(P, n):
    """``(S, largest)``: ``P`` (n, n) as the validation accepts it, or None.

    Finite, symmetric within ``SYMMETRY_RTOL`` of its largest diagonal entry, and that
    entry below ``_HUGE``; ``S`` is ``P`` itself when it is exactly symmetric (the
    validation's symmetrised copy equals it bit for bit), else ``(P + P^T) / 2`` (as the
    validation forms it); ``largest`` its largest diagonal entry. (The Cholesky
    factorisation that follows bounds the other entries by it: a symmetric matrix that
    factorises has no entry above its largest diagonal one, to rounding.)
    """
    rows = P.tolist()
    if not math.isfinite(sum(map(sum, rows))):  # a NaN or an infinity (or an overflow)
        return None
    largest = max([rows[i][i] for i in range(n)])
    if not largest < _HUGE:
        return None
    columns = P.T.tolist()
    if rows == columns:
        return P, largest
    asymmetry = max([abs(u - v) for row, column in zip(rows, columns)
                     for u, v in zip(row, column)])
    if asymmetry > SYMMETRY_RTOL * max([abs(rows[i][i]) for i in range(n)]):
        return None
    S = P + P.T
    S *= 0.5
    return S, largest


def _factor(S, floor):
    """Lower Cholesky factor of ``S`` and its diagonal (a list), or None: LAPACK fails, a
    squared diagonal entry is not above ``floor``, or the squared diagonal spread exceeds
    ``DIAGONAL_TRUST`` (the numpy path then decides from Cholesky factors)."""
    L, info = _dpotrf(S, lower=1, clean=1)
    if info:
        return None
    d = L.diagonal().tolist()
    low, high = min(d), max(d)
    if not (low * low > floor and high * high <= DIAGONAL_TRUST * (low * low)):
        return None
    return L, d


def lean_pair(x1: NDArray[np.float64], P1: NDArray[np.float64], x2: NDArray[np.float64],
              P2: NDArray[np.float64], kind: str, W: Optional[NDArray[np.float64]] = None,
              *, gains: bool = False) -> Optional[tuple[Any, ...]]:
    """Criterion-optimal Covariance Intersection of one pair, or None to decline.

    Parameters
    ----------
    x1, x2 : ndarray, shape (n,)
        The means (float64; their shapes checked by the caller, their values not).
    P1, P2 : ndarray, shape (n, n)
        The covariances (float64, C-contiguous; their shapes checked by the caller, their
        finiteness, symmetry and positive definiteness not). Not modified.
    kind : {"trace", "det", "weighted-trace"}
        The criterion (as :func:`cifilter._numerics.criteria.parse_criterion` gives it).
    W : ndarray, shape (n, n), optional
        The weight matrix of ``"weighted-trace"`` (checked by the caller).
    gains : bool, optional
        Also return the gains ``[K_1, K_2]`` (2, n, n), ``K_2 = I - K_1``: those whose
        bound ``P`` is and with which ``x = x_2 + K_1 (x_1 - x_2)`` was formed (the numpy
        path's to rounding).

    Returns
    -------
    tuple or None
        ``(x, P, omega, info)`` (with ``gains``: ``(x, P, omega, info, gains)``), new
        arrays that share no memory with the inputs (nor with each other, but for the
        gains): the fused mean (n,); the fused covariance (n, n), exactly symmetric, the
        bound ``K_1 P_1 K_1^T / w + K_2 P_2 K_2^T / (1 - w)`` of the gains; the weights
        ``omega = array([w, 1 - w])``; ``info`` with the keys, order, types and meaning of
        :func:`cifilter.covariance_intersection`'s for optimal weights (``criterion``,
        ``rule``, ``iterations``, ``converged``, ``gap``, ``gap_floor``, ``solver``,
        ``value`` and, for ``"det"``, ``log_value``). ``omega``, ``iterations`` and the
        certificate are the numpy path's (the same formulas and LAPACK calls); ``x``,
        ``P``, the gains and ``value`` agree with it to rounding.

        None whenever the numpy path might answer otherwise: non-finite input, diagonal
        entries of ``1e100`` or more, a covariance not symmetric within the validation's
        tolerance, a failed or tiny Cholesky factor, a diagonalisation the numpy path does
        not trust (it then certifies or re-solves from Cholesky factors), an optimum it
        does not certify, a fused covariance that is not numerically positive definite.
        The caller then runs the numpy path, which raises its usual error or solves the
        hard case. This function never raises on bad numerical input.
    """
    try:
        return _lean_pair(x1, P1, x2, P2, kind, W, gains)
    except ArithmeticError:  # (none expected within the bounds above: declined all the same)
        return None


def _lean_pair(x1, P1, x2, P2, kind, W, with_gains):
    n = P1.shape[0]
    first = _checked(P1, n)
    if first is None:
        return None
    second = _checked(P2, n)
    if second is None:
        return None
    if not math.isfinite(sum(x1.tolist()) + sum(x2.tolist())):
        return None
    S1, largest = first
    S2, other = second
    floor = _TINY * max(largest, other)
    f1 = _factor(S1, floor)
    if f1 is None:
        return None
    f2 = _factor(S2, floor)
    if f2 is None:
        return None
    L1, _ = f1
    L2, _ = f2
    # the simultaneous diagonalisation, as the numpy path forms it (_ci_weights._single_pair)
    L1_inv, _ = _dtrtri(L1, lower=1)
    S = L1_inv.dot(S2).dot(L1_inv.T)
    S = S + S.T
    S *= 0.5
    # its diagonal holds Rayleigh quotients: a spread beyond DIAGONAL_TRUST there means one
    # of the eigenvalues too, and the numpy path does not trust them (declined before LAPACK)
    diagonal = S.diagonal().tolist()
    if not max(diagonal) <= DIAGONAL_TRUST * min(diagonal):
        return None
    lam, U, info = _dsyevd(S, compute_v=1, lower=1)
    if info:
        return None
    lam_list = lam.tolist()
    if not (lam_list[0] > 0.0 and lam_list[-1] <= DIAGONAL_TRUST * lam_list[0]):
        return None
    a = [value - 1.0 for value in lam_list]
    if -1.0 in a:  # an eigenvalue below eps: 1 + omega a is 0 at omega = 1
        return None
    T = L1.dot(U)
    if kind == "det":
        c = None
        scale = float(n)
    else:
        if kind == "trace":
            c = _add_reduce(T * T, axis=0).tolist()  # (numpy's square(T).sum(axis=0))
        else:
            c = np.einsum("ik,ij,jk->k", T, W, T).tolist()
        scale = sum([ck * (ak + 1.0) for ck, ak in zip(c, a)]) + sum(c)
    derivative = pair_derivative(a, c, kind)
    sigma = max(lam_list[-1], float(_vdot(L1_inv, L1_inv)) * math.sqrt(float(_vdot(S2, S2))))
    if (abs(derivative(0.0)[0]) <= slope_rounding_single(lam_list, 0.0, c, sigma)
            and abs(derivative(1.0)[0]) <= slope_rounding_single(lam_list, 1.0, c, sigma)):
        omega, iterations = 0.5, 0  # a tie to rounding (as the numpy path)
    else:
        omega, iterations, _ = minimize_convex_scalar(derivative, scale=scale)
    slope, _ = derivative(omega)
    rounding = slope_rounding_single(lam_list, omega, c, sigma)
    value = (None if c is None else
             sum([ck * (ak + 1.0) / (1.0 + omega * ak) for ck, ak in zip(c, a)]))
    gap, floor, computed = pair_certificate(omega, slope, rounding, value)
    if not gap <= GAP_TOL:  # not certified here: the numpy path decides
        return None
    # The bound of the gains K_1 = omega T diag(e) U^T L_1^-1 and K_2 = I - K_1:
    # P = K_1 P_1 K_1^T / omega + K_2 P_2 K_2^T / (1 - omega) = G G^T with
    # G = [K_1 L_1 / sqrt(omega), (L_2 - K_1 L_2) / sqrt(1 - omega)], one Gram product of
    # gain-weighted factors (exactly symmetric, no condition number squared).
    K = np.empty((2, n, n)) if with_gains else None
    if 0.0 < omega < 1.0:
        K1 = (T * [omega * v / (1.0 + omega * ak) for v, ak in zip(lam_list, a)]).dot(
            U.T.dot(L1_inv), out=K[0] if with_gains else None)
        x = K1.dot(x1 - x2)
        x += x2
        G = K1.dot(_concatenate((L1, L2), axis=1))
        right = G[:, n:]
        np.subtract(L2, right, out=right)
        G *= [1.0 / math.sqrt(omega)] * n + [1.0 / math.sqrt(1.0 - omega)] * n
        P = G.dot(G.T)
        if with_gains:
            np.subtract(cached_identity(n), K1, out=K[1])
    elif omega == 1.0:  # K_1 = I, K_2 = 0
        x = x2 + (x1 - x2)
        P = L1.dot(L1.T)
        if with_gains:
            K[0], K[1] = cached_identity(n), 0.0
    else:  # K_1 = 0, K_2 = I
        x = x2 + 0.0 * (x1 - x2)
        P = L2.dot(L2.T)
        if with_gains:
            K[0], K[1] = 0.0, cached_identity(n)
    # the criterion report: P numerically positive definite, the criterion's value
    R, info = _dpotrf(P, lower=1, clean=1)
    if info:
        return None
    r = R.diagonal().tolist()
    low, high = min(r), max(r)
    if not (low > 0.0 and high * high < (low * low) / (n * _EPS)):
        return None
    out = {"criterion": kind, "rule": "optimal", "iterations": np.array(iterations),
           "converged": np.array(gap_converged(gap, floor, computed)),
           "gap": np.array(gap), "gap_floor": np.array(floor), "solver": "diagonalise"}
    if kind == "det":
        log_det = 2.0 * sum([math.log(v) for v in r])
        try:
            value = math.exp(log_det)
        except OverflowError:  # (numpy's exp gives inf)
            value = math.inf
        out["value"] = np.float64(value)
        out["log_value"] = np.float64(log_det)
    elif kind == "trace":
        out["value"] = np.float64(sum(P.diagonal().tolist()))
    else:
        out["value"] = np.float64((W * P).sum())
    if with_gains:
        return x, P, np.array([omega, 1.0 - omega]), out, K
    return x, P, np.array([omega, 1.0 - omega]), out
