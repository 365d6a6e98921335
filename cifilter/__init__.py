"""cifilter: fuse Kalman filter estimates whose cross-correlation is unknown.

Drop-in filterpy filters with a ``fuse`` step, and the fusion rules behind it:

* :func:`covariance_intersection` (``"ci"``), with optimal and fast weights, for N estimates;
* :func:`partial_ci` (``"pci"``), partial-correlation CI given a correlation coefficient
  bound (Wu, Cai & Fu 2018; trace and correlation bounds in :mod:`cifilter.rules.bounds`);
* :mod:`cifilter.horizon`: CI weights chosen for the bound after future filtering
  (Ajgl et al. 2014), also as ``kf.fuse(other, horizon=k)``;
* :func:`naive_fusion` (``"naive"``) and :func:`optimal_fusion` (``"optimal"``), the
  references for independent and for known correlations;
* :func:`ellipsoidal_intersection` (``"ei"``) and :func:`pc_ellipsoidal_intersection`
  (``"pcei"``), which estimate the common information (Sijs & Lazar; Naveen & Taylor);
* :func:`bayesian_fusion` (``"bayes"``), the Monte Carlo MMSE fusion under a Wishart prior
  (Weng & Djurić), and its sampler :func:`sample_joint_covariances`;
* :func:`inverse_covariance_intersection` (``"ici"``), the bound under unknown common
  information (Noack et al. 2017); :func:`split_covariance_intersection` (``"split-ci"``)
  and :class:`SplitCIKalmanFilter` (Julier & Uhlmann; Li, Nashashibi & Yang);
  :func:`cross_covariance_fusion` (``"cross"``), Bar-Shalom-Campo with an assumed
  correlation (MATLAB's ``fusexcov``);
* :func:`covariance_union` (``"cu"``), :func:`largest_ellipsoid` (``"le"``) and
  :func:`sampling_ci` (``"sci"``): covariance union for inconsistent tracks (Uhlmann
  2003), safe fusion (Benaskeur 2002; Nygårds et al. 2016) and sampling CI (Tian,
  Bar-Shalom & Chen 2010);
* every rule is reachable through :func:`fuse` and the registry
  (:func:`register_method`, :func:`available_methods`), which also fuses estimates of part
  of the state (``H=``), of non-Euclidean states (``residual=``, ``add=``) and of other
  times (``times=``, ``at=``, ``motion=``; ``kf.fuse(..., lag=)``) for the rules that
  accept them (``docs/methods/partial_state.rst``, ``docs/methods/time.rst``).
"""

# The floors, bottom up: importing the rules registers them (in rules.BUILT_IN's order);
# importing the horizon attaches its hooks to the rules that choose weights for a horizon.
from . import rules  # noqa: F401
from ._numerics.linalg import IllConditionedError, mahalanobis_sq
from .backend import get_backend, set_backend, use_backend
from .registry import FusionMethod, available_methods, fuse, get_method, register_method
from .result import FusionResult
from .rules.bayes import bayesian_fusion, sample_joint_covariances
from .rules.ci import FAST_OMEGA_RULES, ci_weights, covariance_intersection
from .rules.cross import cross_covariance_fusion
from .rules.ei import ellipsoidal_intersection
from .rules.ici import inverse_covariance_intersection
from .rules.largest_ellipsoid import largest_ellipsoid
from .rules.optimal import naive_fusion, optimal_fusion
from .rules.pci import partial_ci
from .rules.pcei import pc_ellipsoidal_intersection
from .rules.sampling_ci import sampling_ci
from .rules.split_ci import split_covariance_intersection
from .rules.union import covariance_union
from .horizon import horizon_study, optimal_omega, propagate_bound, steady_state_covariance
from .filters import (
    ExtendedKalmanFilter,
    FusionMixin,
    KalmanFilter,
    SplitCIKalmanFilter,
    UnscentedKalmanFilter,
)

__version__ = "0.1.0"

__all__ = [
    "FAST_OMEGA_RULES",
    "ExtendedKalmanFilter",
    "FusionMethod",
    "FusionMixin",
    "FusionResult",
    "IllConditionedError",
    "KalmanFilter",
    "SplitCIKalmanFilter",
    "UnscentedKalmanFilter",
    "available_methods",
    "bayesian_fusion",
    "ci_weights",
    "covariance_intersection",
    "covariance_union",
    "cross_covariance_fusion",
    "ellipsoidal_intersection",
    "fuse",
    "get_backend",
    "get_method",
    "horizon_study",
    "inverse_covariance_intersection",
    "largest_ellipsoid",
    "mahalanobis_sq",
    "naive_fusion",
    "optimal_fusion",
    "optimal_omega",
    "partial_ci",
    "pc_ellipsoidal_intersection",
    "propagate_bound",
    "register_method",
    "sample_joint_covariances",
    "sampling_ci",
    "set_backend",
    "split_covariance_intersection",
    "steady_state_covariance",
    "use_backend",
]
