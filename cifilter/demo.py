"""The main job: two trackers with different sensors, fused by every registered rule.

A target moves with (nearly) constant velocity in the plane. Sensor A measures its
position precisely across track (y) and poorly along it (x); sensor B the other way
round. Each sensor feeds its own ``cifilter.KalmanFilter``. The two tracks share the
target's process noise, so their errors are correlated, by an amount no
node would know in a real network. At every step every registered fusion rule fuses the
two tracks (without feeding back), and the demo scores the fused estimates against the
truth: RMSE, NEES and the share of steps whose NEES lies inside the 95% chi-square bound.

Because the model is linear, the demo also knows the true joint error covariance of the
two tracks (the Bar-Shalom--Campo cross-covariance recursion); rules that need such
knowledge (``"optimal"``) or a bound derived from it get it through their
``truth_options`` hook, so rules registered later appear here without editing this file.
"""

import sys
import time
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ._linalg import mahalanobis_sq
from ._validation import as_rng, check_int
from .filters import KalmanFilter
from .registry import available_methods, fuse, get_method

__all__ = ["DemoData", "constant_velocity_model", "run_demo", "score", "simulate"]

POSITION = [0, 2]  # indices of x and y in the state [x, vx, y, vy]


def constant_velocity_model(dt, q):
    """State transition and process noise of a 2-D constant-velocity model.

    Parameters
    ----------
    dt : float
        Time step [s].
    q : float
        Power spectral density of the white-noise acceleration [m^2/s^3].

    Returns
    -------
    F, Q : ndarray, shape (4, 4)
        For the state ``[x, vx, y, vy]``.

    Examples
    --------
    >>> from cifilter.demo import constant_velocity_model
    >>> F, Q = constant_velocity_model(1.0, 0.1)
    >>> F[0].tolist()
    [1.0, 1.0, 0.0, 0.0]
    """
    F1 = np.array([[1.0, dt], [0.0, 1.0]])
    Q1 = q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    return np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)


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
    >>> from cifilter.demo import simulate
    >>> simulate(runs=1, steps=3, rng=0).truth.shape
    (1, 3, 4)
    """

    truth: np.ndarray
    x_a: np.ndarray
    x_b: np.ndarray
    P_a: np.ndarray
    P_b: np.ndarray
    joint: np.ndarray


def _make_filter(F, Q, H, R, x0, P0):
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.Q, kf.H, kf.R = F, Q, H, R
    kf.x, kf.P = x0.reshape(4, 1).copy(), P0.copy()
    return kf


def simulate(runs=20, steps=100, *, dt=1.0, q=0.5, sigma_a=(10.0, 2.0), sigma_b=(3.0, 8.0),
             rng=None):
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
    >>> from cifilter.demo import simulate
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


def score(x, P, truth):
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
        ``rmse`` (position, m), ``mean_nees`` (4 for a consistent estimator),
        ``inside`` (share of NEES <= the 95% chi-square quantile, 0.95 when consistent)
        and ``mean_trace``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.demo import score
    >>> s = score(np.zeros((3, 4)), np.eye(4), np.zeros((3, 4)))
    >>> s["rmse"], s["mean_nees"], s["inside"]
    (0.0, 0.0, 1.0)
    """
    error = np.asarray(x, dtype=float) - np.asarray(truth, dtype=float)
    P = np.broadcast_to(P, error.shape + error.shape[-1:])
    nees = mahalanobis_sq(error, P)
    bound = stats.chi2.ppf(0.95, df=error.shape[-1])
    return {
        "rmse": float(np.sqrt(np.mean(np.sum(error[..., POSITION] ** 2, axis=-1)))),
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
                     **score(x, P, data.truth)})
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
                     **score(result.x, result.P, data.truth)})
    return rows, fused


def format_table(rows):
    """The demo's table as text (one row per estimator).

    Parameters
    ----------
    rows : list of dict
        As returned by :func:`run_demo`.

    Returns
    -------
    str
        The table.
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


def _plot(data, fused, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plotting import plot_covariance_ellipse

    names = list(fused)
    columns = 3
    grid_rows = 1 + -(-len(names) // columns)
    fig = plt.figure(figsize=(4 * columns, 3.8 * grid_rows), layout="constrained")
    grid = fig.add_gridspec(grid_rows, columns)
    track_ax = fig.add_subplot(grid[0, :])
    track_ax.plot(data.truth[0, :, 0], data.truth[0, :, 2], "k-", lw=2, label="truth")
    track_ax.plot(data.x_a[0, :, 0], data.x_a[0, :, 2], ":", label="local A")
    track_ax.plot(data.x_b[0, :, 0], data.x_b[0, :, 2], ":", label="local B")
    for name in names:
        x = fused[name].x.reshape(data.truth.shape)
        track_ax.plot(x[0, :, 0], x[0, :, 2], lw=1, label=name)
    track_ax.set(xlabel="x [m]", ylabel="y [m]", title="run 0: truth, local and fused tracks")
    track_ax.legend(ncol=4, fontsize="small")
    half = data.truth.shape[1] // 2  # second half of the run: near the steady state
    for i, name in enumerate(names):
        ax = fig.add_subplot(grid[1 + i // columns, i % columns])
        x = fused[name].x.reshape(data.truth.shape)
        error = (x[:, half:] - data.truth[:, half:])[..., POSITION].reshape(-1, 2)
        P = np.broadcast_to(fused[name].P, data.truth.shape + (4,))[0, -1]
        ax.plot(error[:, 0], error[:, 1], ".", ms=2, alpha=0.5, label="errors (2nd half)")
        plot_covariance_ellipse(ax, P[np.ix_(POSITION, POSITION)], color="C3",
                                label="95% ellipse of P")
        ax.set(title=name, xlabel="error x [m]", ylabel="error y [m]", aspect="equal")
        ax.legend(fontsize="x-small", loc="upper right")
    fig.suptitle("cifilter demo: fused position errors and the 95% ellipse of each rule's P")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_demo(seed=0, runs=20, steps=100, methods=None, plot=None, out=None):
    """Run the demo: simulate, fuse with every method, print the table.

    Parameters
    ----------
    seed : int, optional
        Seed of the random generator (same seed, same table).
    runs, steps : int, optional
        Monte Carlo runs and steps per run.
    methods : sequence of str, optional
        Methods to run; default every registered one.
    plot : str or path, optional
        Write a figure of the tracks and the fused error ellipses to this PNG file.
    out : file, optional
        Where to print (default standard output).

    Returns
    -------
    list of dict
        One row per estimator with ``method``, ``guarantee``, ``rmse``, ``mean_nees``,
        ``inside``, ``mean_trace`` and ``time`` (or ``error``).

    Examples
    --------
    >>> import io
    >>> from cifilter.demo import run_demo
    >>> rows = run_demo(runs=2, steps=10, methods=["ci", "naive"], out=io.StringIO())
    >>> [row["method"] for row in rows]
    ['local A', 'local B', 'ci', 'naive']
    """
    out = sys.stdout if out is None else out
    methods = list(available_methods() if methods is None else methods)
    for name in methods:
        get_method(name)  # unknown names fail before the simulation
    rng = as_rng(seed)
    data = simulate(runs, steps, rng=rng)
    rows, fused = _fuse_all(data, methods, rng)
    print(
        f"cifilter demo: 2-D constant-velocity target, sensor A (sigma x, y = 10, 2 m) and "
        f"sensor B (3, 8 m);\n{runs} runs x {steps} steps, seed {seed}. The tracks are "
        "correlated through the common process noise.\nA consistent estimator has "
        "mean NEES 4 and 95% of NEES inside the chi-square bound; a conservative one has "
        "less.\n",
        file=out,
    )
    print(format_table(rows), file=out)
    if plot is not None:
        _plot(data, fused, plot)
        print(f"\nfigure written to {plot}", file=out)
    return rows
