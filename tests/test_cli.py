"""The command line and the demo (the README's main job)."""

import io
import subprocess
import sys

import pytest

from cifilter import available_methods
from cifilter.cli import main
from cifilter.demo import run_demo


def test_demo_runs_every_registered_method_and_writes_the_figure(tmp_path):
    figure = tmp_path / "demo.png"
    completed = subprocess.run(
        [sys.executable, "-m", "cifilter", "demo", "--runs", "3", "--steps", "25",
         "--plot", str(figure)],
        capture_output=True, text=True, timeout=300,
    )
    assert completed.returncode == 0, completed.stderr
    for name in available_methods():
        assert f"\n{name} " in completed.stdout
    assert "failed" not in completed.stdout
    assert figure.stat().st_size > 10_000


def test_demo_is_repeatable_with_a_seed():
    first = run_demo(seed=7, runs=2, steps=15, out=io.StringIO())
    second = run_demo(seed=7, runs=2, steps=15, out=io.StringIO())
    third = run_demo(seed=8, runs=2, steps=15, out=io.StringIO())
    strip = [{k: v for k, v in row.items() if k != "time"} for row in first]
    assert strip == [{k: v for k, v in row.items() if k != "time"} for row in second]
    assert strip != [{k: v for k, v in row.items() if k != "time"} for row in third]


def test_demo_scores_tell_the_known_story():
    rows = {row["method"]: row for row in run_demo(seed=1, runs=10, steps=60,
                                                   methods=["ci", "naive", "optimal"],
                                                   out=io.StringIO())}
    # CI is conservative, naive fusion double counts, the BLUE is consistent and best
    assert rows["ci"]["mean_nees"] < 4 < rows["naive"]["mean_nees"]
    assert rows["optimal"]["mean_trace"] < rows["ci"]["mean_trace"]
    assert rows["optimal"]["rmse"] <= min(rows["local A"]["rmse"], rows["local B"]["rmse"])
    assert abs(rows["optimal"]["mean_nees"] - 4) < 0.5


def test_methods_command_lists_the_registry(capsys):
    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    for name in available_methods():
        assert name in out


def test_unknown_demo_method_is_an_error():
    with pytest.raises(ValueError, match="unknown fusion method"):
        run_demo(methods=["nope"], out=io.StringIO())
