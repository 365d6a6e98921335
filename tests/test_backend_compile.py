"""No foreground compile stall (issue 24): under ``"auto"`` a call never waits for numba.

Each check runs in a fresh process with ``NUMBA_CACHE_DIR`` set to a temporary directory
(empty at first), and reads where the calls went from the dispatcher's report
(``cifilter._kernels.dispatch.report()``), not from timings: the first batched call is
answered by numpy and emits one :class:`cifilter.backend.CompileNotice`; after
``python -m cifilter compile`` a new process's first call runs on the kernels, loaded
from the cache, and agrees with the numpy answer to the documented bound
(``docs/backend.rst``: optimal weights, ``omega`` and ``P`` to ``1e-9``).
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cifilter.backend import numba_available

needs_numba = pytest.mark.skipif(not numba_available(), reason="numba is not installed")

# One process: 1000 pairs of 4x4 covariances, two "auto" calls, the report after each, the
# notices, and the first result saved to OUT.
FIRST_CALLS = """
import json, sys, warnings
import numpy as np
import cifilter
from cifilter._kernels import dispatch

rng = np.random.default_rng(7)
A = rng.standard_normal((1000, 2, 4, 4))
Ps = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(4)
xs = rng.standard_normal((1000, 2, 4))
reports = []
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    first = cifilter.covariance_intersection(xs, Ps)
    reports.append(dispatch.report())
    cifilter.covariance_intersection(xs, Ps)
    reports.append(dispatch.report())
np.savez(sys.argv[1], omega=first.omega, P=first.P, x=first.x)
notices = [str(w.message) for w in caught
           if issubclass(w.category, cifilter.backend.CompileNotice)]
print(json.dumps({"reports": reports, "notices": notices,
                  "backend": cifilter.get_backend()}))
"""


# One process: a single fusion of two 4x4 estimates under "auto" (the single-call route),
# then where it went and whether it started a compilation or warned.
SINGLE_CALL = """
import json, warnings
import numpy as np
import cifilter
from cifilter._kernels import dispatch

with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    cifilter.fuse([(np.zeros(4), np.eye(4)), (np.ones(4), 2.0 * np.eye(4))])
report = dispatch.report()
print(json.dumps({"kernels": report["kernels"], "compiling": report["compiling"],
                  "ready": report["ready"], "warnings": [str(w.message) for w in caught]}))
"""


def _single_call(cache):
    done = _run(["-c", SINGLE_CALL], cache)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def _run(args, cache):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env,
                          timeout=900)


def _first_calls(cache, out):
    done = _run(["-c", FIRST_CALLS, str(out)], cache)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@needs_numba
def test_first_auto_call_uses_numpy_and_after_compile_a_new_process_uses_the_kernels(tmp_path):
    cache = tmp_path / "numba-cache"
    cache.mkdir()

    # 0. empty cache: a single call under auto stays on numpy, starts no compilation and
    # says nothing (the single-call route waits for the kernels to be there)
    single = _single_call(cache)
    assert single == {"kernels": 0, "compiling": False, "ready": False, "warnings": []}

    # 1. empty cache: numpy answers, the compilation runs in the background, one notice
    before = _first_calls(cache, tmp_path / "before.npz")
    assert before["backend"] == "auto"
    first = before["reports"][0]
    assert first["kernels"] == 0
    assert first["numpy_while_compiling"] == 1
    assert first["ready"] is False
    assert len(before["notices"]) == 1, before["notices"]
    assert "python -m cifilter compile" in before["notices"][0]

    # 2. compile ahead of time, in the foreground, into the same cache
    done = _run(["-m", "cifilter", "compile"], cache)
    assert done.returncode == 0, done.stderr
    for name in ("ci_pair", "ci_pair_serial", "weighted_fusion",
                 "weighted_fusion_serial", "ci_many_optimal", "ci_many_optimal_serial",
                 "generalised_pair", "shifted_pair"):
        assert name in done.stdout
    assert "8 kernels ready in" in done.stdout

    # 3. a new process: its first call runs on the kernels (loaded from the cache), silently
    after = _first_calls(cache, tmp_path / "after.npz")
    assert after["reports"][0]["kernels"] == 1
    assert after["reports"][0]["numpy_while_compiling"] == 0
    assert after["reports"][0]["ready"] is True
    assert after["reports"][1]["kernels"] == 2
    assert after["notices"] == []
    # and a new process's first single call under auto takes the compiled route, silently
    single = _single_call(cache)
    assert single == {"kernels": 1, "compiling": False, "ready": True, "warnings": []}

    # 4. the two answers agree to the documented bound of the optimal weights
    a, b = np.load(tmp_path / "before.npz"), np.load(tmp_path / "after.npz")
    np.testing.assert_allclose(a["omega"], b["omega"], rtol=0, atol=1e-9)
    scale = np.abs(a["P"]).max(axis=(-2, -1), keepdims=True)
    assert (np.abs(a["P"] - b["P"]) <= 1e-9 * scale).all()

    # 5. one kernel missing from the cache (a process stopped while it compiled) compiles
    # next to the ones loaded from it: numba cannot link a kernel loaded from its cache
    # into a function compiled afresh, so no kernel calls another kernel
    missing = sorted(cache.rglob("*shifted_pair*"))
    assert missing
    for path in missing:
        path.unlink()
    again = _run(["-m", "cifilter", "compile"], cache)
    assert again.returncode == 0, again.stderr
    assert "8 kernels ready in" in again.stdout
    assert [line.split()[1] for line in again.stdout.splitlines()
            if line.startswith("shifted_pair ")] == ["compiled"]


def test_compile_without_numba_is_a_one_line_error(tmp_path):
    code = ("import sys; sys.modules['numba'] = None\n"
            "from cifilter.cli.main import main\n"
            "sys.exit(main(['compile']))")
    done = _run(["-c", code], tmp_path)
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1
    assert "numba is not installed" in done.stderr

