"""Run a fusion node over a simulated multi-target scenario and score its central tracks.

:func:`run_tracking` feeds the source tracks of :func:`cifilter.network.simulate_targets`
scan by scan to a :class:`~cifilter.tracking.TrackFuser`; :func:`score_tracking` scores
the confirmed central tracks against the truth:

* **GOSPA** (:func:`cifilter.metrics.gospa`, ``alpha = 2``) of the positions per scan,
  averaged over the scans, with its localisation, missed and false parts;
* every scan, the live targets and the confirmed central tracks are *matched* as CLEAR
  MOT does (Bernardin & Stiefelhagen 2008): a target keeps the central track it was
  matched to at its previous match while their positions are closer than ``gate`` (by
  default ``c``), the others are matched by the optimal assignment of positions closer
  than ``gate`` (so two crossing targets, at one point for a scan, are not swapped by the
  score itself). Of the matched pairs: the **ANEES** of the full state with the chi-square
  bounds of as many independent values (:func:`cifilter.metrics.anees`; a scan's values
  are correlated with the next scan's, so the band is narrower than the spread of a
  consistent tracker's ANEES: read it as a bound on the mean, not as a test), the
  **position RMSE**; **ID switches** (a target matched to another central track than at
  its previous match); the mean numbers per scan of **false** (unmatched confirmed) central
  tracks and **missed** (unmatched live) targets; the wall time of ``update`` per scan.

:func:`score_sources` gives the position RMSE and ANEES of each sensor's own tracks (the
reference a fusion node must beat), :func:`compare_tracking` runs several rules on the same
data and :func:`format_tracking` prints the rows in the style of
:func:`cifilter.network.format_summary`.
"""

import time as _time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Callable, Optional, Union

import numpy as np
from numpy.typing import NDArray

from .. import metrics
from .._numerics.validation import check_int, check_scalar
from ..network.targets import POSITION, TargetData
from ..registry import get_method
from .fuser import TrackFuser
from .tracks import CentralTrack, SourceTrack

__all__ = [
    "DEFAULT_METHODS",
    "TrackingRun",
    "TrackingScore",
    "compare_tracking",
    "format_tracking",
    "run_tracking",
    "score_sources",
    "score_tracking",
]

DEFAULT_METHODS = ("ci", "split-ci", "ici", "pci", "naive")
"""The rules :func:`compare_tracking` runs by default (``pci`` with the bound ``rho`` of
its ``options``)."""

_PCI_RHO = 0.5  # the correlation bound assumed for "pci" unless options give one


@dataclass(frozen=True)
class TrackingRun:
    """The central tracks of one rule over one simulation (:func:`run_tracking`).

    The parameters are also the attributes.

    Parameters
    ----------
    method : str
        The rule.
    tracks : tuple of tuple of CentralTrack
        Per scan, every live central track (tentative and confirmed) after the update.
    times : ndarray, shape (scans,)
        Scan times.
    seconds : ndarray, shape (scans,)
        Wall time of each ``update`` call [s].
    options : dict
        The fuser's options.

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> from cifilter.tracking import run_tracking
    >>> run = run_tracking(simulate_targets(multi_target(steps=20), rng=0), "ci")
    >>> len(run.tracks), run.method
    (20, 'ci')
    """

    method: str
    tracks: tuple[tuple[CentralTrack, ...], ...]
    times: NDArray[np.float64]
    seconds: NDArray[np.float64]
    options: Mapping[str, Any]


def run_tracking(data: TargetData, method: str = "ci", *,
                 motion: Optional[Callable[..., Any]] = None,
                 **fuser_options: Any) -> TrackingRun:
    """Run a :class:`~cifilter.tracking.TrackFuser` over every scan of a simulation.

    Parameters
    ----------
    data : TargetData
        From :func:`cifilter.network.simulate_targets`.
    method : str, optional
        A registered rule (default ``"ci"``).
    motion : callable, optional
        ``motion(dt) -> (F, Q)``; default the scenario's own model
        (:meth:`cifilter.network.TargetScenario.motion`).
    **fuser_options
        Options of :class:`~cifilter.tracking.TrackFuser` (``gate``, ``confirm``,
        ``delete_after``, ...) and of the rule (``rho=`` for ``"pci"``).

    Returns
    -------
    TrackingRun

    Raises
    ------
    TypeError
        ``data`` is not a :class:`~cifilter.network.TargetData`.
    ValueError
        From the fuser: an unknown rule, a rule that cannot fuse these tracks.

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> from cifilter.tracking import run_tracking
    >>> data = simulate_targets(multi_target(steps=20), rng=0)
    >>> run = run_tracking(data, "naive", delete_after=2)
    >>> all(track.time == run.times[-1] for track in run.tracks[-1])
    True
    """
    if not isinstance(data, TargetData):
        raise TypeError(f"data must be TargetData (cifilter.network.simulate_targets), got "
                        f"{type(data).__name__}")
    get_method(method)  # an unknown name fails here, with the registry's message
    fuser = TrackFuser(method, motion=data.scenario.motion if motion is None else motion,
                       **fuser_options)
    scans = []
    seconds = np.zeros(data.steps)
    for k in range(data.steps):
        tracks = [SourceTrack(*report) for report in data.reports[k]]
        start = _time.perf_counter()
        out = fuser.update(tracks, float(data.times[k]))
        seconds[k] = _time.perf_counter() - start
        scans.append(tuple(out))
    return TrackingRun(method, tuple(scans), data.times.copy(), seconds, dict(fuser_options))


@dataclass(frozen=True)
class TrackingScore:
    """Scores of central tracks against the truth (:func:`score_tracking`).

    The parameters are also the attributes.

    Parameters
    ----------
    method : str
        The rule.
    gospa : float
        Mean GOSPA distance of the positions per scan [m].
    localisation, missed, false : float
        Mean GOSPA parts per scan (``c^p / 2`` per missed target and per false track;
        their sum is the mean of GOSPA**p).
    anees : float
        Mean NEES of the full state of the matched central tracks (NaN without matches).
    lower, upper : float
        Chi-square bounds of the mean of as many independent NEES values.
    verdict : str
        ``"conservative"`` (below ``lower``), ``"consistent"`` or ``"overconfident"``.
    matches : int
        Matched (target, central track) pairs over all scans.
    rmse : float
        Position RMSE of the matched pairs [m].
    id_switches : int
        Times a target was matched to another central track than at its previous match.
    false_tracks : float
        Mean confirmed central tracks per scan matched to no target.
    missed_targets : float
        Mean live targets per scan matched to no confirmed central track.
    ms_per_scan : float
        Mean wall time of an ``update`` [ms].
    scans : int
        Scans scored.
    c, gate : float
        GOSPA's cut-off and the matching distance [m].

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> from cifilter.tracking import run_tracking, score_tracking
    >>> data = simulate_targets(multi_target(steps=30), rng=0)
    >>> score = score_tracking(run_tracking(data, "ci"), data)
    >>> score.scans, score.verdict in ("conservative", "consistent", "overconfident")
    (30, True)
    """

    method: str
    gospa: float
    localisation: float
    missed: float
    false: float
    anees: float
    lower: float
    upper: float
    verdict: str
    matches: int
    rmse: float
    id_switches: int
    false_tracks: float
    missed_targets: float
    ms_per_scan: float
    scans: int
    c: float
    gate: float

    def as_row(self) -> dict[str, Any]:
        """The score as a dict (a row of :func:`format_tracking`).

        Returns
        -------
        dict
            Every field by name.

        Examples
        --------
        >>> from cifilter.network import multi_target, simulate_targets
        >>> from cifilter.tracking import run_tracking, score_tracking
        >>> data = simulate_targets(multi_target(steps=20), rng=0)
        >>> row = score_tracking(run_tracking(data, "naive"), data).as_row()
        >>> row["method"], row["scans"]
        ('naive', 20)
        """
        return {key: getattr(self, key) for key in self.__dataclass_fields__}


def _verdict(value, lower, upper):
    if not np.isfinite(value):
        return "-"
    return "conservative" if value < lower else (
        "overconfident" if value > upper else "consistent")


def _matches(positions, xs, confirmed, targets, last_match, gate, p):
    """CLEAR MOT's matching: last scan's pairs kept while within the gate, the rest by
    an optimal assignment of positions closer than the gate."""
    kept = []
    taken_rows, taken_cols = set(), set()
    column = {track.id: j for j, track in enumerate(confirmed)}
    for i, target in enumerate(targets):
        j = column.get(last_match.get(int(target), -1))
        if j is not None and np.linalg.norm(xs[j, list(POSITION)] - positions[i]) < gate:
            kept.append((i, j))
            taken_rows.add(i)
            taken_cols.add(j)
    rows = [i for i in range(len(targets)) if i not in taken_rows]
    cols = [j for j in range(len(confirmed)) if j not in taken_cols]
    if rows and cols:
        rest = metrics.gospa(positions[rows], xs[np.ix_(cols, list(POSITION))], c=gate, p=p)
        kept.extend((rows[a], cols[b]) for a, b in rest.assignment)
    return kept


def score_tracking(run: Union[TrackingRun, Sequence[TrackingRun]],
                   data: Union[TargetData, Sequence[TargetData]], *, c: float = 50.0,
                   p: float = 2.0, gate: Optional[float] = None, skip: int = 0,
                   confidence: float = 0.95) -> TrackingScore:
    """Score the confirmed central tracks of one or several runs against their truth.

    Parameters
    ----------
    run : TrackingRun or sequence of TrackingRun
        From :func:`run_tracking` (several runs of one rule: the scores pool them).
    data : TargetData or sequence of TargetData
        The simulations the runs were made on (as many as runs).
    c : float, optional
        GOSPA's cut-off distance [m] (default 50).
    p : float, optional
        GOSPA's exponent (default 2).
    gate : float, optional
        Largest position distance of a matched pair [m] (default ``c``).
    skip : int, optional
        Scans at the start left out of every score (default 0).
    confidence : float, optional
        Probability of the ANEES bounds (default 0.95).

    Returns
    -------
    TrackingScore

    Raises
    ------
    ValueError
        Runs and simulations of different numbers or lengths, runs of different rules, bad
        ``c``, ``p``, ``gate``, ``skip`` or ``confidence``.

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> from cifilter.tracking import run_tracking, score_tracking
    >>> data = simulate_targets(multi_target(steps=30), rng=0)
    >>> score = score_tracking(run_tracking(data, "ci"), data, c=40.0)
    >>> bool(score.rmse < 10.0), score.c, score.gate
    (True, 40.0, 40.0)
    """
    runs = [run] if isinstance(run, TrackingRun) else list(run)
    datas = [data] if isinstance(data, TargetData) else list(data)
    if not runs or len(runs) != len(datas):
        raise ValueError(f"need as many runs as simulations (at least one), got {len(runs)} "
                         f"runs and {len(datas)} simulations")
    if len({r.method for r in runs}) != 1:
        raise ValueError(f"runs of one rule expected, got {sorted({r.method for r in runs})}")
    c = check_scalar(c, "c", low=0, low_open=True)
    gate = c if gate is None else check_scalar(gate, "gate", low=0, low_open=True)
    skip = check_int(skip, "skip", low=0)
    distances, parts, nees, errors = [], [], [], []
    switches = 0
    false_counts: list[int] = []
    missed_counts: list[int] = []
    seconds: list[float] = []
    for one, sim in zip(runs, datas):
        if not isinstance(one, TrackingRun) or not isinstance(sim, TargetData):
            raise TypeError("run must be TrackingRun(s) and data TargetData")
        if len(one.tracks) != sim.steps:
            raise ValueError(f"a run of {len(one.tracks)} scans does not belong to a "
                             f"simulation of {sim.steps}")
        if skip >= sim.steps:
            raise ValueError(f"skip={skip} leaves no scan of {sim.steps}")
        last_match: dict[int, int] = {}
        for k in range(skip, sim.steps):
            targets = np.nonzero(sim.alive[k])[0]
            truth = sim.truth[k, targets]
            confirmed = [t for t in one.tracks[k] if t.confirmed]
            xs = np.array([t.x for t in confirmed]).reshape(len(confirmed), -1)
            result = metrics.gospa(truth[:, POSITION], xs[:, POSITION] if len(xs) else
                                   np.zeros((0, 2)), c=c, p=p)
            distances.append(result.distance)
            parts.append((result.localisation, result.missed, result.false))
            pairs = _matches(truth[:, POSITION], xs, confirmed, targets, last_match, gate, p)
            for i, j in pairs:
                track = confirmed[j]
                target = int(targets[i])
                nees.append(float(metrics.nees(truth[i], track.x, track.P)))
                errors.append(track.x[list(POSITION)] - truth[i, list(POSITION)])
                if target in last_match and last_match[target] != track.id:
                    switches += 1
                last_match[target] = track.id
            false_counts.append(len(confirmed) - len(pairs))
            missed_counts.append(len(targets) - len(pairs))
        seconds.extend(one.seconds[skip:])
    if nees:
        result_anees = metrics.anees(np.array(nees), 4, confidence=confidence)
        value = float(result_anees.value)
        lower, upper = result_anees.lower, result_anees.upper
        rmse = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=-1))))
    else:
        value = lower = upper = rmse = float("nan")
    mean_parts = np.mean(parts, axis=0)
    return TrackingScore(
        runs[0].method, float(np.mean(distances)), float(mean_parts[0]),
        float(mean_parts[1]), float(mean_parts[2]), value, float(lower), float(upper),
        _verdict(value, lower, upper), len(nees), rmse, switches,
        float(np.mean(false_counts)), float(np.mean(missed_counts)),
        1e3 * float(np.mean(seconds)), len(distances), c, gate)


def score_sources(data: Union[TargetData, Sequence[TargetData]], *,
                  skip: int = 0) -> list[dict[str, Any]]:
    """Position RMSE and ANEES of each sensor's own tracks of true targets.

    The reference of a fusion node: its central tracks should be more accurate than the
    best single source. Reports of false tracks, of targets no longer alive and late
    reports (scored against the truth of their own time) are handled as in
    :meth:`cifilter.network.TargetData.report_truth`; partial reports are scored on the
    position.

    Parameters
    ----------
    data : TargetData or sequence of TargetData
        Simulations (pooled).
    skip : int, optional
        Scans at the start left out (default 0).

    Returns
    -------
    list of dict
        One row per sensor: ``method`` (``"source <name>"``), ``rmse`` (position),
        ``anees`` (of the state the sensor sends: 4-D, or 2-D for a partial sensor),
        ``matches`` (reports scored).

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> from cifilter.tracking import score_sources
    >>> rows = score_sources(simulate_targets(multi_target(steps=30), rng=0))
    >>> [row["method"] for row in rows]
    ['source radar-1', 'source radar-2', 'source camera']
    """
    datas = [data] if isinstance(data, TargetData) else list(data)
    skip = check_int(skip, "skip", low=0)
    names = [sensor.name for sensor in datas[0].scenario.sensors]
    errors: dict[str, list[Any]] = {name: [] for name in names}
    nees: dict[str, list[float]] = {name: [] for name in names}
    for sim in datas:
        for k in range(skip, sim.steps):
            truth = sim.report_truth(k)
            for report, target, true in zip(sim.reports[k], sim.origin[k], truth):
                if target < 0 or not np.all(np.isfinite(true)):
                    continue
                source, _, x, P, _, H = report
                state = true if H is None else np.asarray(H) @ true
                position = true[list(POSITION)]
                estimate = x[list(POSITION)] if H is None else x
                errors[source].append(estimate - position)
                nees[source].append(float(metrics.nees(state, x, P)))
    rows = []
    for name in names:
        count = len(nees[name])
        rows.append({
            "method": f"source {name}",
            "rmse": float(np.sqrt(np.mean(np.sum(np.square(errors[name]), axis=-1))))
            if count else float("nan"),
            "anees": float(np.mean(nees[name])) if count else float("nan"),
            "matches": count,
        })
    return rows


def compare_tracking(data: Union[TargetData, Sequence[TargetData]],
                     methods: Sequence[str] = DEFAULT_METHODS, *,
                     options: Optional[Mapping[str, Mapping[str, Any]]] = None,
                     motion: Optional[Callable[..., Any]] = None, c: float = 50.0,
                     gate: Optional[float] = None, skip: int = 0,
                     runs_out: Optional[dict[str, list[TrackingRun]]] = None,
                     **fuser_options: Any) -> list[dict[str, Any]]:
    """Run and score several rules on the same simulations.

    Parameters
    ----------
    data : TargetData or sequence of TargetData
        Simulations (the scores pool them).
    methods : sequence of str, optional
        Registered rules (default :data:`DEFAULT_METHODS`).
    options : mapping, optional
        Per rule, its own options (default ``{"pci": {"rho": 0.5}}``: an *assumed*
        correlation bound, not one derived from the scenario).
    motion : callable, optional
        ``motion(dt) -> (F, Q)`` (default the scenario's).
    c, gate, skip
        As in :func:`score_tracking`.
    runs_out : dict, optional
        If given, filled with ``{method: [TrackingRun, ...]}`` (one per simulation) of the
        rules that ran, for figures.
    **fuser_options
        Options of every :class:`~cifilter.tracking.TrackFuser`.

    Returns
    -------
    list of dict
        One row per rule (:meth:`TrackingScore.as_row`, ``guarantee`` from the registry);
        a rule that cannot run gets ``{"method", "guarantee", "error"}``.

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> from cifilter.tracking import compare_tracking
    >>> data = simulate_targets(multi_target(steps=30), rng=0)
    >>> rows = compare_tracking(data, ["ci", "naive"])
    >>> [row["method"] for row in rows]
    ['ci', 'naive']
    """
    datas = [data] if isinstance(data, TargetData) else list(data)
    per_rule = {"pci": {"rho": _PCI_RHO}} if options is None else options
    rows = []
    for method in methods:
        guarantee = get_method(method).guarantee
        extra = {**fuser_options, **dict(per_rule.get(method, {}))}
        try:
            runs = [run_tracking(sim, method, motion=motion, **extra) for sim in datas]
        except (ValueError, TypeError, np.linalg.LinAlgError) as error:
            rows.append({"method": method, "guarantee": guarantee,
                         "error": str(error).splitlines()[0]})
            continue
        if runs_out is not None:
            runs_out[method] = runs
        row = score_tracking(runs, datas, c=c, gate=gate, skip=skip).as_row()
        row["guarantee"] = guarantee
        if "rho" in extra:
            row["method"] = f"{method} rho={extra['rho']:g}"
        rows.append(row)
    return rows


def _cell(row, key, spec, width):
    value = row.get(key)
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return f"{'-':>{width}}"
    return f"{value:>{width}{spec}}"


def format_tracking(rows: Sequence[Mapping[str, Any]]) -> str:
    """The rows of :func:`compare_tracking` (and :func:`score_sources`) as a table.

    Parameters
    ----------
    rows : sequence of dict
        Rows with ``method`` and the keys of :class:`TrackingScore`; rows of
        :func:`score_sources` (only ``rmse``, ``anees``) and rows with ``error`` are shown
        with ``-`` for what they lack.

    Returns
    -------
    str
        Two lines of column titles, a rule, one line per row.

    Examples
    --------
    >>> from cifilter.tracking import format_tracking
    >>> table = format_tracking([{"method": "ci", "guarantee": "bound", "gospa": 21.3,
    ...     "localisation": 100.0, "missed": 200.0, "false": 300.0, "anees": 2.1,
    ...     "lower": 3.8, "upper": 4.2, "verdict": "conservative", "rmse": 4.5,
    ...     "id_switches": 1, "false_tracks": 0.25, "missed_targets": 0.1,
    ...     "ms_per_scan": 3.2}])
    >>> table.splitlines()[3].split()  # doctest: +NORMALIZE_WHITESPACE
    ['ci', 'bound', '21.30', '100.0', '200.0', '300.0', '2.10', '[3.80,', '4.20]',
     'conservative', '4.50', '1', '0.25', '0.10', '3.2']
    """
    top = (f"{'':<16} {'':<9} {'GOSPA':>7} {'GOSPA^2 parts per scan':^23}  {'ANEES':>6} "
           f"{'95% band of':<15} {'':<13} {'RMSE':>6} {'ID':>4} {'false':>6} "
           f"{'missed':>6} {'ms per':>7}")
    header = (f"{'method':<16} {'guarantee':<9} {'[m]':>7} {'local':>7} {'missed':>7} "
              f"{'false':>7}  {'':>6} {'indep. NEES':<15} {'verdict':<13} {'[m]':>6} "
              f"{'sw.':>4} {'/scan':>6} {'/scan':>6} {'scan':>7}")
    lines = [top, header, "-" * len(header)]
    for row in rows:
        method = str(row["method"])
        guarantee = str(row.get("guarantee", "-"))
        if "error" in row:
            lines.append(f"{method:<16} {guarantee:<9} cannot run: {row['error']}")
            continue

        band = (f"[{row['lower']:.2f}, {row['upper']:.2f}]"
                if "lower" in row and np.isfinite(row["lower"]) else "-")
        lines.append(
            f"{method:<16} {guarantee:<9} {_cell(row, 'gospa', '.2f', 7)} "
            f"{_cell(row, 'localisation', '.1f', 7)} {_cell(row, 'missed', '.1f', 7)} "
            f"{_cell(row, 'false', '.1f', 7)}  {_cell(row, 'anees', '.2f', 6)} {band:<15} "
            f"{row.get('verdict', '-')!s:<13} {_cell(row, 'rmse', '.2f', 6)} "
            f"{_cell(row, 'id_switches', 'd', 4)} {_cell(row, 'false_tracks', '.2f', 6)} "
            f"{_cell(row, 'missed_targets', '.2f', 6)} {_cell(row, 'ms_per_scan', '.1f', 7)}")
    return "\n".join(lines)
