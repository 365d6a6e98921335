"""The registry of fusion rules and :func:`fuse`, the single entry point that dispatches to them.

Each fusion family registers its rules when its module is imported. A rule is a function
``rule(xs, Ps, **options) -> FusionResult`` that receives already validated arrays
``xs`` (..., N, n) and ``Ps`` (..., N, n, n) with a common batch shape.
"""

import inspect
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ._validation import as_estimates, restore_style
from .result import FusionResult

__all__ = ["FusionMethod", "available_methods", "fuse", "get_method", "register_method"]


@dataclass(frozen=True)
class FusionMethod:
    """A registered fusion rule and what is known about it (see :func:`register_method`).

    The parameters are also the attributes of the record.

    Parameters
    ----------
    name : str
        Name used as ``fuse(..., method=name)``.
    function : callable
        ``function(xs, Ps, **options) -> FusionResult`` on validated arrays.
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

    Examples
    --------
    >>> from cifilter import get_method
    >>> record = get_method("optimal")
    >>> record.guarantee, sorted(record.options_given_truth("J", rng=None))
    ('exact', ['joint'])
    """

    name: str
    function: Callable
    summary: str = ""
    reference: str = ""
    guarantee: str = "none"
    truth_options: Optional[Callable] = None

    def options_given_truth(self, joint, rng):
        """Options for this rule in a simulation where the joint covariance is known.

        Parameters
        ----------
        joint : ndarray, shape (..., N*n, N*n)
            True joint error covariance of the estimates to fuse.
        rng : numpy.random.Generator
            Randomness for rules that sample.

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
        return {} if self.truth_options is None else dict(self.truth_options(joint, rng))


GUARANTEES = ("bound", "exact", "none")
_REGISTRY = {}


def register_method(name, function, *, summary="", reference="", guarantee="none",
                    truth_options=None, replace=False):
    """Register a fusion rule so that ``fuse(..., method=name)`` can use it.

    Parameters
    ----------
    name : str
        The method name.
    function : callable
        ``function(xs, Ps, **options) -> FusionResult``. ``xs`` has shape (..., N, n) and
        ``Ps`` shape (..., N, n, n); both are validated copies with one batch shape.
    summary, reference : str, optional
        One-line description and source, shown by ``python -m cifilter methods``.
    guarantee : {"bound", "exact", "none"}, optional
        What the rule's covariance is (see :class:`FusionMethod`); default ``"none"``.
    truth_options : callable, optional
        ``truth_options(joint, rng) -> dict`` giving the options the rule needs when the
        true joint covariance is known (used by the demo).
    replace : bool, optional
        Allow replacing an existing registration (default False).

    Returns
    -------
    FusionMethod
        The registration record.

    Raises
    ------
    TypeError
        If ``name`` is not a string or ``function`` is not callable.
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
    if truth_options is not None and not callable(truth_options):
        raise TypeError("truth_options must be callable or None")
    if name in _REGISTRY and not replace:
        raise ValueError(f"a fusion method named {name!r} is already registered")
    record = FusionMethod(name, function, summary, reference, guarantee, truth_options)
    _REGISTRY[name] = record
    return record


def available_methods():
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


def get_method(name):
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
        If no rule of that name is registered; the message lists the registered names.

    Examples
    --------
    >>> from cifilter import get_method
    >>> get_method("ci").guarantee
    'bound'
    """
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        known = ", ".join(repr(m) for m in _REGISTRY)
        raise ValueError(
            f"unknown fusion method {name!r}; registered methods are {known}"
        ) from None


def _check_options(record, options):
    """Check the options against the rule's signature.

    Rejects options the rule does not accept (naming them and the accepted ones) and
    reports required options that are missing (naming them and the method), both as
    ``TypeError`` before the rule runs.
    """
    try:
        parameters = inspect.signature(record.function).parameters
    except (TypeError, ValueError):  # builtins without a signature: let the call decide
        return
    options_parameters = [
        p for p in list(parameters.values())[2:]
        if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    ]
    missing = [
        p.name for p in options_parameters
        if p.default is inspect.Parameter.empty and p.name not in options
    ]
    if missing:
        example = ", ".join(f"{name}=..." for name in missing)
        raise TypeError(
            f"method {record.name!r} needs the option(s) {', '.join(map(repr, missing))}: "
            f"fuse(estimates, method={record.name!r}, {example})"
        )
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    accepted = [p.name for p in options_parameters]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise TypeError(
            f"method {record.name!r} does not accept option(s) {', '.join(map(repr, unknown))}; "
            f"it accepts {', '.join(map(repr, accepted)) or 'no options'}"
        )


def _split_estimate(item, index):
    if hasattr(item, "x") and hasattr(item, "P"):
        return item.x, item.P
    if isinstance(item, (tuple, list)) and len(item) == 2:
        return item[0], item[1]
    raise TypeError(
        f"estimates[{index}] must be an (x, P) pair or an object with .x and .P attributes "
        f"(such as a filterpy filter), got {type(item).__name__}"
    )


def fuse(estimates, method="ci", **options):
    """Fuse estimates with a registered rule.

    Parameters
    ----------
    estimates : sequence
        N >= 2 estimates, each an ``(x, P)`` pair or an object with ``.x`` and ``.P``
        (a filterpy filter). ``x`` is (..., n) or (..., n, 1), ``P`` is (..., n, n); leading
        batch axes fuse many problems at once and broadcast against each other.
    method : str, optional
        A registered rule (see :func:`available_methods`); default ``"ci"``.
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
        bad shapes, non-finite, non-symmetric or non-positive-definite covariances, or an
        option out of range.
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
    >>> float(r.omega[0]), float(np.trace(r.P))
    (0.5, 3.2)
    """
    return _fuse(estimates, method, options)


def _fuse(estimates, method, options, labels=None):
    """:func:`fuse` with optional labels of the estimates for the messages.

    With ``labels`` (one string per estimate, e.g. ``("this filter", "other")``) messages
    say ``"other's P"``; without, ``"estimates' P[1]"``.
    """
    record = get_method(method)
    if isinstance(estimates, (str, bytes)) or not hasattr(estimates, "__len__"):
        raise TypeError(
            f"estimates must be a sequence of estimates, got {type(estimates).__name__}"
        )
    pairs = [_split_estimate(item, i) for i, item in enumerate(estimates)]
    if len(pairs) < 2:
        raise ValueError(f"at least 2 estimates are needed, got {len(pairs)}")
    _check_options(record, options)
    names = ("estimates' x", "estimates' P") if labels is None else ("x", "P")
    stacked = as_estimates([p[0] for p in pairs], [p[1] for p in pairs], names=names,
                           labels=labels)
    result = record.function(stacked.x, stacked.P, **options)
    if not isinstance(result, FusionResult):
        raise TypeError(
            f"fusion method {record.name!r} returned {type(result).__name__}, not FusionResult"
        )
    x = np.asarray(result.x)
    if x.shape[-1:] == (1,) and x.shape[:-1] == result.P.shape[:-1]:
        x = x[..., 0]  # a rule answered in column style; normalise before restyling
    return result.replace(x=restore_style(x, stacked.column))
