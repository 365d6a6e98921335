"""The command line and the demo (the README's main job)."""

import io
import subprocess
import sys

import pytest

from cifilter import available_methods
from cifilter.cli.demo import (
    network_memory_estimate,
    run_demo,
    run_network_demo,
    run_two_tracks,
)
from cifilter.cli.main import main


def _cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "cifilter", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_network_demo_runs_every_registered_method_and_writes_the_figures(tmp_path, capsys):
    assert main(["demo", "--runs", "2", "--steps", "6", "--plot", str(tmp_path / "figs")]) == 0
    out = capsys.readouterr().out
    assert "feeding the result back" in out
    assert any(line.startswith("method") and "ANEES" in line and "verdict" in line
               for line in out.splitlines())
    for name in ("local", "centralised", *available_methods()):
        assert f"\n{name} " in out
    for figure in ("nees.png", "rmse.png", "network.png"):
        assert (tmp_path / "figs" / figure).stat().st_size > 10_000


def test_two_track_demo_runs_every_registered_method_and_writes_the_figures(tmp_path, capsys):
    assert main(["demo", "--scenario", "two-tracks", "--runs", "3", "--steps", "25",
                 "--plot", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for name in available_methods():
        assert f"\n{name} " in out
    assert "failed" not in out
    for figure in ("two_tracks.png", "two_tracks_errors.png"):
        assert (tmp_path / figure).stat().st_size > 10_000


def test_demo_is_repeatable_with_a_seed():
    first = run_demo(seed=7, runs=2, steps=15, out=io.StringIO())  # the two tracks
    second = run_demo(seed=7, runs=2, steps=15, out=io.StringIO(), scenario="two-tracks")
    third = run_demo(seed=8, runs=2, steps=15, out=io.StringIO())
    strip = [{k: v for k, v in row.items() if k != "time"} for row in first]
    assert strip == [{k: v for k, v in row.items() if k != "time"} for row in second]
    assert strip != [{k: v for k, v in row.items() if k != "time"} for row in third]
    network = [run_network_demo(seed=seed, runs=3, steps=6, methods=["ci"], out=io.StringIO())
               for seed in (1, 1, 2)]
    strip = [[{k: v for k, v in row.items() if k != "us_per_fusion"} for row in rows]
             for rows in network]
    assert strip[0] == strip[1] != strip[2]


def test_two_track_scores_tell_the_known_story():
    rows = {row["method"]: row for row in run_two_tracks(
        seed=1, runs=10, steps=60, methods=["ci", "naive", "optimal"], out=io.StringIO())}
    # CI is conservative, naive fusion double counts, the BLUE is consistent and best
    assert rows["ci"]["mean_nees"] < 4 < rows["naive"]["mean_nees"]
    assert rows["optimal"]["mean_trace"] < rows["ci"]["mean_trace"]
    assert rows["optimal"]["rmse"] <= min(rows["local A"]["rmse"], rows["local B"]["rmse"])
    assert abs(rows["optimal"]["mean_nees"] - 4) < 0.5


def test_network_demo_tells_the_data_incest_story():
    rows = {row["method"]: row for row in run_network_demo(
        seed=0, runs=6, steps=25, methods=["ci", "naive"], out=io.StringIO())}
    assert rows["naive"]["verdict"] == "overconfident"
    assert rows["ci"]["anees"] < rows["ci"]["upper"]


def test_methods_command_lists_the_registry_under_a_header(capsys):
    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split()[:3] == ["method", "P", "is"]
    for name in available_methods():
        assert name in out


def test_unknown_demo_method_is_an_error():
    with pytest.raises(ValueError, match="unknown fusion method"):
        run_demo(methods=["nope"], out=io.StringIO())
    with pytest.raises(ValueError, match="unknown fusion method"):
        run_network_demo(methods=["nope"], out=io.StringIO())


@pytest.mark.parametrize("arguments, message", [
    (["demo", "--methods", "ci,foo"], "unknown method(s) 'foo'"),
    (["demo", "--runs", "0"], "argument --runs: must be at least 1"),
    (["demo", "--steps", "many"], "expected a positive integer"),
    (["demo", "--seed", "-3"], "must be non-negative"),
    (["demo", "--loss", "1.5"], "must be in [0, 1]"),
    (["demo", "--scenario", "star"], "invalid choice"),
    (["demo", "--workers", "2", "--scheduler", "tcp://x:1"], "not allowed with"),
    (["demo", "--scenario", "two-tracks", "--delay"], "--delay applies to the network"),
    (["demo", "--nodes", "4"], "naveen-taylor has a fixed number of nodes"),
    (["demo", "--scenario", "common-information", "--nodes", "3"],
     "common-information has a fixed number of nodes"),
    (["frobnicate"], "invalid choice"),
    (["reproduce", "weng", "--runs", "0"], "argument --runs: must be at least 1"),
    (["reproduce", "naveen", "--plot", "/proc/cifilter-figures"], "argument --plot"),
    (["reproduce"], "required: PAPER"),
    (["demo", "--scenario", "ring", "--nodes", "1"], "--nodes: nodes must be >= 3, got 1"),
    (["demo", "--scenario", "chain", "--nodes", "1"], "--nodes: nodes must be >= 2, got 1"),
    # refused from an estimate of the memory before any work (it grew to 24 GB before)
    (["demo", "--scenario", "ring", "--nodes", "100000"], "--nodes 100000: the study would "
                                                          "need about"),
    # a closed port: refused at once (it waited 30 s, then printed a traceback)
    (["demo", "--scheduler", "tcp://127.0.0.1:1"], "--scheduler: cannot connect to "
                                                   "'tcp://127.0.0.1:1' within 5 s"),
])
def test_bad_arguments_exit_2_with_one_line(arguments, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(arguments)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err
    assert err.startswith("python -m cifilter")


def test_memory_estimate_grows_as_the_square_of_the_nodes():
    small = network_memory_estimate(10_000, 4, 40, 5) - 250e6
    assert network_memory_estimate(6, 4, 40, 5) < 300e6  # the default demo always runs
    assert 3.9 < (network_memory_estimate(20_000, 4, 40, 5) - 250e6) / small < 4.1
    assert network_memory_estimate(100_000, 4, 40, 5) > 1e13
    with pytest.raises(ValueError, match="nodes must be >= 1"):
        network_memory_estimate(0, 4, 40, 5)


def test_unwritable_plot_path_fails_before_the_work_without_traceback(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    completed = _cli("demo", "--plot", str(blocker / "figs"), "--runs", "1000000")
    assert completed.returncode == 2
    assert "Traceback" not in completed.stderr
    assert completed.stderr.count("\n") == 1 and "argument --plot" in completed.stderr
    assert completed.stdout == ""  # nothing ran


@pytest.mark.slow
def test_network_demo_on_two_dask_workers_gives_the_same_table():
    from cifilter import montecarlo
    from cifilter.cli.demo import run_network_demo

    here = run_network_demo(seed=4, runs=10, steps=8, methods=["ci", "naive"],
                            out=io.StringIO())
    with montecarlo.dask_client(workers=2) as client:
        there = run_network_demo(seed=4, runs=10, steps=8, methods=["ci", "naive"],
                                 out=io.StringIO(), client=client)
    strip = [[{k: v for k, v in row.items() if k != "us_per_fusion"} for row in rows]
             for rows in (here, there)]
    assert strip[0] == strip[1]


# --------------------------------------------------- the verdict's band (issue 21, item 7)
def test_demo_verdict_uses_the_pooled_band_and_keeps_the_step_share():
    rows = {row["method"]: row for row in run_network_demo(
        seed=0, runs=10, steps=40, methods=["ci", "cu", "naive"], out=io.StringIO())}
    for row in rows.values():
        assert row["lower"] < 4 < row["upper"]
        assert (row["step_lower"], row["step_upper"]) == pytest.approx((2.44, 5.93), abs=0.01)
        assert 0 <= row["inside"] <= 1
        assert row["trace_position"] + row["trace_velocity"] == pytest.approx(
            row["mean_trace"], rel=1e-12)
        assert row["rmse_velocity"] > 0
    assert rows["cu"]["verdict"] == "conservative"  # 1.62, far below its band
    assert rows["naive"]["verdict"] == "overconfident"


def test_two_tracks_prints_the_network_demos_columns():
    network, two = io.StringIO(), io.StringIO()
    run_network_demo(runs=3, steps=5, methods=["ci"], out=network)
    rows = run_two_tracks(runs=3, steps=20, methods=["ci"], out=two)

    def header(text):
        lines = text.getvalue().splitlines()
        at = next(i for i, line in enumerate(lines) if line.startswith("method "))
        return [line.split() for line in lines[at - 1:at + 1]]

    assert header(two) == header(network)
    assert "guarantee: what the rule's P is" in two.getvalue()
    ci = rows[-1]
    assert ci["trace_position"] + ci["trace_velocity"] == pytest.approx(ci["mean_trace"])
    assert ci["anees"] == pytest.approx(ci["mean_nees"], rel=1e-12)  # the same pooled mean
