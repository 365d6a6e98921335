"""cifilter: fuse Kalman filter estimates whose cross-correlation is unknown.

Drop-in filterpy filters with a ``fuse`` step, and the fusion rules behind it:

* :func:`covariance_intersection` (``"ci"``), with optimal and fast weights, for N estimates;
* :func:`naive_fusion` (``"naive"``) and :func:`optimal_fusion` (``"optimal"``), the
  references for independent and for known correlations;
* every rule is reachable through :func:`fuse` and the registry
  (:func:`register_method`, :func:`available_methods`).
"""

from . import ci as _ci  # noqa: F401  (registers "ci")
from . import ei as _ei  # noqa: F401  (registers "ei")
from . import optimal as _optimal  # noqa: F401  (registers "naive", "optimal")
from . import pcei as _pcei  # noqa: F401  (registers "pcei")
from ._linalg import mahalanobis_sq
from .ci import FAST_OMEGA_RULES, ci_weights, covariance_intersection
from .ei import ellipsoidal_intersection
from .filters import ExtendedKalmanFilter, FusionMixin, KalmanFilter, UnscentedKalmanFilter
from .optimal import naive_fusion, optimal_fusion
from .pcei import pc_ellipsoidal_intersection
from .registry import FusionMethod, available_methods, fuse, get_method, register_method
from .result import FusionResult

__version__ = "0.1.0"

__all__ = [
    "FAST_OMEGA_RULES",
    "ExtendedKalmanFilter",
    "FusionMethod",
    "FusionMixin",
    "FusionResult",
    "KalmanFilter",
    "UnscentedKalmanFilter",
    "available_methods",
    "ci_weights",
    "covariance_intersection",
    "ellipsoidal_intersection",
    "fuse",
    "get_method",
    "mahalanobis_sq",
    "naive_fusion",
    "optimal_fusion",
    "pc_ellipsoidal_intersection",
    "register_method",
]
