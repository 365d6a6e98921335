"""A track-to-track fusion node: source tracks in, central tracks out.

:class:`TrackFuser` receives, scan by scan, the tracks of several sources (each numbering
its tracks its own way, some late, some of part of the state), associates them with its
central tracks by a gated distance consistent with the fusion rule (for CI one that holds
for every correlation: :func:`ci_distance`), fuses each central track through
:func:`cifilter.fuse` (batched: one call per group of tracks with the same signature) and
manages the central tracks' life cycle (tentative, confirmed, coasting, deleted, stable
ids). See ``docs/methods/track_association.rst``.

Examples
--------
>>> import numpy as np
>>> from cifilter.tracking import TrackFuser, SourceTrack
>>> fuser = TrackFuser("ci", motion=lambda dt: (np.eye(1), 0.01 * dt * np.eye(1)))
>>> scan = [SourceTrack("radar", 3, [1.0], [[1.0]], 0.0),
...         SourceTrack("camera", "a", [1.2], [[2.0]], 0.0)]
>>> [(c.id, c.confirmed) for c in fuser.update(scan, 0.0)]
[(1, True)]
"""

from .association import ci_distance, gated_assignment, naive_distance
from .fuser import TrackFuser
from .tracks import CentralTrack, SourceTrack, checked_tracks, scan_time

__all__ = [
    "CentralTrack",
    "SourceTrack",
    "TrackFuser",
    "checked_tracks",
    "ci_distance",
    "gated_assignment",
    "naive_distance",
    "scan_time",
]

# --- study functions (the SCENARIO person's module cifilter/tracking/study.py) ---------------
# Add `from .study import ...` below and the names to __all__ (__all__ += [...]).
from .study import (
    DEFAULT_METHODS,
    TrackingRun,
    TrackingScore,
    compare_tracking,
    format_tracking,
    run_tracking,
    score_sources,
    score_tracking,
)

__all__ += [
    "DEFAULT_METHODS",
    "TrackingRun",
    "TrackingScore",
    "compare_tracking",
    "format_tracking",
    "run_tracking",
    "score_sources",
    "score_tracking",
]
