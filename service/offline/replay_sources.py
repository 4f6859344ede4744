"""The doors and windows a simulated vehicle reports, and its odometry: `TruthSource` (`--observations truth` and
`truth-vo`, service.offline.vehicle) turns a simulated flight's ground truth into what a good front end would
deliver, with realistic errors: odometry that drifts (a scale error, a yaw bias, noise growing with motion),
stereo-like corner noise (depth error ~ z^2) and missed detections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.localizer import Sighting
from macroloc.graph.rigid import rot_z, rotation_angle_rad
from macroloc.proto.recording import FlightFrame, matrix_from_pose


@dataclass(frozen=True)
class TruthFrame:
    """One frame as the vehicle reports it: its odometry pose T_odom_body (4x4, odometry frame z up) and the doors
    and windows in view (corners in the body frame)."""

    T_odom_body: np.ndarray
    sightings: list[Sighting]


@dataclass(frozen=True)
class TruthNoise:
    """Errors added to ground truth. Defaults: a decent stereo VIO and stereo corners at 0.12 m baseline."""

    odom_scale_error: float = 0.01  # odometry measures 1 % too much motion
    odom_yaw_bias_radps: float = 0.001  # ~3.4 deg/min heading drift
    odom_trans_sigma_per_m: float = 0.01
    odom_rot_sigma_per_rad: float = 0.01
    corner_sigma_m: float = 0.01  # lateral, per corner
    depth_sigma_per_m2: float = 0.005  # stereo: sigma_z = 0.3 px * z^2 / (fx * baseline) ~ 0.005 z^2
    gravity_sigma_rad: float = 0.005  # drawn each frame and not sent (the service's up is its own, from the IMU):
    #   kept so that a seed's sightings are those of the replays before issue 56
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

    def __call__(self, frame: FlightFrame) -> TruthFrame:
        """The frame's drifted odometry pose and the doors and windows seen in it, with their noise."""
        gt = frame.ground_truth
        if gt is None:
            raise UserInputError("--observations truth needs a simulated recording with ground truth")
        T_cad_body = matrix_from_pose(gt.T_cad_body)
        T_odom_body = self._odometry(T_cad_body, frame.stamp_ns)
        self.rng.normal(0, self.noise.gravity_sigma_rad, 3)  # a tilt error no longer sent (TruthNoise)
        return TruthFrame(T_odom_body, self._sightings(gt, matrix_from_pose(gt.T_body_cam)))

    def odometry(self, frame: FlightFrame) -> np.ndarray:
        """The frame's odometry pose alone (4x4, odometry frame), as a vehicle's VIO would publish it: the
        ground truth with the drift of `TruthNoise` (the sightings' noise is not drawn)."""
        gt = frame.ground_truth
        if gt is None:
            raise UserInputError("simulated odometry needs a simulated recording with ground truth")
        return self._odometry(matrix_from_pose(gt.T_cad_body), frame.stamp_ns)

    def _odometry(self, T_cad_body: np.ndarray, stamp_ns: int) -> np.ndarray:
        n = self.noise
        if self._T_true_prev is None or self._T_odom is None:
            yaw0 = np.arctan2(T_cad_body[1, 0], T_cad_body[0, 0])
            self._T_odom = np.eye(4)
            self._T_odom[:3, :3] = rot_z(-yaw0) @ T_cad_body[:3, :3]  # odometry frame: level, starts here
        else:
            dT = np.linalg.inv(self._T_true_prev) @ T_cad_body
            step_m = float(np.linalg.norm(dT[:3, 3]))
            angle = rotation_angle_rad(dT[:3, :3])
            dt_s = (stamp_ns - self._stamp_prev) * 1e-9
            noisy = dT.copy()
            noisy[:3, 3] = (dT[:3, 3] * (1 + n.odom_scale_error)
                            + self.rng.normal(0, n.odom_trans_sigma_per_m * step_m, 3))
            dyaw = n.odom_yaw_bias_radps * dt_s + self.rng.normal(0, n.odom_rot_sigma_per_rad * angle + 1e-5)
            noisy[:3, :3] = dT[:3, :3] @ rot_z(dyaw)
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
            sigmas = np.hstack([np.full((4, 2), n.corner_sigma_m), n.depth_sigma_per_m2 * z**2])  # x, y | z (cam)
            noise = self.rng.normal(0, 1, (4, 3)) * sigmas
            corners_cam = corners_cam + noise
            corners_body = (T_body_cam[:3, :3] @ corners_cam.T).T + T_body_cam[:3, 3]
            out.append(Sighting(feat.type, corners_body, truth_id=feat.id))
        return out
