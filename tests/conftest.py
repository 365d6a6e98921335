"""Shared test configuration: hypothesis profiles and a headless matplotlib."""

import os

import matplotlib
from hypothesis import HealthCheck, settings

matplotlib.use("Agg")

settings.register_profile(
    "default", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile(
    "thorough", max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
# CI (CI=true) replays a fixed, derandomised set of examples so that a landing is
# reproducible; local runs draw new examples every time and keep exploring.
settings.register_profile(
    "ci", max_examples=60, deadline=None, derandomize=True, print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
default_profile = "ci" if os.environ.get("CI") else "default"
settings.load_profile(os.environ.get("CIFILTER_HYPOTHESIS_PROFILE", default_profile))
