"""Gravity's direction in the body frame from the IMU's specific force, the vehicle's own acceleration removed.

An accelerometer measures the specific force f = R_odom_body^T (a + g e_z): the reaction to gravity plus the
vehicle's acceleration a. Taking f alone as "up" tilts it by atan(|a| / g): 3 degrees at 0.5 m/s^2, 6.5
degrees in a 1.5 m/s turn of 2 m radius. That tilt reaches the pose graph through its roll/pitch prior, and at
3 degrees it moves a point on the floor 5 m ahead by 0.26 m.

The odometry already knows the acceleration. Between two instants t1 and t2 the mean acceleration is
(v(t2) - v(t1)) / (t2 - t1), whatever it did in between; lines fitted to the odometry's positions near t1 and
t2 give those velocities. The frames' specific forces between t1 and t2, rotated into the odometry frame,
average to that mean acceleration plus g e_z. Their difference is up in the odometry frame, and the newest
attitude takes it into the body frame. Since up is measured in the odometry frame each time, the tilt the
odometry's rotation accumulates is absorbed too.

Frames: odometry frame (gravity roughly -z), body frame of the IMU; metres, seconds.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from macroloc.perception.params import GravityParams


class GravityEstimator:
    """Up (unit, body frame) per frame from the IMU samples and the odometry pose (see module doc)."""

    def __init__(self, params: GravityParams | None = None) -> None:
        self.params = params or GravityParams()
        self._history: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # (t_s, p_odom, f_odom)

    def update(self, stamp_ns: int, T_odom_body: np.ndarray, accel_body_mps2: np.ndarray) -> np.ndarray | None:
        """This frame's IMU specific forces (K, 3, body frame, m/s^2) and odometry pose (4x4) -> up in the body
        frame, or None without IMU samples within the specific force's bounds (or when the odometry jumped)."""
        f = np.asarray(accel_body_mps2, float).reshape(-1, 3)
        norm_f = np.linalg.norm(f, axis=1)
        f = f[(norm_f > self.params.min_specific_force_mps2) & (norm_f < self.params.max_specific_force_mps2)]
        if len(f) == 0:
            return None
        R = np.asarray(T_odom_body, float)[:3, :3]
        t_s = stamp_ns * 1e-9
        self._history.append((t_s, np.asarray(T_odom_body, float)[:3, 3].copy(), R @ f.mean(axis=0)))
        while t_s - self._history[0][0] > self.params.window_s:
            self._history.popleft()
        t = np.array([h[0] for h in self._history])
        p = np.array([h[1] for h in self._history])
        ends = None if t[-1] - t[0] < self.params.min_span_s else end_velocities(t, p, self.params.end_s)
        if ends is None:
            up_odom = self._history[-1][2]  # too little history: the specific force alone
        else:
            f = np.array([h[2] for h in self._history])
            # the mean acceleration between the centres of the window's first and last parts is the difference of
            # their velocities (lines fitted to each part's positions), whatever the acceleration did in between
            t1, v1, t2, v2 = ends
            accel_odom = (v2 - v1) / (t2 - t1)
            inside = (t >= t1) & (t <= t2)
            if np.linalg.norm(accel_odom) > self.params.max_accel_mps2 or not inside.any():
                return None
            up_odom = f[inside].mean(axis=0) - accel_odom
        norm = float(np.linalg.norm(up_odom))
        return R.T @ up_odom / norm if norm > 1e-6 else None


class ImuGravity:
    """Gravity's up from the IMU and the odometry as they arrive: `imu` adds specific forces, `odometry` takes those
    that came since the previous pose, with the pose, into the `GravityEstimator`. The rule for what `up_body` holds
    after a pose (the service and a replay alike, through service.localizer_loop.LocalizerLoop):
    - samples came, and the estimator gives up: that up;
    - samples came, and it gives none (each sample a knock or a free fall, or the odometry jumped): None, up unknown
      (the localizer then adds no roll/pitch prior) until a later pose gives one;
    - no sample came since the previous pose: the previous up (nothing new was measured).
    At most `max_samples` samples wait for a pose (the newest)."""

    def __init__(self, params: GravityParams | None = None, max_samples: int = 256) -> None:
        self.params = params or GravityParams()
        self.max_samples = max_samples
        self._estimator = GravityEstimator(self.params)
        self._accel_body: list[np.ndarray] = []  # (K, 3) blocks of specific forces since the last pose
        self._n_waiting = 0
        self.up_body: np.ndarray | None = None  # unit, body frame, at the newest pose

    def imu(self, accel_body_mps2: np.ndarray) -> None:
        """Specific forces (3,) or (K, 3), body frame, m/s^2, measured since the last pose."""
        f = np.asarray(accel_body_mps2, float).reshape(-1, 3)
        if len(f):
            self._accel_body.append(f)
            self._n_waiting += len(f)
        if self._n_waiting > self.max_samples:
            f_all = np.concatenate(self._accel_body)[-self.max_samples:]
            self._accel_body, self._n_waiting = [f_all], len(f_all)

    def odometry(self, stamp_ns: int, T_odom_body: np.ndarray) -> np.ndarray | None:
        """An odometry pose (4x4): up in the body frame at it, by the rule above."""
        if self._accel_body:
            f = np.concatenate(self._accel_body)
            self._accel_body, self._n_waiting = [], 0
            self.up_body = self._estimator.update(stamp_ns, T_odom_body, f)
        return self.up_body

    def new_time_base(self) -> None:
        """The clock was reset: the history (positions differentiated over stamps) starts again; up stays until
        the next pose gives one."""
        self._estimator = GravityEstimator(self.params)
        self._accel_body, self._n_waiting = [], 0


def end_velocities(t_s: np.ndarray, p: np.ndarray, end_s: float) -> tuple[float, np.ndarray, float, np.ndarray] | None:
    """(t1, v1, t2, v2): the velocities of lines fitted to the positions p (N, 3) at times t_s (N,) within `end_s`
    of the first and of the last, at those parts' mean times; None where either part has fewer than two."""
    first, last = t_s <= t_s[0] + end_s, t_s >= t_s[-1] - end_s
    if first.sum() < 2 or last.sum() < 2:
        return None
    t1, t2 = float(t_s[first].mean()), float(t_s[last].mean())
    v1, v2 = np.polyfit(t_s[first] - t1, p[first], 1)[0], np.polyfit(t_s[last] - t2, p[last], 1)[0]
    return t1, v1, t2, v2
