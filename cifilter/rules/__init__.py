"""The fusion rules: one public module per rule, its private core beside it.

Importing this package registers the built-in rules, in the order of ``BUILT_IN`` (the
order of :func:`cifilter.available_methods`, the CLI's list and the demo's table). Each rule
module describes its rule in a ``REGISTRATION`` record (public function, core on validated
estimates, guarantee, truth hook). The rules sit below the filters, the horizon and the
network: rules that can choose their weights for the bound after future filtering (``ci``,
``pci``) get their ``horizon`` hook when :mod:`cifilter.horizon` is imported, which attaches
it to their record (:func:`cifilter.registry.attach_horizon`).
"""

from ..registry import register_method
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

BUILT_IN = (
    ci.REGISTRATION,
    optimal.NAIVE_REGISTRATION,
    optimal.OPTIMAL_REGISTRATION,
    pci.REGISTRATION,
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
