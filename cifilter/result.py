"""The result object every fusion rule returns."""

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Optional

import numpy as np
from numpy.typing import NDArray

__all__ = ["FusionResult"]


def _frozen(value):
    """A read-only array (a view when ``value`` already is an array)."""
    if value is None:
        return None
    array = value if type(value) is np.ndarray else np.asarray(value)
    if array.flags.writeable:
        array = array.view()
        array.setflags(write=False)  # (faster than flags.writeable = False)
    return array


class _FrozenList(list):
    """A list that cannot be changed (in a result's ``info``); equal to the plain list."""

    def _read_only(self, *args, **kwargs):
        raise TypeError("lists in FusionResult.info are read-only")

    __setitem__ = __delitem__ = __iadd__ = __imul__ = _read_only
    append = extend = insert = pop = remove = clear = sort = reverse = _read_only

    def __reduce__(self):
        return (_FrozenList, (list(self),))


_IMMUTABLE = (str, bytes, int, float, bool, type(None), np.generic)
# the exact types of _IMMUTABLE's usual members (a set look-up, before the isinstance test)
_PLAIN = frozenset((str, bytes, int, float, bool, type(None), np.float64, np.int64,
                    np.bool_))


def _frozen_info(value):
    """A read-only copy of an ``info`` value: arrays read-only, containers frozen.

    Mappings become read-only mappings, lists read-only lists and tuples tuples of frozen
    items, recursively; other values (numbers, strings, numpy scalars) are kept.
    """
    kind = type(value)
    if kind is np.ndarray:  # the common cases first: info is on every result
        if value.flags.writeable:
            value = value.view()
            value.setflags(write=False)  # (faster than flags.writeable = False)
        return value
    if kind in _PLAIN or isinstance(value, _IMMUTABLE):
        return value
    if kind is dict:  # (exactly a dict or a tuple: what the tests below do, sooner)
        return MappingProxyType({key: _frozen_info(item) for key, item in value.items()})
    if kind is tuple:
        return tuple([_frozen_info(item) for item in value])
    if isinstance(value, np.ndarray):
        return _frozen(value)
    if isinstance(value, (dict, MappingProxyType)) or isinstance(value, Mapping):
        return MappingProxyType({key: _frozen_info(item) for key, item in value.items()})
    if isinstance(value, list):
        return _FrozenList(_frozen_info(item) for item in value)
    if type(value) is tuple:  # not NamedTuples, whose constructors take fields
        return tuple(_frozen_info(item) for item in value)
    return value


def _thawed_info(value):
    """Plain containers again (for pickling; the arrays stay as they are)."""
    if isinstance(value, Mapping):
        return {key: _thawed_info(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_thawed_info(item) for item in value]
    if type(value) is tuple:
        return tuple(_thawed_info(item) for item in value)
    return value


@dataclass(frozen=True, repr=False)
class FusionResult:
    """Immutable result of a fusion rule.

    The parameters are also the attributes of the result.

    Parameters
    ----------
    x : ndarray, shape (..., n) or (..., n, 1)
        Fused mean, in the vector style of the first input.
    P : ndarray, shape (..., n, n)
        Fused covariance. For conservative rules (``"ci"``, ``"pci"``) it is an upper
        bound of the error covariance; for ``"optimal"`` and ``"naive"`` it is the error
        covariance under their assumptions; see each method's documentation.
    method : str
        Name of the rule that produced the result.
    omega : ndarray, shape (..., N), or None
        Covariance Intersection's weights on the simplex (rules ``"ci"``; None for rules
        without them).
    gains : ndarray, shape (..., N, n, n)
        Matrices ``K_i`` with ``x = sum_i K_i x_i``.
    info : Mapping
        Diagnostics of the rule (see "Common info keys" below); stored as a read-only
        mapping in which every array is read-only, nested mappings are read-only mappings
        and lists read-only lists.
    weights : ndarray, shape (..., N), or None
        The scalar weights on the estimates, ``P^-1 = sum_i w_i P_i^-1`` for the
        information-form rules: ``omega`` for ``"ci"`` (the default when only ``omega`` is
        given), eq. (24) of Wu, Cai & Fu for ``"pci"`` (they do not sum to one), ones for
        ``"naive"``, ``1/rho`` each for ``"sci"``; for ``"ici"`` and ``"split-ci"`` the pair
        ``(omega, 1 - omega)`` of their own parametrisation (two estimates); None for rules
        whose fusion is not a scalar weighting (``"optimal"``, ``"ei"``, ``"pcei"``,
        ``"bayes"``, ``"cross"``, ``"cu"``, ``"le"``). The registry record's ``weights``
        says what they are for each rule; each method's page documents them.

    Notes
    -----
    Common info keys, with one meaning for every rule that reports them:

    ``rule``
        How the weights were chosen: ``"optimal"`` (the rule's criterion minimised),
        ``"fixed"`` (given by the caller), a fast rule's name, or ``"horizon"`` (chosen
        for the bound after future filtering; details under ``info["horizon"]``).
    ``converged``
        (..., ) bool: the choice of the weights met its tolerance; where a ``gap`` is
        reported, it means that the certified gap is at most the tolerance.
    ``iterations``
        (..., ) int: iterations of the solver that chose the weights.
    ``value``
        (..., ) the rule's criterion at the returned ``P`` (trace, determinant, ...).
    ``gap``
        (..., ) a certified upper bound of the excess of the criterion over its minimum
        (relative for traces, in log det for determinants), where the rule certifies one.

    The arrays are read-only views and ``info`` is a read-only mapping whose arrays (also
    inside nested mappings, lists and tuples) are read-only, so a result can be stored (for
    instance as ``kf.last_fusion``) without being changed by later code. Results pickle and
    copy; the copies are read-only too.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import FusionResult, fuse
    >>> r = fuse([(np.zeros(2), np.eye(2)), (np.ones(2), 2 * np.eye(2))], method="naive")
    >>> r.method, r.x.round(4).tolist()
    ('naive', [0.3333, 0.3333])
    >>> r = FusionResult(np.zeros(1), np.eye(1), "mine", info={"trace": {"P": np.ones(3)}})
    >>> r.info["trace"]["P"].flags.writeable
    False
    """

    x: NDArray[np.float64]
    P: NDArray[np.float64]
    method: str
    omega: Optional[NDArray[np.float64]] = None
    gains: Optional[NDArray[np.float64]] = None
    info: Mapping[str, Any] = field(default_factory=dict)
    weights: Optional[NDArray[np.float64]] = None

    def __post_init__(self):
        _set_fields(self, self.x, self.P, self.omega, self.gains, self.info, self.weights)

    def __repr__(self):
        weights = None if self.weights is None else np.array2string(self.weights, precision=4)
        return (
            f"FusionResult(method={self.method!r}, x shape={self.x.shape}, "
            f"P shape={self.P.shape}, weights={weights}, info keys={sorted(self.info)})"
        )

    def __reduce__(self):
        # A mappingproxy does not pickle; rebuild from plain fields (copy and pickle work).
        return (FusionResult, (self.x, self.P, self.method, self.omega, self.gains,
                               _thawed_info(self.info), self.weights))

    def replace(self, **changes: Any) -> "FusionResult":
        """Return a copy with some fields replaced (like ``dataclasses.replace``).

        Parameters
        ----------
        **changes
            New values for any of ``x``, ``P``, ``method``, ``omega``, ``gains``, ``info``,
            ``weights``.

        Returns
        -------
        FusionResult
            The new result; ``self`` is unchanged.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import FusionResult
        >>> r = FusionResult(np.zeros(2), np.eye(2), "mine")
        >>> r.replace(method="renamed").method
        'renamed'
        """
        if not changes.keys() <= _FIELD_NAMES:  # the constructor's TypeError names them
            fields: dict[str, Any] = dict(
                x=self.x, P=self.P, method=self.method, omega=self.omega, gains=self.gains,
                info=self.info, weights=self.weights,
            )
            fields.update(changes)
            return FusionResult(**fields)
        # The fields of self are frozen already: only the changed ones are frozen again, and
        # of a changed info only the entries that are not self.info's own (the same
        # objects), which the front door's additions (a key or two) make the usual case.
        # The same result as FusionResult(**fields), without re-freezing the rest.
        result = object.__new__(FusionResult)
        get = changes.get
        info = get("info", self.info)
        frozen = info is self.info
        if not frozen and isinstance(info, Mapping):
            known = dict(self.info).get  # (a dict's look-ups: faster than the proxy's)
            info = MappingProxyType({
                key: (item if known(key, _MISSING) is item else _frozen_info(item))
                for key, item in info.items()})
            frozen = True
            if len(changes) == 1:  # info alone (the front door's additions): the other
                # fields are self's, frozen already
                fields = result.__dict__
                fields.update(self.__dict__)
                fields["info"] = info
                return result
        object.__setattr__(result, "method", get("method", self.method))
        _set_fields(result, get("x", self.x), get("P", self.P), get("omega", self.omega),
                    get("gains", self.gains), info, get("weights", self.weights), frozen)
        return result


def owned_result(x: NDArray[np.float64], P: NDArray[np.float64], method: str,
                 omega: Optional[NDArray[np.float64]], gains: Optional[NDArray[np.float64]],
                 info: dict[str, Any]) -> FusionResult:
    """A :class:`FusionResult` of arrays that nobody else holds, frozen in place.

    For the single-call routes of the rules: the arrays (and the arrays among the values of
    the plain dict ``info``, whose other values must be strings or numbers) are the
    caller's fresh ones, made read-only themselves instead of through read-only views. The
    result equals ``FusionResult(x, P, method, omega, gains, info)``.

    Parameters
    ----------
    x, P, omega, gains : ndarray
        The fields (``omega`` and ``gains`` may be None); set read-only here.
    method : str
        The rule's name.
    info : dict
        The diagnostics; stored as a read-only mapping.

    Returns
    -------
    FusionResult
        The result; ``weights`` is ``omega``.
    """
    for array in (x, P, omega, gains):
        if array is not None:
            array.setflags(write=False)
    for value in info.values():
        if type(value) is np.ndarray:
            value.setflags(write=False)
    result = object.__new__(FusionResult)
    result.__dict__.update(x=x, P=P, method=method, omega=omega, gains=gains,
                           info=MappingProxyType(info), weights=omega)
    return result


_FIELD_NAMES = frozenset(("x", "P", "method", "omega", "gains", "info", "weights"))
_MISSING = object()


def _set_fields(result, x, P, omega, gains, info, weights, info_frozen=False):
    """Set the fields of ``result`` frozen: arrays read-only (views), ``info`` a read-only
    mapping of frozen values (kept as it is with ``info_frozen``), ``weights`` ``omega``
    unless given."""
    set_field = object.__setattr__
    set_field(result, "x", _frozen(x))
    set_field(result, "P", _frozen(P))
    omega = _frozen(omega)
    set_field(result, "omega", omega)
    set_field(result, "gains", _frozen(gains))
    if not info_frozen:
        if not isinstance(info, Mapping):  # (pairs, say) a mapping first
            info = dict(info)
        # a mapping is copied by _frozen_info itself (into a fresh read-only mapping)
        info = _frozen_info(info)
    set_field(result, "info", info)
    set_field(result, "weights", omega if weights is None else _frozen(weights))
