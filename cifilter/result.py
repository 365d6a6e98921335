"""The result object every fusion rule returns."""

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Optional

import numpy as np

__all__ = ["FusionResult"]


def _frozen(value):
    """A read-only array (a view when ``value`` already is an array)."""
    if value is None:
        return None
    array = np.asarray(value)
    if array.flags.writeable:
        array = array.view()
        array.flags.writeable = False
    return array


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
        Scalar weights of the inputs, when the rule has them.
    gains : ndarray, shape (..., N, n, n)
        Matrices ``K_i`` with ``x = sum_i K_i x_i``.
    info : Mapping
        Diagnostics of the rule (criterion value, iterations, converged, ...); stored as a
        read-only mapping.

    Notes
    -----
    The arrays are read-only views and ``info`` is a read-only mapping, so a result can be
    stored (for instance as ``kf.last_fusion``) without being changed by later code.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import fuse
    >>> r = fuse([(np.zeros(2), np.eye(2)), (np.ones(2), 2 * np.eye(2))], method="naive")
    >>> r.method, r.x.round(4).tolist()
    ('naive', [0.3333, 0.3333])
    """

    x: np.ndarray
    P: np.ndarray
    method: str
    omega: Optional[np.ndarray] = None
    gains: Optional[np.ndarray] = None
    info: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "x", _frozen(self.x))
        object.__setattr__(self, "P", _frozen(self.P))
        object.__setattr__(self, "omega", _frozen(self.omega))
        object.__setattr__(self, "gains", _frozen(self.gains))
        object.__setattr__(self, "info", MappingProxyType(dict(self.info)))

    def __repr__(self):
        omega = None if self.omega is None else np.array2string(self.omega, precision=4)
        return (
            f"FusionResult(method={self.method!r}, x shape={self.x.shape}, "
            f"P shape={self.P.shape}, omega={omega}, info keys={sorted(self.info)})"
        )

    def __reduce__(self):
        # A mappingproxy does not pickle; rebuild from plain fields (copy and pickle work).
        return (FusionResult, (self.x, self.P, self.method, self.omega, self.gains,
                               dict(self.info)))

    def replace(self, **changes):
        """Return a copy with some fields replaced (like ``dataclasses.replace``).

        Parameters
        ----------
        **changes
            New values for any of ``x``, ``P``, ``method``, ``omega``, ``gains``, ``info``.

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
        fields = dict(
            x=self.x, P=self.P, method=self.method, omega=self.omega, gains=self.gains,
            info=self.info,
        )
        fields.update(changes)
        return FusionResult(**fields)
