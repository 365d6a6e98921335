"""The main job: a sensor network whose nodes fuse each other's tracks, by every rule.

By default (``python -m cifilter demo``) the six nodes of Naveen & Taylor's network
(Section V-B; :func:`cifilter.network.naveen_taylor`) track one target. Every step each
node predicts, updates with its own position measurement, receives its neighbours'
estimates and fuses them into its own with the rule under test, **feeding the result
back** into its filter. The information a node sends returns to it through its
neighbours: a rule that assumes independent errors counts it again and again (data
incest) and becomes overconfident; Covariance Intersection stays conservative. The demo
runs every registered rule on the same simulated data, through
:func:`cifilter.montecarlo.run` (in process, or on Dask with ``--workers``/``--scheduler``),
and scores them with :func:`cifilter.network.summarize`: position and velocity RMSE, the
pooled ANEES with the band in which a consistent filter's lies
(:func:`cifilter.metrics.pooled_anees_band`) and a verdict, the share of steps inside one
step's chi-square bounds, the mean traces of ``P``'s position and velocity blocks and the
time per fusion.

``--scenario two-tracks`` is the earlier demo: two trackers with different sensors, their
tracks fused by every rule *without* feedback (:func:`run_two_tracks`).

``--scenario multi-target`` is a track-to-track fusion centre (:mod:`cifilter.tracking`):
several targets (two crossing, some appearing and disappearing) seen by two radars and a
camera that run their own local trackers, with missed detections and false tracks; the
centre associates the source tracks, manages its central tracks and fuses them with each
rule, scored by GOSPA, the ANEES of the matched central tracks, position RMSE, ID switches
and false and missed tracks (:func:`run_multi_target_demo`).

Rules that need knowledge a real node lacks (``"optimal"``: the true joint covariance;
``"pci"``: a correlation bound) get it from the simulation through their registry
``truth_options`` hook, so rules registered later appear here without editing this file.
"""

import os
import sys
import textwrap
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, TextIO, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from .. import metrics
from .._numerics.validation import as_rng, check_int
from ..filters.kalman import KalmanFilter
from ..network.graph import Scenario, constant_velocity_model, get_scenario
from ..network.study import (
    REFERENCES,
    NetworkStudy,
    format_summary,
    score_track,
    summarize,
)
from ..registry import available_methods, fuse, get_method

if TYPE_CHECKING:  # Dask is optional, imported only when a cluster is asked for
    from distributed import Client

__all__ = [
    "DEMO_CHUNK_SIZE",
    "DemoData",
    "constant_velocity_model",
    "format_table",
    "network_memory_estimate",
    "run_demo",
    "run_multi_target_demo",
    "run_network_demo",
    "run_two_tracks",
    "score",
    "simulate",
]

POSITION = [0, 2]  # indices of x and y in the state [x, vx, y, vy]

DEMO_CHUNK_SIZE = 5
"""Runs per Monte Carlo chunk of the network demo: the numbers depend on the seed and on
this size, never on the number of Dask workers."""

NETWORK_DEFAULTS = {"runs": 10, "steps": 40}
TWO_TRACK_DEFAULTS = {"runs": 20, "steps": 100}
MULTI_TARGET_DEFAULTS = {"runs": 2, "steps": 60}


@dataclass(frozen=True)
class DemoData:
    """Simulated truth and local tracks (returned by :func:`simulate`).

    The parameters are also the attributes.

    Parameters
    ----------
    truth : ndarray, shape (runs, steps, 4)
        True states ``[x, vx, y, vy]``.
    x_a, x_b : ndarray, shape (runs, steps, 4)
        Posterior means of the two local filters.
    P_a, P_b : ndarray, shape (steps, 4, 4)
        Their posterior covariances (the same in every run: the model is linear).
    joint : ndarray, shape (steps, 8, 8)
        True joint error covariance of the two tracks.

    Examples
    --------
    >>> from cifilter.cli.demo import simulate
    >>> simulate(runs=1, steps=3, rng=0).truth.shape
    (1, 3, 4)
    """

    truth: NDArray[np.float64]
    x_a: NDArray[np.float64]
    x_b: NDArray[np.float64]
    P_a: NDArray[np.float64]
    P_b: NDArray[np.float64]
    joint: NDArray[np.float64]


def _make_filter(F, Q, H, R, x0, P0):
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.Q, kf.H, kf.R = F, Q, H, R
    kf.x, kf.P = x0.reshape(4, 1).copy(), P0.copy()
    return kf


def simulate(runs: int = 20, steps: int = 100, *, dt: float = 1.0, q: float = 0.5,
             sigma_a: tuple[float, float] = (10.0, 2.0),
             sigma_b: tuple[float, float] = (3.0, 8.0),
             rng: Optional[Union[int, np.random.Generator]] = None) -> DemoData:
    """Simulate the demo scenario.

    Parameters
    ----------
    runs, steps : int
        Monte Carlo runs and time steps per run.
    dt : float
        Time step [s].
    q : float
        White-noise acceleration density [m^2/s^3] (the common process noise).
    sigma_a, sigma_b : tuple of float
        Standard deviations [m] of sensors A and B in x and y.
    rng : numpy.random.Generator, int or None
        Randomness source.

    Returns
    -------
    DemoData
        Truth, local tracks and the true joint covariance.

    Examples
    --------
    >>> from cifilter.cli.demo import simulate
    >>> data = simulate(runs=2, steps=5, rng=0)
    >>> data.x_a.shape, data.joint.shape
    ((2, 5, 4), (5, 8, 8))
    """
    rng = as_rng(rng)
    runs, steps = check_int(runs, "runs", low=1), check_int(steps, "steps", low=1)
    F, Q = constant_velocity_model(dt, q)
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    R_a, R_b = np.diag(np.square(sigma_a)), np.diag(np.square(sigma_b))
    P0 = np.diag([100.0, 25.0, 100.0, 25.0])
    L_Q, L_P0 = np.linalg.cholesky(Q), np.linalg.cholesky(P0)

    truth = np.empty((runs, steps, 4))
    x_a, x_b = np.empty_like(truth), np.empty_like(truth)
    P_a, P_b = np.empty((steps, 4, 4)), np.empty((steps, 4, 4))
    gains_a, gains_b = np.empty((steps, 4, 2)), np.empty((steps, 4, 2))
    for r in range(runs):
        state = np.array([0.0, 10.0, 0.0, 5.0])
        # Each tracker starts from its own independent prior: the correlation between the
        # tracks comes from the common process noise alone.
        kf_a = _make_filter(F, Q, H, R_a, state + L_P0 @ rng.standard_normal(4), P0)
        kf_b = _make_filter(F, Q, H, R_b, state + L_P0 @ rng.standard_normal(4), P0)
        for k in range(steps):
            state = F @ state + L_Q @ rng.standard_normal(4)
            truth[r, k] = state
            for kf, R, out in ((kf_a, R_a, x_a), (kf_b, R_b, x_b)):
                z = H @ state + np.sqrt(np.diag(R)) * rng.standard_normal(2)
                kf.predict()
                kf.update(z.reshape(2, 1))
                out[r, k] = kf.x[:, 0]
            if r == 0:  # covariances and gains do not depend on the data
                P_a[k], P_b[k] = kf_a.P, kf_b.P
                gains_a[k], gains_b[k] = kf_a.K, kf_b.K

    # Cross-covariance of the two tracks (Bar-Shalom & Campo 1986): the common process
    # noise correlates them; the priors and the measurement noises are independent.
    joint = np.empty((steps, 8, 8))
    cross, eye = np.zeros((4, 4)), np.eye(4)
    for k in range(steps):
        cross = (eye - gains_a[k] @ H) @ (F @ cross @ F.T + Q) @ (eye - gains_b[k] @ H).T
        joint[k] = np.block([[P_a[k], cross], [cross.T, P_b[k]]])
    return DemoData(truth, x_a, x_b, P_a, P_b, joint)


def score(x: ArrayLike, P: ArrayLike, truth: ArrayLike) -> dict[str, float]:
    """RMSE, NEES statistics and mean trace of estimates against the truth.

    Parameters
    ----------
    x : array_like, shape (..., 4)
        Estimates of ``[x, vx, y, vy]``.
    P : array_like, shape (..., 4, 4)
        Their covariances (broadcast against ``x``).
    truth : array_like, shape (..., 4)
        True states.

    Returns
    -------
    dict
        ``rmse`` (position, m; :func:`cifilter.metrics.rmse`), ``mean_nees``
        (:func:`cifilter.metrics.nees` averaged; 4 for a consistent estimator),
        ``inside`` (share of NEES <= the 95% chi-square quantile, 0.95 when consistent)
        and ``mean_trace``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.cli.demo import score
    >>> s = score(np.zeros((3, 4)), np.eye(4), np.zeros((3, 4)))
    >>> s["rmse"], s["mean_nees"], s["inside"]
    (0.0, 0.0, 1.0)
    """
    x, truth = np.asarray(x, dtype=float), np.asarray(truth, dtype=float)
    P = np.broadcast_to(P, x.shape + x.shape[-1:])
    nees = metrics.nees(truth, x, P)
    bound = stats.chi2.ppf(0.95, df=x.shape[-1])
    return {
        "rmse": float(metrics.rmse(truth, x, axis=None, components=POSITION)),
        "mean_nees": float(np.mean(nees)),
        "inside": float(np.mean(nees <= bound)),
        "mean_trace": float(np.mean(np.trace(P, axis1=-2, axis2=-1))),
    }


def _fuse_all(data, methods, rng):
    """Fuse the two tracks of every run and step with each method (one batched call each)."""
    rows, fused = [], {}
    for name, x, P, guarantee in (("local A", data.x_a, data.P_a, "exact"),
                                  ("local B", data.x_b, data.P_b, "exact")):
        rows.append({"method": name, "guarantee": guarantee, "time": 0.0,
                     **score(x, P, data.truth), **_network_columns(x, P, data.truth)})
    for name in methods:
        record = get_method(name)
        start = time.perf_counter()
        try:
            options = record.options_given_truth(data.joint, rng)
            result = fuse([(data.x_a, data.P_a), (data.x_b, data.P_b)], method=name, **options)
        except Exception as exc:  # a user-registered rule may need options the demo lacks
            rows.append({"method": name, "guarantee": record.guarantee,
                         "error": f"{type(exc).__name__}: {exc}"})
            continue
        elapsed = time.perf_counter() - start
        fused[name] = result
        rows.append({"method": name, "guarantee": record.guarantee, "time": elapsed,
                     **score(result.x, result.P, data.truth),
                     **_network_columns(result.x, result.P, data.truth)})
    return rows, fused


def _network_columns(x, P, truth):
    """The network demo's columns for the two tracks (runs, steps), from
    :func:`cifilter.network.score_track`; its ``inside`` (steps in one step's bounds) is
    ``steps_inside`` here, next to :func:`score`'s share of single NEES values."""
    columns = score_track(truth, x, P, position_indices=POSITION)
    columns["steps_inside"] = columns.pop("inside")
    del columns["rmse"], columns["mean_trace"]  # score's, computed the same way
    return columns


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The demo's table as text (one row per estimator).

    Parameters
    ----------
    rows : list of dict
        As returned by :func:`run_two_tracks`.

    Returns
    -------
    str
        The table.

    Examples
    --------
    >>> from cifilter.cli.demo import format_table
    >>> print(format_table([{"method": "ci", "guarantee": "bound", "rmse": 2.6,
    ...                      "mean_nees": 2.8, "inside": 0.99, "mean_trace": 15.0,
    ...                      "time": 0.02}]))  # doctest: +NORMALIZE_WHITESPACE
    method     P is   RMSE pos [m]  mean NEES  NEES<=chi2_95  mean tr(P)  time [ms]
    -------------------------------------------------------------------------------
    ci         bound         2.600       2.80          99.0%       15.00       20.0
    """
    header = (f"{'method':<10} {'P is':<6} {'RMSE pos [m]':>12} {'mean NEES':>10} "
              f"{'NEES<=chi2_95':>14} {'mean tr(P)':>11} {'time [ms]':>10}")
    lines = [header, "-" * len(header)]
    for row in rows:
        if "error" in row:
            lines.append(f"{row['method']:<10} {row['guarantee']:<6} failed: {row['error']}")
            continue
        lines.append(
            f"{row['method']:<10} {row['guarantee']:<6} {row['rmse']:>12.3f} "
            f"{row['mean_nees']:>10.2f} {100 * row['inside']:>13.1f}% "
            f"{row['mean_trace']:>11.2f} {1000 * row['time']:>10.1f}"
        )
    return "\n".join(lines)




def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(count, columns=3, width=4.2, height=3.6, *, top=0.95, bottom=0.85, share=False):
    """A grid of panels with margins in inches (``top`` above the first row for the
    figure's title, ``bottom`` below the last for a figure legend), so that they do not
    grow with the number of rows."""
    plt = _pyplot()
    columns = min(columns, count)
    rows = -(-count // columns)
    # fixed margins: constrained layout costs seconds per figure on a busy machine
    size = height * rows + top + bottom
    fig, axes = plt.subplots(rows, columns, figsize=(width * columns, size), squeeze=False,
                             sharex=share, sharey=share)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=bottom / size, top=1 - top / size,
                        hspace=0.45, wspace=0.3)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return plt, fig, list(axes.flat[:count])


def _title_and_legend(fig, title, handles, labels, *, columns=4):
    """The figure's title at its top edge and one legend for every panel at its bottom."""
    height = fig.get_size_inches()[1]
    fig.suptitle(title, y=1 - 0.12 / height, va="top")
    fig.legend(handles, labels, loc="lower center", ncol=columns, fontsize="small",
               frameon=False, bbox_to_anchor=(0.5, 0.05 / height), markerscale=2)


def _plot_two_tracks(data, fused, directory):
    """Two figures: per rule a zoom on run 0's track with the 95% ellipses of P, and per
    rule the position errors of the second half of all runs with the ellipse of P."""
    from .plotting import covariance_ellipse

    names = list(fused)
    plt, fig, axes = _grid(len(names) + 1)
    steps = data.truth.shape[1]
    window = slice(max(0, steps // 2 - 3), max(1, steps // 2 + 3))  # half a dozen steps
    truth = data.truth[0, window][:, POSITION]
    overview = axes[0]
    overview.plot(data.truth[0, :, 0], data.truth[0, :, 2], "k-", lw=2, label="truth")
    overview.plot(data.x_a[0, :, 0], data.x_a[0, :, 2], ":", label="local A")
    overview.plot(data.x_b[0, :, 0], data.x_b[0, :, 2], ":", label="local B")
    overview.plot(truth[:, 0], truth[:, 1], "rs", ms=3, label="zoomed steps")
    overview.set(title="run 0: truth and local tracks", xlabel="x [m]", ylabel="y [m]")
    # equal scales without flattening the panel: the limits grow instead of the box shrinking
    overview.set_aspect("equal", adjustable="datalim")
    overview.legend(fontsize="x-small", loc="upper left")
    for ax, name in zip(axes[1:], names):
        x = fused[name].x.reshape(data.truth.shape)[0, window]
        P = np.broadcast_to(fused[name].P, data.truth.shape + (4,))[0, window]
        ax.plot(truth[:, 0], truth[:, 1], "k.-", lw=1.5, label="truth")
        ax.plot(x[:, 0], x[:, 2], "C0.-", lw=1, label="fused estimate")
        for k in range(x.shape[0]):
            curve = covariance_ellipse(P[k][np.ix_(POSITION, POSITION)], x[k, POSITION])
            ax.plot(curve[0], curve[1], color="C3", lw=0.8,
                    label="95% ellipse of P" if k == 0 else None)
        ax.set(title=f"{name}: steps {window.start}-{window.stop - 1} of run 0",
               xlabel="x [m]", ylabel="y [m]")
    # one scale for the rules' panels: the same limits, then equal aspect in each
    low = np.min([ax.dataLim.min for ax in axes[1:]], axis=0)
    high = np.max([ax.dataLim.max for ax in axes[1:]], axis=0)
    pad = 0.05 * (high - low)
    for ax in axes[1:]:
        ax.set(xlim=(low[0] - pad[0], high[0] + pad[0]),
               ylim=(low[1] - pad[1], high[1] + pad[1]))
        ax.set_aspect("equal", adjustable="datalim")
    _title_and_legend(fig, "two-track demo: the fused tracks of run 0 (zoom) and the 95% "
                      "ellipse of each rule's P at every step (the same scale in every "
                      "rule's panel)",
                      *axes[1].get_legend_handles_labels(), columns=3)
    tracks = directory / "two_tracks.png"
    fig.savefig(tracks, dpi=110)
    plt.close(fig)

    # one scale for every panel, so that the ellipses compare at a glance
    half = steps // 2  # second half of the run: near the steady state
    errors, ellipses = {}, {}
    for name in names:
        x = fused[name].x.reshape(data.truth.shape)
        errors[name] = (x[:, half:] - data.truth[:, half:])[..., POSITION].reshape(-1, 2)
        P = np.broadcast_to(fused[name].P, data.truth.shape + (4,))[0, -1]
        ellipses[name] = covariance_ellipse(P[np.ix_(POSITION, POSITION)])
    reach = 1.05 * max(max(np.abs(errors[name]).max(), np.abs(ellipses[name]).max())
                       for name in names)
    plt, fig, axes = _grid(len(names), height=4.0, share=True)
    for ax, name in zip(axes, names):
        ax.plot(errors[name][:, 0], errors[name][:, 1], ".", ms=2, alpha=0.5,
                label=f"errors of all runs, steps {half + 1}-{steps}")
        ax.plot(ellipses[name][0], ellipses[name][1], color="C3", label="95% ellipse of P")
        ax.set(title=name, xlabel="error x [m]", ylabel="error y [m]", aspect="equal",
               xlim=(-reach, reach), ylim=(-reach, reach))
        ax.tick_params(labelbottom=True, labelleft=True)
    _title_and_legend(fig, "two-track demo: fused position errors and the 95% ellipse of "
                      "each rule's P (the same scale in every panel)",
                      *axes[0].get_legend_handles_labels(), columns=2)
    errors_path = directory / "two_tracks_errors.png"
    fig.savefig(errors_path, dpi=110)
    plt.close(fig)
    return [tracks, errors_path]


def run_two_tracks(seed: int = 0, runs: int = 20, steps: int = 100,
                   methods: Optional[Sequence[str]] = None,
                   plot: Optional[Union[str, os.PathLike[str]]] = None,
                   out: Optional[TextIO] = None) -> list[dict[str, Any]]:
    """The two-track demo: two trackers, their tracks fused by every rule without feedback.

    Parameters
    ----------
    seed : int, optional
        Seed of the random generator (same seed, same table).
    runs, steps : int, optional
        Monte Carlo runs and steps per run (default 20 x 100).
    methods : sequence of str, optional
        Methods to run; default every registered one.
    plot : str or path, optional
        Directory for the figures ``two_tracks.png`` (a zoom on the fused tracks of run
        0 with the ellipses of ``P``, one panel per rule) and ``two_tracks_errors.png``.
    out : file, optional
        Where to print (default standard output).

    Returns
    -------
    list of dict
        One row per estimator with ``method``, ``guarantee``, ``rmse``, ``mean_nees``,
        ``inside`` (share of single NEES values under the 95% chi-square quantile),
        ``mean_trace`` and ``time`` (or ``error``), and the network demo's columns
        ``rmse_velocity``, ``anees``, ``lower``, ``upper``, ``verdict`` (the pooled band,
        :func:`cifilter.metrics.pooled_anees_band`), ``steps_inside`` (between
        ``step_lower`` and ``step_upper``), ``trace_position`` and ``trace_velocity``
        (:func:`cifilter.network.score_track`): the printed table has the network demo's
        columns.

    Examples
    --------
    >>> import io
    >>> from cifilter.cli.demo import run_two_tracks
    >>> rows = run_two_tracks(runs=2, steps=10, methods=["ci", "naive"], out=io.StringIO())
    >>> [row["method"] for row in rows]
    ['local A', 'local B', 'ci', 'naive']
    """
    out = sys.stdout if out is None else out
    methods = list(available_methods() if methods is None else methods)
    for name in methods:
        get_method(name)  # unknown names fail before the simulation
    directory = None if plot is None else _directory(plot)
    rng = as_rng(seed)
    data = simulate(runs, steps, rng=rng)
    rows, fused = _fuse_all(data, methods, rng)
    print(
        f"cifilter demo --scenario two-tracks: 2-D constant-velocity target, sensor A "
        f"(sigma x, y = 10, 2 m) and sensor B (3, 8 m);\n{runs} runs x {steps} steps, seed "
        f"{seed}. The tracks are correlated through the common process noise and fused "
        "without feedback.\n"
        f"{_network_legend(runs, 4, steps, nodes=False)}\n",
        file=out,
    )
    fusions = runs * steps  # one batched call fuses every run and step
    print(format_summary([
        row if "error" in row else
        {**row, "inside": row["steps_inside"],
         "us_per_fusion": 1e6 * row["time"] / fusions if row["time"] else 0.0}
        for row in rows]), file=out)
    if directory is not None:
        for path in _plot_two_tracks(data, fused, directory):
            print(f"figure written to {path}", file=out)
    return rows


def _directory(plot):
    from pathlib import Path

    directory = Path(plot)
    directory.mkdir(parents=True, exist_ok=True)
    return directory


def _plain_log_ticks(ax):
    """Tick labels 2, 5, 10 rather than 2x10^0 on a logarithmic axis."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    plain = FuncFormatter(lambda value, _: f"{value:g}")
    ax.yaxis.set_major_formatter(plain)
    low, high = ax.get_ylim()
    # label the minor ticks 2, 3 and 5 (not 4, 6, 7, 8, 9: they crowd) when the axis spans
    # little more than a decade
    mantissa = FuncFormatter(
        lambda value, _: f"{value:g}" if round(value / 10 ** np.floor(np.log10(value)))
        in (2, 3, 5) else "")
    ax.yaxis.set_minor_formatter(mantissa if high < 30 * low else NullFormatter())


def _scale_bar(ax, scale):
    """A scale bar in the lower left of a panel drawn at ``scale`` layout units per m."""
    low_x, high_x = ax.get_xlim()
    low_y, high_y = ax.get_ylim()
    metres = 0.2 * (high_x - low_x) / scale  # about a fifth of the panel, rounded to 1-2-5
    exponent = np.floor(np.log10(metres))
    step = min((1.0, 2.0, 5.0), key=lambda s: abs(s * 10**exponent - metres)) * 10**exponent
    x0, y0 = low_x + 0.05 * (high_x - low_x), low_y + 0.06 * (high_y - low_y)
    ax.plot([x0, x0 + step * scale], [y0, y0], color="k", lw=2.5, solid_capstyle="butt")
    ax.annotate(f"{step:g} m", (x0 + step * scale / 2, y0), xytext=(0, 3),
                textcoords="offset points", ha="center", va="bottom", fontsize=8)


def _plot_network(results, rows, scenario, directory):
    """nees.png (ANEES against time per rule with the chi-square band), rmse.png and
    network.png (the graph with every node's error ellipses, one panel per rule)."""
    from .plotting import covariance_ellipse

    names = [row["method"] for row in rows if "error" not in row]
    runs = next(iter(results.values())).shape[0]
    paths = []

    by_name = {row["method"]: row for row in rows if "error" not in row}
    plt, fig, axes = _grid(len(names), top=1.1, bottom=1.25)
    for ax, name in zip(axes, names):
        result = metrics.anees(results[f"{name}/nees"], scenario.dim)  # (steps, nodes)
        steps = np.arange(1, result.value.shape[0] + 1)
        ax.fill_between(steps, result.lower, result.upper, color="0.88",
                        label=f"one step's 95% bounds ({runs} runs)")
        row = by_name[name]
        if np.isfinite(row["lower"]):
            ax.axhspan(row["lower"], row["upper"], color="0.6", alpha=0.5, lw=0,
                       label="95% band of the pooled ANEES (the verdict)")
        ax.axhline(scenario.dim, color="0.3", lw=0.8, ls="--", label=f"n = {scenario.dim}")
        ax.plot(steps, result.value, lw=0.6, alpha=0.5, color="C0")
        ax.plot(steps, result.value.mean(axis=1), lw=1.8, color="C3",
                label="ANEES, mean over nodes")
        ax.plot([], [], lw=0.6, color="C0", label="ANEES of each node")
        ax.axhline(row["anees"], color="C3", lw=1.2, ls=":", label="pooled ANEES")
        ax.set(title=f"{name}: {row['verdict']}", xlabel="step", ylabel="ANEES",
               yscale="log")
        _plain_log_ticks(ax)
    # one legend for all panels, below them (it covered the curves in every panel)
    _title_and_legend(
        fig, f"{scenario.name}: ANEES over {runs} runs against time. The table's verdict "
        "compares the pooled ANEES (dotted)\nwith its band (dark grey): inside consistent, "
        "below conservative, above overconfident",
        *axes[0].get_legend_handles_labels(), columns=3)
    paths.append(directory / "nees.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # rmse.png: one panel per guarantee (at most 7 rules each, every one its own colour),
    # the references in black in each, one scale
    groups = {}
    for name in names:
        if name not in REFERENCES:
            groups.setdefault(by_name[name]["guarantee"], []).append(name)
    meaning = {"exact": "P is the error's covariance", "bound": "P bounds the error",
               "none": "heuristics"}
    groups = dict(sorted(groups.items(), key=lambda item: (
        list(meaning).index(item[0]) if item[0] in meaning else len(meaning))))
    fig, axes = plt.subplots(1, len(groups), figsize=(5 * len(groups), 5.6), sharey=True,
                             squeeze=False)
    axes = axes[0]
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.33, top=0.86, wspace=0.08)
    markers = "osD^vP*X"
    for ax, (guarantee, group) in zip(axes, groups.items()):
        for index, name in enumerate([*REFERENCES, *group]):
            if name not in by_name:
                continue
            rmse = np.sqrt(np.mean(results[f"{name}/squared_error"], axis=(0, 2)))
            steps = np.arange(1, rmse.size + 1)
            if name in REFERENCES:
                ax.plot(steps, rmse, "--" if name == "local" else ":", color="k", lw=2,
                        label=f"{name} (reference)")
                continue
            rank = index - len(REFERENCES)
            ax.plot(steps, rmse, color=f"C{rank % 10}", marker=markers[rank % len(markers)],
                    markevery=(rank % 5, 5), ms=4, lw=1.3, label=name)
        ax.set(title=f"guarantee '{guarantee}'"
               + (f": {meaning[guarantee]}" if guarantee in meaning else ""),
               xlabel="step", yscale="log")
        ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2,
                  frameon=False)
    axes[0].set_ylabel("RMSE [m]")
    _plain_log_ticks(axes[0])
    fig.suptitle(f"{scenario.name}: position RMSE over runs and nodes against time, the "
                 "rules grouped by their guarantee")
    paths.append(directory / "rmse.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    position = list(scenario.position_indices)
    if len(position) != 2:
        return paths
    plt, fig, axes = _grid(len(names))
    ellipses = {}
    for name in names:
        P = np.mean(results[f"{name}/P_last"], axis=0)[:, position][:, :, position]
        error = results[f"{name}/error_last"][..., position]
        empirical = np.einsum("rni,rnj->nij", error, error) / error.shape[0]
        ellipses[name] = (P, empirical)
    # one scale for every panel: the largest ellipse of the references spans ~0.35 units
    sizes = [np.sqrt(np.linalg.eigvalsh(M)[..., -1]).max()
             for name in ("local", "centralised") if name in ellipses for M in ellipses[name]]
    scale = 0.35 / (2.45 * max(sizes or [1.0]))
    xy = scenario.positions
    centre = xy.mean(axis=0)
    for ax, name in zip(axes, names):
        for i, j in scenario.edges:
            ax.plot(xy[[i, j], 0], xy[[i, j], 1], color="0.7", lw=1, zorder=0)
        P, empirical = ellipses[name]
        for node in range(scenario.nodes):
            for M, style, label in ((P, dict(color="C3"), "mean P (95%)"),
                                    (empirical, dict(color="k", ls="--"),
                                     "empirical error covariance (95%)")):
                try:
                    curve = covariance_ellipse(M[node] * scale**2, xy[node])
                except ValueError:  # an empirical covariance of too few runs is singular
                    continue
                ax.plot(curve[0], curve[1], lw=1.2, label=label if node == 0 else None,
                        **style)
            # the label beside the node, away from the centre: it hid small ellipses
            away = xy[node] - centre
            away = away / max(np.linalg.norm(away), 1e-12)
            ax.annotate(str(node), xy[node] + 0.33 * away, fontsize=9, fontweight="bold",
                        ha="center", va="center", color="0.15")
            ax.plot(*xy[node], "o", ms=2.5, color="0.3", zorder=3)
        ax.set(title=name, xticks=[], yticks=[])
        ax.set_aspect("equal", adjustable="datalim")
        ax.margins(0.15)
        _scale_bar(ax, scale)
    _title_and_legend(fig, f"{scenario.name}: position ellipses at every node at the last "
                      "step (the same scale in every panel: see the bar)",
                      *axes[0].get_legend_handles_labels(), columns=2)
    paths.append(directory / "network.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def network_memory_estimate(nodes: int, dim: int, steps: int, chunk: int, *,
                            estimators: int = 15) -> int:
    """Bytes of memory a network study needs at its peak, estimated before it starts.

    The command line refuses ``demo --nodes N`` when this exceeds the memory available.
    The estimate is an upper bound fitted to measurements (peak resident size of one
    chunk of the ring, ``"optimal"`` and ``"ci"`` rules, 100 to 400 nodes): the rules that
    track the joint error covariance of the whole network (``"optimal"``'s truth, the
    centralised filter) hold about ``8 * chunk + 4`` matrices of ``(nodes * dim)**2``
    floats, and every estimator's track holds ``chunk * steps * nodes`` means and
    covariances, plus about 250 MB for the interpreter and the libraries.

    Parameters
    ----------
    nodes, dim : int
        Nodes of the network and state dimension.
    steps : int
        Time steps per run.
    chunk : int
        Runs simulated together (one Monte Carlo chunk).
    estimators : int, optional
        Estimators scored (the rules plus the two references).

    Returns
    -------
    int
        The estimate in bytes.

    Examples
    --------
    >>> from cifilter.cli.demo import network_memory_estimate
    >>> network_memory_estimate(6, 4, 40, 5) < 300e6      # the default demo
    True
    >>> network_memory_estimate(100_000, 4, 40, 5) > 1e13  # a ring of 100 000 nodes
    True
    """
    nodes, dim = check_int(nodes, "nodes", low=1), check_int(dim, "dim", low=1)
    steps, chunk = check_int(steps, "steps", low=1), check_int(chunk, "chunk", low=1)
    estimators = check_int(estimators, "estimators", low=1)
    joint = 8 * (nodes * dim) ** 2 * (8 * chunk + 4)
    tracks = 8 * chunk * steps * nodes * (dim * dim + dim + 3) * (estimators + 3)
    return int(250e6 + joint + tracks)


def _network_legend(runs, dim, values, *, nodes=True):
    """The lines under the demo's title that say what the columns mean (``values``: NEES
    values per run; ``nodes=False``: the two tracks, whose values are per run and step)."""
    lower, upper = metrics.chi2_bounds(dim, runs)
    where = "runs, steps and nodes" if nodes else "runs and steps"
    inside = "steps and nodes" if nodes else "steps"
    band = (
        f"Its 95% band is where the pooled ANEES of a consistent filter lies: {dim} -+ t * "
        f"sqrt(2 * {dim} * d / ({values} * {runs})), {values} values per run, t the 97.5% "
        f"Student t quantile ({runs - 1} degrees of freedom), d the design effect: how much "
        f"the correlation of a run's {inside} widens the spread of its mean, estimated from "
        "the rule's own values, independent of their scale (docs/cli.rst derives it). Below "
        "the band is 'conservative', above 'overconfident'." if runs > 1 else
        "With a single run there is no band (the spread between runs is what it is made "
        "of): the verdict is 'inconclusive'.")
    band = textwrap.fill(
        f"pooled ANEES: the NEES ({dim} when consistent) averaged over {where}. {band} "
        f"'steps in bounds': the share of {inside} whose ANEES over the {runs} "
        f"run{'s' if runs > 1 else ''} lies in one step's 95% chi-square bounds "
        f"[{lower:.2f}, {upper:.2f}].", width=117)
    references = ("'local' never exchanges;\n'centralised' is one filter with every "
                  "measurement (the best possible)." if nodes else
                  "'local A', 'local B': each\ntracker alone.")
    return (
        "guarantee: what the rule's P is: 'exact' the covariance of the error, 'bound' an "
        "upper bound on it for any\ncorrelation, 'none' neither (a heuristic). RMSE of "
        f"position [m] and of velocity [m/s] over {where}.\n"
        f"{band}\n"
        "mean tr P: the trace of P's position block [m^2] and of its velocity block "
        "[(m/s)^2]. 'batched us/fusion': the time\nof a step's fusions of all runs "
        f"at once divided by their number (it falls with more runs). {references}"
    )


def run_network_demo(seed: int = 0, runs: Optional[int] = None, steps: Optional[int] = None,
                     methods: Optional[Sequence[str]] = None,
                     plot: Optional[Union[str, os.PathLike[str]]] = None,
                     out: Optional[TextIO] = None, *,
                     scenario: Union[str, Scenario] = "naveen-taylor",
                     nodes: Optional[int] = None, sequential: bool = True,
                     feedback: bool = True, period: int = 1, loss: float = 0.0,
                     delay: bool = False, client: Optional[Union["Client", str]] = None,
                     progress: Optional[bool] = None) -> list[dict[str, Any]]:
    """The network demo: every rule in a decentralised network with feedback.

    Parameters
    ----------
    seed : int, optional
        Root seed of the Monte Carlo chunks (default 0; same seed, same table).
    runs, steps : int, optional
        Monte Carlo runs and time steps (default 10 x 40).
    methods : sequence of str, optional
        Rules to compare (default every registered one).
    plot : str or path, optional
        Directory for ``nees.png``, ``rmse.png`` and ``network.png``.
    out : file, optional
        Where to print (default standard output).
    scenario : str or Scenario, optional
        A ready scenario's name (:func:`cifilter.network.scenario_names`) or a
        :class:`~cifilter.network.Scenario`; default ``"naveen-taylor"``.
    nodes : int, optional
        Number of nodes of a ring, chain or fully connected scenario.
    sequential, feedback, period, loss, delay : optional
        The exchange (see :func:`cifilter.network.run_network`); the demo fuses the
        received estimates one at a time by default (as Naveen & Taylor fuse along each
        edge), so that the rules that fuse two estimates only (``ei``, ``pcei``) run too.
    client : dask.distributed.Client or str, optional
        Where :func:`cifilter.montecarlo.run` runs the chunks (default in process).
    progress : bool or None, optional
        Progress bar (see :func:`cifilter.montecarlo.run`).

    Returns
    -------
    list of dict
        The rows of :func:`cifilter.network.summarize` (printed by
        :func:`cifilter.network.format_summary`).

    Examples
    --------
    >>> import io
    >>> from cifilter.cli.demo import run_network_demo
    >>> rows = run_network_demo(runs=4, steps=10, methods=["ci", "naive"], out=io.StringIO())
    >>> [row["method"] for row in rows]
    ['local', 'centralised', 'ci', 'naive']
    """
    from .. import montecarlo
    from ..network.graph import Scenario

    out = sys.stdout if out is None else out
    runs = NETWORK_DEFAULTS["runs"] if runs is None else check_int(runs, "runs", low=1)
    steps = NETWORK_DEFAULTS["steps"] if steps is None else check_int(steps, "steps", low=1)
    if not isinstance(scenario, Scenario):
        scenario = get_scenario(scenario, **({} if nodes is None else {"nodes": nodes}))
    study = NetworkStudy(scenario, None if methods is None else tuple(methods), steps,
                         feedback=feedback, period=period, sequential=sequential,
                         delay=delay, loss=loss)
    directory = None if plot is None else _directory(plot)
    start = time.perf_counter()
    results = montecarlo.run(study, runs, chunk_size=DEMO_CHUNK_SIZE, client=client,
                             seed=seed, progress=progress)
    elapsed = time.perf_counter() - start
    rows = summarize(results, scenario)
    exchange = ("one at a time" if sequential else "all at once")
    print(
        f"cifilter demo: {scenario.description}.\n"
        f"{scenario.nodes} nodes, {len(scenario.edges)} link"
        f"{'s' if len(scenario.edges) != 1 else ''}; 2-D constant-velocity "
        f"target; {runs} runs x {steps} steps, seed {seed}.\n"
        f"Every {'' if period == 1 else f'{period}th '}step each node predicts, updates "
        f"with its own measurement and fuses its neighbours' estimates ({exchange}"
        f"{', one step late' if delay else ''}"
        f"{f', {100 * loss:g}% of messages lost' if loss else ''}), "
        f"{'feeding the result back into its filter' if feedback else 'without feedback'}.\n"
        f"{_network_legend(runs, scenario.dim, steps * scenario.nodes)}\n",
        file=out,
    )
    print(format_summary(rows), file=out)
    print(f"\n{elapsed:.1f} s ({sum(1 for r in rows if 'error' not in r) - 2} rules)",
          file=out)
    if directory is not None:
        for path in _plot_network(results, rows, scenario, directory):
            print(f"figure written to {path}", file=out)
    return rows


def run_demo(seed: int = 0, runs: Optional[int] = None, steps: Optional[int] = None,
             methods: Optional[Sequence[str]] = None,
             plot: Optional[Union[str, os.PathLike[str]]] = None,
             out: Optional[TextIO] = None, *, scenario: Union[str, Scenario] = "two-tracks",
             **network_options: Any) -> list[dict[str, Any]]:
    """Run a demo: the two tracks (the default of this function) or a network.

    ``python -m cifilter demo`` runs the network (:func:`run_network_demo`,
    ``scenario="naveen-taylor"``); this function keeps the two-track default of earlier
    versions so that code calling ``run_demo(...)`` gets the rows it got before.

    Parameters
    ----------
    seed : int, optional
        Seed (same seed, same table).
    runs, steps : int, optional
        Monte Carlo runs and steps per run (default 20 x 100 for the two tracks, 10 x 40
        for a network).
    methods : sequence of str, optional
        Methods to run; default every registered one.
    plot : str or path, optional
        Directory for the figures.
    out : file, optional
        Where to print (default standard output).
    scenario : str or Scenario, optional
        ``"two-tracks"`` (default) for :func:`run_two_tracks`, ``"multi-target"`` for
        :func:`run_multi_target_demo`, else a network scenario for
        :func:`run_network_demo` (e.g. ``"naveen-taylor"``).
    **network_options
        Further options of :func:`run_network_demo`.

    Returns
    -------
    list of dict
        One row per estimator.

    Raises
    ------
    ValueError
        Unknown method or scenario, or network options with the two tracks or the
        multi-target scenario.

    Examples
    --------
    >>> import io
    >>> from cifilter.cli.demo import run_demo
    >>> rows = run_demo(runs=2, steps=10, methods=["ci"], out=io.StringIO())
    >>> [row["method"] for row in rows]
    ['local A', 'local B', 'ci']
    >>> rows = run_demo(runs=2, steps=5, methods=["ci"], out=io.StringIO(),
    ...                 scenario="naveen-taylor")
    >>> [row["method"] for row in rows]
    ['local', 'centralised', 'ci']
    """
    if scenario == "multi-target":
        if network_options:
            raise ValueError(f"option(s) {', '.join(sorted(network_options))} apply to the "
                             "network scenarios, not to multi-target")
        return run_multi_target_demo(seed, runs, steps, methods, plot, out)
    if scenario == "two-tracks":
        if network_options:
            raise ValueError(f"option(s) {', '.join(sorted(network_options))} apply to the "
                             "network scenarios, not to two-tracks")
        return run_two_tracks(seed, TWO_TRACK_DEFAULTS["runs"] if runs is None else runs,
                              TWO_TRACK_DEFAULTS["steps"] if steps is None else steps,
                              methods, plot, out)
    return run_network_demo(seed, runs, steps, methods, plot, out, scenario=scenario,
                            **network_options)


def _plot_multi_target(data, runs, rows, directory):
    """One panel per rule that ran: the true paths and the confirmed central tracks of the
    first run (one colour per central ID, the 95% ellipse at the last scan)."""
    from .plotting import plot_central_tracks

    names = [row["method"] for row in rows if "error" not in row]
    methods = list(runs)
    plt, fig, axes = _grid(len(methods), columns=3, width=4.6, height=4.4, bottom=0.6)
    for ax, method, name in zip(axes, methods, names):
        plot_central_tracks(ax, data.truth, runs[method][0].tracks)
        row = next(r for r in rows if r["method"] == name)
        ax.set_title(f"{name}: GOSPA {row['gospa']:.1f} m, ANEES {row['anees']:.2f}",
                     fontsize="small")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.suptitle(f"{data.scenario.description}: true paths (grey) and confirmed central "
                 "tracks of run 0 (one colour per central ID, 95% ellipse at the last scan)",
                 y=1 - 0.12 / fig.get_size_inches()[1], va="top", fontsize="small")
    path = directory / "multi_target.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def run_multi_target_demo(seed: int = 0, runs: Optional[int] = None,
                          steps: Optional[int] = None, methods: Optional[Sequence[str]] = None,
                          plot: Optional[Union[str, os.PathLike[str]]] = None,
                          out: Optional[TextIO] = None) -> list[dict[str, Any]]:
    """A fusion centre over two radars and a camera, by every rule: the multi-target demo.

    The scenario is :func:`cifilter.network.multi_target` (five targets, two crossing,
    targets appearing and disappearing, missed detections, short-lived false tracks); each
    run is simulated by :func:`cifilter.network.simulate_targets` and fed scan by scan to a
    :class:`cifilter.tracking.TrackFuser` per rule (:func:`cifilter.tracking.compare_tracking`).
    The table (:func:`cifilter.tracking.format_tracking`) gives per rule the mean GOSPA of
    the positions (c = 50 m) and its parts, the ANEES of the matched central tracks with
    the chi-square bounds of as many independent values and a verdict, the position RMSE,
    ID switches, false and missed tracks per scan and the time per scan; below, each
    sensor's own tracks (:func:`cifilter.tracking.score_sources`).

    Parameters
    ----------
    seed : int, optional
        Seed (same seed, same table but the times).
    runs, steps : int, optional
        Simulations and scans per simulation (default 2 x 60).
    methods : sequence of str, optional
        Rules (default :data:`cifilter.tracking.DEFAULT_METHODS`; ``"pci"`` with the
        assumed bound ``rho = 0.5``). A rule that cannot fuse these tracks is listed with
        the reason.
    plot : str or path, optional
        Directory for ``multi_target.png`` (the truth and the central tracks of run 0).
    out : file, optional
        Where to print (default standard output).

    Returns
    -------
    list of dict
        One row per rule (:func:`cifilter.tracking.compare_tracking`), then one per sensor
        (:func:`cifilter.tracking.score_sources`).

    Raises
    ------
    ValueError
        An unknown rule; ``steps`` below 8.

    Examples
    --------
    >>> import io
    >>> from cifilter.cli.demo import run_multi_target_demo
    >>> rows = run_multi_target_demo(runs=1, steps=20, methods=["ci"], out=io.StringIO())
    >>> [row["method"] for row in rows]
    ['ci', 'source radar-1', 'source radar-2', 'source camera']
    """
    from ..network.targets import multi_target, simulate_targets
    from ..tracking import DEFAULT_METHODS, compare_tracking, format_tracking, score_sources

    out = sys.stdout if out is None else out
    methods = list(DEFAULT_METHODS if methods is None else methods)
    for name in methods:
        get_method(name)  # unknown names fail before the simulation
    runs = MULTI_TARGET_DEFAULTS["runs"] if runs is None else check_int(runs, "runs", low=1)
    steps = MULTI_TARGET_DEFAULTS["steps"] if steps is None else steps
    directory = None if plot is None else _directory(plot)
    scenario = multi_target(steps=steps)
    rng = as_rng(seed)
    data = [simulate_targets(scenario, rng=rng) for _ in range(runs)]
    kept: dict[str, Any] = {}
    rows = compare_tracking(data, methods, runs_out=kept)
    sources = score_sources(data)
    print(
        f"cifilter demo --scenario multi-target: a track-to-track fusion centre. "
        f"{scenario.description};\n{runs} run{'s' if runs != 1 else ''} x {steps} scans, "
        f"seed {seed}. Each sensor runs its own local trackers (missed detections: a track "
        "coasts; short-lived false tracks);\nthe centre (cifilter.tracking.TrackFuser) "
        "associates their tracks with its central tracks and fuses them with each rule.\n"
        "GOSPA of the positions (c = 50 m, p = 2) per scan, averaged, and its squared "
        "parts; central tracks are confirmed ones. Matched: a target and a confirmed\n"
        "central track closer than 50 m (kept from scan to scan while within it). ANEES: "
        "4-D NEES of the matched tracks, with the 95% chi-square band of as many\n"
        "independent values (successive scans are correlated: the band is narrow). The "
        "source rows score each sensor's own tracks of true targets.\n",
        file=out)
    print(format_tracking(rows + sources), file=out)
    if directory is not None and kept:
        for path in _plot_multi_target(data[0], kept, rows, directory):
            print(f"figure written to {path}", file=out)
    return rows + sources
