"""A tiny seeded multi-target scenario for the tests of :mod:`cifilter.tracking`.

Two targets in the plane with a nearly constant velocity (state ``[px, vx, py, vy]``) cross
half way; sources run one local Kalman filter per target on noisy position measurements
and report those filters' estimates as tracks with their own ids. Options add a gap (no
source reports a target for some scans), a short-lived false track, a late source (its
tracks describe the previous scan) and a partial-state source (it reports the position
only, with ``H``). The local filters share the targets' process noise, so their errors are
correlated: what CI is for.
"""

from typing import NamedTuple, Optional

import numpy as np

from cifilter.tracking import SourceTrack

Q_INTENSITY = 0.05
POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
# the measurement noises: "a" sees x well, "b" sees y well, "c" (position only) both
NOISE = {"a": np.diag([0.5, 16.0]), "b": np.diag([9.0, 1.0]), "c": np.diag([0.25, 0.25])}
# each source numbers its tracks its own way
IDS = {"a": (11, 12), "b": ("t0", "t1"), "c": (501, 502)}


def motion(dt):
    """The nearly-constant-velocity model: ``(F, Q)`` over ``dt``."""
    f = np.array([[1.0, dt], [0.0, 1.0]])
    q = Q_INTENSITY * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    F = np.zeros((4, 4))
    Q = np.zeros((4, 4))
    F[:2, :2] = F[2:, 2:] = f
    Q[:2, :2] = Q[2:, 2:] = q
    return F, Q


class Scenario(NamedTuple):
    scans: list  # per scan: (time, [SourceTrack, ...])
    truth: np.ndarray  # (steps, targets, 4)
    times: np.ndarray  # (steps,)
    origin: dict  # (source, id) -> target index, -1 for the false track


def two_targets(seed: int, steps: int = 21, *, sources=("a", "b"),
                gap: Optional[tuple] = None, false: Optional[tuple] = None,
                late: tuple = (), partial: tuple = (), jump: Optional[tuple] = None
                ) -> Scenario:
    """The scenario.

    gap : (target, first scan, scans)
        No source reports ``target`` in those scans (their local filters only predict).
    false : (source, first scan, scans)
        ``source`` reports a false track (id 99) for those scans, far from the targets.
    late : sources whose tracks describe the previous scan (from scan 1 on).
    partial : sources that report the position only (``H`` = the position rows).
    jump : (source, scan)
        From ``scan`` on, ``source`` reports target 1's estimate under target 0's id and
        target 0's under target 1's (its local tracker swapped them).
    """
    rng = np.random.default_rng(seed)
    dt = 1.0
    F, Q = motion(dt)
    times = np.arange(steps) * dt
    truth = np.zeros((steps, 2, 4))
    # cross at the middle scan: same position, different velocities
    middle = steps // 2
    velocities = np.array([[1.0, 1.0], [1.0, -1.0]])
    crossing = np.array([10.0, 5.0])
    for j in range(2):
        px, py = crossing - middle * velocities[j]
        truth[0, j] = [px, velocities[j, 0], py, velocities[j, 1]]
    for k in range(1, steps):
        for j in range(2):
            truth[k, j] = F @ truth[k - 1, j] + rng.multivariate_normal(np.zeros(4), Q)
    # the process noise moves the meeting point: shift target 1's positions (a constant
    # offset is a trajectory of the same model) so that the targets meet at the middle scan
    mid = steps // 2
    truth[:, 1, [0, 2]] += truth[mid, 0, [0, 2]] - truth[mid, 1, [0, 2]]
    P0 = np.diag([1.0, 0.25, 1.0, 0.25])
    filters = {}
    for s in sources:
        for j in range(2):
            # (the targets' filters start differently, so their covariances differ)
            start = (1.0 + 0.5 * j) * P0
            filters[s, j] = [truth[0, j] + rng.multivariate_normal(np.zeros(4), start), start]
    phantom = None
    history: dict = {}
    scans = []
    origin = {(s, IDS[s][j]): j for s in sources for j in range(2)}
    if false is not None:
        origin[false[0], 99] = -1
    for k in range(steps):
        reports = []
        for s in sources:
            for j in range(2):
                x, P = filters[s, j]
                if k > 0:
                    x, P = F @ x, F @ P @ F.T + Q
                hidden = gap is not None and gap[0] == j and gap[1] <= k < gap[1] + gap[2]
                R = NOISE[s]
                z = POSITION @ truth[k, j] + rng.multivariate_normal(np.zeros(2), R)
                S = POSITION @ P @ POSITION.T + R
                K = np.linalg.solve(S, POSITION @ P).T
                x = x + K @ (z - POSITION @ x)
                I_KH = np.eye(4) - K @ POSITION
                P = I_KH @ P @ I_KH.T + K @ R @ K.T
                filters[s, j] = [x, 0.5 * (P + P.T)]
                history[s, j, k] = (x, filters[s, j][1])
                if hidden:
                    continue
                reported = j
                if jump is not None and s == jump[0] and k >= jump[1]:
                    reported = 1 - j
                when = k - 1 if (s in late and k > 0) else k
                xr, Pr = history[s, j, when]
                H = None
                if s in partial:
                    xr, Pr, H = POSITION @ xr, POSITION @ Pr @ POSITION.T, POSITION
                reports.append(SourceTrack(s, IDS[s][reported], xr.copy(), Pr.copy(),
                                           float(times[when]), H))
        if false is not None and false[1] <= k < false[1] + false[2]:
            if phantom is None:
                phantom = np.array([60.0, -1.0, -40.0, 1.0])
            else:
                phantom = F @ phantom
            reports.append(SourceTrack(false[0], 99, phantom.copy(), np.diag([1.0, 0.3, 1.0, 0.3]),
                                       float(times[k])))
        scans.append((float(times[k]), reports))
    return Scenario(scans, truth, times, origin)


def target_of(central, origin):
    """The target a central track was fed from at this scan (by its sources), or None."""
    targets = {origin.get((s, i)) for s, i in central.sources.items()}
    return targets.pop() if len(targets) == 1 else None
