"""The horizon choice on validated input, shared by the public functions and the hooks.

:func:`choose` takes validated estimates (:class:`cifilter._numerics.validation.Estimates`), a
validated :class:`~cifilter.horizon._model.Model` and a parsed criterion, runs the Riccati
recursion once, and solves the CI (:mod:`cifilter.horizon._ci`) or partial-CI
(:mod:`cifilter.horizon._pci`) problem at the horizon and at horizon 0 (the recursive
approach, for comparison). See ``docs/methods/horizon.rst``.
"""

import inspect
import numbers
from collections.abc import Sequence
from typing import Any, NamedTuple, Optional, Union

import numpy as np
from numpy.typing import ArrayLike

from .._numerics.information import lower_inverse_stack
from .._numerics.linalg import IllConditionedError
from .._numerics.validation import Estimates, as_float_array
from ..rules._partial_correlation import check_rho, effective_rho, partial_weights
from ._ci import ci_fused_information, ci_horizon_weights
from ._model import (
    at_horizon,
    broadcast_terms,
    check_steps_available,
    checked_bound,
    criterion_at,
    horizon_terms,
    propagated_bound,
)
from ._pci import information_bound, pci_horizon_delta

__all__ = ["ARGUMENT_TYPES", "Choice", "PerStep", "Problem", "as_rho", "bind_arguments",
           "choose", "documented_signature", "fused_bound", "problem_of", "solve"]


class Problem(NamedTuple):
    """Validated estimates with the inverse factors and informations the solvers share."""

    est: Estimates  # (..., N, n) means (zeros for covariances alone), covariances, factors
    L_inv: np.ndarray  # (..., N, n, n), L_i^-1
    informations: np.ndarray  # (..., N, n, n), P_i^-1 = L_i^-T L_i^-1


def problem_of(est):
    """The :class:`Problem` of validated estimates (one inversion of the factors)."""
    L_inv = lower_inverse_stack(est.L)
    return Problem(est, L_inv, L_inv.swapaxes(-1, -2) @ L_inv)


def _broadcast(problem, batch):
    est = problem.est
    if est.batch_shape == batch:
        return problem
    tail = est.P.shape[-3:]
    return Problem(
        Estimates(np.broadcast_to(est.x, batch + est.x.shape[-2:]),
                  np.broadcast_to(est.P, batch + tail), np.broadcast_to(est.L, batch + tail),
                  est.column),
        np.broadcast_to(problem.L_inv, batch + tail),
        np.broadcast_to(problem.informations, batch + tail))


def as_rho(rho, count, batch_shape):
    """Validated bounds (..., N) as partial CI uses them (eq. 24; pairs: sqrt(rho_1 rho_2))."""
    if rho is None:
        return None
    try:
        lead = np.shape(rho)[:-1]
    except ValueError:  # ragged: let the validation name it
        lead = ()
    try:
        batch_shape = np.broadcast_shapes(batch_shape, lead)
    except ValueError:
        raise ValueError(f"rho of shape {np.shape(rho)} does not broadcast against the batch "
                         f"shape {batch_shape} of the covariances") from None
    return effective_rho(check_rho(rho, count, batch_shape))


def solve(problem, terms, kind, W, rho, horizons):
    """Criterion-optimal weights (..., N) and the solver's info for the horizon of ``terms``.

    With ``rho`` (..., N) the weights are partial CI's ``delta``. A matrix found singular on
    the way becomes an IllConditionedError naming the horizon (never a NaN optimum).
    """
    batch = np.broadcast_shapes(problem.est.batch_shape, terms.P_c.shape[:-2],
                                terms.log_scale.shape, () if W is None else W.shape[:-2],
                                () if rho is None else rho.shape[:-1])
    problem = _broadcast(problem, batch)
    terms = broadcast_terms(terms, batch)
    try:
        if rho is None:
            weights, info = ci_horizon_weights(problem.est, problem.informations, terms,
                                               kind, W)
        else:
            n = terms.P_c.shape[-1]
            weight = None if kind == "det" else np.eye(n) if kind == "trace" else W
            delta, iterations, converged, gap, solver = pci_horizon_delta(
                problem.L_inv, problem.informations, terms,
                np.broadcast_to(rho, batch + rho.shape[-1:]), weight)
            weights = delta
            info = {"iterations": iterations, "converged": converged, "gap": gap,
                    "solver": solver}
    except ValueError as exc:  # IllConditionedError included: it gains the horizon
        if not isinstance(exc, IllConditionedError) and "not positive definite" not in str(exc):
            raise
        if "at horizon" in str(exc):
            raise
        shown = horizons if np.ndim(horizons) == 0 else f"in {np.asarray(horizons).tolist()}"
        raise IllConditionedError(
            f"at horizon {shown} the horizon terms are numerically singular ({exc}): the "
            "propagated bound's condition number exceeds what float64 resolves (for an "
            "unstable F it grows like the ratio of the two largest |eigenvalues| to the power "
            "2 * horizon); ask for a shorter horizon") from None
    if not np.isfinite(weights).all():
        raise ValueError("the horizon-optimal weights are not finite: the propagated bound "
                         "is not representable in float64 for this model and horizon")
    return weights, info


def fused_bound(problem, terms, weights, rho=None):
    """The propagated bound for CI weights, or partial CI's ``delta`` given ``rho``, / 2^e.

    Multiply by ``2^terms.exponent`` with :func:`cifilter.horizon._model.checked_bound`.
    """
    if rho is not None:
        return information_bound(problem.informations, terms, partial_weights(weights, rho))
    S = problem.informations + terms.Gamma[..., None, :, :]
    return propagated_bound(terms, ci_fused_information(S, weights))


class Choice(NamedTuple):
    """The horizon-optimal weights, their criterion and bound, and the recursive choice."""

    weights: np.ndarray  # (..., N)
    value: np.ndarray  # (...)
    P: np.ndarray  # (..., n, n)
    info: dict  # the solver's info
    weights_recursive: np.ndarray  # (..., N)
    value_recursive: np.ndarray  # (...)


def choose(problem, model, horizon, kind, W, rho=None):
    """Horizon-optimal weights, value and bound, and the recursive approach's for comparison.

    ``problem`` from :func:`problem_of`, ``model`` validated, ``(kind, W)`` parsed, ``rho``
    from :func:`as_rho` or None (CI). One Riccati run gives the terms at 0 and ``horizon``.
    """
    n = problem.est.dim
    check_steps_available(model, horizon)
    terms_list = horizon_terms(model, horizon, n, collect=sorted({0, horizon}))
    start, terms = terms_list[0], terms_list[-1]
    weights, info = solve(problem, terms, kind, W, rho, horizon)
    if horizon == 0:
        recursive = weights
    else:
        recursive, _ = solve(problem, start, kind, W, rho, 0)
    P_hat = fused_bound(problem, terms, weights, rho)
    where = at_horizon(horizon, np.broadcast_to(weights, P_hat.shape[:-2] + weights.shape[-1:]))
    P = checked_bound(P_hat, terms.exponent, where)
    value = criterion_at(P_hat, terms.exponent, kind, W, where)
    if horizon == 0:
        value_recursive = value
    else:
        P_recursive = fused_bound(problem, terms, recursive, rho)
        value_recursive = criterion_at(P_recursive, terms.exponent, kind, W, at_horizon(horizon))
    return Choice(weights, value, P, info, recursive, value_recursive)


# --------------------------------------------------------------------------- argument forms
def _horizon_like(value):
    """An integer or a 1-D sequence of integers (a horizon), never a criterion."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return True
    if isinstance(value, (str, bytes)) or value is None:
        return False
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):
        return False
    return array.ndim == 1 and array.size > 0 and np.issubdtype(array.dtype, np.integer)


def _pair(PA, PB):
    PA, PB = as_float_array(PA, "PA"), as_float_array(PB, "PB")
    for name, M in (("PA", PA), ("PB", PB)):
        if M.ndim < 2 or M.shape[-1] != M.shape[-2]:
            raise ValueError(f"{name} must hold square matrices (..., n, n), got shape {M.shape}")
    if PA.shape[-1] != PB.shape[-1]:
        raise ValueError(f"PA is {PA.shape[-1]}x{PA.shape[-1]} but PB is "
                         f"{PB.shape[-1]}x{PB.shape[-1]}")
    batch = np.broadcast_shapes(PA.shape[:-2], PB.shape[:-2])
    n = PA.shape[-1]
    return np.stack([np.broadcast_to(PA, batch + (n, n)), np.broadcast_to(PB, batch + (n, n))],
                    axis=-3)


def bind_arguments(function, args, kwargs, horizon, keywords):
    """``(Ps, arguments)`` of the two call forms of ``function``.

    ``function(Ps, F, Q, H, R, horizon, criterion, G, **keywords)`` or the pairwise
    ``function(PA, PB, F, Q, H, R, horizon, criterion, G, **keywords)``: the pairwise form
    is recognised by a horizon (an integer, or a 1-D sequence of integers) as the seventh
    positional argument, or by six positional arguments before a keyword ``horizon``
    (``horizon`` is the name of that argument). ``Ps`` is then ``PA`` and ``PB`` stacked.
    """
    if (len(args) >= 7 and _horizon_like(args[6])) or (len(args) == 6 and horizon in kwargs):
        Ps, rest = _pair(args[0], args[1]), args[2:]
    elif args:
        Ps, rest = args[0], args[1:]
    else:
        raise TypeError(f"{function}() needs the covariances Ps (or PA, PB) first")
    names = ("F", "Q", "H", "R", horizon, "criterion", "G")
    if len(rest) > len(names):
        raise TypeError(f"{function}() takes at most {len(names) + 2} positional arguments "
                        "(PA, PB, F, Q, H, R, horizon, criterion, G)")
    bound = dict(zip(names, rest))
    for name, value in kwargs.items():
        if name in bound:
            raise TypeError(f"{function}() got multiple values for argument {name!r}")
        if name not in names and name not in keywords:
            raise TypeError(f"{function}() got an unexpected keyword argument {name!r}")
        bound[name] = value
    missing = [name for name in names[:5] if name not in bound]
    if missing:
        raise TypeError(f"{function}() missing required argument(s) "
                        f"{', '.join(map(repr, missing))}")
    bound.setdefault("criterion", "trace")
    bound.setdefault("G", None)
    return Ps, bound


# H or R of a model: one matrix (or a number, for R) used at every step, one entry per step
# (None for a step without a measurement), or None (no measurements).
PerStep = Optional[Union[ArrayLike, Sequence[Optional[ArrayLike]]]]

# The types of the arguments of the Ps form (those of horizon_weights), for the documented
# signatures of optimal_omega and horizon_study.
ARGUMENT_TYPES: dict[str, Any] = {
    "Ps": Union[ArrayLike, Sequence[ArrayLike]], "F": ArrayLike, "Q": ArrayLike, "H": PerStep,
    "R": PerStep, "horizon": int, "horizons": Union[int, Sequence[int]],
    "criterion": Union[str, ArrayLike], "G": Optional[ArrayLike], "rho": Optional[ArrayLike],
    "limit": bool,
}


def documented_signature(horizon, keywords, returns):
    """The ``Ps`` form's signature, ``(Ps, F, Q, H, R, horizon, criterion, G, *, ...)``,
    annotated and returning ``returns``, shown by ``help``, ``inspect.signature`` and the
    documentation for the functions of :func:`bind_arguments`."""
    P = inspect.Parameter

    def parameter(name, kind, **default):
        return P(name, kind, annotation=ARGUMENT_TYPES[name], **default)

    positional = [parameter(name, P.POSITIONAL_OR_KEYWORD)
                  for name in ("Ps", "F", "Q", "H", "R", horizon)]
    positional += [parameter("criterion", P.POSITIONAL_OR_KEYWORD, default="trace"),
                   parameter("G", P.POSITIONAL_OR_KEYWORD, default=None)]
    return inspect.Signature(positional + [parameter(name, P.KEYWORD_ONLY, default=default)
                                           for name, default in keywords.items()],
                             return_annotation=returns)
