"""Split Covariance Intersection (Julier & Uhlmann 2001; Li, Nashashibi & Yang 2013).

Each estimate's error is split into an independent part (independent of every other
estimate's independent part) and a dependent part (arbitrarily correlated): ``P = P_ind +
P_dep``. Split CI inflates only the dependent parts, ``P_k(omega) = P_k_dep / omega_k +
P_k_ind``, and fuses by the Kalman update. Zero dependent parts give the Kalman (naive)
update, zero independent parts Covariance Intersection. The numerics are in
:mod:`cifilter.rules._split`; derivations in ``docs/methods/split_ci.rst``.
"""

from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.alignment import PartialEstimates
from .._numerics.criteria import criterion_report, parse_criterion
from .._numerics.validation import (
    as_covariance_stack,
    as_estimates,
    as_matrix,
    check_psd,
    check_weights,
    restore_style,
)
from ..result import FusionResult
from ._split import split_pair

__all__ = ["split_covariance_intersection"]


def _parts(P_ind, P_dep, name_ind, name_dep):
    """Validated PSD parts (..., N, n, n) of equal shape."""
    P_ind = as_covariance_stack(P_ind, name_ind)
    P_dep = as_covariance_stack(P_dep, name_dep)
    if P_ind.shape[-3:] != P_dep.shape[-3:]:
        raise ValueError(
            f"{name_ind} has shape {P_ind.shape} and {name_dep} has shape {P_dep.shape}; "
            "each estimate needs an independent and a dependent part of its dimension"
        )
    n = P_ind.shape[-1]
    return check_psd(P_ind, n, name_ind), check_psd(P_dep, n, name_dep)


def split_covariance_intersection(xs: ArrayLike, Ps_independent: ArrayLike,
                                  Ps_dependent: ArrayLike, H: Optional[ArrayLike] = None,
                                  criterion: Union[str, ArrayLike] = "det") -> FusionResult:
    """Split Covariance Intersection of estimates with independent and dependent errors.

    Each estimate k has error covariance ``P_k = P_k_ind + P_k_dep``: the independent
    parts are errors independent of every other estimate's, the dependent parts may be
    correlated arbitrarily. With

        P_1(omega) = P_1_dep / omega + P_1_ind,   P_2(omega) = P_2_dep / (1 - omega) + P_2_ind,

    the fused estimate is the Kalman update of estimate 1 by estimate 2 as a measurement
    of ``H x`` (Julier & Uhlmann 2001, the split CI equations; Li, Nashashibi & Yang 2013,
    eqs. (6)-(10) of the split CI filter):

        K = P_1 H^T (H P_1 H^T + P_2)^-1,   x = x_1 + K (x_2 - H x_1),   P = (I - K H) P_1,

    with omega minimising ``det(P)`` (default), ``trace(P)`` or ``trace(W P)`` (convex in
    omega). The fused covariance is returned with its split: ``P_ind`` the covariance of
    the fused independent error, ``P_dep`` the CI bound of the fused dependent error.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        The means: N >= 2 of shape (n,) or (n, 1) (optionally with batch axes) or one
        array (..., N, n); with ``H`` exactly two, ``x_1`` (..., n) and ``x_2`` (..., m).
    Ps_independent : sequence of array_like or array_like
        The independent parts, symmetric positive semidefinite (zero allowed), one per
        estimate ((..., n, n); with ``H`` the second is (..., m, m)), or an array
        (..., N, n, n).
    Ps_dependent : sequence of array_like or array_like
        The dependent parts, of the same shapes, symmetric positive semidefinite. Every
        ``P_k_ind + P_k_dep`` must be positive definite.
    H : array_like, shape (..., m, n), or sequence, optional
        The second estimate observes ``H x`` (a partial estimate, for instance a position
        fix of a position-velocity state). Two estimates only. Default: the identity.
        Also as :func:`cifilter.fuse` takes it, one entry per estimate: ``[None, H]``
        (the first estimate is of the full state).
    criterion : {"det", "trace"} or array_like, shape (n, n), optional
        What omega minimises: ``det(P)`` (default, as Li, Nashashibi & Yang), ``trace(P)``
        or ``trace(W P)``.

    Returns
    -------
    FusionResult
        ``x`` (..., n) in the style of the first mean, ``P`` (..., n, n) equal to
        ``info["P_independent"] + info["P_dependent"]``, ``weights`` (..., 2) the pair
        ``(omega, 1 - omega)`` (None for N > 2), ``omega`` None, ``gains`` (..., N, n, n)
        with ``x = sum_i K_i x_i`` (None with a rectangular ``H``; then
        ``info["gains"]`` holds ``K_1`` (..., n, n) and ``K_2`` (..., n, m) with
        ``x = K_1 x_1 + K_2 x_2``), and ``info`` with ``P_independent``, ``P_dependent``,
        ``criterion``, ``value``, ``rule`` (``"optimal"`` or ``"sequential"`` for N > 2),
        ``iterations``, ``gap`` and ``converged`` (gap at most 1e-9; at condition numbers
        of 1e9 and above the gap is an estimate, not a bound, see "Measured limits" in
        ``docs/methods/split_ci.rst``); for N > 2 also ``omegas`` (..., N - 1).

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, parts that are
        not symmetric positive semidefinite or whose sum is not positive definite, ``H``
        with more than two estimates or of the wrong shape, an unknown criterion.
    IllConditionedError
        (a ValueError) The fused information or covariance is numerically singular (for
        instance an ``H`` that observes nothing while the first estimate is ignored).
    TypeError
        Non-numeric input.

    See Also
    --------
    covariance_intersection : the case of zero independent parts.
    naive_fusion : the case of zero dependent parts.
    SplitCIKalmanFilter : a filter that keeps the split through predict and update.

    Notes
    -----
    ``P`` bounds the fused error covariance whenever the independent parts are truly
    independent (of each other and of every dependent part) and the dependent parts are
    correlated in any way: the error is ``sum_k K_k (i_k + d_k)``, its independent part
    has covariance ``P_ind = sum_k K_k P_k_ind K_k^T`` exactly and its dependent part is
    bounded by the CI inequality, ``P_dep = sum_k K_k P_k_dep K_k^T / omega_k``. Both
    are assembled from the returned gains, so the bound holds for what is returned, up
    to rounding. An end ``omega = 0`` (or 1) ignores estimate 1 (or 2). N > 2 estimates
    without ``H`` are fused sequentially in the given order; each step is a valid split
    CI (the fused independent error stays independent of the next estimate's), so the
    result is a bound, but it depends on the order.

    References
    ----------
    .. [1] S. J. Julier and J. K. Uhlmann, "General decentralized data fusion with
       covariance intersection (CI)", in Handbook of Multisensor Data Fusion, 2001
       (split CI).
    .. [2] H. Li, F. Nashashibi and M. Yang, "Split covariance intersection filter:
       theory and its application to vehicle localization", IEEE TITS 14(4), 2013.

    Examples
    --------
    Zero independent parts give Covariance Intersection (here the det-optimal omega of
    eq. (34) of Ajgl et al. 2014, 0.6):

    >>> import numpy as np
    >>> from cifilter import split_covariance_intersection
    >>> Pa, Pb = np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])
    >>> zero = np.zeros((2, 2))
    >>> r = split_covariance_intersection([np.zeros(2)] * 2, [zero, zero], [Pa, Pb])
    >>> round(float(r.weights[0]), 9)
    0.6

    Zero dependent parts give the Kalman update (the naive fusion):

    >>> r = split_covariance_intersection([np.zeros(2)] * 2, [Pa, Pb], [zero, zero])
    >>> bool(np.allclose(r.P, np.linalg.inv(np.linalg.inv(Pa) + np.linalg.inv(Pb))))
    True
    """
    H = _second_observation(H, xs)
    if H is None:
        P_ind, P_dep = _parts(Ps_independent, Ps_dependent, "Ps_independent", "Ps_dependent")
        est = as_estimates(xs, P_ind + P_dep, names=("xs", "Ps_independent + Ps_dependent"))
        P_ind = np.broadcast_to(P_ind, est.P.shape)
        P_dep = np.broadcast_to(P_dep, est.P.shape)
        return _split_ci(est, P_ind, P_dep, criterion)
    return _split_ci_partial(xs, Ps_independent, Ps_dependent, H, criterion)


def _second_observation(H, xs):
    """Split CI's ``H``: the second estimate's matrix, given alone or as the front door's
    per-estimate sequence ``[None, H_2]``."""
    if not (isinstance(H, (list, tuple)) and len(H) >= 1
            and any(entry is None for entry in H)):
        return H
    count = len(xs) if isinstance(xs, (list, tuple)) else None
    if len(H) != 2 or H[0] is not None or (count is not None and count != 2):
        raise ValueError(
            "split CI fuses a partial estimate into an estimate of the full state: give H as "
            "the second estimate's matrix or as [None, H_2] (two estimates, the first of the "
            f"full state); got {len(H)} entries"
        )
    return H[1]


def _flatten(array, tail):
    return array.reshape((-1,) + array.shape[array.ndim - tail:])


def _split_ci(est, P_ind, P_dep, criterion, omega=None):
    """Split CI of validated estimates with their (validated) parts, N >= 2, no H."""
    kind, W = parse_criterion(criterion, est.dim)
    batch, n = est.batch_shape, est.dim
    size = int(np.prod(batch, dtype=int))
    Wf = None if W is None else np.broadcast_to(W, batch + (n, n)).reshape(size, n, n)
    H = np.broadcast_to(np.eye(n), (size, n, n))
    x = _flatten(est.x[..., 0, :], 1)
    Pi, Pd = _flatten(P_ind[..., 0, :, :], 2), _flatten(P_dep[..., 0, :, :], 2)
    gains = np.broadcast_to(np.eye(n), (size, 1, n, n))
    omegas, steps = [], []
    for k in range(1, est.count):
        parts = ((Pi, Pd), (_flatten(P_ind[..., k, :, :], 2), _flatten(P_dep[..., k, :, :], 2)))
        w = None if omega is None else omega
        x, _, Pi, Pd, K1, K2, w, info = split_pair(x, _flatten(est.x[..., k, :], 1), parts, H,
                                                   kind, Wf, w)
        gains = np.concatenate([K1[:, None] @ gains, K2[:, None]], axis=1)
        omegas.append(w)
        steps.append(info)
    P = Pi + Pd
    P = 0.5 * (P + P.swapaxes(-1, -2))
    info = {"criterion": kind}
    if omega is None:
        info["rule"] = "optimal" if est.count == 2 else "sequential"
        info["iterations"] = sum(s["iterations"] for s in steps).reshape(batch)
        info["gap"] = np.max([s["gap"] for s in steps], axis=0).reshape(batch)
        info["converged"] = info["gap"] <= 1e-9
    else:
        info["rule"] = "fixed"
    weights = None
    if est.count == 2:
        weights = np.stack([omegas[0], 1.0 - omegas[0]], axis=-1).reshape(batch + (2,))
    else:
        info["omegas"] = np.stack(omegas, axis=-1).reshape(batch + (est.count - 1,))
    P = P.reshape(batch + (n, n))
    info["P_independent"] = Pi.reshape(batch + (n, n))
    info["P_dependent"] = Pd.reshape(batch + (n, n))
    info.update(criterion_report(P, kind, W))
    x = x.reshape(batch + (n,))
    gains = gains.reshape(batch + (est.count, n, n))
    return FusionResult(restore_style(x, est.column), P, "split-ci", None, gains, info,
                        weights=weights)


def _split_ci_partial(xs, Ps_independent, Ps_dependent, H, criterion):
    """Two estimates, the second a (partial) estimate of ``H x``."""
    for value, name in ((xs, "xs"), (Ps_independent, "Ps_independent"),
                        (Ps_dependent, "Ps_dependent")):
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise ValueError(f"with H, {name} must be a sequence of two estimates' values")
    first, second = [], []
    for k, out in ((0, first), (1, second)):
        Pi, Pd = _parts([Ps_independent[k]], [Ps_dependent[k]], f"Ps_independent[{k}]",
                        f"Ps_dependent[{k}]")
        est = as_estimates([xs[k]], Pi + Pd, min_count=1,
                           names=(f"xs[{k}]", f"Ps_independent[{k}] + Ps_dependent[{k}]"))
        out.extend([est, Pi[..., 0, :, :], Pd[..., 0, :, :]])
    est1, est2 = first[0], second[0]
    n, m = est1.dim, est2.dim
    H = as_matrix(H, "H", (m, n))
    return _partial_pair(est1.x[..., 0, :], est2.x[..., 0, :], est1.batch_shape,
                         est2.batch_shape, ((first[1], first[2]), (second[1], second[2])), H,
                         criterion, est1.column)


def _partial_pair(x1, x2, batch1, batch2, parts, H, criterion, column, omega=None):
    """Split CI of a full-state estimate ``x1`` (..., n) and an estimate ``x2`` (..., m) of
    ``H x``, with their parts ``((P1_ind, P1_dep), (P2_ind, P2_dep))``."""
    (P1_ind, P1_dep), (P2_ind, P2_dep) = parts
    n, m = x1.shape[-1], x2.shape[-1]
    kind, W = parse_criterion(criterion, n)
    batch = np.broadcast_shapes(batch1, batch2, H.shape[:-2], P1_ind.shape[:-2],
                                P2_ind.shape[:-2])
    size = int(np.prod(batch, dtype=int))

    def flat(array, tail):
        return np.broadcast_to(array, batch + array.shape[array.ndim - tail:]).reshape(
            (size,) + array.shape[array.ndim - tail:])

    flat_parts = ((flat(P1_ind, 2), flat(P1_dep, 2)), (flat(P2_ind, 2), flat(P2_dep, 2)))
    Wf = None if W is None else flat(W, 2)
    if omega is not None:
        omega = np.broadcast_to(omega, batch).reshape(size)
    x, P, Pi, Pd, K1, K2, w, info = split_pair(flat(x1, 1), flat(x2, 1), flat_parts,
                                               flat(H, 2), kind, Wf, omega)
    P = P.reshape(batch + (n, n))
    out = {"criterion": kind, "rule": info["rule"],
           "P_independent": Pi.reshape(batch + (n, n)),
           "P_dependent": Pd.reshape(batch + (n, n)),
           "gains": (K1.reshape(batch + (n, n)), K2.reshape(batch + (n, m)))}
    if omega is None:
        out.update(iterations=info["iterations"].reshape(batch),
                   gap=info["gap"].reshape(batch), converged=info["converged"].reshape(batch))
    out.update(criterion_report(P, kind, W))
    weights = np.stack([w, 1.0 - w], axis=-1).reshape(batch + (2,))
    gains = None
    if m == n:
        gains = np.stack([K1, K2], axis=1).reshape(batch + (2, n, n))
    return FusionResult(restore_style(x.reshape(batch + (n,)), column), P, "split-ci",
                        None, gains, out, weights=weights)


def _partial_independent_parts(est, independent):
    """``independent=`` for partial estimates: one PSD part per estimate, (n, n) and
    (m, m), with ``P_i - independent_i`` positive semidefinite."""
    if independent is None:
        return [np.zeros(P.shape) for P in est.P]
    if not isinstance(independent, (list, tuple)) or len(independent) != est.count:
        raise ValueError(
            f"with H, independent must be a sequence of {est.count} parts, one per estimate "
            "(of each estimate's own dimension)"
        )
    parts = []
    for i, (part, P) in enumerate(zip(independent, est.P)):
        m = P.shape[-1]
        part = check_psd(part, m, f"independent[{i}]")
        check_psd(P - part, m, f"P - independent[{i}] (the dependent part of estimate {i})")
        parts.append(part)
    return parts


def _split_ci_partial_core(est, independent, criterion, omega):
    """``fuse(..., method="split-ci", H=[None, H_2])``: the partial form of split CI."""
    if est.count != 2 or est.H[0] is not None:
        raise ValueError(
            "split CI with H fuses two estimates, the first of the full state: "
            "H=[None, H_2]"
        )
    P_ind = _partial_independent_parts(est, independent)
    if omega is not None:
        omega = check_weights(omega, 2, batch_shape=est.batch_shape)[..., 0]
    parts = tuple((P_ind[i], est.P[i] - P_ind[i]) for i in range(2))
    return _partial_pair(est.x[0], est.x[1], est.batch_shape, est.batch_shape, parts,
                         est.H[1], criterion, est.column, omega)


def _independent_parts(est, independent, omega_check=False):
    """The front door's ``independent=`` option: parts (..., N, n, n) with ``P - P_ind``
    positive semidefinite; None means every part dependent (CI)."""
    if independent is None:
        return np.zeros_like(est.P)
    P_ind = as_covariance_stack(independent, "independent")
    if P_ind.shape[-3:] != est.P.shape[-3:]:
        raise ValueError(
            f"independent must hold one (n, n) part per estimate, shape (..., "
            f"{est.count}, {est.dim}, {est.dim}); got shape {P_ind.shape}"
        )
    P_ind = check_psd(P_ind, est.dim, "independent")
    try:
        P_ind = np.broadcast_to(P_ind, est.P.shape)
    except ValueError:
        raise ValueError(
            f"independent has batch shape {P_ind.shape[:-3]}, which does not broadcast to "
            f"the estimates' {est.batch_shape}"
        ) from None
    check_psd(est.P - P_ind, est.dim, "P - independent (the dependent parts)")
    return P_ind


def _split_ci_core(est, independent=None, criterion="det", omega=None):
    """The ``"split-ci"`` rule on validated estimates (``fuse(..., method="split-ci")``).

    ``independent`` gives each estimate's independent part (the dependent part is
    ``P - independent``); without it every part is dependent and the rule is CI with the
    determinant criterion. ``omega`` (two estimates) fixes the weight. Partial estimates
    (``fuse(..., H=[None, H_2])``) take the partial form of :func:`split_pair`.
    """
    if isinstance(est, PartialEstimates):
        return _split_ci_partial_core(est, independent, criterion, omega)
    P_ind = _independent_parts(est, independent)
    if omega is not None:
        if est.count != 2:
            raise ValueError("omega can be given for two estimates only")
        omega = check_weights(omega, 2, batch_shape=est.batch_shape)[..., 0].reshape(-1)
    return _split_ci(est, P_ind, est.P - P_ind, criterion, omega)


REGISTRATION: dict[str, Any] = dict(
    name="split-ci",
    function=lambda xs, Ps, **options: _split_ci_core(as_estimates(xs, Ps), **options),
    core=_split_ci_core,
    summary="Split CI: bound when the independent parts (independent=) are independent",
    reference="Julier & Uhlmann 2001; Li, Nashashibi & Yang 2013",
    guarantee="bound",
    weights="(omega, 1 - omega): P_k(omega) = P_k_dep / omega_k + P_k_ind (two estimates); "
            "None for N > 2 (sequential; info['omegas'])",
    front_door=("H", "residual"),
)
"""The record of the ``"split-ci"`` rule (registered by :mod:`cifilter.rules`).

``fuse(..., method="split-ci", independent=[P1_ind, P2_ind])``: the dependent parts are
``P_k - P_k_ind``. Its ``"bound"`` holds when the independent parts are truly independent
(of each other and of the dependent parts) and the dependent parts arbitrarily
correlated; without ``independent=`` every part is dependent and the rule is CI.
"""
