"""Decentralised sensor networks: nodes that track one target and fuse their neighbours'
estimates, feeding the result back into their filters.

* :mod:`cifilter.network.graph`: :class:`Scenario` (target model, the nodes' sensors,
  the graph) and the ready scenarios :func:`naveen_taylor` (six nodes, Naveen & Taylor,
  Section V-B), :func:`ring`, :func:`chain` (Weng & Djurić's k nodes),
  :func:`fully_connected`, :func:`two_tracks` and :func:`common_information` (two nodes
  whose correlation is genuinely common information, where Inverse CI's bound applies);
* :mod:`cifilter.network.simulate`: :func:`simulate_data` and :func:`run_network`,
  vectorised over Monte Carlo runs and nodes, with feedback, exchange period, all-at-once
  or sequential fusion, packet loss, a one-step delay, tracks that arrive late and out of
  order (``simulate_data(lateness=)``; ``run_network(late=)`` aligns them in time through
  the front door, ignores the delay or drops them) and nodes that send only part of their
  track (``run_network(partial_nodes=, partial=)``, fused through ``H=`` or dropped);
  :func:`centralised`, the reference;
* :mod:`cifilter.network.study`: :func:`compare` (every registered rule on the same data)
  and :class:`NetworkStudy`, the same as a study for :func:`cifilter.montecarlo.run`,
  scored with :mod:`cifilter.metrics` by :func:`summarize` (the columns of ``python -m
  cifilter demo``: position and velocity RMSE, the pooled ANEES and its band, the traces
  of ``P``'s position and velocity blocks) and printed by :func:`format_summary`;
  :func:`score_track` gives the same columns for estimates from elsewhere;
* :mod:`cifilter.network.targets`: many targets seen by several sensors that run their own
  local trackers (:func:`multi_target`, :func:`simulate_targets`): the source tracks a
  track-to-track fusion centre (:mod:`cifilter.tracking`) receives, with crossing targets,
  targets that appear and disappear, missed detections, short-lived false tracks, late
  reports and sensors that send part of the state.
"""

from .graph import (
    NAVEEN_TAYLOR_EDGES,
    Scenario,
    adjacency_matrix,
    chain,
    common_information,
    constant_velocity_model,
    fully_connected,
    get_scenario,
    naveen_taylor,
    ring,
    scenario_names,
    two_tracks,
)
from .simulate import NetworkData, NetworkTrack, centralised, run_network, simulate_data
from .study import REFERENCES, NetworkStudy, compare, format_summary, score_track, summarize
from .targets import TargetData, TargetScenario, TrackingSensor, multi_target, simulate_targets

__all__ = [
    "NAVEEN_TAYLOR_EDGES",
    "REFERENCES",
    "NetworkData",
    "NetworkStudy",
    "NetworkTrack",
    "Scenario",
    "TargetData",
    "TargetScenario",
    "TrackingSensor",
    "adjacency_matrix",
    "centralised",
    "chain",
    "common_information",
    "compare",
    "constant_velocity_model",
    "format_summary",
    "fully_connected",
    "get_scenario",
    "multi_target",
    "naveen_taylor",
    "ring",
    "run_network",
    "scenario_names",
    "score_track",
    "simulate_data",
    "simulate_targets",
    "summarize",
    "two_tracks",
]
