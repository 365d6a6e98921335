"""The track-to-track fusion node: association, central tracks and their life cycle, and
batched fusion through the front door (:func:`cifilter.fuse`).

One :meth:`TrackFuser.update` per scan:

1. check the scan (every source track, the scan time) and predict the central tracks to
   the scan time with ``motion(dt) -> (F, Q)``;
2. associate: a source track that fed a central track at the previous scan keeps it while
   it passes the gate; the others, source by source, by an optimal assignment on the gated
   distance of the rule (:func:`~cifilter.tracking.ci_distance` for unknown correlation,
   :func:`~cifilter.tracking.naive_distance` for ``"naive"``); the source tracks left over
   are assigned to the tracks born in this scan, or start new tentative tracks (full-state
   tracks only);
3. fuse every updated central track at the scan time, with one ``fuse`` call per group of
   tracks with the same signature (number of estimates, their ``H``, their times);
4. confirm (M of N scans, or enough sources in one scan), coast, delete, remember the
   associations. The fuser's state changes only when all of this succeeded.

See ``docs/methods/track_association.rst``.
"""

from collections.abc import Mapping, Sequence
from typing import Any, Callable, Optional

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from .._numerics.alignment import motion_matrices, predicted
from .._numerics.linalg import cholesky
from ..registry import fuse, get_method
from .association import ci_distance, gated_assignment, naive_distance
from .tracks import CentralTrack, CheckedTrack, SourceTrack, checked_tracks, scan_time

__all__ = ["TrackFuser"]

# The largest condition number of F accepted to bring a late partial-state track to the
# scan time (it needs H F^-1).
_MAX_CONDITION = 1e12


class _Aligned:
    """A checked source track brought to the scan time, for gating and fusion."""

    __slots__ = ("H", "P", "_key", "fuse_H", "fuse_P", "fuse_x", "offset", "track", "x")

    def __init__(self, track: CheckedTrack, x: NDArray[np.float64], P: NDArray[np.float64],
                 H: Optional[NDArray[np.float64]], fuse_x: NDArray[np.float64],
                 fuse_P: NDArray[np.float64], fuse_H: Optional[NDArray[np.float64]],
                 offset: float) -> None:
        self.track = track
        self.x, self.P, self.H = x, P, H  # at the scan time: estimates H x
        # what enters the fusion: the full-state track as given (the front door predicts
        # it, offset = scan time - its time), or the partial one at the scan time
        self.fuse_x, self.fuse_P, self.fuse_H, self.offset = fuse_x, fuse_P, fuse_H, offset
        self._key: Optional[tuple] = None

    def key(self) -> tuple:
        """The estimate's place in a fusion signature: full or partial, size, time offset,
        ``H``."""
        if self._key is None:
            H = self.fuse_H
            self._key = ((0, self.fuse_x.shape[0], self.offset, b"") if H is None
                         else (1, H.shape, self.offset, H.tobytes()))
        return self._key


class TrackFuser:
    """A fusion node: source tracks in, central tracks out, one scan at a time.

    Parameters
    ----------
    method : str, optional
        The fusion rule, any registered name (default ``"ci"``). Late full-state tracks
        are brought to the scan time by the front door (``times=``) for the rules that
        accept it, by the same exact prediction in the node otherwise; partial-state tracks
        need a rule that accepts ``H=`` (``cifilter.fuse`` refuses the others, naming the
        rules that do).
    motion : callable
        ``motion(dt) -> (F, Q)`` for ``dt > 0``: the central state's transition over ``dt``
        and the process noise it adds (n x n each).
    dim : int, optional
        The central state's dimension n; default: that of the first full-state track (or
        the first ``H``).
    gate : float, optional
        The gate probability in (0, 1): a pair is a candidate when its distance is at most
        ``chi2.ppf(gate, m)`` (m the size of the source's estimate). Default 0.9999.
    confirm : (int, int), optional
        A tentative track is confirmed when it was updated in M of the last N scans
        (default (2, 3)); a tentative track that has lived N scans without reaching M is
        deleted.
    confirm_sources : int, optional
        A track updated by at least this many sources in one scan is confirmed at once
        (default 2).
    delete_after : int, optional
        A track is deleted after this many consecutive scans without a source track
        (default 3).
    association : {"ci", "naive"}, optional
        The gated distance: ``"ci"`` (the bound over every correlation,
        :func:`~cifilter.tracking.ci_distance`) or ``"naive"`` (independence,
        :func:`~cifilter.tracking.naive_distance`). Default ``"naive"`` for
        ``method="naive"`` and ``"ci"`` otherwise.
    fuse_prediction : bool, optional
        Whether a central track's own prediction is one of the estimates it is fused from.
        Default: True for ``"ci"`` (CI needs no independence, and the prediction keeps the
        track's memory), False otherwise (``"naive"`` would count the sources' earlier
        information twice). A track whose sources at a scan are all of part of the state is
        always fused with its prediction.
    **options
        Options of the rule, passed to :func:`cifilter.fuse` (e.g. ``criterion="det"``).

    Attributes
    ----------
    tracks : list of CentralTrack
        The live central tracks after the last update, sorted by id.
    time : float or None
        The last scan time (None before the first scan).
    last_scan : Mapping
        Diagnostics of the last update: ``"fuse_calls"`` (calls of :func:`cifilter.fuse`),
        ``"groups"`` (a list of ``(estimates per track, tracks)`` per call), ``"kept"``
        (associations kept from the previous scan), ``"assigned"`` (new associations),
        ``"born"`` and ``"deleted"`` (central ids), ``"unassigned"`` (the (source, id) of
        partial-state tracks that matched no central track and cannot start one).

    Raises
    ------
    ValueError
        An unknown method, an option out of range.
    TypeError
        ``motion`` not callable, options of the wrong type.

    Notes
    -----
    A partial-state source track (``H`` given) alone cannot start a central track: it does
    not observe the whole state. It updates central tracks it is associated with.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.tracking import TrackFuser, SourceTrack
    >>> def motion(dt):
    ...     return np.array([[1.0, dt], [0.0, 1.0]]), 0.01 * np.eye(2)
    >>> fuser = TrackFuser("ci", motion=motion)
    >>> scan = [SourceTrack("a", 1, np.array([0.0, 1.0]), np.eye(2), 0.0),
    ...         SourceTrack("b", 7, np.array([0.2, 1.0]), np.eye(2), 0.0)]
    >>> [(c.id, c.confirmed, dict(c.sources)) for c in fuser.update(scan, 0.0)]
    [(1, True, {'a': 1, 'b': 7})]
    >>> scan = [SourceTrack("a", 1, np.array([1.0, 1.0]), np.eye(2), 1.0)]
    >>> [(c.id, dict(c.sources)) for c in fuser.update(scan, 1.0)]
    [(1, {'a': 1})]
    >>> fuser.last_scan["fuse_calls"]
    1
    """

    def __init__(self, method: str = "ci", *, motion: Callable[..., Any],
                 dim: Optional[int] = None, gate: float = 0.9999,
                 confirm: tuple[int, int] = (2, 3), confirm_sources: int = 2,
                 delete_after: int = 3, association: Optional[str] = None,
                 fuse_prediction: Optional[bool] = None, **options: Any) -> None:
        record = get_method(method)
        self.method = record.name
        self._accepts_times = "times" in record.front_door
        if not callable(motion):
            raise TypeError(f"motion must be callable (dt -> (F, Q)), got "
                            f"{type(motion).__name__}")
        self.motion = motion
        if dim is not None:
            dim = _positive_int(dim, "dim")
        self.dim = dim
        if isinstance(gate, (bool, np.bool_)) or not isinstance(gate, (int, float, np.floating)):
            raise TypeError(f"gate must be a probability (a float), got {type(gate).__name__}")
        if not 0.0 < float(gate) < 1.0:
            raise ValueError(f"gate must be a probability in (0, 1), got {gate}")
        self.gate = float(gate)
        if not (isinstance(confirm, (tuple, list)) and len(confirm) == 2):
            raise TypeError(f"confirm must be a pair (M, N), got {confirm!r}")
        M, N = _positive_int(confirm[0], "confirm's M"), _positive_int(confirm[1], "confirm's N")
        if M > N:
            raise ValueError(f"confirm=(M, N) needs M <= N, got {tuple(confirm)}")
        self.confirm = (M, N)
        self.confirm_sources = _positive_int(confirm_sources, "confirm_sources")
        self.delete_after = _positive_int(delete_after, "delete_after")
        if association is None:
            association = "naive" if self.method == "naive" else "ci"
        if association not in ("ci", "naive"):
            raise ValueError(f"association must be 'ci' or 'naive', got {association!r}")
        self.association = association
        if fuse_prediction is None:
            fuse_prediction = self.method == "ci"
        if not isinstance(fuse_prediction, (bool, np.bool_)):
            raise TypeError(f"fuse_prediction must be a bool, got "
                            f"{type(fuse_prediction).__name__}")
        self.fuse_prediction = bool(fuse_prediction)
        self.options = dict(options)
        self._thresholds: dict = {}
        self.reset()

    # --- state -------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget every track, the associations and the time.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.tracking import TrackFuser
        >>> fuser = TrackFuser(motion=lambda dt: (np.eye(1), np.eye(1)))
        >>> fuser.reset(); fuser.tracks, fuser.time
        ([], None)
        """
        self._tracks: tuple = ()
        self._history: dict = {}
        self._memory: dict = {}
        self._next_id = 1
        self._time: Optional[float] = None
        self._n: Optional[int] = self.dim
        self.last_scan: Mapping[str, Any] = {}

    @property
    def tracks(self) -> list[CentralTrack]:
        """The live central tracks after the last update, sorted by id."""
        return list(self._tracks)

    @property
    def time(self) -> Optional[float]:
        """The last scan time (None before the first scan)."""
        return self._time

    # --- one scan ----------------------------------------------------------------------

    def update(self, tracks: Sequence[SourceTrack], time: float) -> list[CentralTrack]:
        """Process one scan of source tracks.

        Parameters
        ----------
        tracks : sequence of SourceTrack
            Every source's tracks at this scan (each at a time no later than ``time``).
        time : float
            The scan time, not earlier than the previous one.

        Returns
        -------
        list of CentralTrack
            Every live central track at ``time`` (tentative and confirmed), sorted by id.

        Raises
        ------
        ValueError
            A scan time earlier than the fuser's; a bad source track (the same (source, id)
            twice, NaN, a covariance that is not symmetric or not positive definite, a state
            size no ``H`` explains, a time later than the scan time), named by source and
            id; a late partial-state track whose ``F`` is singular; a fusion that fails or
            gives a covariance that is not finite, symmetric and positive definite.
        TypeError
            Entries that are not :class:`SourceTrack`, non-numeric values.

        Notes
        -----
        When it raises, the fuser is unchanged (tracks, associations, time).

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.tracking import TrackFuser, SourceTrack
        >>> fuser = TrackFuser(motion=lambda dt: (np.eye(1), 0.1 * dt * np.eye(1)))
        >>> out = fuser.update([SourceTrack("a", 1, [0.0], [[1.0]], 0.0)], 0.0)
        >>> out[0].id, out[0].confirmed, out[0].hits
        (1, False, 1)
        """
        t = scan_time(time, self._time)
        checked, n = checked_tracks(tracks, t, self._n)
        motions: dict = {}

        def step(dt):
            if dt not in motions:
                motions[dt] = motion_matrices(self.motion, dt, n)
            return motions[dt]

        # the central tracks predicted to the scan time
        old = list(self._tracks)
        pred_x, pred_P = [], []
        if old:
            X = np.stack([c.x for c in old])
            P = np.stack([c.P for c in old])
            if self._time is not None and t > self._time:
                F, Q = step(t - self._time)
                X, P = predicted(X, cholesky(P, "a central track's P"), F, Q)
            pred_x, pred_P = list(X), list(P)
        aligned = [self._aligned(item, t, step) for item in checked]

        # association
        assigned: dict = {}  # central index -> {source: aligned index}
        distances: dict = {}  # central index -> {source: distance}
        taken = np.zeros(len(aligned), dtype=bool)
        kept = 0
        index_of = {c.id: k for k, c in enumerate(old)}
        remembered = [(i, index_of[self._memory[a.track.source, a.track.id]])
                      for i, a in enumerate(aligned)
                      if self._memory.get((a.track.source, a.track.id)) in index_of]
        if remembered:
            pairs = self._pair_distances([aligned[i] for i, _ in remembered],
                                         [pred_x[k] for _, k in remembered],
                                         [pred_P[k] for _, k in remembered])
            for (i, k), s in zip(remembered, pairs):
                a = aligned[i]
                if s <= self._threshold(a.x.shape[0]):
                    assigned.setdefault(k, {})[a.track.source] = i
                    distances.setdefault(k, {})[a.track.source] = float(s)
                    taken[i] = True
                    kept += 1
        sources = list(dict.fromkeys(a.track.source for a in aligned))
        fresh = 0
        for source in sources:
            rows = [i for i, a in enumerate(aligned) if a.track.source == source and not taken[i]]
            columns = [k for k in range(len(old)) if source not in assigned.get(k, {})]
            fresh += self._assign(aligned, rows, columns, pred_x, pred_P, assigned,
                                  distances, taken)
        # left over: to the tracks born in this scan, or a new track
        born: list = []  # aligned indices that started a track
        born_x: list = []
        born_P: list = []
        unassigned = []
        for source in sources:
            rows = [i for i, a in enumerate(aligned) if a.track.source == source and not taken[i]]
            base = len(old)
            columns = [base + j for j in range(len(born))
                       if source not in assigned.get(base + j, {})]
            fresh += self._assign(aligned, rows, columns, pred_x + born_x, pred_P + born_P,
                                  assigned, distances, taken)
            for i in rows:
                if taken[i]:
                    continue
                a = aligned[i]
                if a.H is not None:
                    unassigned.append((a.track.source, a.track.id))
                    continue
                k = base + len(born)
                born.append(i)
                born_x.append(a.x)
                born_P.append(a.P)
                assigned[k] = {source: i}
                distances[k] = {}
                taken[i] = True

        # fusion, batched by signature
        all_x = pred_x + born_x
        all_P = pred_P + born_P
        ids = [c.id for c in old] + [self._next_id + j for j in range(len(born))]
        results, fuse_calls, groups = self._fuse_all(assigned, aligned, all_x, all_P,
                                                     len(old), t, ids)

        # life cycle
        M, N = self.confirm
        new_tracks = []
        history = {}
        memory = {}
        deleted = []
        next_id = self._next_id
        born_ids = []
        for k in range(len(old) + len(born)):
            members = assigned.get(k, {})
            if k < len(old):
                previous = old[k]
                cid, hits, born_time = previous.id, previous.hits, previous.born
                misses, confirmed = previous.misses, previous.confirmed
                past = self._history[cid]
            else:
                cid, hits, born_time, misses, confirmed, past = next_id, 0, t, 0, False, ()
                next_id += 1
                born_ids.append(cid)
            if members:
                x, P, info = results[k]
                info = dict(info, distances=dict(distances.get(k, {})))
                hits, misses = hits + 1, 0
            else:
                x, P, info = all_x[k], all_P[k], {}
                misses += 1
            past = (past + (bool(members),))[-N:]
            confirmed = (confirmed or sum(past) >= M
                         or len(members) >= self.confirm_sources)
            if misses >= self.delete_after or (not confirmed and len(past) >= N
                                               and sum(past) < M):
                deleted.append(cid)
                continue
            ordered = {aligned[i].track.source: aligned[i].track.id
                       for i in sorted(members.values(), key=lambda i: aligned[i].key())}
            for source, i in members.items():
                memory[(source, aligned[i].track.id)] = cid
            x = np.array(x, dtype=float)
            P = np.array(P, dtype=float)
            x.flags.writeable = False
            P.flags.writeable = False
            new_tracks.append(CentralTrack(id=cid, x=x, P=P, time=t, confirmed=confirmed,
                                           sources=ordered, hits=hits, misses=misses,
                                           born=born_time, info=info))
            history[cid] = past
        new_tracks.sort(key=lambda c: c.id)

        # commit
        self._tracks = tuple(new_tracks)
        self._history = history
        self._memory = memory
        self._next_id = next_id
        self._time = t
        self._n = n
        self.last_scan = dict(fuse_calls=fuse_calls, groups=groups, kept=kept,
                              assigned=fresh, born=born_ids, deleted=deleted,
                              unassigned=unassigned)
        return list(self._tracks)

    # --- helpers -----------------------------------------------------------------------

    def _threshold(self, m: int) -> float:
        """``chi2.ppf(gate, m)``, computed once per m."""
        value = self._thresholds.get(m)
        if value is None:
            value = self._thresholds[m] = float(chi2.ppf(self.gate, m))
        return value

    def _aligned(self, item: CheckedTrack, t: float, step: Callable) -> _Aligned:
        """The source track at the scan time (``docs/methods/track_association.rst``)."""
        offset = t - item.time
        if offset == 0.0:
            return _Aligned(item, item.x, item.P, item.H, item.x, item.P, item.H, 0.0)
        F, Q = step(offset)
        if item.H is None:
            x, P = predicted(item.x, item.L, F, Q)
            if self._accepts_times:  # the front door predicts it (times=)
                return _Aligned(item, x, P, None, item.x, item.P, None, offset)
            # the same exact prediction here, for a rule without times=
            return _Aligned(item, x, P, None, x, P, None, 0.0)
        # a late estimate of H x(t_s) is one of H F^-1 x(t) with the error
        # e - H F^-1 w, w the process noise in between (independent of e)
        if not np.linalg.cond(F) <= _MAX_CONDITION:
            raise ValueError(f"{item.label} estimates part of the state at time {item.time:g}, "
                             f"earlier than the scan; bringing it to {t:g} needs F^-1, but F "
                             f"of motion({offset!r}) is singular or too ill-conditioned")
        G = np.linalg.solve(F.T, item.H.T).T  # H F^-1
        P = item.P + G @ Q @ G.T  # P_s plus a positive semidefinite term
        P = 0.5 * (P + P.T)
        return _Aligned(item, item.x, P, G, item.x, P, G, 0.0)

    def _pair_distances(self, rows: Sequence[_Aligned], xs: Sequence[NDArray[np.float64]],
                        Ps: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
        """The gated distance of ``rows[r]`` to the central estimate ``(xs[r], Ps[r])``, for
        every r; rows with the same ``H`` in one batched call. A distance above the gate
        may be a lower bound only (enough to reject it)."""
        out = np.full(len(rows), np.inf)
        groups: dict = {}
        for r, a in enumerate(rows):
            key = b"" if a.H is None else (a.H.shape, a.H.tobytes())
            groups.setdefault(key, []).append(r)
        for members in groups.values():
            H = rows[members[0]].H
            X = np.stack([xs[r] for r in members])
            P = np.stack([Ps[r] for r in members])
            if H is None:
                hx, A = X, P
            else:
                hx = X @ H.T
                A = H @ P @ H.T
                A = 0.5 * (A + np.swapaxes(A, -1, -2))
            d = np.stack([rows[r].x for r in members]) - hx
            B = np.stack([rows[r].P for r in members])
            if self.association == "naive":
                s = naive_distance(d, A, B)
            else:
                s, _ = ci_distance(d, A, B, threshold=self._threshold(d.shape[-1]))
            out[members] = s
        return out

    def _distances(self, rows: Sequence[_Aligned], xs: Sequence[NDArray[np.float64]],
                   Ps: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
        """The gated distance of each row to each central estimate, (rows, columns)."""
        if not rows or not xs:
            return np.full((len(rows), len(xs)), np.inf)
        count = len(xs)
        flat = self._pair_distances([a for a in rows for _ in range(count)],
                                    list(xs) * len(rows), list(Ps) * len(rows))
        return flat.reshape(len(rows), count)

    def _assign(self, aligned: list, rows: list, columns: list, xs: list, Ps: list,
                assigned: dict, distances: dict, taken: NDArray[np.bool_]) -> int:
        """Assign ``rows`` (aligned indices of one source) to ``columns`` (central
        indices); returns how many were assigned."""
        if not rows or not columns:
            return 0
        cost = self._distances([aligned[i] for i in rows], [xs[k] for k in columns],
                               [Ps[k] for k in columns])
        limits = np.array([self._threshold(aligned[i].x.shape[0]) for i in rows])
        cost = np.where(cost <= limits[:, None], cost, np.inf)
        pairs = gated_assignment(cost, np.inf)
        for r, c in pairs:
            i, k = rows[r], columns[c]
            source = aligned[i].track.source
            assigned.setdefault(k, {})[source] = i
            distances.setdefault(k, {})[source] = float(cost[r, c])
            taken[i] = True
        return len(pairs)

    def _fuse_all(self, assigned, aligned, all_x, all_P, n_old, t, ids):
        """Fuse every updated track; one :func:`cifilter.fuse` call per signature."""
        results: dict = {}
        batches: dict = {}
        for k, members in assigned.items():
            if not members:
                continue
            items = sorted((aligned[i] for i in members.values()), key=_Aligned.key)
            partial_only = all(a.H is not None for a in items)
            with_prediction = k < n_old and (self.fuse_prediction or partial_only)
            entries = []
            if with_prediction:
                entries.append((all_x[k], all_P[k], None, 0.0))
            entries.extend((a.fuse_x, a.fuse_P, a.fuse_H, a.offset) for a in items)
            if len(entries) == 1:  # one full-state source track: it is the track
                a = items[0]
                results[k] = (a.x, a.P, dict(method=self.method, estimates=1,
                                             prediction=False))
                continue
            signature = tuple((x.shape[0], None if H is None else (H.shape, H.tobytes()),
                               offset) for x, _, H, offset in entries)
            batches.setdefault(signature, []).append((k, entries, with_prediction))
        groups = []
        for signature, members in batches.items():
            count = len(signature)
            estimates = [(np.stack([entries[j][0] for _, entries, _ in members]),
                          np.stack([entries[j][1] for _, entries, _ in members]))
                         for j in range(count)]
            Hs = [members[0][1][j][2] for j in range(count)]
            offsets = [members[0][1][j][3] for j in range(count)]
            kwargs: dict = dict(self.options)
            if any(H is not None for H in Hs):
                kwargs["H"] = Hs
            if any(offset != 0.0 for offset in offsets):
                kwargs.update(times=[t - offset for offset in offsets], at=t,
                              motion=self.motion)
            result = fuse(estimates, self.method, **kwargs)
            groups.append((count, len(members)))
            x = np.asarray(result.x).reshape(len(members), -1)
            P = np.asarray(result.P)
            _check_result(x, P, [ids[k] for k, _, _ in members])
            weights = None if result.weights is None else np.asarray(result.weights)
            converged = result.info.get("converged")
            for b, (k, _, with_prediction) in enumerate(members):
                info: dict = dict(method=self.method, estimates=count,
                                  prediction=with_prediction)
                if weights is not None:
                    info["weights"] = tuple(float(v) for v in weights[b])
                if converged is not None:
                    info["converged"] = bool(np.asarray(converged).reshape(-1)[b]
                                             if np.ndim(converged) else converged)
                results[k] = (x[b], P[b], info)
        return results, len(groups), groups


def _check_result(x, P, which):
    """A fused result that is not finite, symmetric and positive definite is an error."""
    if np.isfinite(x).all() and np.isfinite(P).all():
        scale = np.abs(np.diagonal(P, axis1=-2, axis2=-1)).max(axis=-1)
        asymmetry = np.abs(P - np.swapaxes(P, -1, -2)).max(axis=(-2, -1))
        if np.all(asymmetry <= 1e-8 * scale):
            try:
                np.linalg.cholesky(P)
                return
            except np.linalg.LinAlgError:
                pass  # find the track below
    for b in range(x.shape[0]):
        bad = None
        if not (np.all(np.isfinite(x[b])) and np.all(np.isfinite(P[b]))):
            bad = "is not finite"
        elif np.abs(P[b] - P[b].T).max() > 1e-8 * np.abs(np.diagonal(P[b])).max():
            bad = "has a covariance that is not symmetric"
        else:
            try:
                np.linalg.cholesky(P[b])
            except np.linalg.LinAlgError:
                bad = "has a covariance that is not positive definite"
        if bad is not None:
            raise ValueError(f"the fusion of central track {which[b]} {bad}")


def _positive_int(value, name):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    if value < 1:
        raise ValueError(f"{name} must be at least 1, got {value}")
    return int(value)

