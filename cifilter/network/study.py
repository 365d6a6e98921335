"""Every registered rule on the same network data, as a Monte Carlo study.

:class:`NetworkStudy` is a study in the sense of :func:`cifilter.montecarlo.run`: called
with a random generator and a number of runs, it simulates the scenario once
(:func:`~cifilter.network.simulate_data`), runs the local filters, the centralised filter
and the network under every rule on those data, and returns per-run arrays (NEES, squared
position and velocity errors, traces, the last step's covariances and errors, fusion
times). Chunks of runs concatenate along the first axis; :func:`summarize` scores the
concatenated arrays with :mod:`cifilter.metrics` (the columns of ``python -m cifilter
demo``) and :func:`format_summary` prints them under the demo's column titles.
:func:`compare` simulates and scores in this process; :func:`score_track` gives the same
columns for estimates from elsewhere.

Rules registered later appear without editing this module: the rules are looked up in
the registry, and a rule that cannot run in the scenario (it fuses two estimates only, its
truth hook fails, ...) is reported with the reason instead of stopping the study.
"""

import numbers
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import metrics
from .._numerics.validation import (
    as_float_array,
    as_rng,
    check_finite,
    check_int,
    check_scalar,
)
from ..registry import available_methods, get_method
from .graph import POSITION, Scenario
from .simulate import centralised, run_network, simulate_data

__all__ = ["REFERENCES", "NetworkStudy", "compare", "format_summary",
           "score_track", "summarize"]

REFERENCES = ("local", "centralised")
"""The reference estimators of every study: each node's own filter without exchange, and
one filter with every node's measurements."""


def _rule_rng(base, name):
    """A generator for one rule, derived from the study's seed and the rule's name (stable
    whatever other rules are compared)."""
    return np.random.default_rng([base, zlib.crc32(name.encode())])


@dataclass(frozen=True)
class NetworkStudy:
    """The network under every rule, as a study for :func:`cifilter.montecarlo.run`.

    The parameters are also the attributes; calling the study runs it.

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    methods : tuple of str
        Registered rules to compare (default: all registered when the study is made).
    steps : int
        Time steps per run.
    feedback, period, sequential, delay : optional
        The exchange (see :func:`~cifilter.network.run_network`).
    loss : float, optional
        Packet loss probability (see :func:`~cifilter.network.simulate_data`).
    options : dict, optional
        Options per rule, ``{name: {option: value}}``.
    lateness : int or tuple of float, optional
        How late the messages arrive (see :func:`~cifilter.network.simulate_data`;
        default 0, on time).
    late : {"align", "ignore", "drop"}, optional
        What a node does with a late track (see :func:`~cifilter.network.run_network`;
        default ``"align"``).
    partial_nodes, partial : optional
        Nodes that send only part of their track (a tuple of node indices or a dict
        ``{node: S}``; default none) and what the others do with it (``"fuse"``, the
        default, or ``"drop"``); see :func:`~cifilter.network.run_network`.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.network import NetworkStudy, ring
    >>> study = NetworkStudy(ring(4), ("ci", "naive"), steps=5)
    >>> out = study(np.random.default_rng(0), 3)
    >>> out["ci/nees"].shape, out["local/nees"].shape
    ((3, 5, 4), (3, 5, 4))
    >>> late = NetworkStudy(ring(4), ("ci",), steps=5, lateness=3, late="ignore")
    >>> late(np.random.default_rng(0), 3)["ci/nees"].shape
    (3, 5, 4)
    """

    scenario: Scenario
    methods: Optional[tuple[str, ...]] = None
    steps: int = 100
    feedback: bool = True
    period: int = 1
    sequential: bool = False
    delay: bool = False
    loss: float = 0.0
    options: Optional[dict[str, dict[str, Any]]] = field(default=None, compare=False)
    lateness: Union[int, tuple[float, ...]] = 0
    late: str = "align"
    partial_nodes: Optional[Union[tuple[int, ...], dict[int, Any]]] = field(default=None,
                                                                           compare=False)
    partial: str = "fuse"

    def __post_init__(self):
        if not isinstance(self.scenario, Scenario):
            raise TypeError(f"scenario must be a Scenario, got {type(self.scenario).__name__}")
        methods = available_methods() if self.methods is None else tuple(self.methods)
        for name in methods:
            get_method(name)  # unknown names fail before any work
        object.__setattr__(self, "methods", methods)
        object.__setattr__(self, "steps", check_int(self.steps, "steps", low=1))
        object.__setattr__(self, "loss", check_scalar(self.loss, "loss", low=0, high=1))
        object.__setattr__(self, "options", dict(self.options or {}))
        # bad exchange options fail before any work too: a run of one step, no rule
        data = simulate_data(self.scenario, 1, 1, lateness=self.lateness, rng=0)
        run_network(self.scenario, data, None, **self._config())
        if not isinstance(self.lateness, numbers.Integral):
            object.__setattr__(self, "lateness", tuple(self.lateness))
        if self.partial_nodes is not None and not isinstance(self.partial_nodes, Mapping):
            object.__setattr__(self, "partial_nodes", tuple(self.partial_nodes))

    def _config(self):
        return dict(feedback=self.feedback, period=self.period, sequential=self.sequential,
                    delay=self.delay, late=self.late, partial_nodes=self.partial_nodes,
                    partial=self.partial)

    def __call__(self, rng, runs):
        """Simulate ``runs`` runs and score every estimator per run.

        Parameters
        ----------
        rng : numpy.random.Generator or int
            The study's randomness (data, packet losses, and the rules that sample).
        runs : int
            Number of runs, simulated together.

        Returns
        -------
        dict of ndarray
            For every estimator ``e`` (``"local"``, ``"centralised"``, then the rules):
            ``e/nees``, ``e/squared_error`` (position), ``e/velocity_squared_error`` (the
            other components), ``e/trace``, ``e/trace_position`` and
            ``e/trace_velocity`` (of ``P`` and of its position and velocity blocks) of
            shape (runs, steps, nodes); ``e/P_last`` (runs, nodes, n, n) and
            ``e/error_last`` (runs, nodes, n) of the last step; ``e/seconds`` and
            ``e/fusions`` (runs,), each run's share of the fusion time and count. A rule
            that failed has only ``e/failed`` (runs,), the reason.

        Examples
        --------
        >>> from cifilter.network import NetworkStudy, two_tracks
        >>> out = NetworkStudy(two_tracks(), ("ci",), steps=3)(0, 2)
        >>> sorted(k for k in out if k.startswith("ci/"))[:3]
        ['ci/P_last', 'ci/error_last', 'ci/fusions']
        """
        rng = as_rng(rng)
        runs = check_int(runs, "runs", low=1)
        data = simulate_data(self.scenario, runs, self.steps, loss=self.loss,
                             lateness=self.lateness, rng=rng)
        base = int(rng.integers(2**63 - 1))
        out = {}
        config = self._config()
        self._score(out, run_network(self.scenario, data, None, **config), data, runs)
        self._score(out, centralised(self.scenario, data), data, runs)
        for name in self.methods:
            try:
                track = run_network(self.scenario, data, name, rng=_rule_rng(base, name),
                                    options=self.options.get(name), **config)
            except Exception as error:
                out[f"{name}/failed"] = np.full(runs, f"{type(error).__name__}: {error}")
                continue
            self._score(out, track, data, runs)
        return out

    def _score(self, out, track, data, runs):
        name = track.method
        values = _values(data.truth[:, :, None], track.x, track.P,
                         self.scenario.position_indices)
        for key, value in values.items():
            out[f"{name}/{key}"] = value
        out[f"{name}/P_last"] = np.array(track.P[:, -1])
        out[f"{name}/error_last"] = np.array(track.x[:, -1] - data.truth[:, -1, None])
        out[f"{name}/seconds"] = np.full(runs, track.fuse_seconds / runs)
        out[f"{name}/fusions"] = np.full(runs, track.fusions / runs)


# the arrays a study keeps of every estimator, per run, step and node
_VALUES = ("nees", "squared_error", "velocity_squared_error", "trace", "trace_position",
           "trace_velocity")


def _values(truth, x, P, position):
    """Per run, step (and node): the NEES, the squared position and velocity errors, and
    the traces of P, of its position block and of the rest ("velocity")."""
    x = np.asarray(x, dtype=float)
    P = np.broadcast_to(np.asarray(P, dtype=float), x.shape + x.shape[-1:])
    error = x - np.asarray(truth, dtype=float)
    position = list(position)
    velocity = [i for i in range(x.shape[-1]) if i not in position]
    diagonal = np.diagonal(P, axis1=-2, axis2=-1)
    return {
        "nees": metrics.nees(truth, x, P),
        "squared_error": np.sum(error[..., position] ** 2, axis=-1),
        "velocity_squared_error": np.sum(error[..., velocity] ** 2, axis=-1),
        "trace": np.trace(P, axis1=-2, axis2=-1),
        "trace_position": np.sum(diagonal[..., position], axis=-1),
        "trace_velocity": np.sum(diagonal[..., velocity], axis=-1),
    }


def _verdict(value, lower, upper):
    if not (np.isfinite(lower) and np.isfinite(upper)):
        return "inconclusive"
    return "conservative" if value < lower else "overconfident" if value > upper \
        else "consistent"


def _columns(values, dim, confidence):
    """One estimator's columns from its per-estimate arrays (runs first)."""
    pooled, lower, upper = metrics.pooled_anees_band(values["nees"], dim, confidence)
    steps = metrics.anees(values["nees"], dim, confidence=confidence)
    return {
        "rmse": float(np.sqrt(np.mean(values["squared_error"]))),
        "rmse_velocity": float(np.sqrt(np.mean(values["velocity_squared_error"]))),
        "anees": pooled,
        "lower": lower,
        "upper": upper,
        "verdict": _verdict(pooled, lower, upper),
        "inside": steps.share_inside,
        "step_lower": steps.lower,
        "step_upper": steps.upper,
        "mean_trace": float(np.mean(values["trace"])),
        "trace_position": float(np.mean(values["trace_position"])),
        "trace_velocity": float(np.mean(values["trace_velocity"])),
    }


def score_track(truth: ArrayLike, x: ArrayLike, P: ArrayLike, *,
                position_indices: Sequence[int] = POSITION,
                confidence: float = 0.95) -> dict[str, Any]:
    """The columns of :func:`summarize` for one estimator's estimates.

    For estimates that did not come from a :class:`NetworkStudy` (for instance the two
    tracks of ``python -m cifilter demo --scenario two-tracks``, fused once per run and
    step): the same numbers, computed the same way.

    Parameters
    ----------
    truth : array_like, shape (runs, ..., n)
        True states; broadcast against ``x`` (for a network, ``truth[:, :, None]`` against
        estimates of shape (runs, steps, nodes, n)).
    x : array_like, shape (runs, ..., n)
        Estimates, the independent Monte Carlo runs along the first axis.
    P : array_like, shape (..., n, n)
        Their covariances, broadcast against ``x``.
    position_indices : sequence of int, optional
        The state's position components (default ``(0, 2)``, the x and y of the state
        ``[x, vx, y, vy]``); the others are reported as the velocity.
    confidence : float, optional
        Probability of the bands (default 0.95).

    Returns
    -------
    dict
        ``rmse``, ``rmse_velocity``, ``anees``, ``lower``, ``upper``, ``verdict``,
        ``inside``, ``step_lower``, ``step_upper``, ``mean_trace``, ``trace_position``
        and ``trace_velocity``, as in :func:`summarize`.

    Raises
    ------
    ValueError
        If the shapes do not broadcast, a value is not finite, a covariance is not
        positive definite, a position index is outside the state or repeated, or
        ``confidence`` is outside (0, 1).
    TypeError
        If an array is not numeric.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.network import score_track
    >>> rng = np.random.default_rng(0)
    >>> truth = np.zeros((50, 20, 4))
    >>> x = rng.standard_normal((50, 20, 4))        # errors of covariance I
    >>> row = score_track(truth, x, np.eye(4))
    >>> row["verdict"], round(row["trace_position"], 1), round(row["trace_velocity"], 1)
    ('consistent', 2.0, 2.0)
    """
    x = as_float_array(x, "x")
    if x.ndim < 2:
        raise ValueError(f"x must have a runs axis and a state axis, got shape {x.shape}")
    n = x.shape[-1]
    truth, P = as_float_array(truth, "truth"), as_float_array(P, "P")
    for name, array in (("truth", truth), ("x", x), ("P", P)):
        check_finite(array, name)
    try:
        np.broadcast_shapes(truth.shape, x.shape)
    except ValueError:
        raise ValueError(f"truth of shape {truth.shape} does not broadcast against x of "
                         f"shape {x.shape}") from None
    if P.ndim < 2 or P.shape[-2:] != (n, n):
        raise ValueError(f"P must have shape (..., {n}, {n}) to match x, got {P.shape}")
    try:
        np.broadcast_shapes(P.shape[:-2], x.shape[:-1])
    except ValueError:
        raise ValueError(f"the batch axes of P {P.shape[:-2]} do not broadcast against "
                         f"those of x {x.shape[:-1]}") from None
    position: list[int] = []
    for index in position_indices:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, numbers.Integral) \
                or not 0 <= index < n or index in position:
            raise ValueError(f"position_indices must be distinct state indices in "
                             f"[0, {n}), got {tuple(position_indices)!r}")
        position.append(int(index))
    return _columns(_values(truth, x, P, position), n, confidence)


def _estimators(results):
    names = []
    for key in results:
        name = key.rsplit("/", 1)[0]
        if name not in names:
            names.append(name)
    return names


def summarize(results: Mapping[str, NDArray[Any]], scenario: Scenario, *,
              confidence: float = 0.95) -> list[dict[str, Any]]:
    """Score a study's results: one row per estimator, the columns of the demo's table.

    Parameters
    ----------
    results : dict of ndarray
        What :class:`NetworkStudy` returns, possibly concatenated over chunks by
        :func:`cifilter.montecarlo.run`.
    scenario : Scenario
        The scenario of the study (its state dimension and position components).
    confidence : float, optional
        Probability of the bands (default 0.95).

    Returns
    -------
    list of dict
        Per estimator: ``method``; ``guarantee`` (``"exact"`` for the references, else
        the registry's); ``rmse`` and ``rmse_velocity`` (position [m] and the other
        components, "velocity" [m/s], over runs, steps and nodes); ``anees``, the pooled
        ANEES (the NEES averaged over runs, steps and nodes); ``lower`` and ``upper``, its
        band (:func:`cifilter.metrics.pooled_anees_band`); ``verdict``
        (``"conservative"`` below the band, ``"overconfident"`` above it, else
        ``"consistent"``; ``"inconclusive"`` with a single run); ``inside``, the share of
        the steps and nodes whose ANEES over the runs lies inside one step's two-sided
        chi-square bounds ``step_lower``, ``step_upper``
        (:func:`cifilter.metrics.anees`); ``mean_trace``, ``trace_position`` and
        ``trace_velocity``, the mean trace of ``P`` and of its position and velocity
        blocks (m^2 and (m/s)^2 apart); ``us_per_fusion``, the fusion time divided by the
        number of node fusions, in microseconds (the calls are batched over the runs, so
        it falls with more runs). A rule that could not run has ``method``,
        ``guarantee`` and ``error`` only. :func:`format_summary` prints the rows.

    Examples
    --------
    >>> from cifilter.network import NetworkStudy, summarize, two_tracks
    >>> scenario = two_tracks()
    >>> rows = summarize(NetworkStudy(scenario, ("ci",), steps=20)(0, 10), scenario)
    >>> [row["method"] for row in rows]
    ['local', 'centralised', 'ci']
    >>> ci = rows[2]    # CI's P bounds the error: its pooled ANEES is below the band
    >>> round(ci["anees"], 2), round(ci["lower"], 2), ci["verdict"]
    (2.79, 3.11, 'conservative')
    """
    rows = []
    for name in _estimators(results):
        guarantee = "exact" if name in REFERENCES else get_method(name).guarantee
        if f"{name}/failed" in results:
            rows.append({"method": name, "guarantee": guarantee,
                         "error": str(results[f"{name}/failed"][0])})
            continue
        fusions = float(np.sum(results[f"{name}/fusions"]))
        rows.append({
            "method": name,
            "guarantee": guarantee,
            **_columns({key: results[f"{name}/{key}"] for key in _VALUES}, scenario.dim,
                       confidence),
            "us_per_fusion": (1e6 * float(np.sum(results[f"{name}/seconds"])) / fusions
                              if fusions else 0.0),
        })
    return rows


def format_summary(rows: Sequence[Mapping[str, Any]]) -> str:
    """The rows of :func:`summarize` as a table under two lines of column titles.

    It is the table ``python -m cifilter demo`` prints (whose header says what the
    columns mean; :doc:`/cli` has the details).

    Parameters
    ----------
    rows : sequence of dict
        Rows of :func:`summarize` or :func:`compare`. Of rows from elsewhere, only
        ``method``, ``guarantee``, ``rmse``, ``anees``, ``lower``, ``upper``, ``verdict``
        and ``inside`` are needed: a missing velocity RMSE or trace and a zero or
        missing ``us_per_fusion`` are shown as ``-``.

    Returns
    -------
    str
        The table; a rule that could not run is listed with the reason.

    Examples
    --------
    >>> from cifilter.network import format_summary
    >>> table = format_summary([{"method": "ci", "guarantee": "bound", "rmse": 3.8,
    ...     "rmse_velocity": 1.2, "anees": 3.0, "lower": 3.8, "upper": 4.2, "inside": 0.75,
    ...     "trace_position": 20.5, "trace_velocity": 5.1, "verdict": "conservative",
    ...     "us_per_fusion": 120.0}])
    >>> table.splitlines()[1].split()[:2]   # under a line of column titles
    ['method', 'guarantee']
    >>> table.splitlines()[3].split()  # doctest: +NORMALIZE_WHITESPACE
    ['ci', 'bound', '3.800', '1.200', '3.00', '[3.80,', '4.20]', 'conservative', '75.0%',
     '20.50', '5.10', '120']
    """
    top = (f"{'':<12} {'':<9} {'RMSE':>8} {'RMSE':>8} {'pooled':>8}  "
           f"{'95% band of':<15} {'':<13} {'steps in':>9} {'mean tr P':>9} "
           f"{'mean tr P':>10} {'batched':>8}")
    header = (f"{'method':<12} {'guarantee':<9} {'pos [m]':>8} {'vel[m/s]':>8} {'ANEES':>8}  "
              f"{'pooled ANEES':<15} {'verdict':<13} {'bounds':>9} {'pos [m2]':>9} "
              f"{'vel[m2/s2]':>10} {'us/fusion':>8}")
    lines = [top, header, "-" * len(header)]
    for row in rows:
        if "error" in row:
            lines.append(f"{row['method']:<12} {row['guarantee']:<9} cannot run: "
                         f"{row['error']}")
            continue
        band = (f"[{row['lower']:.2f}, {row['upper']:.2f}]"
                if np.isfinite(row["lower"]) and np.isfinite(row["upper"]) else "-")
        timing = f"{row['us_per_fusion']:.0f}" if row.get("us_per_fusion") else "-"
        # 8 characters also for the huge ANEES of data incest (5.41e+10)
        anees = f"{row['anees']:.2f}" if row["anees"] < 1e5 else f"{row['anees']:.2e}"
        velocity, position_trace, velocity_trace = (
            f"{row[key]:{spec}}" if key in row else "-"
            for key, spec in (("rmse_velocity", ".3f"), ("trace_position", ".2f"),
                              ("trace_velocity", ".2f")))
        lines.append(
            f"{row['method']:<12} {row['guarantee']:<9} {row['rmse']:>8.3f} "
            f"{velocity:>8} {anees:>8}  {band:<15} "
            f"{row['verdict']:<13} {100 * row['inside']:>8.1f}% "
            f"{position_trace:>9} {velocity_trace:>10} {timing:>8}"
        )
    return "\n".join(lines)


def compare(scenario: Scenario, methods: Optional[Sequence[str]] = None, *, runs: int = 20,
            steps: int = 100, rng: Optional[Union[int, np.random.Generator]] = None,
            confidence: float = 0.95, **config: Any) -> list[dict[str, Any]]:
    """Compare rules on one network in this process: simulate, run, score.

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    methods : sequence of str, optional
        Registered rules (default all).
    runs, steps : int, optional
        Monte Carlo runs and time steps (default 20 x 100).
    rng : numpy.random.Generator, int or None, optional
        Randomness.
    confidence : float, optional
        Probability of the bands (default 0.95).
    **config
        ``feedback``, ``period``, ``sequential``, ``delay``, ``loss``, ``options``,
        ``lateness``, ``late``, ``partial_nodes``, ``partial`` (see :class:`NetworkStudy`).

    Returns
    -------
    list of dict
        The rows of :func:`summarize`.

    Examples
    --------
    >>> from cifilter.network import compare, naveen_taylor
    >>> rows = compare(naveen_taylor(), ["ci", "naive"], runs=10, steps=30, rng=0)
    >>> {row["method"]: row["verdict"] for row in rows}["naive"]
    'overconfident'
    """
    study = NetworkStudy(scenario, None if methods is None else tuple(methods), steps,
                         **config)
    return summarize(study(rng, runs), scenario, confidence=confidence)
