"""Inverse Covariance Intersection (Noack, Sijs, Reinhardt & Hanebeck 2017).

ICI fuses two estimates whose errors are correlated through *common information* (each
estimate's information is an independent part of its own plus an unknown shared part) as

    P^-1 = Pa^-1 + Pb^-1 - Gamma^-1,   Gamma = omega Pa + (1 - omega) Pb,
    Ka = P (Pa^-1 - omega Gamma^-1),   Kb = P (Pb^-1 - (1 - omega) Gamma^-1),

and ``P`` bounds the error covariance for every common information the two estimates can
share. It is not a bound for arbitrary correlation (that is what Covariance Intersection
gives). More than two estimates are fused sequentially. Derivations and the numerical
formulation: ``docs/methods/ici.rst``.
"""

from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.criteria import criterion_report, gap_converged, parse_criterion
from .._numerics.linalg import cholesky
from .._numerics.validation import as_estimates, check_weights, restore_style
from ..result import FusionResult
from ._inverse_ci import (
    inverse_ci_fusion,
    inverse_ci_pair,
    optimal_inverse_omega,
)

__all__ = ["inverse_covariance_intersection"]


def inverse_covariance_intersection(xs: ArrayLike, Ps: ArrayLike,
                                    criterion: Union[str, ArrayLike] = "trace",
                                    omega: Union[float, ArrayLike, None] = None
                                    ) -> FusionResult:
    """Inverse Covariance Intersection of estimates that share unknown common information.

    For two estimates (Noack, Sijs, Reinhardt & Hanebeck 2017, the ICI equations of
    Sec. 4, also on bennoack.net/ICI):

        P^-1 = Pa^-1 + Pb^-1 - (omega Pa + (1 - omega) Pb)^-1,
        x = Ka xa + Kb xb,   Ka = P (Pa^-1 - omega Gamma^-1),
        Kb = P (Pb^-1 - (1 - omega) Gamma^-1),   Gamma = omega Pa + (1 - omega) Pb.

    ``P`` bounds the fused error covariance under the *common-information model*: the
    estimates' information matrices are ``Pa^-1 = Aa + C`` and ``Pb^-1 = Ab + C`` with
    independent exclusive parts ``Aa, Ab >= 0`` and an unknown common part ``C >= 0``
    (cross-covariance ``Pab = Pa C Pb``). Under arbitrary correlation it is *not* a bound
    (use :func:`covariance_intersection`). N > 2 estimates are fused sequentially, in the
    given order, each step with its own optimal omega; see Notes.

    Parameters
    ----------
    xs : sequence of array_like or array_like
        N >= 2 means, each (n,) or (n, 1), optionally with leading batch axes; or one
        array of shape (..., N, n).
    Ps : sequence of array_like or array_like
        Their covariances, (..., n, n) each, or one array (..., N, n, n). Symmetric
        positive definite.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What omega minimises: ``trace(P)`` (default), ``det(P)`` or ``trace(W P)`` for a
        positive semidefinite weight matrix ``W``. All three are convex in omega.
    omega : None, float or array_like, optional
        ``None`` (default): the criterion-optimal omega, found to 1e-13 and certified
        (exactly 0 or 1 at a boundary optimum). A float (two estimates) fixes omega; an
        array (..., 2) gives ``(omega, 1 - omega)`` per problem. Fixed weights need N = 2.

    Returns
    -------
    FusionResult
        ``x`` (..., n) or (..., n, 1) in the style of the first mean, ``P`` (..., n, n),
        ``gains`` (..., N, n, n) with ``x = sum_i K_i x_i``, ``weights`` (..., 2) equal to
        ``(omega, 1 - omega)`` for two estimates (None for N > 2), ``omega`` None (the
        field is CI's) and ``info`` with ``criterion``, ``value`` (``log_value`` for
        det), ``rule`` (``"optimal"``, ``"fixed"``, or ``"sequential"`` for N > 2) and,
        for optimal weights, ``iterations``, ``gap`` (a certified bound of the excess of
        the criterion over its minimum, the rounding of the slope included),
        ``gap_floor`` (the part of it due to rounding) and ``converged`` (optimal to the
        precision the inputs allow: ``gap <= max(1e-9, 2 gap_floor)``, see
        ``docs/conventions.rst``); for N > 2 also ``omegas`` (..., N - 1), the omega of
        each step (the gap and floor are those of the worst step, converged that of
        every step).

    Raises
    ------
    ValueError
        Fewer than two estimates, mismatched shapes, non-finite values, covariances that
        are not symmetric positive definite, an unknown criterion, omega off [0, 1] or
        given for N > 2.
    IllConditionedError
        (a ValueError) The fused information or covariance is numerically singular.
    TypeError
        Non-numeric input.

    See Also
    --------
    covariance_intersection : the bound for arbitrary correlation.
    fuse : the same rule as ``method="ici"``.

    Notes
    -----
    The returned ``P`` is the common-information bound of the *returned gains*,
    ``Ka Pa Ka^T + Kb Pb Kb^T + t Ka Pa Pb^-1 Pa Ka^T + Kb Pb Pa^-1 Pb Kb^T / t`` with
    ``t = omega / (1 - omega)``, which equals the ICI equation above in exact arithmetic
    and is assembled from factors without squaring a condition number (ICI as the
    information fusion of the inflated covariances ``Ya = (1 - omega) Pa + omega Pa Pb^-1
    Pa`` and ``Yb = omega Pb + (1 - omega) Pb Pa^-1 Pb`` with weights ``(1 - omega,
    omega)``). Omega is found by a safeguarded Newton iteration, in the simultaneously
    diagonalised form where that is accurate and from the factors elsewhere, and
    certified by the convexity gap. Derivation: ``docs/methods/ici.rst``.

    *N > 2.* The fused estimate of a and b and a third estimate c are not in the
    common-information model with each other, so the sequential result carries no proved
    bound, and it depends on the order of the estimates. We did not find a batch form of
    ICI for N estimates whose conservativeness is established (see the documentation).

    References
    ----------
    .. [1] B. Noack, J. Sijs, M. Reinhardt and U. D. Hanebeck, "Decentralized data fusion
       with inverse covariance intersection", Automatica 79, 2017.
    .. [2] B. Noack, "Inverse Covariance Intersection", bennoack.net/ICI.

    Examples
    --------
    The estimates of Example 2 of Wu, Cai & Fu (2018): ICI's trace-optimal omega is 1/2,
    and its bound ``diag(20/17, 20/17)`` is tighter than CI's ``diag(1.6, 1.6)``:

    >>> import numpy as np
    >>> from cifilter import inverse_covariance_intersection
    >>> r = inverse_covariance_intersection([np.zeros(2), np.zeros(2)],
    ...                                     [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    >>> round(float(r.weights[0]), 9), np.diag(r.P).round(9).tolist()
    (0.5, [1.176470588, 1.176470588])
    >>> bool(r.info["converged"])
    True
    """
    est = as_estimates(xs, Ps)
    return _inverse_covariance_intersection(est, criterion, omega)


def _pair_result(x, P, L, kind, W, omega):
    """ICI of the pairs ``x`` (..., 2, n): ``(x, P, gains, omega, info)``."""
    batch, n = x.shape[:-2], x.shape[-1]
    pair = inverse_ci_pair(x, P, L)
    info = {}
    if omega is None:
        Wf = None if W is None else np.broadcast_to(W, batch + (n, n)).reshape(-1, n, n)
        w, iterations, cert = optimal_inverse_omega(pair, kind, Wf)
        info.update(rule="optimal", iterations=iterations.reshape(batch),
                    gap=cert.gap.reshape(batch), gap_floor=cert.floor.reshape(batch),
                    converged=gap_converged(*cert).reshape(batch))
    else:
        w = np.broadcast_to(omega, batch).reshape(-1)
        info["rule"] = "fixed"
    fused_x, fused_P, gains = inverse_ci_fusion(pair, w)
    return (fused_x.reshape(batch + (n,)), fused_P.reshape(batch + (n, n)),
            gains.reshape(batch + (2, n, n)), w.reshape(batch), info)


def _inverse_covariance_intersection(est, criterion="trace", omega=None):
    """The ``"ici"`` rule on validated estimates (the core of the public function)."""
    kind, W = parse_criterion(criterion, est.dim)
    if omega is not None:
        if est.count != 2:
            raise ValueError(
                f"omega can be given for two estimates only (ICI fuses N = {est.count} "
                "estimates sequentially, each step with its optimal omega)"
            )
        omega = check_weights(omega, 2, batch_shape=est.batch_shape)[..., 0]
    x, P, gains, w, info = _pair_result(est.x[..., :2, :], est.P[..., :2, :, :],
                                        est.L[..., :2, :, :], kind, W, omega)
    if est.count == 2:
        weights = np.stack([w, 1.0 - w], axis=-1)
    else:  # sequential: the fused estimate, then the next one
        omegas, steps = [w], [info]
        for k in range(2, est.count):
            pair_x = np.stack([x, est.x[..., k, :]], axis=-2)
            pair_P = np.stack([P, est.P[..., k, :, :]], axis=-3)
            L_fused = cholesky(P, "the sequentially fused covariance")
            pair_L = np.stack([L_fused, est.L[..., k, :, :]], axis=-3)
            x, P, step_gains, w, step_info = _pair_result(pair_x, pair_P, pair_L, kind, W,
                                                          None)
            gains = np.concatenate([step_gains[..., :1, :, :] @ gains,
                                    step_gains[..., 1:, :, :]], axis=-3)
            omegas.append(w)
            steps.append(step_info)
        weights = None
        info = {
            "rule": "sequential",
            "omegas": np.stack(omegas, axis=-1),
            "iterations": sum(s["iterations"] for s in steps),
            "gap": np.max([s["gap"] for s in steps], axis=0),
            "gap_floor": np.max([s["gap_floor"] for s in steps], axis=0),
            "converged": np.logical_and.reduce([s["converged"] for s in steps]),
        }
    info["criterion"] = kind
    info.update(criterion_report(P, kind, W))
    return FusionResult(restore_style(x, est.column), P, "ici", None, gains, info,
                        weights=weights)


REGISTRATION: dict[str, Any] = dict(
    name="ici",
    function=inverse_covariance_intersection,
    core=_inverse_covariance_intersection,
    summary="Inverse CI: bound when the correlation is unknown common information",
    reference="Noack, Sijs, Reinhardt & Hanebeck 2017 (Automatica 79)",
    guarantee="bound",
    weights="(omega, 1 - omega) with Gamma = omega Pa + (1 - omega) Pb (two estimates); "
            "None for N > 2 (sequential; info['omegas'])",
)
"""The record of the ``"ici"`` rule (registered by :mod:`cifilter.rules`).

Its ``"bound"`` holds under the common-information model only (each estimate's
information is an independent part plus an unknown shared part, ``Pab = Pa C Pb`` with
``0 <= C <= Pa^-1, Pb^-1``), for two estimates; not for arbitrary correlation, and not
proved for the sequential fusion of N > 2 estimates.
"""
