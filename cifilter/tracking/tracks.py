"""The tracks a fusion node receives and the tracks it keeps.

:class:`SourceTrack` is one track of one source (a sensor's local tracker, a node of a
network) as the fusion node receives it: the source's own track number, an estimate and its
time, and ``H`` when the source estimates only part of the state. :class:`CentralTrack` is
the node's own track, the result of :meth:`cifilter.tracking.TrackFuser.update`.
:func:`checked_tracks` validates one scan of source tracks before the node uses them.
"""

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.alignment import finite_real
from .._numerics.linalg import cholesky
from .._numerics.validation import SYMMETRY_RTOL, as_float_array

__all__ = ["CentralTrack", "SourceTrack", "checked_tracks", "scan_time"]


@dataclass(frozen=True)
class SourceTrack:
    """One source's track at one time, as the fusion node receives it.

    Parameters
    ----------
    source : hashable
        The sensor or node that sent it.
    id : hashable
        That source's own track number (unique within the source and the scan).
    x : array_like, shape (m,) or (m, 1)
        The estimate: of the full state (``m = n``) or of ``H x``.
    P : array_like, shape (m, m)
        Its covariance (symmetric positive definite).
    time : float
        The time the estimate describes (at most the scan time: a late track is predicted to
        the scan time).
    H : array_like, shape (m, n), optional
        The source estimates ``H x`` of the n-dimensional central state (full row rank);
        None (default) for the full state.

    Notes
    -----
    Nothing is checked here: :meth:`TrackFuser.update <cifilter.tracking.TrackFuser.update>`
    checks every track of a scan and names the source and track of the first bad one.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import SourceTrack
    >>> t = SourceTrack("radar", 7, x=np.zeros(4), P=np.eye(4), time=1.0)
    >>> t.source, t.id, t.H is None
    ('radar', 7, True)
    """

    source: Hashable
    id: Hashable
    x: ArrayLike
    P: ArrayLike
    time: float
    H: Optional[ArrayLike] = None


@dataclass(frozen=True)
class CentralTrack:
    """A track of the fusion node at the time of a scan.

    Parameters
    ----------
    id : int
        Stable central ID: 1, 2, 3, ... in order of birth, never reused.
    x : ndarray, shape (n,)
        The fused (or, when coasting, predicted) state; read-only.
    P : ndarray, shape (n, n)
        Its covariance (for ``"ci"`` an upper bound of the error covariance); read-only.
    time : float
        The scan time.
    confirmed : bool
        Confirmed (M of N scans with an update, or enough sources in one scan); once
        confirmed a track stays confirmed until it is deleted.
    sources : Mapping
        ``{source: source track id}`` of the source tracks fused into it at this scan
        (empty when coasting).
    hits : int
        Scans with at least one source track since birth.
    misses : int
        Consecutive scans without a source track (0 when updated at this scan).
    born : float
        The time of the scan that started it.
    info : Mapping
        The fusion's diagnostics at this scan: ``"method"``, ``"estimates"`` (how many were
        fused), ``"prediction"`` (whether the track's own prediction was one of them),
        ``"weights"`` (the rule's weights on the estimates in the order prediction first,
        then the sources sorted as in ``sources``, when the rule has them), ``"converged"``
        where the rule reports it, ``"distances"`` (``{source: association distance}``).
        Empty when coasting.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import CentralTrack
    >>> c = CentralTrack(id=1, x=np.zeros(2), P=np.eye(2), time=0.0, confirmed=False,
    ...                  sources={"radar": 7}, hits=1, misses=0, born=0.0, info={})
    >>> c.id, dict(c.sources)
    (1, {'radar': 7})
    """

    id: int
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    time: float
    confirmed: bool
    sources: Mapping[Hashable, Hashable]
    hits: int
    misses: int
    born: float
    info: Mapping[str, Any] = field(default_factory=dict)


class CheckedTrack(NamedTuple):
    """A validated source track: copies as float arrays, ``P`` symmetrised, its Cholesky
    factor ``L``, ``H`` None or (m, n), and ``label`` naming it in messages."""

    source: Hashable
    id: Hashable
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    L: NDArray[np.float64]
    time: float
    H: Optional[NDArray[np.float64]]
    label: str


def scan_time(time: Any, last: Optional[float]) -> float:
    """The scan time as a float: finite, real and not earlier than ``last``.

    Parameters
    ----------
    time : float
        The scan time given to ``update``.
    last : float or None
        The fuser's time (None before the first scan).

    Returns
    -------
    float

    Raises
    ------
    TypeError
        ``time`` is not a real number.
    ValueError
        ``time`` is not finite or earlier than ``last``.

    Examples
    --------
    >>> from cifilter.tracking import scan_time
    >>> scan_time(2, 1.0)
    2.0
    """
    value = finite_real(time, "the scan time")
    if last is not None and value < last:
        raise ValueError(f"the scan time {value:g} is earlier than the fuser's time {last:g} "
                         "(scans must come in time order)")
    return value


def _key(value):
    """A hashable key of a source or track id, or a TypeError naming it."""
    try:
        hash(value)
    except TypeError:
        raise TypeError(f"source and track ids must be hashable, got "
                        f"{type(value).__name__}") from None
    return value


def checked_tracks(tracks: Sequence[Any], time: float, n: Optional[int]
                   ) -> tuple[list[CheckedTrack], Optional[int]]:
    """Validate one scan of source tracks.

    Parameters
    ----------
    tracks : sequence of SourceTrack
        The scan.
    time : float
        The scan time (already checked by :func:`scan_time`).
    n : int or None
        The central state's dimension; None when not known yet (then the first full-state
        track, or else the first ``H``, sets it).

    Returns
    -------
    checked : list of CheckedTrack
        In the order given.
    n : int or None
        The state dimension (None only for an empty scan with ``n`` unknown).

    Raises
    ------
    TypeError
        ``tracks`` not a sequence, an entry that is not a :class:`SourceTrack`, unhashable
        ids, non-numeric arrays or times.
    ValueError
        The same (source, id) twice; NaN or inf in ``x``, ``P``, ``H`` or the time; ``P``
        not square, not symmetric or not positive definite; a state size no ``H`` explains
        (``x`` of size m with ``H`` None and ``m != n``, or ``H`` not (m, n), or ``H``
        without full row rank); a time later than the scan time. Every message names the
        source and the track.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import SourceTrack, checked_tracks
    >>> scan = [SourceTrack("a", 1, np.zeros(2), np.eye(2), 0.0)]
    >>> checked, n = checked_tracks(scan, 0.0, None)
    >>> checked[0].label, n
    ("source 'a' track 1", 2)
    """
    if isinstance(tracks, (str, bytes)) or not hasattr(tracks, "__len__"):
        raise TypeError(f"tracks must be a sequence of SourceTrack, got "
                        f"{type(tracks).__name__}")
    seen: dict = {}
    out = []
    for position, track in enumerate(tracks):
        if not isinstance(track, SourceTrack):
            raise TypeError(f"tracks[{position}] must be a SourceTrack, got "
                            f"{type(track).__name__}")
        key = (_key(track.source), _key(track.id))
        label = f"source {track.source!r} track {track.id!r}"
        if key in seen:
            raise ValueError(f"{label} appears twice in the scan (tracks[{seen[key]}] and "
                             f"tracks[{position}]); a source's track ids must be unique")
        seen[key] = position
        out.append(_checked_one(track, label, time, n))
        if n is None:
            n = out[-1].x.shape[0] if out[-1].H is None else out[-1].H.shape[1]
    for item in out:  # n may have been set by a later track
        dim = item.x.shape[0] if item.H is None else item.H.shape[1]
        if dim != n:
            _explain_size(item.label, item.x.shape[0], item.H, n)
    return out, n


def _explain_size(label, m, H, n):
    if H is None:
        raise ValueError(f"{label} has a state of size {m} but the central state has size "
                         f"{n}, and no H says which part it estimates (give H of shape "
                         f"({m}, {n}))")
    raise ValueError(f"{label}'s H has shape {H.shape}; with x of size {m} and the central "
                     f"state of size {n} it must be ({m}, {n})")


def _checked_one(track, label, time, n):
    t = finite_real(track.time, f"{label}'s time")
    if t > time:
        raise ValueError(f"{label} is at time {t:g}, later than the scan time {time:g}")
    x = as_float_array(track.x, f"{label}'s x")
    if x.ndim == 2 and x.shape[1] == 1:
        x = x[:, 0]
    if x.ndim != 1 or x.shape[0] == 0:
        raise ValueError(f"{label}'s x must have shape (m,) or (m, 1), got "
                         f"{np.shape(track.x)}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{label}'s x contains non-finite values (NaN or inf)")
    m = x.shape[0]
    P = as_float_array(track.P, f"{label}'s P")
    if P.shape != (m, m):
        raise ValueError(f"{label}'s P has shape {P.shape}; x of size {m} needs ({m}, {m})")
    if not np.all(np.isfinite(P)):
        raise ValueError(f"{label}'s P contains non-finite values (NaN or inf)")
    scale = float(np.abs(np.diagonal(P)).max())
    asymmetry = float(np.abs(P - P.T).max())
    if asymmetry > SYMMETRY_RTOL * scale:
        raise ValueError(f"{label}'s P is not symmetric (max |P - P^T| = {asymmetry:.3g})")
    P = 0.5 * (P + P.T)
    L = cholesky(P, f"{label}'s P")
    H = None
    if track.H is not None:
        H = as_float_array(track.H, f"{label}'s H")
        if H.ndim != 2 or H.shape[0] != m:
            raise ValueError(f"{label}'s H has shape {H.shape}; with x of size {m} it must be "
                             f"(m, n) = ({m}, n)")
        if n is not None and H.shape[1] != n:
            _explain_size(label, m, H, n)
        if not np.all(np.isfinite(H)):
            raise ValueError(f"{label}'s H contains non-finite values (NaN or inf)")
        if H.shape[1] < m or np.linalg.matrix_rank(H) < m:
            raise ValueError(f"{label}'s H (shape {H.shape}) does not have full row rank: "
                             "its rows must be independent combinations of the state")
    elif n is not None and m != n:
        _explain_size(label, m, None, n)
    return CheckedTrack(track.source, track.id, x, P, L, t, H, label)
