"""Covariance Intersection (Julier & Uhlmann 1997) for two or N estimates.

The fused estimate of CI is

    P^-1 = sum_i w_i P_i^-1,    x = P sum_i w_i P_i^-1 x_i,    w on the simplex,

(eq. (2) of Wu, Cai & Fu 2018; the unnumbered CI equations of Weng & Djurić 2012 and of
the journal version, Sec. I), and ``P`` bounds the error covariance for every
cross-covariance of the inputs. The weights are chosen by minimising a criterion of
``P`` (trace, determinant or ``trace(W P)``) or by a fast non-iterative rule.
"""

from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._kernels import dispatch as kernels
from .._numerics.alignment import PartialEstimates, aligned_pair, pair_step
from .._numerics.criteria import (
    criterion_report,
    gap_converged,
    parse_criterion,
    parsed_or_none,
)
from .._numerics.information import weighted_fusion
from .._numerics.validation import as_covariances, as_estimates, check_weights, restore_style
from ..result import FusionResult, owned_result
from ._ci_lean import lean_pair
from ._ci_weights import FAST_OMEGA_RULES, optimal_weights
from ._generalised_ci import generalised_ci, partial_pair_route

__all__ = ["FAST_OMEGA_RULES", "ci_weights", "covariance_intersection"]


def ci_weights(Ps: ArrayLike, criterion: Union[str, ArrayLike] = "trace", *,
               method: str = "auto") -> tuple[NDArray[np.float64], dict[str, Any]]:
    """Criterion-optimal Covariance Intersection weights.

    Parameters
    ----------
    Ps : sequence of array_like or array_like, shape (..., N, n, n)
        Covariances of the N >= 2 estimates.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise: ``trace(P)``, ``det(P)`` or ``trace(W P)`` for a positive
        semidefinite weight matrix ``W``.
    method : {"auto", "diagonalise", "simplex"}, optional
        ``"diagonalise"`` (two estimates only) reduces the problem to one variable by a
        simultaneous diagonalisation of P_1 and P_2; ``"simplex"`` is the active-set
        Newton method for any N; ``"auto"`` picks the first for N = 2.

    Returns
    -------
    omega : ndarray, shape (..., N)
        The weights, on the simplex; optima on the boundary are exact.
    info : dict
        ``iterations``, ``converged`` (optimal to the precision the inputs allow: the
        certified gap at most ``max(1e-9, 2 * gap_floor)``), ``gap``, ``gap_floor`` per
        problem, ``solver``.

    Raises
    ------
    ValueError
        Bad covariances or criterion, or ``method="diagonalise"`` with N != 2.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import ci_weights
    >>> omega, info = ci_weights([np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])],
    ...                          criterion="det")
    >>> omega.round(6).tolist(), bool(info["converged"])
    ([0.6, 0.4], True)
    """
    est = as_covariances(Ps)
    kind, W = parse_criterion(criterion, est.dim)
    if method not in ("auto", "diagonalise", "simplex"):
        raise ValueError(f"method must be 'auto', 'diagonalise' or 'simplex', got {method!r}")
    if method == "diagonalise" and est.count != 2:
        raise ValueError("method='diagonalise' needs exactly two estimates")
    omega, info, _ = optimal_weights(est, kind, W, method)
    return omega, info


# --------------------------------------------------------------------------- public function
def covariance_intersection(xs: ArrayLike, Ps: ArrayLike,
                            criterion: Union[str, ArrayLike] = "trace",
                            omega: Union[float, str, ArrayLike, None] = None) -> FusionResult:
    """Covariance Intersection of two or more estimates with unknown cross-correlation.

    Computes ``P^-1 = sum_i w_i P_i^-1`` and ``x = P sum_i w_i P_i^-1 x_i`` with weights
    ``w`` on the probability simplex (Julier & Uhlmann 1997; eq. (2) of Wu, Cai & Fu 2018).
    ``P`` bounds the covariance of the fused error for every admissible cross-covariance.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array of shape (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n). Symmetric
        positive definite.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What the optimal weights minimise: ``trace(P)`` (default, the mean square error
        bound), ``det(P)`` (the volume of the bound), or ``trace(W P)`` for a positive
        semidefinite weight matrix ``W`` (e.g. to weight position over velocity).
    omega : None, float, array_like or str, optional
        ``None`` (default) minimises the criterion exactly over the simplex; the problem
        is convex and the optimum is found to 1e-12 in omega, on the boundary exactly.
        A float gives the weights ``(omega, 1 - omega)`` of two estimates; an array
        (..., N) gives all weights. A string selects a fast non-iterative rule:
        ``"fast"`` (Niehsen 2002, w_i proportional to 1/trace(P_i), eq. (2) of Weng &
        Djurić, journal version), ``"improved-fast"`` (Franken & Hupper 2005) or
        ``"det-ratio"`` (eq. (7) of Weng & Djurić 2012, w_i proportional to 1/det(P_i)).

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``omega`` (..., N), ``gains`` (..., N, n, n) with ``K_i = w_i P P_i^-1`` and
        ``info`` with ``criterion``, ``value`` (criterion at the result; for ``"det"``
        also ``log_value``, which does not overflow), ``rule`` (``"optimal"``,
        ``"fixed"`` or the fast rule's name), and for optimal weights ``iterations``,
        ``converged`` (the certified gap is at most ``max(1e-9, 2 * gap_floor)``, see
        ``docs/conventions.rst``), ``gap`` (a certified bound on
        the excess of the criterion over its minimum: relative for the trace criteria, in
        log det for ``"det"``) and ``solver``.

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, weights off the simplex, an unknown criterion
        or fast rule.
    IllConditionedError
        (a ValueError) The fused information or the fused covariance is numerically
        singular; only for inputs beyond the conditioning contract (condition numbers
        above 1e12).
    TypeError
        Non-numeric input.

    See Also
    --------
    ci_weights : the optimal weights alone.
    fuse : the same rule through the registry (``method="ci"``).

    Notes
    -----
    ``P`` is returned as the bound of the returned gains, ``sum_i K_i P_i K_i^T / w_i``
    (equal to ``(sum_i w_i P_i^-1)^-1`` in exact arithmetic), formed from Cholesky factors
    without squaring a condition number: for input condition numbers up to 1e12 it is
    finite, symmetric, positive definite and dominates the error covariance of the
    returned gains for every cross-covariance, up to rounding (the conditioning contract).
    For two estimates the optimal weight is proposed by a simultaneous diagonalisation of
    ``P_1`` and ``P_2`` that turns the criterion into a sum of scalar terms (one Newton
    iteration costs O(n) per problem) and certified by its gap; problems it does not
    certify are solved again from the Cholesky factors. For N > 2 an active-set Newton
    method on the simplex is used. Both stop at exact boundary optima (``omega = 0`` or
    ``1``). Derivations: ``docs/methods/ci.rst``, "Numerical formulation".

    References
    ----------
    .. [1] S. J. Julier and J. K. Uhlmann, "A non-divergent estimation algorithm in the
       presence of unknown correlations", ACC 1997.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 2018, eq. (2) and Example 2.
    .. [3] W. Niehsen, "Information fusion based on fast covariance intersection
       filtering", FUSION 2002.
    .. [4] D. Franken and A. Hupper, "Improved fast covariance intersection for
       distributed data fusion", FUSION 2005.
    .. [5] Z. Weng and P. M. Djurić, "A Bayesian approach to covariance estimation and
       data fusion", EUSIPCO 2012, eq. (7).

    Examples
    --------
    Example 2 of Wu, Cai & Fu (2018):

    >>> import numpy as np
    >>> from cifilter import covariance_intersection
    >>> r = covariance_intersection([np.zeros(2), np.zeros(2)],
    ...                             [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    >>> float(r.omega[0]), float(np.trace(r.P))
    (0.5, 3.2)
    >>> np.diag(r.gains[0]).round(6).tolist()
    [0.8, 0.2]
    """
    if omega is None:  # the routes of the common calls, as fuse() takes them
        if (isinstance(xs, (list, tuple)) and isinstance(Ps, (list, tuple)) and len(xs) == 2
                and len(Ps) == 2):
            fast = _fuse_pair(((xs[0], Ps[0]), (xs[1], Ps[1])),
                              {"criterion": criterion})
        else:
            fast = _checked_pairs(xs, Ps, criterion)
        if fast is not None:
            return fast
    est = as_estimates(xs, Ps)
    return _covariance_intersection(est, criterion, omega)


def _checked_pairs(xs, Ps, criterion):
    """Optimal CI of a batch of pairs given as float64 arrays ``xs`` (..., 2, n) or
    (..., 2, n, 1) and ``Ps`` (..., 2, n, n), with the validation folded into the kernel's
    pass (:func:`cifilter._kernels.dispatch.pair_checked`); None where the usual route
    runs (the numpy backend, other input, any item that fails a check: the validation then
    raises its error). The result is the usual route's under the numba backend up to the
    rounding of the Cholesky factors (the kernel's own here, LAPACK's there)."""
    if not (type(xs) is np.ndarray and type(Ps) is np.ndarray and Ps.dtype.char == "d"
            and xs.dtype.char == "d"):
        return None
    shape = Ps.shape
    if len(shape) < 4 or shape[-3] != 2 or shape[-1] != shape[-2] or Ps.size == 0:
        return None
    if xs.shape == shape[:-1]:
        column = False
    elif xs.shape == shape[:-1] + (1,):
        column = True
    else:
        return None
    parsed = parsed_or_none(criterion, shape[-1])
    if parsed is None:
        return None
    kind, W = parsed

    def numpy_path(sub, sub_W):
        return optimal_weights(sub, kind, sub_W, compiled=False)

    solved = kernels.pair_checked(xs, Ps, column, kind, W, numpy_path)
    if solved is None:
        return None
    weights, solver_info, (x, P, gains), report = solved
    info = {"criterion": kind, "rule": "optimal"}
    info.update(solver_info)
    info.update(report)
    return FusionResult(restore_style(x, column), P, "ci", weights, gains, info)


def _covariance_intersection(est, criterion="trace", omega=None):
    """The ``"ci"`` rule on validated estimates (the core of :func:`covariance_intersection`).

    Estimates of parts of the state (``fuse(..., H=...)``, validated as
    :class:`~cifilter._numerics.alignment.PartialEstimates`) take generalised CI
    (:func:`cifilter.rules._generalised_ci.generalised_ci`, ``docs/methods/partial_state.rst``).
    """
    kind, W = parse_criterion(criterion, est.dim)
    if isinstance(est, PartialEstimates):
        return generalised_ci(est, kind, W, omega, tuple(FAST_OMEGA_RULES))
    info = {"criterion": kind}
    fused = report = None
    if omega is None:
        weights, solver_info, fused, report = optimal_weights(est, kind, W, report=True)
        info.update(rule="optimal", **solver_info)
    elif isinstance(omega, str):
        if omega not in FAST_OMEGA_RULES:
            raise ValueError(
                f"omega must be None, weights or one of {', '.join(map(repr, FAST_OMEGA_RULES))}; "
                f"got {omega!r}"
            )
        weights = FAST_OMEGA_RULES[omega](est)
        info["rule"] = omega
    else:
        weights = check_weights(omega, est.count, batch_shape=est.batch_shape)
        info["rule"] = "fixed"
    if fused is None:
        compiled = kernels.weighted(est, weights, kind, W, weighted_fusion)
        if compiled is None:
            assembled = weighted_fusion(est.x, est.L, weights)
            fused = (assembled.x, assembled.P, assembled.gains)
        else:
            fused, report = compiled
    x, P, gains = fused
    info.update(criterion_report(P, kind, W) if report is None else report)
    return FusionResult(restore_style(x, est.column), P, "ci", weights, gains, info)


def _fuse_pair(pairs, options, H=None, times=None):
    """The ``"ci"`` rule's route for two single estimates (the record's ``pair``): one
    compiled call from the raw arrays to the result, or None (the usual route).

    Taken for two ``(x, P)`` pairs of float64 arrays, ``P`` (n, n) and ``x`` (n,) or
    (n, 1) alike, with no option but ``criterion`` (optimal weights): one compiled call
    when the backend runs the kernels for single calls
    (:func:`cifilter._kernels.dispatch.single_ready`), else LAPACK directly
    (:func:`cifilter.rules._ci_lean.lean_pair`: omega and its certificate bit for bit the
    numpy path's, ``x`` and ``P`` to rounding); pairs of batches of one shape (..., n, n)
    take :func:`_checked_pairs`.
    ``H`` (checked observation matrices) sends the pair to generalised CI's route;
    ``times`` (``(times, at, motion, labels)`` of the front door's ``times=``) first brings
    the pair to one time the short way and adds the front door's ``at`` and
    ``retrodiction_alpha`` to ``info``: where single calls run on the kernels and one
    estimate moves by whole steps of a filter (``lag=``), brought and fused in the same
    compiled call (:func:`cifilter._numerics.alignment.pair_step`'s matrices,
    :func:`cifilter._kernels.dispatch.shifted_pair_single`), else brought by
    :func:`cifilter._numerics.alignment.aligned_pair` and fused as above.
    The kernel checks the input as the validation does; any failed check, and any pair the
    kernel hands back, returns None, and the usual route validates (raising its error) and
    solves. The result is the usual route's under the numba backend (the same kernel, the
    same certificate and ``info``), up to the rounding of the Cholesky factors (the
    kernel's own here, LAPACK's there).
    """
    if options:
        if len(options) != 1 or "criterion" not in options:
            return None
        criterion = options["criterion"]
    else:
        criterion = "trace"
    if H is not None:  # kf.fuse(other, H=H): generalised CI's compiled pair
        return partial_pair_route(pairs, H, criterion)
    (x1, P1), (x2, P2) = pairs
    if not (type(P1) is np.ndarray and type(P2) is np.ndarray and type(x1) is np.ndarray
            and type(x2) is np.ndarray):
        return None
    shape, x_shape = P1.shape, x1.shape
    if (len(shape) < 2 or shape[-1] != shape[-2] or P2.shape != shape
            or x2.shape != x_shape or P1.dtype.char != "d" or P2.dtype.char != "d"
            or x1.dtype.char != "d" or x2.dtype.char != "d"):
        return None
    if len(shape) > 2:  # batches: the batched route, on the stacked arrays
        if times is not None:
            return None
        if x_shape == shape[:-1]:
            xs = np.stack((x1, x2), axis=-2)
        elif x_shape == shape[:-1] + (1,):
            xs = np.stack((x1, x2), axis=-3)
        else:
            return None
        return _checked_pairs(xs, np.stack((P1, P2), axis=-3), criterion)
    n = shape[0]
    if x_shape == (n,):
        column = False
    elif x_shape == (n, 1):
        column = True
    else:
        return None
    if n == 0:
        return None
    parsed = parsed_or_none(criterion, n)
    if parsed is None or (parsed[1] is not None and parsed[1].ndim != 2):
        return None  # (a batch of criterion matrices makes a batch of problems)
    kind, W = parsed
    compiled = kernels.single_ready(n)
    extra = None
    step = None
    if times is not None:  # kf.fuse(other, lag=k): (after the options: no wasted shift)
        if compiled:  # brought and fused in one compiled call where the step allows
            step = pair_step(times[0], times[1], times[2], n)
        if step is None:
            aligned = aligned_pair(pairs, *times)
            if aligned is None:
                return None
            ((x1, P1), (x2, P2)), at, alpha = aligned
            extra = {"at": at, "retrodiction_alpha": alpha}
    if not compiled:
        # the numpy backend (and "auto" before the kernels are there): one pair through
        # LAPACK directly (rules/_ci_lean.py), or the usual route where it declines
        lean = lean_pair(x1.reshape(n), np.ascontiguousarray(P1), x2.reshape(n),
                         np.ascontiguousarray(P2), kind, W, gains=True)
        if lean is None:
            return None
        x, P, weights, info, gains = lean
        if extra:
            info.update(_owned_extra(extra))
        return owned_result(x[:, None] if column else x, P, "ci", weights, gains, info)
    if step is None:
        solved = kernels.pair_single(x1, P1, x2, P2, kind, W)
    else:
        moved, M, N, backward, at = step
        solved = kernels.shifted_pair_single(x1, P1, x2, P2, moved, M, N, backward, kind, W)
        if solved is not None:  # (floats and None: nothing to freeze)
            alpha = (solved[4], None) if moved == 0 else (None, solved[4])
            extra = {"at": at, "retrodiction_alpha": alpha}
    if solved is None:
        return None
    scalars, x, P, gains = solved[:4]
    omega = float(scalars[0])
    gap, floor, computed = float(scalars[2]), float(scalars[3]), float(scalars[4])
    info = {"criterion": kind, "rule": "optimal", "iterations": np.array(int(scalars[1])),
            "converged": np.array(gap_converged(gap, floor, computed)),
            "gap": np.array(gap), "gap_floor": np.array(floor), "solver": "diagonalise",
            "value": np.array(scalars[5])}
    if kind == "det":
        info["log_value"] = np.array(scalars[6])
    if extra:
        info.update(extra if step is not None else _owned_extra(extra))
    return owned_result(x[:, None] if column else x, P, "ci", np.array([omega, 1.0 - omega]),
                        gains, info)


def _owned_extra(extra):
    """The front door's additions to a route's ``info`` (``at``, ``retrodiction_alpha``:
    numbers, None and the alignment's fresh arrays), frozen for :func:`owned_result`."""
    for value in extra.values():
        for item in (value if type(value) is tuple else (value,)):
            if type(item) is np.ndarray:
                item.setflags(write=False)
    return extra


REGISTRATION: dict[str, Any] = dict(
    name="ci",
    function=covariance_intersection,
    core=_covariance_intersection,
    summary="Covariance Intersection; omega minimises trace/det of the bound, or a fast rule",
    reference="Julier & Uhlmann 1997; Niehsen 2002; Franken & Hupper 2005",
    guarantee="bound",
    weights="omega, on the simplex: P^-1 = sum_i omega_i P_i^-1",
    front_door=("H", "residual", "times"),
    pair=_fuse_pair,
)
"""The record of the ``"ci"`` rule (registered by :mod:`cifilter.rules`).

Its ``front_door`` options: ``H=`` (generalised CI, ``docs/methods/partial_state.rst``),
``residual=``/``add=`` and ``times=``/``at=``/``motion=`` (``docs/methods/time.rst``): CI's
bound holds for any correlation, so it holds for retrodicted bounds too.
"""
