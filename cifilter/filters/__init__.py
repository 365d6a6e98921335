"""Drop-in filterpy filters with a ``fuse`` step: a thin layer above the rules.

:class:`KalmanFilter`, :class:`ExtendedKalmanFilter` and :class:`UnscentedKalmanFilter` are
filterpy's classes with :class:`FusionMixin` (:mod:`cifilter.filters.kalman`);
:class:`SplitCIKalmanFilter` keeps its covariance split into a dependent and an independent
part (:mod:`cifilter.filters.split`). The filters read their model, call the front door
(:func:`cifilter.fuse`) and write the result back atomically.
"""

from .kalman import ExtendedKalmanFilter, FusionMixin, KalmanFilter, UnscentedKalmanFilter
from .split import SplitCIKalmanFilter

__all__ = [
    "ExtendedKalmanFilter",
    "FusionMixin",
    "KalmanFilter",
    "SplitCIKalmanFilter",
    "UnscentedKalmanFilter",
]
