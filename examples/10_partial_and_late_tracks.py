"""Fusing what trackers really hold: part of the state, angles, and other times.

A runnable tour of cifilter's front-door options (issue 22; docs/methods/partial_state.rst
and docs/methods/time.rst):

1. a constant-velocity track fuses a position-only track (``H=``);
2. an unscented filter with a wrapping heading fuses +179 and -179 degrees to 180;
3. a track that is three steps old (``lag=3``) and one that is two steps ahead
   (``lag=-2``, retrodicted with a bound that survives the unknown correlation of its
   error with the process noise).

Run it with ``python examples/10_partial_and_late_tracks.py``; it prints each result and
checks it (an AssertionError means the claim it shows does not hold).
"""

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints

import cifilter

# --- 1. part of the state ---------------------------------------------------------------
dt = 1.0
F = np.array([[1.0, dt, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
              [0.0, 0.0, 1.0, dt], [0.0, 0.0, 0.0, 1.0]])  # state (x, vx, y, vy)
q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
Q = 0.1 * np.kron(np.eye(2), q)
kf = cifilter.KalmanFilter(dim_x=4, dim_z=2)
kf.F, kf.Q = F, Q
kf.x = np.array([[10.0], [1.0], [5.0], [-0.5]])
kf.P = np.diag([4.0, 1.0, 4.0, 1.0])
radar = (np.array([10.8, 4.6]), np.diag([1.0, 1.0]))  # a position-only track
H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
before = np.trace(kf.P)
result = kf.fuse(radar, H=H)
print(f"1. position-only track: omega = {result.omega.round(3)}, "
      f"trace P {before:.2f} -> {np.trace(kf.P):.2f}, gain of the track "
      f"{result.info['gains'][1].shape}")
assert np.trace(kf.P) < before and result.info["converged"]

# --- 2. angles ----------------------------------------------------------------------------


def wrap(angle):
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def residual_x(a, b):
    d = a - b
    d[0] = wrap(d[0])  # the heading
    return d


points = MerweScaledSigmaPoints(2, alpha=0.1, beta=2.0, kappa=1.0)
ukf = cifilter.UnscentedKalmanFilter(2, 1, 1.0, hx=lambda x: x[:1], fx=lambda x, dt: x,
                                     points=points, residual_x=residual_x)
ukf.x, ukf.P = np.array([np.radians(179.0), 0.0]), np.diag([0.01, 1.0])
ukf.fuse((np.array([np.radians(-179.0), 0.0]), np.diag([0.01, 1.0])))
print(f"2. headings +179 and -179 degrees fuse to {np.degrees(ukf.x[0]):.1f} degrees")
assert abs(abs(np.degrees(wrap(ukf.x[0]))) - 180.0) < 1e-9

# --- 3. other times -----------------------------------------------------------------------
kf.x, kf.P = np.array([[10.0], [1.0], [5.0], [-0.5]]), np.diag([4.0, 1.0, 4.0, 1.0])
old = (np.array([7.1, 0.9, 6.4, -0.6]), np.diag([1.0, 0.5, 1.0, 0.5]))
result = kf.fuse(old, lag=3)  # it describes the state three steps ago: predicted
print(f"3. a three-step-old track, predicted: omega = {result.omega.round(3)}, "
      f"at = {result.info['at']}")
ahead = (np.array([12.4, 1.1, 3.8, -0.6]), np.diag([1.0, 0.5, 1.0, 0.5]))
result = kf.fuse(ahead, lag=-2)  # two steps ahead: retrodicted with the bound
alpha = float(result.info["retrodiction_alpha"][1])
print(f"   a track two steps ahead, retrodicted (alpha = {alpha:.3f}): "
      f"omega = {result.omega.round(3)}")
assert 0.0 < alpha < 1.0

# The same through the front door, with times and a motion model:


def motion(steps):
    F_k, Q_k = np.eye(4), np.zeros((4, 4))
    for _ in range(round(float(steps))):
        F_k, Q_k = F @ F_k, F @ Q_k @ F.T + Q
    return F_k, Q_k


here = (np.array([10.0, 1.0, 5.0, -0.5]), np.diag([4.0, 1.0, 4.0, 1.0]))
precise = (ahead[0], 0.2 * ahead[1])
fused = cifilter.fuse([here, precise], times=[0.0, 2.0], at=0.0, motion=motion)
print(f"   through cifilter.fuse: omega = {fused.omega.round(3)}, x = {fused.x.round(3)}")
assert fused.info["at"] == 0.0 and fused.omega[1] > 0.0
