"""The built-in fusion rules, registered in this order (the order of
:func:`cifilter.available_methods`, the CLI's list and the demo's table).

Each rule module describes its rule in a ``REGISTRATION`` record (public function, core on
validated estimates, guarantee, truth hook); rules that can choose their weights for the
bound after future filtering get their ``horizon`` hook from :mod:`cifilter.horizon`.
"""

from . import (
    bayes,
    ci,
    cross,
    ei,
    ici,
    largest_ellipsoid,
    optimal,
    pcei,
    pci,
    sampling_ci,
    split_ci,
    union,
)
from .horizon import ci_horizon_options, pci_horizon_options
from .registry import register_method

BUILT_IN = (
    dict(ci.REGISTRATION, horizon=ci_horizon_options),
    optimal.NAIVE_REGISTRATION,
    optimal.OPTIMAL_REGISTRATION,
    dict(pci.REGISTRATION, horizon=pci_horizon_options),
    ei.REGISTRATION,
    pcei.REGISTRATION,
    bayes.REGISTRATION,
    ici.REGISTRATION,
    split_ci.REGISTRATION,
    cross.REGISTRATION,
    union.REGISTRATION,
    largest_ellipsoid.REGISTRATION,
    sampling_ci.REGISTRATION,
)

for _registration in BUILT_IN:
    register_method(**_registration)
