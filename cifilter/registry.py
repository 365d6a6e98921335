"""The registry of fusion rules and :func:`fuse`, the front door that dispatches to them.

:func:`fuse` validates the estimates once (shapes, finiteness, symmetry, positive
definiteness, with the Cholesky factors kept) and hands them to the rule's *core*, a
function that trusts its input; the rule's public function (for instance
:func:`cifilter.covariance_intersection`) validates and calls the same core. Options such
as ``horizon=`` are handled here for every rule whose record declares them. The built-in
rules are registered, in an explicit order, by :mod:`cifilter.rules`.

The front door also brings the estimates to one state space and one time before a rule
runs, for the rules whose record declares it (``front_door``): ``H=`` (estimates of parts
``H_i x`` of the state), ``residual=``/``add=`` (non-Euclidean states, fused as residuals
relative to the first estimate) and ``times=``/``at=``/``motion=`` (estimates of other
times, predicted or retrodicted to ``at``); see ``docs/methods/partial_state.rst`` and
``docs/methods/time.rst``.
"""

import dataclasses
import inspect
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np
from numpy.typing import ArrayLike

from ._numerics.alignment import (
    PartialEstimates,
    added_to_reference,
    align_estimates,
    align_in_time,
    as_partial_estimates,
    check_observation_matrices,
    check_times,
    residuals_to_reference,
)
from ._numerics.linalg import cholesky
from ._numerics.validation import as_estimates, restore_style
from .result import FusionResult

__all__ = ["FusionMethod", "available_methods", "fuse", "get_method", "register_method"]

# A horizon hook: ``hook(estimates, model, steps, options) -> (core_options, info)``.
_HorizonHook = Callable[..., tuple[Mapping[str, Any], Mapping[str, Any]]]
# A rule's route for two single estimates:
# ``pair(pairs, options, H=None, times=None) -> FusionResult or None``.
_PairRoute = Callable[..., Optional[FusionResult]]

# The options the front door handles for the rules whose record lists them in
# ``front_door``: what each name enables, and what it means (for the messages).
FRONT_DOOR_OPTIONS = {
    "H": ("H=", "accept H="),
    "residual": ("residual= and add=", "accept residual= and add="),
    "times": ("times=, at= and motion=", "bring estimates of other times to at= (times=)"),
}


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
    front_door : tuple of str
        The front-door options the rule supports, among ``"H"`` (its ``core`` also takes
        :class:`cifilter._numerics.alignment.PartialEstimates`: estimates ``x_i`` of
        ``H_i x`` with their own dimensions), ``"residual"`` (``residual=``/``add=``: the
        rule's fused mean is an affine combination ``sum_i K_i x_i`` with
        ``sum_i K_i = I``, so it may fuse residuals) and ``"times"``
        (``times=``/``at=``/``motion=``: its guarantee holds for estimates whose covariance
        bounds their error and whose correlation is unknown, which the time alignment
        produces). Empty: none of them.
    pair : callable or None
        ``pair(pairs, options, H=None, times=None) -> FusionResult or None``: a shorter
        route for the commonest call, two single ``(x, P)`` pairs (as given; not validated)
        and the rule's options, without front-door options but ``H=`` (then ``H`` holds the
        checked observation matrices, one per pair, None for the full state) or ``times=``
        (then ``times`` is ``(times, at, motion, labels)`` as given to :func:`fuse`, for
        :func:`cifilter._numerics.alignment.aligned_pair` or
        :func:`~cifilter._numerics.alignment.pair_step`, and the result's ``info`` has
        the front door's ``at`` and ``retrodiction_alpha``). :func:`fuse` tries
        it first; None sends the call the usual way (which validates and explains any
        error), so the route must give the usual way's result whenever it answers (for
        ``"ci"``: one compiled call).
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
    >>> get_method("ci").front_door
    ('H', 'residual', 'times')
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
    front_door: tuple[str, ...] = ()
    signature: Optional[tuple[tuple[str, ...], tuple[str, ...], bool]] = field(
        default=None, repr=False, compare=False)
    truth_takes_count: bool = field(default=False, init=False, repr=False, compare=False)
    truth_takes_sizes: bool = field(default=False, init=False, repr=False, compare=False)
    pair: Optional[_PairRoute] = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        # computed once: inspect.signature is slow per call (the network simulation asks
        # for truth options at every fusion)
        if self.signature is None:
            signature = (_option_signature(self.core, 1) if self.core is not None
                         else _option_signature(self.function, 2))
            object.__setattr__(self, "signature", signature)
        parameters = (inspect.signature(self.truth_options).parameters
                      if self.truth_options is not None else {})
        object.__setattr__(self, "truth_takes_count", "count" in parameters)
        object.__setattr__(self, "truth_takes_sizes", "sizes" in parameters)

    def options_given_truth(self, joint: ArrayLike, rng: Optional[np.random.Generator],
                            count: int = 2,
                            sizes: Optional[Sequence[int]] = None) -> dict[str, Any]:
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
        sizes : sequence of int, optional
            The dimension of each estimate's block of ``joint`` (estimates of parts
            ``H_i x`` of the state have blocks of unequal size); given to the hook when it
            takes a ``sizes`` argument (a hook that uses the joint whole, such as the
            optimal fusion's, need not).

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
        if not self.truth_takes_sizes:  # a hook that uses the joint whole
            sizes = None
        extra: dict[str, Any] = {}
        if self.truth_takes_count:
            extra["count"] = count
        if sizes is not None:
            extra["sizes"] = sizes
        return dict(self.truth_options(joint, rng, **extra))


GUARANTEES = ("bound", "exact", "none")
_REGISTRY: dict[str, FusionMethod] = {}


def register_method(name: str, function: Callable[..., FusionResult], *, summary: str = "",
                    reference: str = "", guarantee: str = "none",
                    truth_options: Optional[Callable[..., Mapping[str, Any]]] = None,
                    core: Optional[Callable[..., FusionResult]] = None,
                    horizon: Optional[_HorizonHook] = None, weights: str = "",
                    front_door: Sequence[str] = (), replace: bool = False,
                    pair: Optional[_PairRoute] = None) -> FusionMethod:
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
    front_door : sequence of str, optional
        The front-door options the rule supports (see :class:`FusionMethod`): ``"H"``
        (needs ``core``), ``"residual"``, ``"times"``. Default: none.
    replace : bool, optional
        Allow replacing an existing registration (default False).
    pair : callable, optional
        A shorter route for two single estimates (see :class:`FusionMethod`); it must
        return the result the usual route gives, or None.

    Returns
    -------
    FusionMethod
        The registration record.

    Raises
    ------
    TypeError
        If ``name`` is not a string or ``function``, ``core``, ``horizon``, ``pair`` or
        ``truth_options`` is not callable, or ``horizon`` or ``front_door=("H",)`` is given
        without ``core``.
    ValueError
        If ``name`` is empty, already registered and ``replace`` is False,
        ``guarantee`` is not one of the three values, or ``front_door`` names an unknown
        option.

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
                            ("horizon", horizon), ("pair", pair)):
        if value is not None and not callable(value):
            raise TypeError(f"{argument} must be callable or None")
    if horizon is not None and core is None:
        raise TypeError("horizon= needs core=: the front door fuses with the chosen weights "
                        "through the rule's core")
    if isinstance(front_door, str):
        front_door = (front_door,)
    front_door = tuple(front_door)
    unknown = [option for option in front_door if option not in FRONT_DOOR_OPTIONS]
    if unknown:
        raise ValueError(
            f"front_door may list {', '.join(map(repr, FRONT_DOOR_OPTIONS))}; got "
            f"{', '.join(map(repr, unknown))}"
        )
    if "H" in front_door and core is None:
        raise TypeError("front_door=('H',) needs core=: estimates of parts of the state "
                        "reach the rule's core only")
    if name in _REGISTRY and not replace:
        raise ValueError(f"a fusion method named {name!r} is already registered")
    record = FusionMethod(name, function, summary, reference, guarantee, truth_options,
                          core, horizon, weights, front_door, pair=pair)
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


def fuse(estimates: Sequence[Any], method: str = "ci", *, H: Optional[Sequence[Any]] = None,
         residual: Optional[Callable[..., Any]] = None,
         add: Optional[Callable[..., Any]] = None, times: Optional[Sequence[float]] = None,
         at: Optional[float] = None, motion: Optional[Callable[..., Any]] = None,
         horizon: Optional[int] = None, model: Any = None, **options: Any) -> FusionResult:
    """Fuse estimates with a registered rule.

    Parameters
    ----------
    estimates : sequence
        N >= 2 estimates, each an ``(x, P)`` pair or an object with ``.x`` and ``.P``
        (a filterpy filter). ``x`` is (..., n) or (..., n, 1), ``P`` is (..., n, n); leading
        batch axes fuse many problems at once and broadcast against each other.
    method : str, optional
        A registered rule (see :func:`available_methods`); default ``"ci"``.
    H : sequence, optional
        One entry per estimate: None (the estimate is of the full state) or an (m_i, n)
        matrix: estimate ``i`` (``x_i`` of dimension m_i) estimates ``H_i x`` of the
        n-dimensional state. For the rules that accept it (``"ci"``: generalised CI
        ``P^-1 = sum_i w_i H_i^T P_i^-1 H_i`` with optimal, fast or given weights;
        ``"naive"``; ``"optimal"`` with the joint of the partial estimates; ``"split-ci"``,
        a partial second estimate); see ``docs/methods/partial_state.rst``. The gains
        ``K_i`` (n x m_i) are then ``info["gains"]`` (``gains`` is None unless every
        ``m_i = n``). If the estimates together do not observe the state (``sum_i H_i^T
        P_i^-1 H_i`` singular) a ValueError names the unobserved directions.
    residual : callable, optional
        ``residual(a, b)``: ``a - b`` in the state space (for instance wrapping an angle),
        called on 1-D copies of two full-state means. The rule then fuses the residuals
        ``residual(x_i, x_1)`` relative to the first estimate (which must be of the full
        state; estimates of ``H_i x`` contribute ``x_i - H_i x_1``) and the result is
        ``add(x_1, fused residual)``. Default with ``add`` only: plain subtraction.
    add : callable, optional
        ``add(x, dx)``: ``x + dx`` in the state space (for instance normalising an angle).
        Default with ``residual`` only: plain addition.
    times : sequence of float, optional
        The time of each estimate. Every estimate is brought to ``at`` before the rule
        runs: an older one is predicted (``F x``, ``F P F^T + Q``, exact), a newer one
        retrodicted with the bound ``F^-1 (P / alpha + Q / (1 - alpha)) F^-T`` (the plain
        ``F^-1 (P + Q) F^-T`` is not a bound: the estimate's error is correlated with the
        process noise in between); ``(F, Q) = motion(|at - t_i|)``. Proof:
        ``docs/methods/time.rst``. ``info["at"]`` is the time of the result and
        ``info["retrodiction_alpha"]`` the alpha per estimate (None unless retrodicted).
        For the rules whose guarantee survives the shift (``"ci"``).
    at : float, optional
        The time to fuse at; default the latest of ``times``.
    motion : callable, optional
        ``motion(dt) -> (F, Q)`` for ``dt > 0``: the state transition over ``dt`` and the
        covariance of the process noise it adds (n x n each, ``Q`` symmetric positive
        semidefinite). Needed when some ``times[i] != at``.
    horizon : int, optional
        Choose the rule's weights for the bound ``horizon`` predict/update steps of
        ``model`` after the fusion (Ajgl et al. 2014; :mod:`cifilter.horizon`), for rules
        whose record declares it (``"ci"``, and ``"pci"`` with ``rho``). The rule then fuses
        with those weights; ``info["rule"]`` is ``"horizon"``, ``info["horizon"]`` holds the
        horizon solver's diagnostics (``steps``, ``criterion``, ``value``,
        ``value_recursive``, ``weights_recursive``, ``iterations``, ``converged``, ``gap``,
        ``solver``) and ``info["converged"]``, ``info["iterations"]`` and ``info["gap"]`` are
        those of that choice. ``horizon=0`` is the rule's own optimum. Not with ``H``.
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
        ``model``, ``model`` without ``horizon``; ``H``, ``residual``/``add`` or ``times``
        for a rule that does not accept them (the message names the rules that do), an
        ``H`` entry of the wrong shape, estimates that do not observe the state, ``at`` or
        ``motion`` without ``times``, non-finite times, a ``motion`` whose matrices have
        the wrong shape or a ``Q`` that is not positive semidefinite, a singular ``F``
        for a newer estimate (an :class:`~cifilter.IllConditionedError`).
    TypeError
        An estimate of the wrong kind, non-numeric, boolean or complex values, an option
        the rule does not accept or a required option that is missing (for instance
        ``joint`` of ``"optimal"``), a ``residual``, ``add`` or ``motion`` that is not
        callable or returns the wrong kind of value.

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

    A position-only estimate fused into a position-velocity one (generalised CI):

    >>> position = (np.array([0.5]), np.array([[0.5]]))
    >>> r = fuse([a, position], H=[None, np.array([[1.0, 0.0]])])
    >>> r.x.shape, r.info["gains"][1].shape
    ((2,), (2, 1))

    An estimate two seconds older than the other, predicted by a constant-velocity model:

    >>> def motion(dt):
    ...     return np.array([[1.0, dt], [0.0, 1.0]]), 0.01 * dt * np.eye(2)
    >>> r = fuse([a, b], times=[0.0, 2.0], motion=motion)
    >>> r.info["at"]
    2.0
    """
    return fuse_estimates(estimates, method, options, horizon=horizon, model=model, H=H,
                          residual=residual, add=add, times=times, at=at, motion=motion)


def _front_door_refusal(record, option):
    """The error for a front-door option the rule's record does not declare."""
    given, meaning = FRONT_DOOR_OPTIONS[option]
    supporting = [name for name, r in _REGISTRY.items() if option in r.front_door]
    keyword = given.split(" ")[0].rstrip(",")
    if option == "H":
        return ValueError(
            f"method {record.name!r} does not accept H=; the rules that accept H are "
            f"{', '.join(map(repr, supporting)) or 'none'}"
        )
    return ValueError(
        f"method {record.name!r} does not accept {keyword}; the rules that {meaning} are "
        f"{', '.join(map(repr, supporting)) or 'none'}"
    )


def fuse_estimates(estimates: Sequence[Any], method: str, options: Mapping[str, Any], *,
                   horizon: Optional[int] = None, model: Any = None,
                   labels: Optional[Sequence[str]] = None, H: Optional[Sequence[Any]] = None,
                   residual: Optional[Callable[..., Any]] = None,
                   add: Optional[Callable[..., Any]] = None,
                   times: Optional[Sequence[float]] = None, at: Optional[float] = None,
                   motion: Optional[Callable[..., Any]] = None) -> FusionResult:
    """:func:`fuse` with the options as a mapping and optional labels for the messages.

    With ``labels`` (one string per estimate, e.g. ``("this filter", "other")``) messages
    say ``"other's P"``; without, ``"estimates' P[1]"``. The filter classes call this.
    """
    record = get_method(method)
    if isinstance(estimates, (str, bytes)) or not hasattr(estimates, "__len__"):
        raise TypeError(
            f"estimates must be a sequence of estimates, got {type(estimates).__name__}"
        )
    # (a plain 2-tuple is an (x, P) pair as it is: split_estimate's answer, without its
    # attribute look-ups)
    pairs = [item if type(item) is tuple and len(item) == 2 else split_estimate(item, i, labels)
             for i, item in enumerate(estimates)]
    if len(pairs) < 2:
        raise ValueError(f"at least 2 estimates are needed, got {len(pairs)}")
    if (H is None and residual is None and add is None and times is None and at is None
            and motion is None and horizon is None and model is None):
        # no front-door option: the checks below reduce to the rule's options
        if record.pair is not None and len(pairs) == 2:
            result = record.pair(pairs, options)
            if result is not None:
                return result
        _check_options(record, options)
        stacked = as_estimates([p[0] for p in pairs], [p[1] for p in pairs],
                               names=_NAMES if labels is None else _LABELLED_NAMES,
                               labels=labels)
        return _call_rule(record, stacked, options)
    if (times is not None and H is None and residual is None and add is None
            and horizon is None and model is None):
        # times= alone (kf.fuse(lag=)): the checks and steps below, for this case only
        if "times" not in record.front_door:
            raise _front_door_refusal(record, "times")
        if record.pair is not None and len(pairs) == 2:
            # the rule's short way of two single estimates (kf.fuse(other, lag=k)): the
            # moved one checked and brought as below (alignment.aligned_pair, or pair_step
            # and a compiled call), the other and the options checked by the route (None
            # for anything else: see below)
            result = record.pair(pairs, options, times=(times, at, motion, labels))
            if result is not None:
                return result
        _check_options(record, options)
        stacked = as_estimates([p[0] for p in pairs], [p[1] for p in pairs],
                               names=_NAMES if labels is None else _LABELLED_NAMES,
                               labels=labels)
        times, at = check_times(times, len(pairs), at)
        alpha = align_estimates(stacked, times, at, motion, labels)
        result = None
        if record.pair is not None and len(pairs) == 2 and not stacked.batch_shape:
            # the rule's route for two single estimates, on the aligned ones
            x = stacked.x[..., None] if stacked.column else stacked.x
            result = record.pair([(x[0], stacked.P[0]), (x[1], stacked.P[1])], options)
        if result is None:
            result = _call_rule(record, stacked, options)
        return result.replace(info={**result.info, "at": at, "retrodiction_alpha": alpha})
    Hs = check_observation_matrices(H, len(pairs))
    if (Hs is not None and residual is None and add is None and times is None and at is None
            and motion is None and horizon is None and model is None):
        # H= alone (kf.fuse(H=)): the checks and steps below, for this case only
        if "H" not in record.front_door:
            raise _front_door_refusal(record, "H")
        if record.pair is not None and len(pairs) == 2:
            result = record.pair(pairs, options, Hs)
            if result is not None:
                return result
        _check_options(record, options)
        return _call_rule(record, as_partial_estimates(pairs, Hs, labels), options)
    requested = [option for option, given in (("H", Hs is not None),
                                              ("residual", residual is not None
                                               or add is not None),
                                              ("times", times is not None)) if given]
    if times is None and (at is not None or motion is not None):
        raise ValueError("at= and motion= bring estimates of other times to one time; give "
                         "times= (one time per estimate) too")
    for option in requested:
        if option not in record.front_door:
            raise _front_door_refusal(record, option)
    if horizon is None and model is not None:
        raise ValueError("model= describes the steps after the fusion; give horizon= too")
    if horizon is not None and record.horizon is None:
        supporting = [name for name, r in _REGISTRY.items() if r.horizon is not None]
        raise ValueError(
            f"method {record.name!r} does not support horizon=; the methods that choose "
            f"their weights for a horizon are {', '.join(map(repr, supporting))}"
        )
    if horizon is not None and Hs is not None:
        raise ValueError("horizon= chooses weights for estimates of the full state; it "
                         "does not support H=")
    if horizon is None:  # with horizon= the rule's hook checks the options it takes
        _check_options(record, options)
    names = ("estimates' x", "estimates' P") if labels is None else ("x", "P")
    if not requested:
        stacked = as_estimates([p[0] for p in pairs], [p[1] for p in pairs], names=names,
                               labels=labels)
        if horizon is not None:
            return _fuse_for_horizon(record, stacked, horizon, model, options)
        return _call_rule(record, stacked, options)
    return _fuse_through_front_door(record, pairs, options, horizon, model, labels, names, Hs,
                                    residual, add, times, at, motion)


_NAMES = ("estimates' x", "estimates' P")
_LABELLED_NAMES = ("x", "P")


def _call_rule(record, estimates, options):
    """The rule's core on validated estimates (or its function, restyled)."""
    if record.core is not None:
        return record.core(estimates, **options)
    result = record.function(estimates.x, estimates.P, **options)
    if not isinstance(result, FusionResult):
        raise TypeError(
            f"fusion method {record.name!r} returned {type(result).__name__}, not FusionResult"
        )
    x = np.asarray(result.x)
    if x.shape[-1:] == (1,) and x.shape[:-1] == result.P.shape[:-1]:
        x = x[..., 0]  # a rule answered in column style; normalise before restyling
    return result.replace(x=restore_style(x, estimates.column))


def _fuse_through_front_door(record, pairs, options, horizon, model, labels, names, Hs,
                             residual, add, times, at, motion):
    """Validate once, bring the estimates to one time and to residuals, run the rule and
    add the fused residual back (``docs/methods/partial_state.rst``, ``time.rst``)."""
    count = len(pairs)
    if Hs is None:
        # (validated copies: the aligned estimates are written into them)
        stacked = as_estimates([p[0] for p in pairs], [p[1] for p in pairs], names=names,
                               labels=labels)
        n, column, H = stacked.dim, stacked.column, (None,) * count
    else:
        partial = as_partial_estimates(pairs, Hs, labels)
        x, L, P = list(partial.x), list(partial.L), list(partial.P)
        n, column, H = partial.dim, partial.column, partial.H
    extra: dict[str, Any] = {}
    if times is not None:
        times, at = check_times(times, count, at)
        if Hs is None:  # in place, with the new factors
            alpha = align_estimates(stacked, times, at, motion, labels)
        else:
            where = [f"estimates[{i}]" if labels is None else labels[i] for i in range(count)]
            x, P_new, alpha, changed = align_in_time(x, L, [h is None for h in H], times, at,
                                                     motion, n, where)
            for i in changed:
                P[i] = P_new[i]
                L[i] = cholesky(P_new[i], f"{where[i]}'s P brought to at={at:g}")
        extra.update(at=at, retrodiction_alpha=tuple(alpha))
    reference = None
    if residual is not None or add is not None:
        residual = np.subtract if residual is None else residual
        add = np.add if add is None else add
        for name, function in (("residual", residual), ("add", add)):
            if not callable(function):
                raise TypeError(f"{name} must be callable, got {type(function).__name__}")
        if H[0] is not None:
            raise ValueError("residual= and add= fuse residuals relative to the first "
                             "estimate, which must estimate the full state (H[0] None)")
        if Hs is None:
            x = [stacked.x[..., i, :] for i in range(count)]
        batch = np.broadcast_shapes(*(xi.shape[:-1] for xi in x))
        x = [np.broadcast_to(xi, batch + xi.shape[-1:]) for xi in x]
        reference = np.array(x[0])
        x = residuals_to_reference(x, H, residual)
        if Hs is None:
            for i in range(count):
                stacked.x[..., i, :] = x[i]
    if Hs is None:
        estimates: Any = stacked
    else:
        estimates = PartialEstimates(tuple(x), tuple(P), tuple(L), H, n, column)
    if horizon is not None:
        result = _fuse_for_horizon(record, estimates, horizon, model, options)
    else:
        result = _call_rule(record, estimates, options)
    if reference is None and not extra:
        return result
    changes: dict[str, Any] = {}
    if reference is not None:
        fused = np.asarray(result.x)
        fused = fused[..., 0] if column else fused
        changes["x"] = restore_style(added_to_reference(reference, fused, add), column)
    if extra:
        info = dict(result.info)
        info.update(extra)
        changes["info"] = info
    return result.replace(**changes)


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
