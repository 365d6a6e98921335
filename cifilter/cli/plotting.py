"""Small plotting helpers (matplotlib is imported only when a function draws)."""

from typing import TYPE_CHECKING, Any, Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from .._numerics.validation import as_float_array, check_covariances, check_scalar

if TYPE_CHECKING:  # matplotlib is optional (the plot extra) and imported lazily
    from matplotlib.axes import Axes
    from matplotlib.lines import Line2D

__all__ = ["covariance_ellipse", "plot_central_tracks", "plot_covariance_ellipse"]


def covariance_ellipse(P: ArrayLike, mean: ArrayLike = (0.0, 0.0),
                       confidence: Optional[float] = 0.95,
                       n_points: int = 100) -> NDArray[np.float64]:
    """Points on the confidence ellipse of a 2-D Gaussian.

    Parameters
    ----------
    P : array_like, shape (2, 2)
        Covariance (symmetric positive definite).
    mean : array_like, shape (2,), optional
        Centre of the ellipse.
    confidence : float, optional
        Probability mass inside the ellipse, in (0, 1); the squared radius is the
        chi-square quantile with 2 degrees of freedom. ``None`` draws the unit ellipse
        ``e^T P^-1 e = 1`` (as in the figures of Ajgl et al. 2014).
    n_points : int, optional
        Number of points.

    Returns
    -------
    ndarray, shape (2, n_points)
        The closed curve (first point repeated at the end).

    Raises
    ------
    ValueError
        ``P`` not a 2x2 symmetric positive definite matrix, ``confidence`` outside (0, 1).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.cli.plotting import covariance_ellipse
    >>> covariance_ellipse(np.eye(2), confidence=None, n_points=5).round(3)[:, 0].tolist()
    [1.0, 0.0]
    """
    P = as_float_array(P, "P")
    if P.shape != (2, 2):
        raise ValueError(f"P must be a 2x2 covariance, got shape {P.shape}")
    P, L = check_covariances(P, "P")
    radius = 1.0
    if confidence is not None:
        confidence = check_scalar(confidence, "confidence", low=0, high=1, low_open=True,
                                  high_open=True)
        radius = np.sqrt(stats.chi2.ppf(confidence, df=2))
    angle = np.linspace(0.0, 2.0 * np.pi, n_points)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    return np.asarray(mean, dtype=float).reshape(2, 1) + radius * (L @ circle)


def plot_covariance_ellipse(ax: "Axes", P: ArrayLike, mean: ArrayLike = (0.0, 0.0),
                            confidence: Optional[float] = 0.95, *, equal_aspect: bool = True,
                            **line_kwargs: Any) -> "list[Line2D]":
    """Draw a covariance ellipse on a matplotlib axes (with equal aspect by default).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Where to draw.
    P : array_like, shape (2, 2)
        Covariance.
    mean : array_like, shape (2,), optional
        Centre.
    confidence : float or None, optional
        See :func:`covariance_ellipse`.
    equal_aspect : bool, optional
        Give the axes an equal aspect ratio (default True): an ellipse drawn with unequal
        scales misstates which direction is uncertain.
    **line_kwargs
        Passed to ``ax.plot``.

    Returns
    -------
    list of matplotlib.lines.Line2D
        The drawn line.

    Examples
    --------
    >>> import matplotlib
    >>> matplotlib.use("Agg")
    >>> import matplotlib.pyplot as plt
    >>> import numpy as np
    >>> from cifilter.cli.plotting import plot_covariance_ellipse
    >>> fig, ax = plt.subplots()
    >>> lines = plot_covariance_ellipse(ax, np.diag([4.0, 1.0]), label="P")
    >>> ax.get_aspect()
    1.0
    >>> plt.close(fig)
    """
    points = covariance_ellipse(P, mean, confidence)
    if equal_aspect:
        ax.set_aspect("equal")
    return ax.plot(points[0], points[1], **line_kwargs)


def plot_central_tracks(ax: "Axes", truth: ArrayLike, scans: Any, *,
                        position: tuple[int, int] = (0, 2), confirmed_only: bool = True,
                        ellipses: bool = True) -> dict[int, Any]:
    """Draw true paths and a fusion node's central tracks (one colour per central ID).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Where to draw (given an equal aspect).
    truth : array_like, shape (steps, targets, n)
        True states, NaN where a target is not alive (drawn as grey lines).
    scans : sequence of sequence of CentralTrack
        Per scan, the central tracks (objects with ``id``, ``x``, ``P``, ``confirmed``).
    position : tuple of int, optional
        Indices of x and y in the state (default (0, 2)).
    confirmed_only : bool, optional
        Draw only confirmed tracks (default True).
    ellipses : bool, optional
        Draw each track's 95% position ellipse at its last scan (default True).

    Returns
    -------
    dict
        ``{central id: Line2D}`` of the drawn tracks.

    Examples
    --------
    >>> import matplotlib
    >>> matplotlib.use("Agg")
    >>> import matplotlib.pyplot as plt
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from cifilter.cli.plotting import plot_central_tracks
    >>> truth = np.zeros((2, 1, 4))
    >>> scans = [[SimpleNamespace(id=1, x=np.zeros(4), P=np.eye(4), confirmed=True)]] * 2
    >>> fig, ax = plt.subplots()
    >>> sorted(plot_central_tracks(ax, truth, scans))
    [1]
    >>> plt.close(fig)
    """
    truth = np.asarray(truth, dtype=float)
    i, j = position
    for target in range(truth.shape[1]):
        ax.plot(truth[:, target, i], truth[:, target, j], color="0.6", lw=2.5, alpha=0.6,
                zorder=1)
    paths: dict[int, list[Any]] = {}
    last: dict[int, Any] = {}
    for scan in scans:
        for track in scan:
            if confirmed_only and not track.confirmed:
                continue
            paths.setdefault(track.id, []).append(np.asarray(track.x)[[i, j]])
            last[track.id] = track
    lines = {}
    for track_id, points in paths.items():
        xy = np.array(points)
        (line,) = ax.plot(xy[:, 0], xy[:, 1], ".-", ms=3, lw=0.8, zorder=2)
        lines[track_id] = line
        if ellipses:
            P = np.asarray(last[track_id].P)[np.ix_([i, j], [i, j])]
            plot_covariance_ellipse(ax, P, xy[-1], color=line.get_color(), lw=0.8)
        ax.annotate(str(track_id), xy[-1], fontsize=7, color=line.get_color(),
                    xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal")
    return lines
