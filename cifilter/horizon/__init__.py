"""Horizon-aware Covariance Intersection: weights chosen for the bound after future filtering.

Ajgl, Šimandl, Reinhardt, Noack & Hanebeck (2014): the CI weight that minimises the fused
bound now is not the one that minimises it after the filter has processed more
measurements. This package chooses the weights for a horizon (CI, or partial CI with
``rho=``), propagates bounds and compares the batch and recursive approaches. Method,
proofs and numerical formulation: ``docs/methods/horizon.rst``.

Modules: :mod:`~cifilter.horizon.model` (propagation and steady state),
:mod:`~cifilter.horizon.weights` (the weights), :mod:`~cifilter.horizon.study` (the
comparison over horizons) and :mod:`~cifilter.horizon.fusion` (the hooks of
``cifilter.fuse(..., horizon=)``).
"""

from ..registry import attach_horizon
from .fusion import ci_horizon_options, pci_horizon_options
from .model import propagate_bound, steady_state_covariance
from .study import HorizonStudy, horizon_study
from .weights import HorizonOmega, horizon_weights, optimal_omega

# The horizon sits above the rules: it gives the rules that can choose their weights for a
# horizon their hook here, so that cifilter.fuse(..., horizon=) works for them.
attach_horizon("ci", ci_horizon_options)
attach_horizon("pci", pci_horizon_options)

__all__ = [
    "HorizonOmega",
    "HorizonStudy",
    "ci_horizon_options",
    "horizon_study",
    "horizon_weights",
    "optimal_omega",
    "pci_horizon_options",
    "propagate_bound",
    "steady_state_covariance",
]
