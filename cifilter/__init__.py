"""cifilter: fuse Kalman filter estimates whose cross-correlation is unknown.

Drop-in filterpy filters with a ``fuse`` step, and the fusion rules behind it:

* :func:`covariance_intersection` (``"ci"``), with optimal and fast weights, for N estimates;
* :func:`naive_fusion` (``"naive"``) and :func:`optimal_fusion` (``"optimal"``), the
  references for independent and for known correlations;
* :func:`bayesian_fusion` (``"bayes"``), the Monte Carlo MMSE fusion under a Wishart prior
  (Weng & Djurić), and its sampler :func:`sample_joint_covariances`;
* every rule is reachable through :func:`fuse` and the registry
  (:func:`register_method`, :func:`available_methods`).
"""

from . import ci as _ci  # noqa: F401  (registers "ci")
from . import optimal as _optimal  # noqa: F401  (registers "naive", "optimal")

# isort: split
from . import bayes as _bayes  # noqa: F401  (registers "bayes", after the rules above)
from ._linalg import mahalanobis_sq
from .bayes import bayesian_fusion, sample_joint_covariances
from .ci import FAST_OMEGA_RULES, ci_weights, covariance_intersection
from .filters import ExtendedKalmanFilter, FusionMixin, KalmanFilter, UnscentedKalmanFilter
from .optimal import naive_fusion, optimal_fusion
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
    "bayesian_fusion",
    "ci_weights",
    "covariance_intersection",
    "fuse",
    "get_method",
    "mahalanobis_sq",
    "naive_fusion",
    "optimal_fusion",
    "register_method",
    "sample_joint_covariances",
]
