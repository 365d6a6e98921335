"""The registry of fusion rules and :func:`fuse`, the front door that dispatches to them.

:func:`fuse` validates the estimates once (shapes, finiteness, symmetry, positive
definiteness, with the Cholesky factors kept) and hands them to the rule's *core*, a
function that trusts its input; the rule's public function (for instance
:func:`cifilter.covariance_intersection`) validates and calls the same core. Options such
as ``horizon=`` are handled here for every rule whose record declares them. The built-in
rules are registered, in an explicit order, by :mod:`cifilter.rules`.
"""

import dataclasses
import inspect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np
from numpy.typing import ArrayLike

from ._numerics.validation import as_estimates, restore_style
from .result import FusionResult

__all__ = ["FusionMethod", "available_methods", "fuse", "get_method", "register_method"]

# A horizon hook: ``hook(estimates, model, steps, options) -> (core_options, info)``.
_HorizonHook = Callable[..., tuple[Mapping[str, Any], Mapping[str, Any]]]


def _option_signature(function, skip):
    """(accepted, required, any): the rule's option names after its ``skip`` leading
    arguments, the required ones, and whether it takes ``**options``; None if unknown."""
    try:
        parameters = inspect.signature(function).parameters
    except (TypeError, ValueError):  # builtins without a signature: let the call decide
        return None
    options = [
        p for p in list(parameters.values())[skip:]
        if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    ]
    required = tuple(p.name for p in options if p.default is inspect.Parameter.empty)
    var_keyword = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    return tuple(p.name for p in options), required, var_keyword


@dataclass(frozen=True)
class FusionMethod:
    """A registered fusion rule and what is known about it (see :func:`register_method`).

    The parameters are also the attributes of the record.

    Parameters
    ----------
    name : str
        Name used as ``fuse(..., method=name)``.
    function : callable
        ``function(xs, Ps, **options) -> FusionResult``, the rule's public function.
    summary : str
        One line describing the rule.
    reference : str
        The paper (author, year) or other source of the rule.
    guarantee : {"bound", "exact", "none"}
        What ``P`` is: ``"bound"`` when it bounds the true error covariance for every
        cross-covariance the rule admits (CI; partial CI given its rho), ``"exact"`` when it
        is the error covariance given the information the rule is told (optimal fusion with
        the true joint covariance), ``"none"`` when neither is guaranteed.
    truth_options : callable or None
        ``truth_options(joint, rng) -> dict``: the options the rule needs in a simulation
        where the true joint error covariance ``joint`` (..., N*n, N*n) is known. The demo
        and the benchmarks use it to run every registered rule without knowing it.
    core : callable or None
        ``core(estimates, **options) -> FusionResult`` on validated estimates (a
        :class:`cifilter._numerics.validation.Estimates`: means ``x`` (..., N, n), covariances ``P``
        (..., N, n, n), their Cholesky factors ``L`` and the caller's vector style
        ``column``); it returns ``x`` in the caller's style. :func:`fuse` calls it when
        given, so the estimates are validated once; otherwise it calls ``function``.
    horizon : callable or None
        ``horizon(estimates, model, steps, options) -> (core_options, info)`` when the rule
        can choose its weights for the bound ``steps`` filter steps after the fusion
        (``fuse(..., horizon=steps, model=...)``): the options to fuse with (the chosen
        weights) and the diagnostics stored as ``info["horizon"]``.
    weights : str
        What ``FusionResult.weights`` holds for this rule (for the documentation).
    signature : tuple or None
        The option names the rule accepts, those it requires and whether it takes any
        keyword (computed from ``core`` or ``function`` when None, once; likewise the
        attribute ``truth_takes_count``, whether ``truth_options`` takes ``count``).

    Examples
    --------
    >>> from cifilter import get_method
    >>> record = get_method("optimal")
    >>> record.guarantee, sorted(record.options_given_truth("J", rng=None))
    ('exact', ['joint'])
    >>> get_method("ci").horizon is not None, get_method("ei").horizon is None
    (True, True)
    """

    name: str
    function: Callable[..., FusionResult]
    summary: str = ""
    reference: str = ""
    guarantee: str = "none"
    truth_options: Optional[Callable[..., Mapping[str, Any]]] = None
    core: Optional[Callable[..., FusionResult]] = None
    horizon: Optional[_HorizonHook] = None
    weights: str = ""
    signature: Optional[tuple[tuple[str, ...], tuple[str, ...], bool]] = field(
        default=None, repr=False, compare=False)
    truth_takes_count: bool = field(default=False, init=False, repr=False, compare=False)

    def __post_init__(self):
        # computed once: inspect.signature is slow per call (the network simulation asks
        # for truth options at every fusion)
        if self.signature is None:
            signature = (_option_signature(self.core, 1) if self.core is not None
                         else _option_signature(self.function, 2))
            object.__setattr__(self, "signature", signature)
        takes_count = (self.truth_options is not None
                       and "count" in inspect.signature(self.truth_options).parameters)
        object.__setattr__(self, "truth_takes_count", takes_count)

    def options_given_truth(self, joint: ArrayLike, rng: Optional[np.random.Generator],
                            count: int = 2) -> dict[str, Any]:
        """Options for this rule in a simulation where the joint covariance is known.

        Parameters
        ----------
        joint : ndarray, shape (..., N*n, N*n)
            True joint error covariance of the estimates to fuse.
        rng : numpy.random.Generator
            Randomness for rules that sample.
        count : int, optional
            The number N of estimates in ``joint`` (default 2); given to the hook when it
            takes a ``count`` argument (hooks written for two estimates need not).

        Returns
        -------
        dict
            Keyword options for :func:`fuse` (empty when the rule needs none).

        Examples
        --------
        >>> from cifilter import get_method
        >>> get_method("ci").options_given_truth(joint=None, rng=None)
        {}
        """
        if self.truth_options is None:
            return {}
        if self.truth_takes_count:
            return dict(self.truth_options(joint, rng, count=count))
        return dict(self.truth_options(joint, rng))


GUARANTEES = ("bound", "exact", "none")
_REGISTRY: dict[str, FusionMethod] = {}


def register_method(name: str, function: Callable[..., FusionResult], *, summary: str = "",
                    reference: str = "", guarantee: str = "none",
                    truth_options: Optional[Callable[..., Mapping[str, Any]]] = None,
                    core: Optional[Callable[..., FusionResult]] = None,
                    horizon: Optional[_HorizonHook] = None, weights: str = "",
                    replace: bool = False) -> FusionMethod:
    """Register a fusion rule so that ``fuse(..., method=name)`` can use it.

    Parameters
    ----------
    name : str
        The method name.
    function : callable
        ``function(xs, Ps, **options) -> FusionResult``. Called by :func:`fuse` (when no
        ``core`` is given) with ``xs`` of shape (..., N, n) and ``Ps`` (..., N, n, n),
        validated copies with one batch shape.
    summary, reference : str, optional
        One-line description and source, shown by ``python -m cifilter methods``.
    guarantee : {"bound", "exact", "none"}, optional
        What the rule's covariance is (see :class:`FusionMethod`); default ``"none"``.
    truth_options : callable, optional
        ``truth_options(joint, rng) -> dict`` giving the options the rule needs when the
        true joint covariance is known (used by the demo and :mod:`cifilter.network`); a hook
        that also takes ``count`` receives the number of estimates in ``joint``.
    core : callable, optional
        ``core(estimates, **options) -> FusionResult`` on already validated estimates
        (see :class:`FusionMethod`); :func:`fuse` then calls it instead of ``function``.
    horizon : callable, optional
        The rule's support of ``fuse(..., horizon=, model=)`` (see :class:`FusionMethod`).
    weights : str, optional
        What the result's ``weights`` are for this rule (documentation).
    replace : bool, optional
        Allow replacing an existing registration (default False).

    Returns
    -------
    FusionMethod
        The registration record.

    Raises
    ------
    TypeError
        If ``name`` is not a string or ``function``, ``core``, ``horizon`` or
        ``truth_options`` is not callable, or ``horizon`` is given without ``core``.
    ValueError
        If ``name`` is empty, already registered and ``replace`` is False, or
        ``guarantee`` is not one of the three values.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import FusionResult, fuse, register_method
    >>> def first(xs, Ps):
    ...     gains = np.zeros(Ps.shape)
    ...     gains[..., 0, :, :] = np.eye(Ps.shape[-1])
    ...     return FusionResult(xs[..., 0, :], Ps[..., 0, :, :], "first", gains=gains)
    >>> _ = register_method("first", first, summary="keep the first estimate")
    >>> fuse([(np.zeros(2), np.eye(2)), (np.ones(2), np.eye(2))], method="first").x
    array([0., 0.])
    """
    if not isinstance(name, str):
        raise TypeError(f"name must be a str, got {type(name).__name__}")
    if not name:
        raise ValueError("name must not be empty")
    if not callable(function):
        raise TypeError(f"function must be callable, got {type(function).__name__}")
    if guarantee not in GUARANTEES:
        raise ValueError(f"guarantee must be one of {GUARANTEES}, got {guarantee!r}")
    for argument, value in (("truth_options", truth_options), ("core", core),
                            ("horizon", horizon)):
        if value is not None and not callable(value):
            raise TypeError(f"{argument} must be callable or None")
    if horizon is not None and core is None:
        raise TypeError("horizon= needs core=: the front door fuses with the chosen weights "
                        "through the rule's core")
    if name in _REGISTRY and not replace:
        raise ValueError(f"a fusion method named {name!r} is already registered")
    record = FusionMethod(name, function, summary, reference, guarantee, truth_options,
                          core, horizon, weights)
    _REGISTRY[name] = record
    return record


def attach_horizon(name: str, hook: _HorizonHook) -> FusionMethod:
    """Give a registered rule its horizon hook (see :class:`FusionMethod`).

    The rules sit below :mod:`cifilter.horizon`, so their records cannot name the hook that
    chooses their weights for a horizon; the horizon package attaches it when it is
    imported. The record keeps its place in the registration order.

    Parameters
    ----------
    name : str
        A registered method name whose record has a ``core``.
    hook : callable
        ``hook(estimates, model, steps, options) -> (core_options, info)``.

    Returns
    -------
    FusionMethod
        The new record.

    Raises
    ------
    ValueError
        If no rule of that name is registered.
    TypeError
        If ``hook`` is not callable or the rule has no ``core``.

    Examples
    --------
    >>> from cifilter.registry import get_method
    >>> get_method("ci").horizon.__name__
    'ci_horizon_options'
    """
    record = get_method(name)
    if not callable(hook):
        raise TypeError(f"hook must be callable, got {type(hook).__name__}")
    if record.core is None:
        raise TypeError(f"method {name!r} has no core: the front door fuses with the chosen "
                        "weights through the rule's core")
    _REGISTRY[name] = dataclasses.replace(record, horizon=hook)
    return _REGISTRY[name]


def available_methods() -> tuple[str, ...]:
    """Names of the registered fusion rules, in registration order.

    Returns
    -------
    tuple of str
        The names accepted by :func:`fuse`.

    Examples
    --------
    >>> from cifilter import available_methods
    >>> {"ci", "naive", "optimal"} <= set(available_methods())
    True
    """
    return tuple(_REGISTRY)


def get_method(name: str) -> FusionMethod:
    """The registration record of a fusion rule.

    Parameters
    ----------
    name : str
        A registered method name.

    Returns
    -------
    FusionMethod
        The record.

    Raises
    ------
    ValueError
        If no rule of that name is registered; the message lists the registered names, or
        says that none are and why (most likely a directory named ``cifilter`` without
        ``__init__.py`` on ``sys.path``, for instance in the current folder, imported as a
        namespace package in place of this one; the message gives its path).

    Examples
    --------
    >>> from cifilter import get_method
    >>> get_method("ci").guarantee
    'bound'
    """
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        if not _REGISTRY:
            raise ValueError(f"unknown fusion method {name!r}: no fusion methods are "
                             f"registered; {_why_empty()}") from None
        known = ", ".join(repr(m) for m in _REGISTRY)
        raise ValueError(
            f"unknown fusion method {name!r}; registered methods are {known}"
        ) from None


def _why_empty():
    """Why the registry is empty: most likely a directory named ``cifilter`` without an
    ``__init__.py`` (an empty folder, or one holding a clone) in the current folder or
    elsewhere on ``sys.path``, which Python imports as a namespace package instead of
    this package, so ``cifilter/__init__.py`` (which registers the built-in rules by
    importing :mod:`cifilter.rules`) never runs."""
    import sys

    package = sys.modules.get(__name__.rpartition(".")[0])
    if package is not None and getattr(package, "__file__", None) is None:
        paths = ", ".join(repr(str(p)) for p in getattr(package, "__path__", ()))
        return (f"'import cifilter' found the namespace package at {paths} (a directory "
                "named 'cifilter' without __init__.py, for instance an empty folder or one "
                "holding a clone) instead of the installed package, so cifilter/__init__.py, "
                "which registers the built-in rules, never ran. Rename or move that "
                "directory, or run from another folder")
    return ("the built-in rules are registered when the package is imported "
            "('import cifilter' runs cifilter/__init__.py, which imports cifilter.rules); "
            "this registry module was imported without it")


def _check_options(record, options):
    """Check the options against the rule's signature.

    Rejects options the rule does not accept (naming them and the accepted ones) and
    reports required options that are missing (naming them and the method), both as
    ``TypeError`` before the rule runs.
    """
    if record.signature is None:
        return
    accepted, required, var_keyword = record.signature
    missing = [name for name in required if name not in options]
    if missing:
        example = ", ".join(f"{name}=..." for name in missing)
        raise TypeError(
            f"method {record.name!r} needs the option(s) {', '.join(map(repr, missing))}: "
            f"fuse(estimates, method={record.name!r}, {example})"
        )
    if var_keyword:
        return
    unknown = [name for name in options if name not in accepted]
    if unknown:
        raise TypeError(
            f"method {record.name!r} does not accept option(s) "
            f"{', '.join(map(repr, sorted(unknown)))}; it accepts "
            f"{', '.join(map(repr, accepted)) or 'no options'}"
        )


def split_estimate(item: Any, index: int, labels: Optional[Sequence[str]] = None
                   ) -> tuple[ArrayLike, ArrayLike]:
    """``(x, P)`` of one estimate: an ``(x, P)`` pair or an object with ``.x`` and ``.P``."""
    if hasattr(item, "x") and hasattr(item, "P"):
        return item.x, item.P
    if isinstance(item, (tuple, list)) and len(item) == 2:
        return item[0], item[1]
    where = f"estimates[{index}]" if labels is None else labels[index]
    raise TypeError(
        f"{where} must be an (x, P) pair or an object with .x and .P attributes "
        f"(such as a filterpy filter), got {type(item).__name__}"
    )


def fuse(estimates: Sequence[Any], method: str = "ci", *, horizon: Optional[int] = None,
         model: Any = None, **options: Any) -> FusionResult:
    """Fuse estimates with a registered rule.

    Parameters
    ----------
    estimates : sequence
        N >= 2 estimates, each an ``(x, P)`` pair or an object with ``.x`` and ``.P``
        (a filterpy filter). ``x`` is (..., n) or (..., n, 1), ``P`` is (..., n, n); leading
        batch axes fuse many problems at once and broadcast against each other.
    method : str, optional
        A registered rule (see :func:`available_methods`); default ``"ci"``.
    horizon : int, optional
        Choose the rule's weights for the bound ``horizon`` predict/update steps of
        ``model`` after the fusion (Ajgl et al. 2014; :mod:`cifilter.horizon`), for rules
        whose record declares it (``"ci"``, and ``"pci"`` with ``rho``). The rule then fuses
        with those weights; ``info["rule"]`` is ``"horizon"``, ``info["horizon"]`` holds the
        horizon solver's diagnostics (``steps``, ``criterion``, ``value``,
        ``value_recursive``, ``weights_recursive``, ``iterations``, ``converged``, ``gap``,
        ``solver``) and ``info["converged"]``, ``info["iterations"]`` and ``info["gap"]`` are
        those of that choice. ``horizon=0`` is the rule's own optimum.
    model : mapping or object, optional
        The model of the steps after the fusion, needed with ``horizon``: a mapping or an
        object (such as a ``KalmanFilter``) with ``F`` and ``Q`` and optionally ``H``, ``R``
        (None or absent: no measurements) and ``G``; ``H`` and ``R`` may be per-step lists
        (see :func:`cifilter.horizon.propagate_bound`).
    **options
        Options of the rule, for instance ``criterion="det"`` for ``"ci"`` or ``joint=``
        for ``"optimal"``.

    Returns
    -------
    FusionResult
        The fused estimate; ``x`` comes back in the vector style of the first estimate.

    Raises
    ------
    ValueError
        Unknown method (the message lists the registered ones), fewer than two estimates,
        bad shapes, non-finite, non-symmetric or non-positive-definite covariances, an
        option out of range, ``horizon`` for a rule that does not support it or without
        ``model``, ``model`` without ``horizon``.
    TypeError
        An estimate of the wrong kind, non-numeric, boolean or complex values, an option
        the rule does not accept or a required option that is missing (for instance
        ``joint`` of ``"optimal"``).

    See Also
    --------
    covariance_intersection, optimal_fusion, naive_fusion

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import fuse
    >>> a = (np.array([1.0, 0.0]), np.diag([1.0, 4.0]))
    >>> b = (np.array([0.0, 1.0]), np.diag([4.0, 1.0]))
    >>> r = fuse([a, b], method="ci")
    >>> float(r.weights[0]), float(np.trace(r.P))
    (0.5, 3.2)

    The weights that are best for the bound after five steps of a local filter:

    >>> model = dict(F=np.array([[1.0, 1.0], [0.0, 1.0]]), Q=0.1 * np.eye(2),
    ...              H=np.array([[1.0, 0.0]]), R=np.eye(1))
    >>> r = fuse([a, b], method="ci", horizon=5, model=model)
    >>> r.info["rule"], r.info["horizon"]["steps"], bool(r.info["converged"])
    ('horizon', 5, True)
    """
    return fuse_estimates(estimates, method, options, horizon=horizon, model=model)


def fuse_estimates(estimates: Sequence[Any], method: str, options: Mapping[str, Any], *,
                   horizon: Optional[int] = None, model: Any = None,
                   labels: Optional[Sequence[str]] = None) -> FusionResult:
    """:func:`fuse` with the options as a mapping and optional labels for the messages.

    With ``labels`` (one string per estimate, e.g. ``("this filter", "other")``) messages
    say ``"other's P"``; without, ``"estimates' P[1]"``. The filter classes call this.
    """
    record = get_method(method)
    if isinstance(estimates, (str, bytes)) or not hasattr(estimates, "__len__"):
        raise TypeError(
            f"estimates must be a sequence of estimates, got {type(estimates).__name__}"
        )
    pairs = [split_estimate(item, i, labels) for i, item in enumerate(estimates)]
    if len(pairs) < 2:
        raise ValueError(f"at least 2 estimates are needed, got {len(pairs)}")
    if horizon is None and model is not None:
        raise ValueError("model= describes the steps after the fusion; give horizon= too")
    if horizon is not None and record.horizon is None:
        supporting = [name for name, r in _REGISTRY.items() if r.horizon is not None]
        raise ValueError(
            f"method {record.name!r} does not support horizon=; the methods that choose "
            f"their weights for a horizon are {', '.join(map(repr, supporting))}"
        )
    if horizon is None:  # with horizon= the rule's hook checks the options it takes
        _check_options(record, options)
    names = ("estimates' x", "estimates' P") if labels is None else ("x", "P")
    stacked = as_estimates([p[0] for p in pairs], [p[1] for p in pairs], names=names,
                           labels=labels)
    if horizon is not None:
        return _fuse_for_horizon(record, stacked, horizon, model, options)
    if record.core is not None:
        return record.core(stacked, **options)
    result = record.function(stacked.x, stacked.P, **options)
    if not isinstance(result, FusionResult):
        raise TypeError(
            f"fusion method {record.name!r} returned {type(result).__name__}, not FusionResult"
        )
    x = np.asarray(result.x)
    if x.shape[-1:] == (1,) and x.shape[:-1] == result.P.shape[:-1]:
        x = x[..., 0]  # a rule answered in column style; normalise before restyling
    return result.replace(x=restore_style(x, stacked.column))


def _fuse_for_horizon(record, estimates, steps, model, options):
    """The rule with the weights its horizon hook chose; the hook's diagnostics nested."""
    if model is None:
        raise ValueError(
            "horizon= needs the model of the steps after the fusion: "
            "fuse(..., horizon=k, model=dict(F=..., Q=..., H=..., R=...))"
        )
    core_options, diagnostics = record.horizon(estimates, model, steps, dict(options))
    result = record.core(estimates, **core_options)
    info = dict(result.info)
    info.update(rule="horizon", horizon=diagnostics)
    for key in ("iterations", "converged", "gap"):  # of the choice of the weights
        if key in diagnostics:
            info[key] = diagnostics[key]
    return result.replace(info=info)
