"""Every registered rule on the same network data, as a Monte Carlo study.

:class:`NetworkStudy` is a study in the sense of :func:`cifilter.montecarlo.run`: called
with a random generator and a number of runs, it simulates the scenario once
(:func:`~cifilter.network.simulate_data`), runs the local filters, the centralised filter
and the network under every rule on those data, and returns per-run arrays (NEES, squared
position errors, traces, the last step's covariances and errors, fusion times). Chunks of
runs concatenate along the first axis; :func:`summarize` scores the concatenated arrays
with :mod:`cifilter.metrics`. :func:`compare` does both in this process.

Rules registered later appear without editing this module: the rules are looked up in
the registry, and a rule that cannot run in the scenario (it fuses two estimates only, its
truth hook fails, ...) is reported with the reason instead of stopping the study.
"""

import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import NDArray

from .. import metrics
from .._numerics.validation import as_rng, check_int, check_scalar
from ..registry import available_methods, get_method
from .graph import Scenario
from .simulate import centralised, run_network, simulate_data

__all__ = ["REFERENCES", "NetworkStudy", "compare", "summarize"]

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

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.network import NetworkStudy, ring
    >>> study = NetworkStudy(ring(4), ("ci", "naive"), steps=5)
    >>> out = study(np.random.default_rng(0), 3)
    >>> out["ci/nees"].shape, out["local/nees"].shape
    ((3, 5, 4), (3, 5, 4))
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
            ``e/nees``, ``e/squared_error`` (position) and ``e/trace`` of shape
            (runs, steps, nodes); ``e/P_last`` (runs, nodes, n, n) and ``e/error_last``
            (runs, nodes, n) of the last step; ``e/seconds`` and ``e/fusions`` (runs,),
            each run's share of the fusion time and count. A rule that failed has only
            ``e/failed`` (runs,), the reason.

        Examples
        --------
        >>> from cifilter.network import NetworkStudy, two_tracks
        >>> out = NetworkStudy(two_tracks(), ("ci",), steps=3)(0, 2)
        >>> sorted(k for k in out if k.startswith("ci/"))[:3]
        ['ci/P_last', 'ci/error_last', 'ci/fusions']
        """
        rng = as_rng(rng)
        runs = check_int(runs, "runs", low=1)
        data = simulate_data(self.scenario, runs, self.steps, loss=self.loss, rng=rng)
        base = int(rng.integers(2**63 - 1))
        out = {}
        config = dict(feedback=self.feedback, period=self.period, sequential=self.sequential,
                      delay=self.delay)
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
        truth = data.truth[:, :, None]
        error = track.x - truth
        position = list(self.scenario.position_indices)
        name = track.method
        out[f"{name}/nees"] = metrics.nees(truth, track.x, track.P)
        out[f"{name}/squared_error"] = np.sum(error[..., position] ** 2, axis=-1)
        out[f"{name}/trace"] = np.trace(track.P, axis1=-2, axis2=-1)
        out[f"{name}/P_last"] = np.array(track.P[:, -1])
        out[f"{name}/error_last"] = np.array(error[:, -1])
        out[f"{name}/seconds"] = np.full(runs, track.fuse_seconds / runs)
        out[f"{name}/fusions"] = np.full(runs, track.fusions / runs)


def _estimators(results):
    names = []
    for key in results:
        name = key.rsplit("/", 1)[0]
        if name not in names:
            names.append(name)
    return names


def summarize(results: Mapping[str, NDArray[Any]], scenario: Scenario, *,
              confidence: float = 0.95) -> list[dict[str, Any]]:
    """Score a study's results: one row per estimator.

    Parameters
    ----------
    results : dict of ndarray
        What :class:`NetworkStudy` returns, possibly concatenated over chunks by
        :func:`cifilter.montecarlo.run`.
    scenario : Scenario
        The scenario of the study (its state dimension).
    confidence : float, optional
        Probability of the chi-square bounds (default 0.95).

    Returns
    -------
    list of dict
        Per estimator: ``method``, ``guarantee`` (``"exact"`` for the references, else
        the registry's), ``rmse`` (position, over runs, steps and nodes), ``anees`` (the
        ANEES over runs per step and node, averaged), ``lower`` and ``upper`` (its
        two-sided bounds, :func:`cifilter.metrics.chi2_bounds`), ``inside`` (share of the
        steps and nodes whose ANEES lies inside them), ``mean_trace`` (of ``P``),
        ``verdict`` (``"conservative"``: mean ANEES below the lower bound,
        ``"overconfident"``: above the upper one, else ``"consistent"``) and
        ``us_per_fusion`` (fusion time per node fusion, in microseconds); or ``method``,
        ``guarantee`` and ``error`` for a rule that could not run.

    Examples
    --------
    >>> from cifilter.network import NetworkStudy, summarize, two_tracks
    >>> scenario = two_tracks()
    >>> rows = summarize(NetworkStudy(scenario, ("ci",), steps=20)(0, 10), scenario)
    >>> [row["method"] for row in rows], rows[2]["verdict"]
    (['local', 'centralised', 'ci'], 'consistent')
    """
    rows = []
    for name in _estimators(results):
        guarantee = "exact" if name in REFERENCES else get_method(name).guarantee
        if f"{name}/failed" in results:
            rows.append({"method": name, "guarantee": guarantee,
                         "error": str(results[f"{name}/failed"][0])})
            continue
        result = metrics.anees(results[f"{name}/nees"], scenario.dim, confidence=confidence)
        fusions = float(np.sum(results[f"{name}/fusions"]))
        rows.append({
            "method": name,
            "guarantee": guarantee,
            "rmse": float(np.sqrt(np.mean(results[f"{name}/squared_error"]))),
            "anees": result.mean,
            "lower": result.lower,
            "upper": result.upper,
            "inside": result.share_inside,
            "mean_trace": float(np.mean(results[f"{name}/trace"])),
            "verdict": result.verdict,
            "us_per_fusion": (1e6 * float(np.sum(results[f"{name}/seconds"])) / fusions
                              if fusions else 0.0),
        })
    return rows


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
        Probability of the chi-square bounds.
    **config
        ``feedback``, ``period``, ``sequential``, ``delay``, ``loss``, ``options`` (see
        :class:`NetworkStudy`).

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
