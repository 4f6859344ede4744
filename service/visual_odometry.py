"""The stereo visual odometry of the per-frame front end (service.front_end, `[service] odometry = "visual"`): the
vehicle's pose in its odometry frame from the stereo frames and the IMU's samples between them, for a vehicle that
sends no odometry of its own, and for replays of recordings without one.

`VisualOdometry` runs perception.odometry.StereoOdometry on the rectified pair, its rotation checked against the
IMU's gyroscope (integrated over the frame's samples), and where it loses track its position dead-reckoned on the
accelerometer (perception.inertial); the odometry frame is the first body frame levelled by the IMU's gravity.
Frames: odom (z up), body, cam (the left camera). Metres.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.graph.rigid import rotation_aligning
from macroloc.perception.inertial import InertialDeadReckoning
from macroloc.perception.odometry import StereoOdometry
from macroloc.perception.params import PerceptionParams
from macroloc.perception.stereo import FrameDisparity, SgbmMatcher
from macroloc.proto.recording import FlightFrame
from macroloc.service.frames import StereoDepth, stereo_rig, stereo_T_body_cam

if TYPE_CHECKING:
    from macroloc.perception.odometry import StereoOdometry
    from macroloc.perception.params import PerceptionParams
    from macroloc.perception.stereo import FrameDisparity


class VisualOdometry:
    """T_odom_body from the stereo visual odometry on the recorded images, its rotation checked against the
    IMU's gyroscope (integrated over the frame's samples), and where it loses track its position dead-reckoned
    on the accelerometer (perception.inertial); the odometry frame is the first body frame levelled by the IMU's
    gravity. After each frame, `points_body` / `measure_depth` are the stereo depth points as the service measures
    them on that frame (service.frames.StereoDepth: on demand for a keyframe, by default)."""

    def __init__(self, disparity: FrameDisparity | None = None, params: PerceptionParams | None = None) -> None:
        """`disparity`: the frame's one SGBM, shared by the odometry's keyframes, the depth points and (given to
        it too) the perception chain; None: a new one (`params.stereo`) for the odometry and the depth points.
        `params`: the odometry's and the dead reckoning's (their defaults without)."""
        self._params = p = params or PerceptionParams()
        self._disparity = disparity or FrameDisparity(SgbmMatcher(p.stereo))
        self._odometry: StereoOdometry | None = None
        self._T_odom_cam0: np.ndarray | None = None
        self._last_imu_ns: int | None = None
        self._inertial = InertialDeadReckoning(p.inertial)
        self._depth = StereoDepth.configured(p.depth, self._disparity)
        self.points_body: np.ndarray | None = None  # the last frame's stereo depth points, when it measured some
        self.measure_depth: Callable[[], np.ndarray] | None = None  # the last frame's, measured when called
        self.dead_reckoned_s = 0.0  # the last frame's seconds of dead reckoning (tracking lost)
        self._last_stamp_ns: int | None = None

    def __call__(self, frame: FlightFrame, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        T_body_cam = stereo_T_body_cam(frame.stereo)
        if self._odometry is None:
            rig = stereo_rig(frame.stereo)
            self._odometry = StereoOdometry(rig, self._params.odometry, disparity=self._disparity)
            T_odom_body0 = np.eye(4)
            up_body = _up_from_imu(frame)
            if up_body is not None:
                T_odom_body0[:3, :3] = rotation_aligning(up_body, np.array([0.0, 0.0, 1.0]))
            self._T_odom_cam0 = T_odom_body0 @ T_body_cam
        assert self._T_odom_cam0 is not None
        R_body_cam = T_body_cam[:3, :3]
        R_gyro = _gyro_rotation(frame.imu, self._last_imu_ns)
        if frame.imu:
            self._last_imu_ns = frame.imu[-1].header.stamp_ns
        R_prev_cur = None if R_gyro is None else R_body_cam.T @ R_gyro @ R_body_cam
        f_body = _specific_forces(frame)
        T_odom_cam0 = self._T_odom_cam0
        stamps_s = np.array([s.header.stamp_ns for s in frame.imu], float) * 1e-9

        def lost_position(T_oc_cam: np.ndarray) -> np.ndarray | None:
            """The coasted camera's position (its odometry's frame, the first camera's) at the height the IMU
            dead-reckons (perception.inertial: its horizontal position needs a velocity and a tilt better than the
            odometry has as it loses track)."""
            T_odom_body = T_odom_cam0 @ T_oc_cam @ np.linalg.inv(T_body_cam)
            p_odom_body = self._inertial.predict(stamps_s, f_body @ T_odom_body[:3, :3].T)
            if p_odom_body is None:
                return None
            T_odom_body[2, 3] = p_odom_body[2]
            return (np.linalg.inv(T_odom_cam0) @ T_odom_body @ T_body_cam)[:3, 3]

        result = self._odometry.track(left, right, R_prev_cur, lost_position)
        self.dead_reckoned_s = 0.0 if result.tracked or self._last_stamp_ns is None else \
            (frame.stamp_ns - self._last_stamp_ns) * 1e-9
        self._last_stamp_ns = frame.stamp_ns
        self.points_body = self._depth(left, right, self._odometry.rig, T_body_cam)
        self.measure_depth = self._depth.deferred(left, right, self._odometry.rig, T_body_cam)
        if self.measure_depth is not None and self._params.odometry.rekey_at_session_keyframes:
            self.measure_depth = _rekeying(self._odometry, self.measure_depth)
        T_odom_body = T_odom_cam0 @ result.T_odom_cam @ np.linalg.inv(T_body_cam)
        self._inertial.update(frame.stamp_ns * 1e-9, T_odom_body[:3, 3], f_body @ T_odom_body[:3, :3].T,
                              result.tracked)
        return T_odom_body


def _rekeying(odometry: StereoOdometry, measure: Callable[[], np.ndarray]) -> Callable[[], np.ndarray]:
    """The depth measurement of a session keyframe that first makes the frame the odometry's reference keyframe
    (StereoOdometry.rekey): both take the frame's one whole-frame SGBM."""
    def rekey_and_measure() -> np.ndarray:
        odometry.rekey()
        return measure()
    return rekey_and_measure


def _gyro_rotation(samples: list, last_ns: int | None) -> np.ndarray | None:
    """The body's rotation over the samples' span (previous body frame <- this one) from their angular rates
    (each held from the previous sample's stamp to its own); None without samples or a previous stamp."""
    if not samples or last_ns is None:
        return None

    R = np.eye(3)
    t_prev = last_ns
    for s in samples:
        dt = (s.header.stamp_ns - t_prev) * 1e-9
        t_prev = s.header.stamp_ns
        w = np.array([s.gyro_radps.x, s.gyro_radps.y, s.gyro_radps.z])
        R = R @ Rotation.from_rotvec(w * dt).as_matrix()
    return R


def _specific_forces(frame: FlightFrame) -> np.ndarray:
    """(K, 3) the frame's IMU specific forces, body frame, m/s^2."""
    return np.array([[s.accel_mps2.x, s.accel_mps2.y, s.accel_mps2.z] for s in frame.imu], float).reshape(-1, 3)


def _up_from_imu(frame: FlightFrame) -> np.ndarray | None:
    """Unit up direction in the body frame: the mean specific force of the frame's IMU samples (gravity plus
    the vehicle's acceleration: a first guess, to level the odometry frame at the start)."""
    if not frame.imu:
        return None
    f = _specific_forces(frame).mean(axis=0)
    norm = float(np.linalg.norm(f))
    return f / norm if norm > 1e-6 else None
