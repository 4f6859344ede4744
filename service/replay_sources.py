"""Where the replay's per-frame inputs come from: odometry, gravity and door/window sightings.

`TruthSource` (`--observations truth`) turns a simulated flight's ground truth into what a good front end
would deliver, with realistic errors: odometry that drifts (a scale error, a yaw bias, noise growing with
motion), stereo-like corner noise (depth error ~ z^2), missed detections, and gravity with a small tilt
error. `PerceptionSource` (`--observations perception`) runs the perception chain and the visual odometry
on the recorded images, once they exist. Both return a `FrameInput` per recorded frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from graph.errors import UserInputError
from graph.localizer import Sighting
from service.recording import FlightFrame, matrix_from_pose


@dataclass(frozen=True)
class FrameInput:
    """One frame's inputs to the localizer. T_odom_body: 4x4 odometry pose (odometry frame z up);
    up_body: unit up direction in the body frame (from the IMU), or None."""

    stamp_ns: int
    T_odom_body: np.ndarray
    sightings: list[Sighting]
    up_body: np.ndarray | None
    T_body_cam: np.ndarray


class ObservationSource(Protocol):
    def __call__(self, frame: FlightFrame) -> FrameInput: ...


@dataclass(frozen=True)
class TruthNoise:
    """Errors added to ground truth. Defaults: a decent stereo VIO and stereo corners at 0.12 m baseline."""

    odom_scale_error: float = 0.01  # odometry measures 1 % too much motion
    odom_yaw_bias_radps: float = 0.001  # ~3.4 deg/min heading drift
    odom_trans_sigma_per_m: float = 0.01
    odom_rot_sigma_per_rad: float = 0.01
    corner_sigma_m: float = 0.01  # lateral, per corner
    depth_sigma_per_m2: float = 0.005  # stereo: sigma_z = 0.3 px * z^2 / (fx * baseline) ~ 0.005 z^2
    gravity_sigma_rad: float = 0.005
    miss_rate: float = 0.1
    min_visible_corners: int = 3  # three corners complete a rectangle


class TruthSource:
    """Ground truth with realistic errors (see module doc); deterministic for a seed."""

    def __init__(self, noise: TruthNoise | None = None, seed: int = 0) -> None:
        self.noise = noise or TruthNoise()
        self.rng = np.random.default_rng(seed)
        self._T_true_prev: np.ndarray | None = None
        self._T_odom: np.ndarray | None = None
        self._stamp_prev = 0

    def __call__(self, frame: FlightFrame) -> FrameInput:
        gt = frame.ground_truth
        if gt is None:
            raise UserInputError("--observations truth needs a simulated recording with ground truth")
        T_cad_body = matrix_from_pose(gt.T_cad_body)
        T_body_cam = matrix_from_pose(gt.T_body_cam)
        T_odom_body = self._odometry(T_cad_body, frame.stamp_ns)
        up_body = T_cad_body[:3, :3].T @ np.array([0.0, 0.0, 1.0]) + self.rng.normal(0, self.noise.gravity_sigma_rad, 3)
        return FrameInput(frame.stamp_ns, T_odom_body, self._sightings(gt, T_body_cam), up_body / np.linalg.norm(up_body),
                          T_body_cam)

    def _odometry(self, T_cad_body: np.ndarray, stamp_ns: int) -> np.ndarray:
        n = self.noise
        if self._T_true_prev is None or self._T_odom is None:
            yaw0 = np.arctan2(T_cad_body[1, 0], T_cad_body[0, 0])
            self._T_odom = np.eye(4)
            self._T_odom[:3, :3] = _rot_z(-yaw0) @ T_cad_body[:3, :3]  # odometry frame: level, starts here
        else:
            dT = np.linalg.inv(self._T_true_prev) @ T_cad_body
            step_m = float(np.linalg.norm(dT[:3, 3]))
            angle = float(np.arccos(np.clip((np.trace(dT[:3, :3]) - 1) / 2, -1, 1)))
            dt_s = (stamp_ns - self._stamp_prev) * 1e-9
            noisy = dT.copy()
            noisy[:3, 3] = dT[:3, 3] * (1 + n.odom_scale_error) + self.rng.normal(0, n.odom_trans_sigma_per_m * step_m, 3)
            dyaw = n.odom_yaw_bias_radps * dt_s + self.rng.normal(0, n.odom_rot_sigma_per_rad * angle + 1e-5)
            noisy[:3, :3] = dT[:3, :3] @ _rot_z(dyaw)
            self._T_odom = self._T_odom @ noisy
        self._T_true_prev, self._stamp_prev = T_cad_body, stamp_ns
        return self._T_odom.copy()

    def _sightings(self, gt, T_body_cam: np.ndarray) -> list[Sighting]:  # noqa: ANN001 - pb.GroundTruth
        n = self.noise
        out = []
        for k, feat in enumerate(gt.features_cam):
            visible = list(gt.corner_visible[4 * k: 4 * k + 4])
            if sum(visible) < n.min_visible_corners or self.rng.random() < n.miss_rate:
                continue
            corners_cam = np.array([[c.x, c.y, c.z] for c in feat.corners])
            z = corners_cam[:, 2:3]
            noise = self.rng.normal(0, 1, (4, 3)) * np.hstack([np.full((4, 2), n.corner_sigma_m), n.depth_sigma_per_m2 * z**2])
            corners_cam = corners_cam + noise
            corners_body = (T_body_cam[:3, :3] @ corners_cam.T).T + T_body_cam[:3, 3]
            out.append(Sighting(feat.type, corners_body, truth_id=feat.id))
        return out


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class PerceptionSource:
    """The perception chain and visual odometry on recorded stereo images (needs perception.pipeline)."""

    def __init__(self) -> None:
        try:
            from perception import pipeline  # noqa: F401
        except ImportError:
            raise UserInputError("--observations perception: the perception chain (perception.pipeline) "
                                 "is not available yet; use --observations truth") from None
        raise UserInputError("--observations perception is not wired yet; use --observations truth")

    def __call__(self, frame: FlightFrame) -> FrameInput:  # pragma: no cover - not wired yet
        raise NotImplementedError
