"""Dead reckoning on the accelerometer while the visual odometry has lost track.

A camera nearer a wall than stereo measures (0.45 m with 128 disparities) or facing a bare surface has nothing to
track, and the odometry used to coast at its last velocity. A drone keeps manoeuvring meanwhile: it brakes, turns,
climbs. The IMU still measures that. Its specific force, rotated into the odometry frame, is the acceleration plus
gravity; integrating it twice from the velocity at the loss follows the manoeuvre.

Doing that with gravity taken as 9.81 m/s^2 along the odometry frame's z fails: that frame is levelled once, at the
first frame (a degree off is common), the gyro-driven rotation tilts it further, and the accelerometer
has a bias (0.05 m/s^2 a side on the simulated IMU). At 1 deg, gravity leaks 0.17 m/s^2 sideways: 1.2 m after
3.8 s. So gravity is calibrated against the odometry, as perception.gravity does for its direction: over the last
`calibrate_s` of tracked frames, the mean specific force in the odometry frame minus the odometry's own mean
acceleration (the difference of the velocities fitted at the span's ends) is gravity as this odometry frame and
this accelerometer see it, tilt and bias included. The velocity at the loss is a line fitted to the last
`end_s` of tracked positions.

The replay's visual odometry (service.offline.replay_sources.VisualOdometry) takes only the height from it and keeps
the coasted horizontal position. Where the odometry tracked well up to the loss, dead reckoning beats coasting on
both axes; but a real loss comes after frames the odometry tracked poorly (a camera closing on a wall), the velocity
fitted there is off, and the horizontal dead reckoning then ends further off than coasting, while the height still
gains (docs/measurements.md, "Dead reckoning on the accelerometer"). The height needs neither the tilt nor a good
horizontal velocity (gravity's magnitude is calibrated, and a degree of tilt changes it by 0.015 %). A body that
yaws turns the accelerometer's bias in the odometry frame away from what was calibrated: 0.23 m after 3 s at 0.3
rad/s with a 0.06 m/s^2 bias (the test's flight).

Frames: the odometry frame (z roughly up) and the body frame of the IMU; metres, seconds.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from macroloc.perception.gravity import end_velocities
from macroloc.perception.params import InertialParams


class InertialDeadReckoning:
    """Feed every frame: `predict` before the odometry decides whether it tracked, then `update` with its pose.

    Each frame's mean specific force (odometry frame) and each tracked frame's position are kept for
    `calibrate_s`. On the first lost frame the velocity and gravity are taken from them, and `predict` integrates
    the frame's IMU samples from there (and from the previous lost frame's state after it) until tracking
    returns. A lost frame's position is not kept (it is the dead reckoning's), its specific force is: the
    velocity change across it is the odometry's."""

    def __init__(self, params: InertialParams | None = None) -> None:
        self.params = params or InertialParams()
        self._positions: deque[tuple[float, np.ndarray]] = deque()  # (t_s, p_odom) of tracked frames
        self._forces: deque[tuple[float, np.ndarray]] = deque()  # (t_s, mean f_odom) of every frame with samples
        self._coasting: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None  # (t_s, p, v, g), odom
        self._predicted: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None

    def predict(self, stamps_s: np.ndarray, f_odom_mps2: np.ndarray) -> np.ndarray | None:
        """The position (3,) in the odometry frame at the last of this frame's IMU samples (stamps (K,), specific
        forces (K, 3) rotated into the odometry frame by the frame's attitude) were tracking lost on it; None
        without samples or without enough tracked flight to calibrate gravity."""
        stamps = np.asarray(stamps_s, float).reshape(-1)
        f = np.asarray(f_odom_mps2, float).reshape(-1, 3)
        self._predicted = None
        state = self._coasting or self._start()
        if state is None or len(stamps) == 0:
            return None
        t, p, v, g = state
        p, v = p.copy(), v.copy()
        for ts, fk in zip(stamps, f, strict=True):
            dt = max(0.0, float(ts) - t)
            a = fk - g
            p += v * dt + 0.5 * a * dt * dt
            v += a * dt
            t = max(t, float(ts))
        self._predicted = (t, p, v, g)
        return p

    def update(self, t_s: float, p_odom: np.ndarray, f_odom_mps2: np.ndarray, tracked: bool) -> None:
        """This frame's outcome: where the odometry put it, its IMU samples' specific forces in the odometry frame
        (K, 3), and whether it tracked (else the prediction, if one was made, is where the coasting goes on)."""
        f = np.asarray(f_odom_mps2, float).reshape(-1, 3)
        if len(f):
            self._forces.append((float(t_s), f.mean(axis=0)))
        if tracked:
            self._coasting = None
            self._positions.append((float(t_s), np.asarray(p_odom, float).copy()))
        else:
            self._coasting = self._predicted
        for kept in (self._positions, self._forces):
            while kept and t_s - kept[0][0] > self.params.calibrate_s:
                kept.popleft()

    def _start(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """(t, p, v, g) at the last tracked frame: velocity from its last `end_s`, gravity calibrated over the
        history (see module doc); None with too short a history."""
        if not self._positions or not self._forces:
            return None
        t = np.array([h[0] for h in self._positions])
        p = np.array([h[1] for h in self._positions])
        ends = None if t[-1] - t[0] < self.params.min_calibrate_s else end_velocities(t, p, self.params.end_s)
        if ends is None:
            return None
        t1, v1, t2, v2 = ends
        accel = (v2 - v1) / (t2 - t1)
        t_f = np.array([h[0] for h in self._forces])
        inside = (t_f > t1) & (t_f <= t2)
        if np.linalg.norm(accel) > self.params.max_accel_mps2 or not inside.any():
            return None
        forces = np.array([h[1] for h in self._forces])
        g = forces[inside].mean(axis=0) - accel
        # the fitted velocity is the last end_s's mean, at t2: carried to the last frame by the specific forces since
        after = (t_f > t2) & (t_f <= t[-1])
        dt = np.diff(np.concatenate([[t2], t_f[after]]))
        v = np.asarray(v2, float) + ((forces[after] - g) * dt[:, None]).sum(axis=0)
        return float(t[-1]), p[-1].copy(), v, g
