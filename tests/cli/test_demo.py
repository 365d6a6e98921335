"""The demo prints the library's rows (cifilter.network.summarize / score_track) with the
library's table (format_summary), and its band is that of a consistent estimator."""

import io

import numpy as np
from scipy import stats

from cifilter import metrics
from cifilter.cli.demo import run_network_demo, run_two_tracks, simulate
from cifilter.network import format_summary


def _table(text):
    lines = text.getvalue().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("method "))
    end = next((i for i in range(at, len(lines)) if not lines[i].strip()), len(lines))
    return "\n".join(lines[at - 1:end])


def test_network_demo_prints_the_librarys_table_of_its_rows():
    out = io.StringIO()
    rows = run_network_demo(runs=3, steps=5, methods=["ci", "naive"], out=out)
    assert _table(out) == format_summary(rows)
    header = out.getvalue()
    # the header says what the band is and where it is derived
    assert "design effect" in header and "docs/cli.rst" in header
    assert "4 -+ t * sqrt(2 * 4 * d / (30 * 3))" in header  # 5 steps x 6 nodes, 3 runs


def test_two_tracks_prints_the_same_columns_with_the_librarys_band():
    out = io.StringIO()
    rows = run_two_tracks(seed=3, runs=4, steps=12, methods=["ci"], out=out)
    printed = [{**row, "inside": row["steps_inside"],
                "us_per_fusion": 1e6 * row["time"] / 48 if row["time"] else 0.0}
               for row in rows]
    assert _table(out) == format_summary(printed)
    # the band of 'local A', from its NEES by hand: the same data from the same seed
    data = simulate(4, 12, rng=np.random.default_rng(3))
    nees = metrics.nees(data.truth, data.x_a, data.P_a)
    assert rows[0]["method"] == "local A"
    assert (rows[0]["anees"], rows[0]["lower"], rows[0]["upper"]) == \
        metrics.pooled_anees_band(nees, 4)


def test_an_overconfident_rules_band_is_that_of_a_consistent_one():
    """The default demo's size: naive fusion's band was [0.00, 512.91] when it came from
    naive fusion's own spread of run means; now it is at most as wide as the band of a
    consistent estimator whose values of a run all move together (one chi-square value
    per run, the widest the design effect allows)."""
    rows = {row["method"]: row for row in run_network_demo(
        seed=0, runs=10, steps=40, methods=["naive"], out=io.StringIO())}
    widest = stats.t.ppf(0.975, 9) * np.sqrt(2 * 4 / 10)
    naive = rows["naive"]
    assert 4 - widest <= naive["lower"] < 4 < naive["upper"] <= 4 + widest
    assert naive["verdict"] == "overconfident" and naive["anees"] > 100 * naive["upper"]
