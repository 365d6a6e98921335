"""Generalised Covariance Intersection: estimates of parts ``H_i x`` of one state ``x``.

With estimate ``i`` of ``H_i x`` (``H_i`` of shape (m_i, n), the identity for a full-state
estimate) and weights ``w`` on the simplex (eqs. (H1)-(H3) of
``docs/methods/partial_state.rst``):

    P^-1 = sum_i w_i H_i^T P_i^-1 H_i,   K_i = w_i P H_i^T P_i^-1,   x = sum_i K_i x_i,

and ``P = sum_i K_i P_i K_i^T / w_i`` is the bound of the returned gains for every
cross-covariance (eq. (H4)). The information comes from square roots: with
``P_i = L_i L_i^T`` and ``G_i = L_i^-1 H_i`` (m_i x n), ``H_i^T P_i^-1 H_i = G_i^T G_i``;
no ``P_i^-1`` is formed and no condition number is squared. ``G_i`` padded with zero rows
to n x n (or, for m_i > n, replaced by the triangular factor of its QR decomposition) has
the same Gram matrix, so the weighted information fusion of
:mod:`cifilter._numerics.information` (which uses its inverse Cholesky factors only through
``L_inv^T L_inv`` and products with them) and the simplex solver of
:mod:`cifilter._numerics.optimize` serve unchanged; weights at which the fused information
is singular have an infinite criterion, which the solver's line searches reject.

The naive rule with ``H`` is the same fusion with all weights one (then ``P`` is the error
covariance of the gains for independent errors).

One full-state and one partial estimate (``kf.fuse(other, H=H)``) take the diagonalised
pair path (:func:`_pair_single`, eqs. (H7)-(H8)); under the backends that run the compiled
kernels its compiled twin (:mod:`cifilter._kernels.generalised`) answers it, and
:func:`partial_pair_route` reaches that kernel from the raw arrays (the kernel checks them
as the validation does), for the front door's ``H=`` without other options.
"""

import math
from typing import Any, NamedTuple, Optional

import numpy as np
from scipy.linalg import lapack

from .._kernels import dispatch
from .._numerics.alignment import unobserved_directions
from .._numerics.criteria import (
    GAP_TOL,
    certified_gap,
    criterion_gradient,
    criterion_of_factor,
    criterion_report,
    criterion_value,
    parsed_or_none,
)
from .._numerics.information import (
    information_factors,
    lower_inverse_stack,
    single_diagonalisation_trusted,
    trace_curvature,
)
from .._numerics.linalg import ill_conditioned, lower_inverse_single, symmetrize
from .._numerics.optimize import interval_gap, minimize_convex_scalar, minimize_convex_simplex
from .._numerics.validation import check_weights, restore_style
from ..backend import get_backend
from ..result import FusionResult, owned_result

_EPS = float(np.finfo(float).eps)

__all__ = [
    "SquareRoots",
    "check_observable",
    "generalised_assembly",
    "generalised_ci",
    "generalised_naive",
    "generalised_weights",
    "partial_pair_route",
    "square_roots",
]


class SquareRoots(NamedTuple):
    """The information square roots of partial estimates (one batch)."""

    G: np.ndarray  # (..., N, n, n): Gram matrix G_i^T G_i = H_i^T P_i^-1 H_i
    L_inv: tuple  # N arrays (..., m_i, m_i): inverses of the Cholesky factors
    rotation: tuple  # N entries: None, or Q_i (..., m_i, n) with L_i^-1 H_i = Q_i G_i (m_i > n)


def square_roots(est: Any) -> SquareRoots:
    """``G_i`` for every estimate (see the module docstring), stacked (..., N, n, n)."""
    n = est.dim
    stacked: list[Any] = []
    L_invs: list[Any] = []
    rotations: list[Any] = []
    for i in range(est.count):
        L_inv = lower_inverse_stack(est.L[i])
        L_invs.append(L_inv)
        H = est.H[i]
        if H is None:
            stacked.append(L_inv)
            rotations.append(None)
            continue
        G = L_inv @ H  # (..., m_i, n)
        m = G.shape[-2]
        if m > n:
            Q, R = np.linalg.qr(G)  # G = Q R, R (..., n, n): R^T R = G^T G
            stacked.append(R)
            rotations.append(Q)
            continue
        if m < n:
            G = np.concatenate([G, np.zeros(G.shape[:-2] + (n - m, n))], axis=-2)
        stacked.append(G)
        rotations.append(None)
    return SquareRoots(np.stack(stacked, axis=-3), tuple(L_invs), tuple(rotations))


def _state_gains(est, roots, factors):
    """``P H_i^T L_i^-T`` (..., n, m_i) for every estimate, from ``B_i = P G~_i^T``."""
    out = []
    for i in range(est.count):
        B = factors.B[..., i, :, :]
        m = est.x[i].shape[-1]
        if roots.rotation[i] is not None:
            out.append(B @ roots.rotation[i].swapaxes(-1, -2))
        else:
            out.append(B[..., :, :m])
    return out


def generalised_assembly(est, roots, weights, factors):
    """The fused mean, the bound of the gains and the gains at ``weights`` (batched).

    ``K_i = w_i (P H_i^T L_i^-T) L_i^-1``; where some estimates are of the full state, the
    one of largest weight gets ``I - sum_{j != i} K_j H_j`` instead, so that
    ``sum_i K_i H_i = I`` holds to rounding (the fused mean is unbiased and its error is
    ``sum_i K_i e_i``), and ``x = x_ref + sum_{j != ref} K_j (x_j - H_j x_ref)``; unless
    that largest weight is 0, when every gain stays ``w_i P H_i^T P_i^-1`` and
    ``x = sum_i K_i x_i``.
    ``P = sum_i (K_i L_i)(K_i L_i)^T / w_i`` over the positive weights: the bound of
    exactly these gains (eq. (H4)). Returns ``(x, P, gains)`` with ``gains`` a tuple of
    (..., n, m_i) arrays.
    """
    n, count = est.dim, est.count
    batch = est.batch_shape
    gains = []
    for i, PG in enumerate(_state_gains(est, roots, factors)):
        K = weights[..., i, None, None] * (PG @ roots.L_inv[i])
        gains.append(K)
    full = est.full
    # the plain sum: the mean where no full-state estimate of positive weight takes the
    # remainder
    x = np.zeros(batch + (n,))
    for i in range(count):
        x = x + (gains[i] @ est.x[i][..., None])[..., 0]
    if full:
        candidates = np.array(full)
        reference = candidates[np.argmax(weights[..., candidates], axis=-1)]  # (...)
        # a reference of weight 0 (every full-state estimate dropped, possible at rho = 1
        # of partial CI or a given weight) keeps its zero gain: the remainder would be
        # rounding amplified by the condition number, with no term for it in P
        takes = np.take_along_axis(weights, reference[..., None], axis=-1)[..., 0] > 0.0
        others = np.zeros(batch + (n, n))
        x_ref = np.zeros(batch + (n,))
        for i in range(count):
            mine = reference == i
            KH = gains[i] if est.H[i] is None else gains[i] @ est.H[i]
            others = others + np.where(mine[..., None, None], 0.0, KH)
            if est.H[i] is None:
                x_ref = np.where(mine[..., None], est.x[i], x_ref)
        remainder = np.eye(n) - others
        x_remainder = x_ref.copy()
        for i in range(count):
            mine = reference == i
            if est.H[i] is None:
                gains[i] = np.where((mine & takes)[..., None, None], remainder, gains[i])
            innovation = est.x[i] - (x_ref if est.H[i] is None else x_ref @ est.H[i].T)
            step = (gains[i] @ innovation[..., None])[..., 0]
            x_remainder = x_remainder + np.where(mine[..., None], 0.0, step)
        x = np.where(takes[..., None], x_remainder, x)
    P = np.zeros(batch + (n, n))
    for i in range(count):
        w = weights[..., i, None, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            M = np.where(w > 0.0, (gains[i] @ est.L[i]) / np.sqrt(w), 0.0)
        P = P + M @ M.swapaxes(-1, -2)
    return x, symmetrize(P), tuple(gains)


def _singular_message(est, roots, weights, problem, what):
    """The error for a fused information that is singular at ``weights`` (one problem):
    a ValueError naming the directions that the estimates of positive weight do not
    observe, or, where they observe every direction and only the weights make the
    information numerically singular, an IllConditionedError."""
    index = tuple(int(i) for i in problem)
    used = [i for i in range(est.count) if weights[index + (i,)] > 0.0]
    G = np.concatenate([roots.G[index + (i,)] for i in used], axis=0)
    directions = unobserved_directions(G)
    where = f" (problem {list(index)})" if index else ""
    if not directions:
        J = sum(weights[index + (i,)] * roots.G[index + (i,)].T @ roots.G[index + (i,)]
                for i in used)
        return ill_conditioned(
            f"{what}{where}: the fused information sum_i w_i H_i^T P_i^-1 H_i",
            np.linalg.cond(J))
    shown = ", ".join(str(v) for v in directions)
    return ValueError(
        f"{what}{where}: sum_i {'w_i ' if what.startswith('with') else ''}H_i^T P_i^-1 H_i "
        f"is singular; unobserved direction(s) of the state (a basis of its null space, in "
        f"state coordinates): {shown}"
    )


def _factors_or_raise(est, roots, weights, what):
    """:func:`information_factors` at ``weights``; a singular problem raises the error
    naming its unobserved directions."""
    factors = information_factors(roots.G, weights, failures="nan")
    singular = np.isnan(factors.R[..., 0, 0])
    if np.any(singular):
        problem = np.unravel_index(int(np.argmax(singular.ravel())), singular.shape)
        raise _singular_message(est, roots, weights, problem, what)
    return factors


def check_observable(est, roots):
    """Raise a ValueError naming the unobserved directions when ``sum_i H_i^T P_i^-1 H_i``
    is singular (never when some estimate is of the full state)."""
    if est.full:
        return
    uniform = np.full(est.batch_shape + (est.count,), 1.0 / est.count)
    _factors_or_raise(est, roots, uniform,
                      "the estimates together do not observe the state")


def generalised_weights(roots, kind, W, count, shape):
    """Criterion-optimal weights by the active-set Newton method on the simplex.

    As the full-state simplex solver (``docs/methods/simplex_solver.rst``) on the square
    roots ``G_i``: ``g_i = -trace(W B_i B_i^T)`` or ``-||C_i||^2`` and the Hessians of
    :func:`cifilter._numerics.information.trace_curvature`; where the fused information is
    singular the criterion is +inf (rejected by the line searches). The solver's last,
    unchecked step can land on such a face (next to an optimum close to it): then the best
    finite point it evaluated is returned instead. Returns ``(weights, iterations)``.
    """
    size = int(np.prod(shape, dtype=int))
    G = roots.G.reshape((size,) + roots.G.shape[-3:])
    Wf = None if W is None else np.broadcast_to(W, shape + W.shape[-2:]).reshape(
        (size,) + W.shape[-2:])
    best_f = np.full(size, np.inf)
    best_w = np.full((size, count), 1.0 / count)

    def remember(w, index, f):
        better = np.isfinite(f) & (f < best_f[index])
        best_f[index[better]] = f[better]
        best_w[index[better]] = w[better]

    def objective(w, index):
        factors = information_factors(G[index], w, failures="nan")
        value = criterion_of_factor(factors.R_inv, kind, None if Wf is None else Wf[index])
        value = np.where(np.isnan(value), np.inf, value)
        remember(w, index, value)
        return value

    def evaluate(w, index):
        factors = information_factors(G[index], w, failures="nan")
        Wi = None if Wf is None else Wf[index]
        f = criterion_of_factor(factors.R_inv, kind, Wi)
        g = criterion_gradient(factors, kind, Wi)
        if kind == "det":
            CtC = np.einsum("...iab,...jac->...ijbc", factors.C, factors.C)
            H = np.einsum("...ijbc,...ijbc->...ij", CtC, CtC)
        else:
            H = 2.0 * trace_curvature(factors, Wi)
        singular = np.isnan(f)
        f = np.where(singular, np.inf, f)
        remember(w, index, f)
        g = np.where(singular[:, None], 0.0, g)
        H = np.where(singular[:, None, None], np.eye(w.shape[-1]), symmetrize(H))
        return f, -g, H

    with np.errstate(invalid="ignore", over="ignore"):
        weights, iterations, _ = minimize_convex_simplex(
            evaluate, objective, count, (size,), gtol=0.25 * GAP_TOL,
            absolute_gap=kind == "det", subset=True)
        final = information_factors(G, weights.reshape(size, count), failures="nan")
    landed = np.isnan(final.R[:, 0, 0])  # on a singular face: the best point seen
    weights = np.where(landed[:, None], best_w, weights.reshape(size, count))
    return weights.reshape(shape + (count,)), iterations.reshape(shape)


def _certify(roots, weights, kind, W):
    """``(factors, gap)`` at ``weights`` (gap inf where the information is singular)."""
    factors = information_factors(roots.G, weights, failures="nan")
    g = criterion_gradient(factors, kind, W)
    value = criterion_of_factor(factors.R_inv, kind, W)
    with np.errstate(invalid="ignore"):
        gap = certified_gap(weights, g, value, kind)
    return factors, np.where(np.isnan(gap), np.inf, gap)


def _pair_single(est, kind, W):
    """One problem of two estimates, one of them of the full state: the diagonalised path.

    With ``a`` the full-state estimate (weight ``w``), ``b`` the partial one and the SVD
    ``L_b^-1 H L_a = V S U^T``, ``T = L_a U`` gives ``P(w) = T diag(d) T^T`` with
    ``d_k = 1 / (mu_k + w (1 - mu_k))``, ``mu_k = s_k^2`` (0 beyond the rank), so the
    criterion is a sum of scalar terms (eq. (H7)); Newton's method in Python floats, the
    certified gap of :func:`cifilter._numerics.optimize.interval_gap`. The directions
    beyond the rank share ``d_k = 1 / w`` and enter the criterion as one term (weight
    ``sum_k c_k`` for a trace, their count for the determinant). Gains (eq. (H8)):
    ``K_b = (1 - w) T diag(d) S^T V^T L_b^-1``, ``K_a = I - K_b H``, and ``P`` is the bound
    of these gains (eq. (H4)), checked finite and positive definite here (the conditioning
    contract; a failure goes the long way, whose check raises). Returns None where the
    diagonalisation is not trusted (spread of the nonzero ``mu`` or of the factors'
    diagonals above 1e6, as for full states); the simplex path decides there. Where the
    backend runs the kernels (:func:`_kernel_allowed`) the compiled twin of this path
    (:func:`cifilter._kernels.generalised.partial_pair`, on the validated factors) answers
    first; it returns None where it does not decide, and this path runs.
    """
    Hs = est.H
    if len(Hs) != 2 or est.x[0].ndim != 1 or (Hs[0] is None) == (Hs[1] is None):
        return None  # (not two estimates of one problem, one of them of the full state)
    a = 0 if Hs[0] is None else 1
    b = 1 - a
    n = est.dim
    La, Lb, H = est.L[a], est.L[b], Hs[b]
    if _kernel_allowed(n):
        compiled = _compiled_pair()(est.x[a], est.P[a], est.x[b], est.P[b], H, kind, W,
                                    (La, Lb))
        if compiled is not None:
            x, P, w, info = compiled
            Ka, Kb = info.pop("gains")
            weights = np.array((w, 1.0 - w) if a == 0 else (1.0 - w, w))
            return weights, info, (x, P, (Ka, Kb) if a == 0 else (Kb, Ka))
    # (ndarray.dot, not @: the same BLAS calls, bitwise, with less overhead on small arrays)
    Lb_inv = lower_inverse_single(Lb)
    V, s, Ut, failed = lapack.dgesdd(Lb_inv.dot(H).dot(La), compute_uv=1, full_matrices=1)
    if failed:
        return None
    singular = s.tolist()  # descending
    r = len(singular)
    mu = [v * v for v in singular]
    if not single_diagonalisation_trusted(mu[::-1], (La, Lb)):
        return None
    T = La.dot(Ut.T)
    determinant = kind == "det"
    if determinant:
        coefficients = [1.0] * r
        rest = float(n - r)
    else:
        columns = (np.square(T) if kind == "trace" else W.dot(T) * T).sum(axis=0).tolist()
        coefficients = columns[:r]
        rest = sum(columns[r:])
    # (mu_k, 1 - mu_k, c_k) per term, the directions beyond the rank as one (mu = 0)
    terms = [(m, 1.0 - m, ck) for m, ck in zip(mu, coefficients)]
    if r < n:
        terms.append((0.0, 1.0, rest))
    scale = float(n) if determinant else sum(coefficients) + rest
    derivative = _log_det_derivative(terms) if determinant else _trace_derivative(terms)
    w, iterations, _ = minimize_convex_scalar(derivative, scale=scale)
    slope, _ = derivative(w)
    gap = interval_gap(w, slope)
    d = []
    for m, one_minus, _ in terms:
        den = m + w * one_minus
        if not den > 0.0 or not math.isfinite(1.0 / den):
            return None
        d.append(1.0 / den)
    if not determinant:
        gap /= sum(ck * dk for (_, _, ck), dk in zip(terms, d))
    if not math.isfinite(gap):
        return None
    m = H.shape[0]
    if w == 1.0:
        Kb = np.zeros((n, m))
    else:
        scaled = T[:, :r] * np.array([(1.0 - w) * dk * sk for dk, sk in zip(d, singular)])
        Kb = scaled.dot(V.T if r == m else V[:, :r].T).dot(Lb_inv)
    # (M M^T is exactly symmetric (numpy's syrk), and so is P: no symmetrisation)
    if w == 0.0:
        Ka = np.zeros((n, n))
        M = Kb.dot(Lb)
        P = M.dot(M.T)
        x = Kb.dot(est.x[b])
    else:
        Ka = np.subtract(_identity(n), Kb.dot(H))
        M = Ka.dot(La)
        P = M.dot(M.T)
        if w < 1.0:
            M = Kb.dot(Lb)
            P /= w
            P += M.dot(M.T) / (1.0 - w)
        x = est.x[a] + Kb.dot(est.x[b] - H.dot(est.x[a]))
    report = _pair_report(P, kind, W)
    if report is None:
        return None
    weights = np.array((w, 1.0 - w) if a == 0 else (1.0 - w, w))
    gains = (Ka, Kb) if a == 0 else (Kb, Ka)
    info = {"iterations": np.array(iterations), "converged": np.array(gap <= GAP_TOL),
            "gap": np.array(gap), "solver": "diagonalise"}
    info.update(report)
    return weights, info, (x, P, gains)


def partial_pair_route(pairs: Any, H: tuple, criterion: Any) -> Optional[FusionResult]:
    """The ``"ci"`` rule's route for ``kf.fuse(other, H=H)``: one compiled call from the
    raw arrays to the result, or None (the usual route: validation, then
    :func:`generalised_ci`).

    Taken for two single ``(x, P)`` pairs of float64 arrays (``x`` (m,) or (m, 1)), one
    of the full state (its ``H`` entry None) and one of ``H x`` (``H`` (m, n) with
    ``m <= n``, as checked by
    :func:`cifilter._numerics.alignment.check_observation_matrices`) and the ``criterion``
    of optimal weights (the ``"ci"`` record's route passes it when it is the only
    option), when the backend runs the kernel
    (:func:`_kernel_allowed`). The covariances are factored by LAPACK as given and the
    kernel checks the rest as the validation does; any failed check, a covariance that is
    not exactly symmetric (the validation symmetrises it) and any problem the kernel does
    not decide return None, and the usual route validates (raising its error) and solves.
    Where the route answers, its result is the usual route's bit for bit (the same factors,
    kernel, certificate and ``info``).
    """
    if get_backend() == "numpy":
        return None
    if len(pairs) != 2 or len(H) != 2 or (H[0] is None) == (H[1] is None):
        return None
    a = 0 if H[0] is None else 1
    b = 1 - a
    (xa, Pa), (xb, Pb) = pairs[a], pairs[b]
    Hb = H[b]
    if not (type(xa) is np.ndarray and type(Pa) is np.ndarray and type(xb) is np.ndarray
            and type(Pb) is np.ndarray and type(Hb) is np.ndarray):
        return None
    if (Pa.dtype.char != "d" or Pb.dtype.char != "d" or xa.dtype.char != "d"
            or xb.dtype.char != "d" or Hb.dtype.char != "d" or Pa.ndim != 2 or Pb.ndim != 2):
        return None
    n, m = Pa.shape[0], Pb.shape[0]
    if (Pa.shape != (n, n) or Pb.shape != (m, m) or Hb.shape != (m, n) or m == 0 or m > n
            or xa.shape not in ((n,), (n, 1)) or xb.shape not in ((m,), (m, 1))):
        return None
    parsed = parsed_or_none(criterion, n)
    if parsed is None:
        return None
    kind, W = parsed
    if not _kernel_allowed(n):
        return None
    # (LAPACK's factors of the covariances as given, as the validation takes them: the
    # kernel checks the rest, and an answer is the usual route's bit for bit)
    La, failed = lapack.dpotrf(Pa, lower=1, clean=1)
    if failed:
        return None
    Lb, failed = lapack.dpotrf(Pb, lower=1, clean=1)
    if failed:
        return None
    compiled = _compiled_pair()(xa.reshape(n), Pa, xb.reshape(m), Pb, Hb, kind, W,
                                (La, Lb), check=True)
    if compiled is None:
        return None
    x, P, w, solver_info = compiled
    Ka, Kb = solver_info.pop("gains")
    weights = np.array((w, 1.0 - w) if a == 0 else (1.0 - w, w))
    info: dict[str, Any] = {"criterion": kind, "rule": "optimal"}
    info.update(solver_info)
    info["gains"] = (Ka, Kb) if a == 0 else (Kb, Ka)
    return _owned(x, P, weights, info, pairs[0][0].ndim == 2)


def _owned(x, P, weights, info, column):
    """The result of the pair (arrays of its own, nobody else holds them: frozen in place,
    the gains in ``info`` too; equal to ``FusionResult(x, P, "ci", weights, None, info)``)."""
    for K in info["gains"]:
        K.setflags(write=False)
    return owned_result(restore_style(x, column), P, "ci", weights, None, info)


def _compiled_pair():
    """:func:`cifilter._kernels.generalised.partial_pair`, imported on first use (importing
    cifilter never imports numba)."""
    if not _COMPILED:
        from .._kernels.generalised import partial_pair

        _COMPILED.append(partial_pair)
    return _COMPILED[0]


_COMPILED: list = []


def _kernel_allowed(n):
    """Whether a single pair of dimension ``n`` runs on the compiled kernel
    (:func:`cifilter._kernels.generalised.partial_pair`): where single calls of the CI
    kernels do (:func:`cifilter._kernels.dispatch.single_ready`; under ``"auto"`` once the
    kernels, this one among them, are compiled or in numba's cache: a single call never
    starts or waits for a compile)."""
    return dispatch.single_ready(n)


def _trace_derivative(terms):
    """``(f', f'')`` of ``f(w) = sum_k c_k / (mu_k + w (1 - mu_k))`` (the trace, eq. (H7))
    for ``terms`` of ``(mu_k, 1 - mu_k, c_k)``; ``(-inf, inf)`` where a denominator is not
    positive."""
    def derivative(w):
        slope = curvature = 0.0
        for m, one_minus, ck in terms:
            den = m + w * one_minus
            if den <= 0.0:
                return -math.inf, math.inf
            ad = one_minus / den
            term = ck * ad / den
            slope -= term
            curvature += 2.0 * term * ad
        return slope, curvature
    return derivative


def _log_det_derivative(terms):
    """As :func:`_trace_derivative` for ``f(w) = -sum_k c_k log(mu_k + w (1 - mu_k))`` (log
    det ``P``, with ``c_k`` the multiplicities)."""
    def derivative(w):
        slope = curvature = 0.0
        for m, one_minus, ck in terms:
            den = m + w * one_minus
            if den <= 0.0:
                return -math.inf, math.inf
            ad = one_minus / den
            term = ck * ad
            slope -= term
            curvature += term * ad
        return slope, curvature
    return derivative


def _identity(n):
    """The n x n identity, read-only, made once per n."""
    eye = _IDENTITIES.get(n)
    if eye is None:
        eye = np.eye(n)
        eye.setflags(write=False)
        _IDENTITIES[n] = eye
    return eye


_IDENTITIES: dict = {}


def _pair_report(P, kind, W):
    """:func:`cifilter._numerics.criteria.criterion_report` of one fused ``P`` whose
    Cholesky factor passes the same test (finite, diagonal spread below ``1 / (n eps)``),
    from that factor; None otherwise (then the long way's report raises its error)."""
    L, failed = lapack.dpotrf(P, lower=1, clean=0)
    if failed:
        return None
    diagonal = L.diagonal()
    d = [abs(v) for v in diagonal.tolist()]
    if not (all(math.isfinite(v) for v in d)
            and max(d) ** 2 < min(d) ** 2 / (P.shape[0] * _EPS)):
        return None
    if kind == "det":
        log_det = 2.0 * np.log(diagonal).sum()
        with np.errstate(over="ignore", under="ignore"):
            return {"value": np.exp(log_det), "log_value": log_det}
    if kind == "trace":
        # (below 8 terms numpy's sum of the diagonal is this sequential one, bitwise)
        return {"value": np.float64(sum(P.diagonal().tolist())) if len(d) < 8
                else P.trace()}
    return {"value": criterion_value(P, kind, W)}


def _fast_partial_weights(est, roots):
    """Niehsen's fast rule for partial estimates: ``w_i`` proportional to
    ``1 / tr((H_i^T P_i^-1 H_i)^+)`` (eq. (H9)): ``1 / tr(P_i)`` for a full-state estimate,
    the trace of the covariance of the observed part otherwise (``tr(P_i)`` for a selection
    ``H_i``), from the singular values of ``L_i^-1 H_i``."""
    traces = []
    for i in range(est.count):
        if est.H[i] is None:
            traces.append(np.trace(est.P[i], axis1=-2, axis2=-1))
            continue
        G = roots.L_inv[i] @ est.H[i]
        s = np.linalg.svd(G, compute_uv=False)
        top = s.max(axis=-1, keepdims=True)
        keep = s > max(G.shape[-2:]) * np.finfo(float).eps * top
        traces.append(np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0).sum(axis=-1))
    inverse = 1.0 / np.stack(traces, axis=-1)
    return inverse / inverse.sum(axis=-1, keepdims=True)


def _result(est, method, x, P, gains, weights, omega, info, kind=None, W=None):
    n = est.dim
    if kind is not None:
        info.update(criterion_report(P, kind, W))
    else:
        criterion_report(P, "trace", None)  # the conditioning contract's check of P
    info["gains"] = gains
    stacked = None
    if all(K.shape[-1] == n for K in gains):
        stacked = np.stack(gains, axis=-3)
    return FusionResult(restore_style(x, est.column), P, method, omega, stacked, info,
                        weights=weights)


def generalised_ci(est: Any, kind: str, W: Optional[np.ndarray], omega: Any = None,
                   fast_rules: tuple = ()) -> FusionResult:
    """The ``"ci"`` rule on :class:`~cifilter._numerics.alignment.PartialEstimates`.

    ``omega`` None minimises the criterion (the diagonalised path for one problem of a
    full-state and a partial estimate, else the simplex solver), a fast rule's name
    (``"fast"`` only: the determinant rules compare covariances of different dimensions),
    or given weights. The result's ``gains`` are (..., N, n, n) when every ``m_i = n``,
    else None; ``info["gains"]`` always holds the tuple of ``K_i`` (..., n, m_i).
    """
    info = {"criterion": kind}
    if omega is None and (W is None or W.ndim == 2):
        single = _pair_single(est, kind, W)  # (a full-state estimate: observable)
        if single is not None:
            weights, solver_info, (x, P, gains) = single
            info.update(rule="optimal", **solver_info)  # (its report: P checked)
            info["gains"] = gains
            return _owned(x, P, weights, info, est.column)  # (new arrays, all of them)
    roots = square_roots(est)
    check_observable(est, roots)
    if omega is None:
        Wb = None if W is None else np.broadcast_to(W, est.batch_shape + W.shape[-2:])
        weights, iterations = generalised_weights(roots, kind, Wb, est.count,
                                                  est.batch_shape)
        factors, gap = _certify(roots, weights, kind, Wb)
        info.update(rule="optimal", iterations=iterations, converged=gap <= GAP_TOL,
                    gap=gap, solver="simplex")
    elif isinstance(omega, str):
        if omega not in fast_rules:
            raise ValueError(
                f"omega must be None, weights or one of {', '.join(map(repr, fast_rules))}; "
                f"got {omega!r}")
        if omega != "fast":
            raise ValueError(
                f"omega={omega!r} compares the determinants of the estimates' covariances, "
                "which with H= are of different dimensions; use omega='fast', given "
                "weights or the optimal weights (omega=None)")
        weights = _fast_partial_weights(est, roots)
        factors = _factors_or_raise(est, roots, weights, "with the weights of omega='fast'")
        info["rule"] = "fast"
    else:
        weights = check_weights(omega, est.count, batch_shape=est.batch_shape)
        factors = _factors_or_raise(est, roots, weights, "with the given weights omega")
        info["rule"] = "fixed"
    x, P, gains = generalised_assembly(est, roots, weights, factors)
    return _result(est, "ci", x, P, gains, weights, weights, info, kind, W)


def generalised_naive(est: Any) -> FusionResult:
    """The ``"naive"`` rule on partial estimates: all weights one,
    ``P^-1 = sum_i H_i^T P_i^-1 H_i`` and ``P = sum_i K_i P_i K_i^T`` (eq. (H5))."""
    roots = square_roots(est)
    check_observable(est, roots)
    weights = np.ones(est.batch_shape + (est.count,))
    factors = _factors_or_raise(est, roots, weights,
                                "the estimates together do not observe the state")
    x, P, gains = generalised_assembly(est, roots, weights, factors)
    return _result(est, "naive", x, P, gains, weights, None, {})
