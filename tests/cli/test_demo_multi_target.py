"""The multi-target demo: a fusion centre's table per rule (the library's rows and table)
and its figure."""

import io

import pytest

from cifilter.cli.demo import run_demo, run_multi_target_demo
from cifilter.cli.main import _build_parser, main
from cifilter.network import multi_target, simulate_targets
from cifilter.tracking import compare_tracking, format_tracking, score_sources


def _table(text):
    lines = text.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("method "))
    end = next((i for i in range(at, len(lines)) if not lines[i].strip()
                or lines[i].startswith("figure")), len(lines))
    return "\n".join(lines[at - 1:end])


def test_prints_the_librarys_table_of_the_librarys_rows(tmp_path):
    pytest.importorskip("matplotlib")
    out = io.StringIO()
    rows = run_demo(seed=2, runs=1, steps=24, methods=["ci", "naive"], out=out,
                    scenario="multi-target", plot=tmp_path / "figs")
    assert _table(out.getvalue()) == format_tracking(rows)
    assert [row["method"] for row in rows] == ["ci", "naive", "source radar-1",
                                               "source radar-2", "source camera"]
    # the same rows from the library on the same seeded data (the times aside)
    data = [simulate_targets(multi_target(steps=24), rng=2)]
    expected = compare_tracking(data, ["ci", "naive"]) + score_sources(data)
    for got, want in zip(rows, expected):
        assert {k: v for k, v in got.items() if k != "ms_per_scan"} == {
            k: v for k, v in want.items() if k != "ms_per_scan"}
    figure = tmp_path / "figs" / "multi_target.png"
    assert figure.stat().st_size > 10_000
    assert f"figure written to {figure}" in out.getvalue()
    assert "GOSPA" in out.getvalue() and "1 run x 24 scans, seed 2" in out.getvalue()


def test_a_rule_that_cannot_fuse_the_tracks_is_listed_with_the_reason():
    out = io.StringIO()
    rows = run_multi_target_demo(runs=1, steps=16, methods=["ci", "ei"], out=out)
    ei = next(row for row in rows if row["method"] == "ei")
    assert "error" in ei
    assert "ei" in out.getvalue() and "cannot run" in out.getvalue()


def test_network_options_and_unknown_rules_are_refused():
    with pytest.raises(ValueError, match="multi-target"):
        run_demo(scenario="multi-target", feedback=False)
    with pytest.raises(ValueError):
        run_multi_target_demo(methods=["no-such-rule"], out=io.StringIO())


def test_command_line(capsys):
    choices = next(a for a in _build_parser()._subparsers._group_actions[0].choices[
        "demo"]._actions if a.dest == "scenario").choices
    if "multi-target" not in choices:
        pytest.skip("cifilter/cli/main.py does not offer --scenario multi-target yet "
                    "(the parser's choices come from network.scenario_names())")
    assert main(["demo", "--scenario", "multi-target", "--runs", "1", "--steps", "16",
                 "--methods", "ci"]) == 0
    assert "cifilter demo --scenario multi-target" in capsys.readouterr().out
