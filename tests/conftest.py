"""Shared test configuration: hypothesis profiles, a headless matplotlib, and the
``ci_backend`` fixture that runs the CI-family tests on every installed backend."""

import os

import matplotlib
import pytest
from hypothesis import HealthCheck, settings

import cifilter
from cifilter.backend import compile_kernels, numba_available

matplotlib.use("Agg")

# (the ci_backend fixture is function-scoped on purpose: it only selects a backend, which
# every hypothesis example of the test shares)
SUPPRESSED = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture]
settings.register_profile(
    "default", max_examples=60, deadline=None, suppress_health_check=SUPPRESSED
)
settings.register_profile(
    "thorough", max_examples=500, deadline=None, suppress_health_check=SUPPRESSED
)
# CI (CI=true) replays a fixed, derandomised set of examples so that a landing is
# reproducible; local runs draw new examples every time and keep exploring.
settings.register_profile(
    "ci", max_examples=60, deadline=None, derandomize=True, print_blob=True,
    suppress_health_check=SUPPRESSED,
)
default_profile = "ci" if os.environ.get("CI") else "default"
settings.load_profile(os.environ.get("CIFILTER_HYPOTHESIS_PROFILE", default_profile))

# The backends the CI-family tests run on: numpy always, the compiled kernels when numba is
# installed (the test extra installs it). "numba" forces the kernels for every problem,
# single ones included, so that each test of the numpy path also checks the kernels.
TEST_BACKENDS = ["numpy", "numba"] if numba_available() else ["numpy"]


def pytest_configure(config):
    """Compile the kernels once, before the workers start (what ``python -m cifilter
    compile`` does), so every process's ``"auto"`` uses them from its first call: results
    under ``"auto"`` then do not depend on whether a background compilation has finished
    (several tests compare in-process and Dask runs bitwise)."""
    if numba_available() and not hasattr(config, "workerinput"):
        compile_kernels()


@pytest.fixture(params=TEST_BACKENDS)
def ci_backend(request):
    """Run the test under each backend of :mod:`cifilter.backend` (the parameter)."""
    with cifilter.use_backend(request.param):
        yield request.param


@pytest.hookimpl(hookwrapper=True)
def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Keep nbmake's closing advertisement out of the output (its summary hook prints only
    that line when ``--nbmake`` is on; failures are reported by pytest as usual)."""
    nbmake = getattr(config.option, "nbmake", None)
    config.option.nbmake = False
    yield
    config.option.nbmake = nbmake
