"""A simulated vehicle for closed-loop runs: a kinematic multirotor and the drifting odometry it would report.

`KinematicDrone` holds the true pose T_cad_body (body: x forward, y left, z up; level flight, so roll and
pitch stay zero) and moves by commanded body-frame velocity and yaw rate, limited in speed and acceleration.
`DriftingOdometry` is a visual-inertial odometry stand-in: it integrates the true motion between steps with
noise proportional to the distance travelled, in its own frame `odom` (T_cad_odom unknown to anyone else),
so its drift grows with the path like a real VIO's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def yaw_of(T: np.ndarray) -> float:
    """Heading (rad) of a level pose's x axis in its parent frame."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def level_pose(xyz: np.ndarray, yaw_rad: float) -> np.ndarray:
    """4x4 T_parent_body of a level body at xyz (m) with heading yaw_rad."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = xyz
    return T


@dataclass(frozen=True)
class DroneLimits:
    max_speed_mps: float = 1.0
    max_accel_mps2: float = 1.5
    max_yaw_rate_radps: float = 1.2


class KinematicDrone:
    """True state of the vehicle in the CAD frame; `step` integrates a body-frame velocity command."""

    def __init__(self, T_cad_body: np.ndarray, limits: DroneLimits | None = None) -> None:
        self.T_cad_body = np.array(T_cad_body, float)
        self.limits = limits or DroneLimits()
        self.velocity_cad = np.zeros(3)  # m/s
        self.accel_cad = np.zeros(3)  # m/s^2, over the last step (what an accelerometer adds to gravity)
        self.distance_m = 0.0

    def step(self, dt_s: float, velocity_body_cmd: np.ndarray, yaw_rate_cmd_radps: float) -> None:
        """Move for dt_s seconds toward the commanded body-frame velocity (m/s) and yaw rate (rad/s)."""
        lim = self.limits
        v_cmd = self.T_cad_body[:3, :3] @ np.asarray(velocity_body_cmd, float)
        speed = float(np.linalg.norm(v_cmd))
        if speed > lim.max_speed_mps:
            v_cmd *= lim.max_speed_mps / speed
        dv = v_cmd - self.velocity_cad
        dv_max = lim.max_accel_mps2 * dt_s
        if np.linalg.norm(dv) > dv_max:
            dv *= dv_max / np.linalg.norm(dv)
        self.velocity_cad = self.velocity_cad + dv
        self.accel_cad = dv / dt_s if dt_s > 0 else np.zeros(3)
        yaw = yaw_of(self.T_cad_body) + float(np.clip(yaw_rate_cmd_radps, -lim.max_yaw_rate_radps,
                                                      lim.max_yaw_rate_radps)) * dt_s
        step = self.velocity_cad * dt_s
        self.distance_m += float(np.linalg.norm(step))
        self.T_cad_body = level_pose(self.T_cad_body[:3, 3] + step, yaw)

    def specific_force_body(self, gravity_mps2: float = 9.81) -> np.ndarray:
        """(3,) what an accelerometer on the body measures now: gravity's reaction plus the acceleration, m/s^2."""
        return self.T_cad_body[:3, :3].T @ (self.accel_cad + np.array([0.0, 0.0, gravity_mps2]))


class DriftingOdometry:
    """T_odom_body integrated from the true motion with noise: sigma = drift_per_m x distance of each step."""

    def __init__(self, T_cad_odom: np.ndarray, T_cad_body0: np.ndarray, seed: int, drift_per_m: float = 0.01,
                 yaw_drift_rad_per_m: float = 0.002) -> None:
        self.rng = np.random.default_rng(seed)
        self.drift_per_m = drift_per_m
        self.yaw_drift_rad_per_m = yaw_drift_rad_per_m
        self.T_odom_body = np.linalg.inv(T_cad_odom) @ T_cad_body0
        self._T_cad_body_prev = np.array(T_cad_body0, float)

    def update(self, T_cad_body: np.ndarray) -> np.ndarray:
        """The odometry pose after the vehicle moved to T_cad_body (4x4); returns T_odom_body (4x4)."""
        delta = np.linalg.inv(self._T_cad_body_prev) @ T_cad_body  # true motion, previous body frame
        d = float(np.linalg.norm(delta[:3, 3]))
        noisy = level_pose(delta[:3, 3] + self.rng.normal(0.0, self.drift_per_m * d, 3) * [1, 1, 0.3],
                           yaw_of(delta) + self.rng.normal(0.0, self.yaw_drift_rad_per_m * d))
        self.T_odom_body = self.T_odom_body @ noisy
        self._T_cad_body_prev = np.array(T_cad_body, float)
        return self.T_odom_body
