"""Many targets seen by several sensors, each running its own local trackers.

The data a track-to-track fusion centre receives (:mod:`cifilter.tracking`): per scan, a
list of *source tracks*, each a local tracker's estimate under that sensor's own track
number. :func:`multi_target` describes the scene (2-D constant-velocity targets, two of
them crossing, targets that appear and disappear, two radars and a camera-like sensor) and
:func:`simulate_targets` draws the truth, the detections and the local tracks:

* each sensor detects a live target with probability ``p_detect`` and measures its
  position with a noise that depends on the direction from the sensor to the target
  (``sigma_range`` along it, ``sigma_cross`` across it: a radar measures range well, a
  camera bearing);
* each sensor runs one Kalman filter per target it has detected (association is known:
  the point is the source tracks). A missed detection makes the local track coast (it is
  predicted and still reported); after more than ``max_coast`` misses in a row it is
  deleted, and the next detection starts a new local track under a new number;
* each sensor also reports short-lived *false* tracks (started on clutter, 1 to 3 scans
  long), a Poisson number of new ones per scan;
* optionally the reports of some sensors arrive late (each describes the state 0 to
  ``lateness`` scans earlier, so they arrive out of order) and some sensors send only the
  position part of their tracks (``H`` selects it from the central state).

The local filters know their sensors' noise and the targets' model exactly, so their
tracks are consistent (NEES chi-square with 4 degrees of freedom after the first scans);
two sensors' tracks of one target are correlated through the common process noise, the
unknown correlation the fusion rules must handle.

The data are plain arrays and tuples; this module does not import :mod:`cifilter.tracking`
(the network floor only generates data).
"""

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.validation import as_float_array, as_rng, check_int, check_scalar
from .graph import constant_velocity_model

__all__ = [
    "TargetData",
    "TargetScenario",
    "TrackingSensor",
    "multi_target",
    "simulate_targets",
]

POSITION = (0, 2)  # x and y in the state [x, vx, y, vy]
_SELECT = np.zeros((2, 4))
_SELECT[0, 0] = _SELECT[1, 2] = 1.0


@dataclass(frozen=True)
class TrackingSensor:
    """A sensor that measures target positions and runs its own local trackers.

    The parameters are also the attributes.

    Parameters
    ----------
    name : str
        The source name of its tracks.
    location : array_like, shape (2,)
        Where it stands [m].
    sigma_range, sigma_cross : float
        Standard deviations of the position measurement along and across the line of
        sight from the sensor to the target [m].
    p_detect : float, optional
        Probability of detecting a live target in a scan, in (0, 1] (default 0.9).
    false_rate : float, optional
        Mean number of false tracks started per scan (Poisson; default 0.2).
    max_coast : int, optional
        Misses in a row after which a local track is deleted (default 3).

    Examples
    --------
    >>> from cifilter.network import TrackingSensor
    >>> radar = TrackingSensor("radar", (0.0, 0.0), 5.0, 20.0)
    >>> radar.noise([[100.0, 0.0]]).round(1).tolist()   # along the x axis: range noise in x
    [[[25.0, 0.0], [0.0, 400.0]]]
    """

    name: str
    location: Any
    sigma_range: float
    sigma_cross: float
    p_detect: float = 0.9
    false_rate: float = 0.2
    max_coast: int = 3

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"name must be a non-empty string, got {self.name!r}")
        location = as_float_array(self.location, f"location of sensor {self.name!r}")
        if location.shape != (2,) or not np.all(np.isfinite(location)):
            raise ValueError(f"location of sensor {self.name!r} must be 2 finite numbers, got "
                             f"{location.tolist()}")
        object.__setattr__(self, "location", location)
        for key in ("sigma_range", "sigma_cross"):
            object.__setattr__(self, key, check_scalar(getattr(self, key),
                                                       f"{key} of sensor {self.name!r}",
                                                       low=0, low_open=True))
        object.__setattr__(self, "p_detect", check_scalar(
            self.p_detect, f"p_detect of sensor {self.name!r}", low=0, high=1, low_open=True))
        object.__setattr__(self, "false_rate", check_scalar(
            self.false_rate, f"false_rate of sensor {self.name!r}", low=0))
        object.__setattr__(self, "max_coast", check_int(
            self.max_coast, f"max_coast of sensor {self.name!r}", low=0))

    def noise(self, positions: ArrayLike) -> NDArray[np.float64]:
        """The measurement noise covariance at target positions.

        Parameters
        ----------
        positions : array_like, shape (..., 2)
            Target positions [m].

        Returns
        -------
        ndarray, shape (..., 2, 2)
            ``sigma_range^2 u u^T + sigma_cross^2 v v^T`` with ``u`` the unit vector from
            the sensor to the target and ``v`` perpendicular to it (``u`` along x for a
            target on the sensor).

        Examples
        --------
        >>> from cifilter.network import TrackingSensor
        >>> camera = TrackingSensor("camera", (0.0, 0.0), 40.0, 3.0)
        >>> camera.noise([0.0, 50.0]).round(1).tolist()   # depth along y
        [[9.0, 0.0], [0.0, 1600.0]]
        """
        offset = np.asarray(positions, dtype=float) - self.location
        distance = np.hypot(offset[..., 0], offset[..., 1])
        safe = np.where(distance > 0, distance, 1.0)
        u = np.where(distance[..., None] > 0, offset / safe[..., None], [1.0, 0.0])
        v = np.stack([-u[..., 1], u[..., 0]], axis=-1)
        R = (self.sigma_range**2 * u[..., :, None] * u[..., None, :]
             + self.sigma_cross**2 * v[..., :, None] * v[..., None, :])
        return 0.5 * (R + np.swapaxes(R, -1, -2))


def _default_sensors(p_detect, false_rate):
    return (
        TrackingSensor("radar-1", (0.0, 0.0), 4.0, 25.0, p_detect, false_rate),
        TrackingSensor("radar-2", (1000.0, 0.0), 8.0, 15.0, p_detect, false_rate),
        TrackingSensor("camera", (-300.0, 500.0), 40.0, 3.0, min(p_detect, 0.8), false_rate),
    )


@dataclass(frozen=True)
class TargetScenario:
    """Targets, their model and the sensors of a multi-target scenario.

    Made by :func:`multi_target`; the parameters are also the attributes.

    Parameters
    ----------
    initial : ndarray, shape (targets, 4)
        Each target's mean state ``[x, vx, y, vy]`` at its birth.
    birth, death : ndarray of int, shape (targets,)
        The first scan a target is alive and the first scan it is not (``death`` may be
        beyond the end of a simulation).
    sensors : tuple of TrackingSensor
        The sensors (source names must differ).
    crossing : tuple of int
        ``(i, j, k)``: targets ``i`` and ``j`` are at the same position (plus
        ``separation``) at scan ``k``.
    dt, q : float
        Scan period [s] and the white-noise acceleration density [m^2/s^3].
    separation : float
        Distance of the two crossing targets at scan ``k`` [m].
    region : tuple of float
        ``(xmin, xmax, ymin, ymax)`` where false tracks start [m].
    velocity_sigma : float
        Standard deviation of the velocity a local track starts with [m/s].
    steps : int
        The default number of scans of :func:`simulate_targets`.
    name, description : str
        For tables and figures.

    Examples
    --------
    >>> from cifilter.network import multi_target
    >>> scenario = multi_target()
    >>> scenario.targets, [sensor.name for sensor in scenario.sensors]
    (5, ['radar-1', 'radar-2', 'camera'])
    """

    initial: NDArray[np.float64]
    birth: NDArray[np.int_]
    death: NDArray[np.int_]
    sensors: tuple[TrackingSensor, ...]
    crossing: tuple[int, int, int]
    dt: float = 1.0
    q: float = 0.05
    separation: float = 0.0
    region: tuple[float, float, float, float] = (0.0, 1000.0, 0.0, 1000.0)
    velocity_sigma: float = 15.0
    steps: int = 60
    name: str = "multi-target"
    description: str = field(default="")

    def __post_init__(self):
        initial = as_float_array(self.initial, "initial")
        if initial.ndim != 2 or initial.shape[1] != 4 or not np.all(np.isfinite(initial)):
            raise ValueError(f"initial must be finite states of shape (targets, 4), got shape "
                             f"{initial.shape}")
        object.__setattr__(self, "initial", initial)
        for key in ("birth", "death"):
            values = np.asarray(getattr(self, key))
            if values.shape != (len(initial),) or values.dtype.kind not in "iu":
                raise ValueError(f"{key} must be {len(initial)} integers, got {values!r}")
            object.__setattr__(self, key, values.astype(int))
        if np.any(self.birth < 0) or np.any(self.death <= self.birth):
            raise ValueError("every target needs 0 <= birth < death")
        names = [sensor.name for sensor in self.sensors]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"sensors need distinct names, got {names}")
        i, j, k = self.crossing
        for target in (i, j):
            if not (0 <= target < len(initial)) or not self.birth[target] <= k < self.death[
                    target]:
                raise ValueError(f"crossing target {target} must exist and be alive at scan {k}")

    @property
    def targets(self) -> int:
        """Number of targets."""
        return len(self.initial)

    @property
    def dim(self) -> int:
        """State dimension (4)."""
        return 4

    @property
    def position_indices(self) -> tuple[int, int]:
        """Indices of x and y in the state."""
        return POSITION

    def motion(self, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The targets' model over ``dt`` seconds (``motion=`` of the fuser).

        Parameters
        ----------
        dt : float
            Time step [s] (negative for a retrodiction's transition).

        Returns
        -------
        F, Q : ndarray, shape (4, 4)
            :func:`cifilter.network.constant_velocity_model` with this scenario's ``q``
            (``Q`` of ``|dt|``).

        Examples
        --------
        >>> from cifilter.network import multi_target
        >>> F, Q = multi_target().motion(2.0)
        >>> F[0].tolist(), float(Q[1, 1])
        ([1.0, 2.0, 0.0, 0.0], 0.1)
        """
        F, Q = constant_velocity_model(float(dt), self.q)
        if dt < 0:
            Q = constant_velocity_model(-float(dt), self.q)[1]
        return F, Q


def multi_target(targets: int = 5, *, dt: float = 1.0, q: float = 0.05, steps: int = 60,
                 p_detect: float = 0.9, false_rate: float = 0.2, separation: float = 0.0,
                 sensors: Optional[Sequence[TrackingSensor]] = None) -> TargetScenario:
    """The multi-target scenario: targets (two crossing) over two radars and a camera.

    Targets 0 and 1 are alive throughout and cross at scan ``steps // 2`` at a shallow
    angle (headings of +-11.3 degrees: they are within 50 m of each other for about 25
    scans);
    target 2 disappears after two thirds of the scans, target 3 appears after a quarter,
    target 4 appears after a third and disappears in the last sixth; further targets
    cross the region on staggered lives. Speeds are about 10 m/s in a 1 km square.

    Parameters
    ----------
    targets : int, optional
        Number of targets, at least 4 (default 5).
    dt : float, optional
        Scan period [s] (default 1).
    q : float, optional
        White-noise acceleration density [m^2/s^3] (default 0.05).
    steps : int, optional
        Scans of a simulation, at least 8 (default 60).
    p_detect : float, optional
        Detection probability of the radars (the camera's is ``min(p_detect, 0.8)``).
    false_rate : float, optional
        Mean new false tracks per sensor and scan.
    separation : float, optional
        Distance of the crossing targets at the crossing scan [m] (default 0).
    sensors : sequence of TrackingSensor, optional
        Other sensors (default: ``radar-1`` at (0, 0) with 4 m range and 25 m cross-range
        noise, ``radar-2`` at (1000, 0) with 8 m and 15 m, ``camera`` at (-300, 500) with
        40 m depth and 3 m lateral noise).

    Returns
    -------
    TargetScenario

    Raises
    ------
    ValueError
        ``targets`` below 4, ``steps`` below 8, or a parameter out of its range.

    Examples
    --------
    >>> from cifilter.network import multi_target
    >>> scenario = multi_target(targets=6, steps=40)
    >>> scenario.crossing, scenario.birth.tolist()
    ((0, 1, 20), [0, 0, 0, 10, 13, 17])
    """
    targets = check_int(targets, "targets", low=4)
    steps = check_int(steps, "steps", low=8)
    dt = check_scalar(dt, "dt", low=0, low_open=True)
    q = check_scalar(q, "q", low=0, low_open=True)
    separation = check_scalar(separation, "separation", low=0)
    cross = steps // 2
    centre = np.array([500.0, 500.0])
    # the crossing pair: the same point at scan `cross`, 10.2 m/s at +-11.3 degrees
    velocities = [np.array([10.0, 2.0]), np.array([10.0, -2.0])]
    initial = [np.array([p[0], v[0], p[1], v[1]]) for p, v in (
        (centre - v * cross * dt, v) for v in velocities)]
    birth = [0, 0]
    death = [steps + 1, steps + 1]
    # the others, on deterministic staggered paths
    extra = [
        (np.array([150.0, 850.0]), np.array([7.0, -6.0]), 0, (2 * steps) // 3),
        (np.array([850.0, 900.0]), np.array([-6.0, -9.0]), steps // 4, steps + 1),
        (np.array([200.0, 150.0]), np.array([9.0, 7.0]), steps // 3, steps - max(steps // 6, 1)),
    ]
    for index in range(3, targets):
        angle = 2.0 * np.pi * index / 7.0
        start = centre + 420.0 * np.array([np.cos(angle), np.sin(angle)])
        heading = -np.array([np.cos(angle + 0.5), np.sin(angle + 0.5)]) * 9.0
        life = ((index * steps) // 7 % max(steps // 2, 1), steps + 1)
        extra.append((start, heading, life[0], life[1]))
    for position, velocity, born, died in extra[:targets - 2]:
        initial.append(np.array([position[0], velocity[0], position[1], velocity[1]]))
        birth.append(born)
        death.append(died)
    if sensors is None:
        sensors = _default_sensors(p_detect, false_rate)
    return TargetScenario(
        np.array(initial), np.array(birth), np.array(death), tuple(sensors), (0, 1, cross),
        dt=dt, q=q, separation=separation, steps=steps,
        description=(f"{targets} targets (two crossing at scan {cross}), "
                     f"{len(sensors)} sensors: " + ", ".join(s.name for s in sensors)))


@dataclass(frozen=True)
class TargetData:
    """Truth and source tracks of a multi-target simulation (:func:`simulate_targets`).

    The parameters are also the attributes.

    Parameters
    ----------
    scenario : TargetScenario
        What was simulated.
    truth : ndarray, shape (steps, targets, 4)
        True states; NaN where a target is not alive.
    alive : ndarray of bool, shape (steps, targets)
        Which targets exist at each scan.
    times : ndarray, shape (steps,)
        Scan times [s].
    reports : list of tuple
        Per scan, the source tracks received, each ``(source, id, x, P, time, H)``: the
        sensor's name, its own track number, the mean ``(m,)`` and covariance ``(m, m)``,
        the time they describe (earlier than the scan's for a late report) and ``H``
        (``(2, 4)`` for a sensor that sends only the position, else None).
    origin : list of tuple of int
        Per scan, the true target of each report (-1 for a false track).
    partial : tuple of str
        The sensors that send only the position.
    late : tuple of str
        The sensors whose reports may be late.

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> data = simulate_targets(multi_target(steps=10), rng=0)
    >>> data.truth.shape, len(data.reports), data.reports[0][0][:2]
    ((10, 5, 4), 10, ('radar-1', 1))
    """

    scenario: TargetScenario
    truth: NDArray[np.float64]
    alive: NDArray[np.bool_]
    times: NDArray[np.float64]
    reports: list[tuple[tuple[Any, ...], ...]]
    origin: list[tuple[int, ...]]
    partial: tuple[str, ...] = ()
    late: tuple[str, ...] = ()

    @property
    def steps(self) -> int:
        """Number of scans."""
        return len(self.times)

    def report_truth(self, scan: int) -> NDArray[np.float64]:
        """The true full state each report of a scan describes.

        Parameters
        ----------
        scan : int
            The scan.

        Returns
        -------
        ndarray, shape (reports, 4)
            The true state of the report's target at the report's time (NaN for false
            tracks and for targets no longer alive).

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.network import multi_target, simulate_targets
        >>> data = simulate_targets(multi_target(steps=10), rng=0)
        >>> truth = data.report_truth(3)
        >>> truth.shape == (len(data.reports[3]), 4)
        True
        >>> bool(np.isnan(truth[np.array(data.origin[3]) < 0]).all())   # false tracks
        True
        """
        out = np.full((len(self.reports[scan]), 4), np.nan)
        for row, (report, target) in enumerate(zip(self.reports[scan], self.origin[scan])):
            if target >= 0:
                step = round((report[4] - self.times[0]) / self.scenario.dt)
                out[row] = self.truth[step, target]
        return out


def _names(value, scenario, name):
    known = [sensor.name for sensor in scenario.sensors]
    if value is None:
        return ()
    if isinstance(value, str):
        value = (value,)
    value = tuple(value)
    unknown = [item for item in value if item not in known]
    if unknown:
        raise ValueError(f"{name} names unknown sensors {unknown}; sensors: {known}")
    return value


def _initial_tracks(z, R, sigma_v):
    """Local tracks started on measurements ``z`` (..., 2) with noise ``R`` (..., 2, 2)."""
    shape = z.shape[:-1]
    x = np.zeros(shape + (4,))
    x[..., 0], x[..., 2] = z[..., 0], z[..., 1]
    P = np.zeros(shape + (4, 4))
    P[..., 0, 0], P[..., 0, 2] = R[..., 0, 0], R[..., 0, 1]
    P[..., 2, 0], P[..., 2, 2] = R[..., 1, 0], R[..., 1, 1]
    P[..., 1, 1] = P[..., 3, 3] = sigma_v**2
    return x, P


def _kalman_update(x, P, z, R):
    """Batched position update in Joseph form."""
    S = P[..., POSITION, :][..., :, POSITION] + R
    PHt = P[..., :, POSITION]
    K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
    innovation = z - x[..., POSITION]
    x = x + np.einsum("...ij,...j->...i", K, innovation)
    A = np.eye(4) - K @ _SELECT
    P = A @ P @ np.swapaxes(A, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def _draw(L, rng, shape):
    """Gaussian draws with covariance ``L L^T`` (L (..., d, d) broadcast to ``shape``)."""
    return np.einsum("...ij,...j->...i", L, rng.standard_normal(shape))


def simulate_targets(scenario: TargetScenario, steps: Optional[int] = None, *,
                     rng: Optional[Union[int, np.random.Generator]] = None,
                     lateness: int = 0, late: Optional[Sequence[str]] = None,
                     partial: Optional[Sequence[str]] = None) -> TargetData:
    """Simulate the truth, the detections and every sensor's local tracks.

    Parameters
    ----------
    scenario : TargetScenario
        The scene (:func:`multi_target`).
    steps : int, optional
        Scans (default ``scenario.steps``).
    rng : numpy.random.Generator, int or None, optional
        Randomness (the same seed gives the same data). Truth, detections, measurement
        noise, false tracks and lateness draw from separate streams, so switching
        ``lateness`` or ``partial`` on changes no other draw.
    lateness : int, optional
        The reports of the sensors in ``late`` describe the state ``d`` scans earlier,
        ``d`` uniform over ``0..lateness`` per report (default 0: all on time).
    late : sequence of str, optional
        The late sensors (default: all of them when ``lateness > 0``).
    partial : sequence of str, optional
        Sensors that send only the position part of their tracks, with
        ``H = [[1, 0, 0, 0], [0, 0, 1, 0]]`` (default none).

    Returns
    -------
    TargetData

    Raises
    ------
    ValueError
        ``steps`` below 1 or beyond which the crossing lies, ``lateness`` negative, an
        unknown sensor name in ``late`` or ``partial``.
    TypeError
        ``steps`` or ``lateness`` not an integer, ``rng`` of another type.

    Examples
    --------
    >>> from cifilter.network import multi_target, simulate_targets
    >>> data = simulate_targets(multi_target(), 40, rng=1, partial=["camera"])
    >>> i, j, k = data.scenario.crossing
    >>> float(abs(data.truth[k, i, [0, 2]] - data.truth[k, j, [0, 2]]).max()) < 1e-9
    True
    >>> {report[0]: report[2].shape for report in data.reports[5]}["camera"]
    (2,)
    """
    steps = scenario.steps if steps is None else check_int(steps, "steps", low=1)
    lateness = check_int(lateness, "lateness", low=0)
    if scenario.crossing[2] >= steps:
        raise ValueError(f"steps={steps} ends before the crossing at scan "
                         f"{scenario.crossing[2]}")
    late_names = _names(late, scenario, "late") if late is not None else (
        tuple(s.name for s in scenario.sensors) if lateness > 0 else ())
    if lateness == 0:
        late_names = ()
    partial_names = _names(partial, scenario, "partial")
    streams = [np.random.default_rng(seed) for seed in
               as_rng(rng).integers(0, 2**63, size=5)]
    truth_rng, detect_rng, noise_rng, false_rng, late_rng = streams
    F, Q = constant_velocity_model(scenario.dt, scenario.q)
    LQ = np.linalg.cholesky(Q)
    T, S = scenario.targets, len(scenario.sensors)
    times = scenario.dt * np.arange(steps)
    index = np.arange(steps)
    alive = (index[:, None] >= scenario.birth) & (index[:, None] < scenario.death)

    # truth: every target moves from its birth on (vectorised over targets)
    noise = _draw(LQ, truth_rng, (steps, T, 4))
    truth = np.full((steps, T, 4), np.nan)
    state = scenario.initial.copy()
    for k in range(steps):
        state = np.where((scenario.birth < k)[:, None], state @ F.T + noise[k], state)
        truth[k] = np.where(alive[k][:, None], state, np.nan)
    i, j, cross = scenario.crossing
    # the crossing pair meets by construction: a constant position shift of target j is
    # another constant-velocity path with the same noise
    shift = truth[cross, i] - truth[cross, j]
    shift[[1, 3]] = 0.0
    direction = truth[cross, j, [1, 3]]
    normal = np.array([-direction[1], direction[0]]) / max(np.hypot(*direction), 1e-12)
    shift[[0, 2]] += scenario.separation * normal
    truth[:, j] += shift

    # detections and measurements of every (sensor, target), drawn whole
    positions = truth[..., POSITION]
    R = np.stack([sensor.noise(np.nan_to_num(positions)) for sensor in scenario.sensors],
                 axis=1)                                             # (steps, S, T, 2, 2)
    p_detect = np.array([sensor.p_detect for sensor in scenario.sensors])
    detected = (detect_rng.random((steps, S, T)) < p_detect[:, None]) & alive[:, None, :]
    z = positions[:, None] + _draw(np.linalg.cholesky(R), noise_rng, (steps, S, T, 2))

    max_coast = np.array([sensor.max_coast for sensor in scenario.sensors])[:, None]
    x = np.zeros((S, T, 4))
    P = np.tile(np.eye(4), (S, T, 1, 1))
    active = np.zeros((S, T), dtype=bool)
    misses = np.zeros((S, T), dtype=int)
    ids = np.zeros((S, T), dtype=int)
    next_id = np.ones(S, dtype=int)
    history: list[Any] = []  # (x, P, ids, active) of the last `lateness` scans
    false_tracks: list[list[Any]] = [[] for _ in range(S)]  # [id, x, P, scans left]
    low = np.array(scenario.region[::2])
    high = np.array(scenario.region[1::2])
    reports: list[tuple[tuple[Any, ...], ...]] = []
    origin: list[tuple[int, ...]] = []
    for k in range(steps):
        if k > 0:
            x = np.einsum("ij,...j->...i", F, x)
            P = F @ P @ F.T + Q
            P = 0.5 * (P + np.swapaxes(P, -1, -2))
        hit = detected[k]
        start = hit & ~active
        x_new, P_new = _initial_tracks(z[k], R[k], scenario.velocity_sigma)
        x_upd, P_upd = _kalman_update(x, P, z[k], R[k])
        update = hit & active
        x = np.where(start[..., None], x_new, np.where(update[..., None], x_upd, x))
        P = np.where(start[..., None, None], P_new,
                     np.where(update[..., None, None], P_upd, P))
        for s, t in zip(*np.nonzero(start)):  # new local numbers, in a fixed order
            ids[s, t] = next_id[s]
            next_id[s] += 1
        misses = np.where(hit, 0, misses + 1)
        active = hit | (active & (misses <= max_coast))
        history.append((x.copy(), P.copy(), ids.copy(), active.copy()))
        if len(history) > lateness + 1:
            history.pop(0)
        delay = (late_rng.integers(0, lateness + 1, size=(S, T)) if late_names
                 else np.zeros((S, T), dtype=int))
        scan: list[tuple[Any, ...]] = []
        truths: list[int] = []
        for s, sensor in enumerate(scenario.sensors):
            is_late = sensor.name in late_names
            is_partial = sensor.name in partial_names
            for t in range(T):
                d = min(int(delay[s, t]), len(history) - 1) if is_late else 0
                hx, hP, hid, hactive = history[-1 - d]
                if hactive[s, t]:
                    scan.append(_report(sensor.name, int(hid[s, t]), hx[s, t], hP[s, t],
                                        float(times[k - d]), is_partial))
                    truths.append(t)
            # false tracks: the old ones move on a clutter measurement, new ones start
            survivors = []
            for track in false_tracks[s]:
                track_id, fx, fP, left = track
                fx, fP = F @ fx, F @ fP @ F.T + Q
                fP = 0.5 * (fP + fP.T)
                fR = sensor.noise(fx[list(POSITION)])
                S_ = fP[np.ix_(POSITION, POSITION)] + fR
                fz = fx[list(POSITION)] + np.linalg.cholesky(S_) @ false_rng.standard_normal(2)
                fx, fP = _kalman_update(fx, fP, fz, fR)
                if left > 0:
                    survivors.append([track_id, fx, fP, left - 1])
            for _ in range(false_rng.poisson(sensor.false_rate)):
                where = low + (high - low) * false_rng.random(2)
                fR = sensor.noise(where)
                fx, fP = _initial_tracks(where, fR, scenario.velocity_sigma)
                survivors.append([int(next_id[s]), fx, fP, int(false_rng.integers(0, 3))])
                next_id[s] += 1
            false_tracks[s] = survivors
            for track_id, fx, fP, _ in survivors:
                scan.append(_report(sensor.name, track_id, fx, fP, float(times[k]),
                                    is_partial))
                truths.append(-1)
        reports.append(tuple(scan))
        origin.append(tuple(truths))
    return TargetData(scenario, truth, alive, times, reports, origin, partial_names,
                      late_names)


def _report(source, track_id, x, P, time, partial):
    if partial:
        return (source, track_id, x[list(POSITION)].copy(),
                P[np.ix_(POSITION, POSITION)].copy(), time, _SELECT.copy())
    return (source, track_id, x.copy(), P.copy(), time, None)
