"""The ``horizon`` hooks of the ``"ci"`` and ``"pci"`` rules for :func:`cifilter.fuse`.

The front door validates the estimates once and hands them here with the model; the
hooks validate the model and the criterion once and run the core shared with
:func:`~cifilter.horizon.horizon_weights`. See ``docs/methods/horizon.rst``.
"""

from collections.abc import Mapping
from typing import Any

from .._numerics.criteria import parse_criterion
from .._numerics.validation import Estimates, check_int
from ._core import as_rho, choose, problem_of
from ._model import as_model, model_parts

__all__ = ["ci_horizon_options", "pci_horizon_options"]


def _choose(estimates, model, steps, options, fixed, accepted, rho):
    if fixed in options:
        raise ValueError(f"{fixed}= fixes the weights and horizon= chooses them; give one")
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise TypeError(f"horizon= accepts the option(s) "
                        f"{', '.join(map(repr, sorted(accepted)))}, got "
                        f"{', '.join(map(repr, unknown))}")
    steps = check_int(steps, "horizon", low=0)
    F, Q, H, R, G = model_parts(model)
    criterion = options.get("criterion", "trace")
    kind, W = parse_criterion(criterion, estimates.dim)
    model = as_model(F, Q, H, R, G, estimates.dim)
    rho = as_rho(rho, estimates.count, estimates.batch_shape)
    choice = choose(problem_of(estimates), model, steps, kind, W, rho)
    diagnostics = {
        "steps": steps,
        "criterion": kind,
        "value": choice.value,
        "value_recursive": choice.value_recursive,
        "weights_recursive": choice.weights_recursive,
        "iterations": choice.info["iterations"],
        "converged": choice.info["converged"],
        "gap": choice.info["gap"],
        "solver": choice.info["solver"],
    }
    return choice.weights, criterion, diagnostics


def ci_horizon_options(estimates: Estimates, model: Any, steps: int,
                       options: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``"ci"`` rule's support of ``fuse(..., horizon=steps, model=model)``.

    Parameters
    ----------
    estimates : cifilter._numerics.validation.Estimates
        The validated estimates (covariances and their Cholesky factors are used as they
        are).
    model : mapping or object
        ``F``, ``Q`` and optionally ``H``, ``R``, ``G`` of the steps after the fusion.
    steps : int
        The horizon.
    options : dict
        The rule's options; only ``criterion`` is accepted (``omega`` fixes the weights).

    Returns
    -------
    core_options : dict
        ``{"criterion": ..., "omega": w}`` with the horizon-optimal weights.
    diagnostics : dict
        ``steps``, ``criterion``, ``value``, ``value_recursive``, ``weights_recursive``,
        ``iterations``, ``converged``, ``gap`` and ``solver`` (stored as
        ``info["horizon"]``).

    Raises
    ------
    ValueError
        ``omega`` given, a bad model, criterion or horizon, or an error of
        :func:`~cifilter.horizon.horizon_weights`.
    TypeError
        An option other than ``criterion``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import fuse
    >>> model = dict(F=np.eye(2), Q=0.0, H=np.eye(2), R=np.diag([1.0, 2.0]))
    >>> r = fuse([(np.zeros(2), np.diag([1.0, 2.0])), (np.ones(2), np.diag([2.0, 1.0]))],
    ...          method="ci", horizon=1, model=model)
    >>> r.omega.round(4).tolist(), r.info["horizon"]["steps"]
    ([0.0, 1.0], 1)
    """
    omega, criterion, diagnostics = _choose(
        estimates, model, steps, options, "omega", {"criterion"}, None)
    return {"criterion": criterion, "omega": omega}, diagnostics


def pci_horizon_options(estimates: Estimates, model: Any, steps: int,
                        options: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``"pci"`` rule's support of ``fuse(..., horizon=steps, model=model)``.

    Parameters
    ----------
    estimates : cifilter._numerics.validation.Estimates
        The validated estimates.
    model : mapping or object
        ``F``, ``Q`` and optionally ``H``, ``R``, ``G`` of the steps after the fusion.
    steps : int
        The horizon.
    options : dict
        The rule's options: ``rho`` (required) and ``criterion`` (``delta`` fixes the
        weights).

    Returns
    -------
    core_options : dict
        ``{"rho": rho, "delta": d}`` with the horizon-optimal ``delta``.
    diagnostics : dict
        As for :func:`ci_horizon_options`.

    Raises
    ------
    ValueError
        No ``rho``, ``delta`` given, or as :func:`ci_horizon_options`.
    TypeError
        An option other than ``rho`` and ``criterion``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import fuse
    >>> model = dict(F=np.eye(2), Q=0.0, H=np.eye(2), R=np.diag([1.0, 2.0]))
    >>> r = fuse([(np.zeros(2), np.diag([1.0, 2.0])), (np.ones(2), np.diag([2.0, 1.0]))],
    ...          method="pci", rho=0.3, horizon=1, model=model)
    >>> r.info["rule"], bool(r.info["converged"])
    ('horizon', True)
    """
    rho = options.get("rho")
    if rho is None:
        raise ValueError("the 'pci' rule needs a correlation coefficient bound: "
                         "fuse(..., method='pci', rho=..., horizon=...)")
    delta, _, diagnostics = _choose(
        estimates, model, steps, options, "delta", {"criterion", "rho"}, rho)
    return {"rho": rho, "delta": delta}, diagnostics
