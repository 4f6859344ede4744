"""PX4 through its uXRCE-DDS topics on Zenoh (like any ROS 2 topic: zenoh-bridge-ros2dds's keys, or rmw_zenoh's with
`[ros] middleware = "rmw_zenoh"`, service.ros_transport): external-vision
odometry for PX4's EKF2 and offboard setpoints along macroloc's plan.

Out (keys `[<ns>/]fmu/in/...`, px4_msgs CDR, proto/px4_msgs):
- `vehicle_visual_odometry` VehicleOdometry: T_cad_body as a pose in NED (body FRD). The CAD frame is taken as a
  local ENU frame (z up; x, y the model's axes) made NED by `service.ned`; where the model is geo-referenced
  (`T_enu_cad` given) that frame is true ENU and `pose_frame` is NED, else its heading is arbitrary and
  `pose_frame` is FRD (PX4: "constant arbitrary heading offset from true north"). Velocity in the same frame where
  known (`Motion`), variances from the covariance's diagonal (position in the world frame, orientation in the body
  frame, as the message states), `reset_counter` incremented whenever T_cad_map jumps (a re-localization or a jump
  of the CAD anchor beyond `reset_jump_m` / `reset_jump_deg`), `quality` 100 localized, 50 degraded.
- `trajectory_setpoint` TrajectorySetpoint: the next waypoint of the active plan (NED, yaw from the plan's yaw) and
  `offboard_control_mode` (position) at `offboard_rate_hz` (>= 2 Hz) from a timer thread while a plan is active.
Timestamps are the pose's stamp in microseconds (the vehicle's clock, as macroloc's poses carry it).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from macroloc.graph.localizer import Estimate
from macroloc.graph.rigid import rotation_angle_rad
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.ros_types import msg, to_cdr
from macroloc.service.ned import (
    R_FLU_FRD,
    R_NED_ENU,
    T_ned_frd_from_T_enu_flu,
    quat_wxyz_from_matrix,
    yaw_ned_from_yaw_enu,
)
from macroloc.service.ros_transport import RosTransport
from macroloc.service.vehicle_out import Motion, waypoints_arrays

log = logging.getLogger(__name__)

VEHICLE_ODOMETRY = "px4_msgs/msg/VehicleOdometry"
TRAJECTORY_SETPOINT = "px4_msgs/msg/TrajectorySetpoint"
OFFBOARD_CONTROL_MODE = "px4_msgs/msg/OffboardControlMode"
NAN3 = np.full(3, np.nan, np.float32)


@dataclass(frozen=True)
class Px4Keys:
    namespace: str = ""

    def _k(self, leaf: str) -> str:
        ns = self.namespace.strip("/")
        return f"{ns}/fmu/in/{leaf}" if ns else f"fmu/in/{leaf}"

    @property
    def visual_odometry(self) -> str:
        return self._k("vehicle_visual_odometry")

    @property
    def trajectory_setpoint(self) -> str:
        return self._k("trajectory_setpoint")

    @property
    def offboard_control_mode(self) -> str:
        return self._k("offboard_control_mode")

    @property
    def vehicle_odometry(self) -> str:
        """PX4's own odometry, out of the vehicle: `[<ns>/]fmu/out/vehicle_odometry`."""
        ns = self.namespace.strip("/")
        return f"{ns}/fmu/out/vehicle_odometry" if ns else "fmu/out/vehicle_odometry"


class ResetCounter:
    """PX4's reset_counter (uint8, wraps): +1 at every re-localization (a localized estimate after the service had
    lost its pose or restarted its graph, having been localized before) and whenever T_cad_map moves by more than
    jump_m or jump_rad between consecutive estimates that have one (the anchor kept while none has one); one
    estimate adds one at most."""

    def __init__(self, jump_m: float = 0.10, jump_rad: float = np.deg2rad(2.0)) -> None:
        self.jump_m, self.jump_rad = jump_m, jump_rad
        self.count = 0
        self._last: np.ndarray | None = None
        self._lost_since_localized = False

    def update(self, T_cad_map: np.ndarray | None, status: str = "localized") -> int:
        if status in ("lost", "exploring") and self._last is not None:
            self._lost_since_localized = True
        if T_cad_map is None:
            return self.count
        last, self._last = self._last, np.asarray(T_cad_map, float).copy()
        relocalized = self._lost_since_localized and status == "localized"
        jumped = last is not None and (float(np.linalg.norm(T_cad_map[:3, 3] - last[:3, 3])) > self.jump_m
                                       or rotation_angle_rad(last[:3, :3].T @ T_cad_map[:3, :3]) > self.jump_rad)
        if relocalized or jumped:
            self.count = (self.count + 1) % 256
        if status == "localized":
            self._lost_since_localized = False
        return self.count


class Px4Messages:
    """Estimates and plans as px4_msgs (rosbags' classes); `T_enu_cad`: the model's geo-reference, or None."""

    def __init__(self, T_enu_cad: np.ndarray | None = None, reset: ResetCounter | None = None) -> None:
        self.T_enu_cad = np.eye(4) if T_enu_cad is None else np.asarray(T_enu_cad, float)
        self.geo_referenced = T_enu_cad is not None
        self.reset = reset or ResetCounter()

    def T_ned_frd(self, T_cad_body: np.ndarray) -> np.ndarray:
        """The body (FRD) in NED (or FRD-world where not geo-referenced), from T_cad_body (FLU in the CAD frame)."""
        return T_ned_frd_from_T_enu_flu(self.T_enu_cad @ T_cad_body)

    def odometry(self, est: Estimate, velocity_cad: np.ndarray | None) -> Any:
        assert est.T_cad_body is not None
        Odo = msg(VEHICLE_ODOMETRY)
        T = self.T_ned_frd(est.T_cad_body)
        R_ned_cad = R_NED_ENU @ self.T_enu_cad[:3, :3]
        velocity = NAN3 if velocity_cad is None else (R_ned_cad @ velocity_cad).astype(np.float32)
        pos_var, rot_var = np.full(3, np.nan), np.full(3, np.nan)
        if est.covariance is not None:  # GTSAM [rot; trans] in the body's tangent space (FLU)
            cov = np.asarray(est.covariance, float)
            R_ned_flu = R_ned_cad @ est.T_cad_body[:3, :3]
            pos_var = np.diag(R_ned_flu @ cov[3:, 3:] @ R_ned_flu.T)  # world (NED) position variances, m^2
            rot_var = np.diag(R_FLU_FRD.T @ cov[:3, :3] @ R_FLU_FRD)  # body (FRD) attitude variances, rad^2
        stamp_us = est.stamp_ns // 1000
        frame = Odo.POSE_FRAME_NED if self.geo_referenced else Odo.POSE_FRAME_FRD
        vframe = Odo.VELOCITY_FRAME_NED if self.geo_referenced else Odo.VELOCITY_FRAME_FRD
        return Odo(timestamp=stamp_us, timestamp_sample=stamp_us, pose_frame=frame,
                   position=T[:3, 3].astype(np.float32), q=quat_wxyz_from_matrix(T[:3, :3]).astype(np.float32),
                   velocity_frame=vframe, velocity=velocity, angular_velocity=NAN3,
                   position_variance=pos_var.astype(np.float32), orientation_variance=rot_var.astype(np.float32),
                   velocity_variance=NAN3, reset_counter=self.reset.update(est.T_cad_map, est.status),
                   quality=100 if est.status == "localized" else 50)

    def setpoint(self, point_cad: np.ndarray, yaw_cad_rad: float, stamp_us: int) -> Any:
        """TrajectorySetpoint at a CAD point with a CAD-frame yaw (about +z from +x), as NED position and yaw."""
        p_ned = R_NED_ENU @ (self.T_enu_cad[:3, :3] @ point_cad + self.T_enu_cad[:3, 3])
        R = self.T_enu_cad[:3, :3]
        yaw_enu = yaw_cad_rad + float(np.arctan2(R[1, 0], R[0, 0]))  # the model's x axis heading in ENU
        return msg(TRAJECTORY_SETPOINT)(timestamp=stamp_us, position=p_ned.astype(np.float32), velocity=NAN3,
                                        acceleration=NAN3, jerk=NAN3, yaw=np.float32(yaw_ned_from_yaw_enu(yaw_enu)),
                                        yawspeed=np.float32(np.nan))

    @staticmethod
    def offboard_mode(stamp_us: int) -> Any:
        return msg(OFFBOARD_CONTROL_MODE)(timestamp=stamp_us, position=True, velocity=False, acceleration=False,
                                          attitude=False, body_rate=False, thrust_and_torque=False,
                                          direct_actuator=False)


class PlanCursor:
    """The active plan's next waypoint: advances past the waypoints within reach_m of the vehicle."""

    def __init__(self, reach_m: float = 0.5) -> None:
        self.reach_m = reach_m
        self.points_cad = np.zeros((0, 3))
        self.yaw_rad = np.zeros(0)
        self.index = 0

    def set(self, points_cad: np.ndarray, yaw_rad: np.ndarray) -> None:
        self.points_cad, self.yaw_rad = points_cad, yaw_rad
        self.index = min(1, len(points_cad) - 1) if len(points_cad) else 0

    @property
    def active(self) -> bool:
        return len(self.points_cad) > 0

    def advance(self, position_cad: np.ndarray) -> None:
        while self.index < len(self.points_cad) - 1 and \
                np.linalg.norm(self.points_cad[self.index] - position_cad) < self.reach_m:
            self.index += 1

    def target(self) -> tuple[np.ndarray, float]:
        return self.points_cad[self.index], float(self.yaw_rad[self.index])


class Px4Output:
    """Publishes `Px4Messages` on PX4's keys (a `service.vehicle_out.VehicleOutput`); a timer thread sends the
    setpoint and offboard_control_mode at `rate_hz` while a plan is active."""

    def __init__(self, transport: RosTransport, keys: Px4Keys, messages: Px4Messages | None = None,
                 rate_hz: float = 4.0, reach_m: float = 0.5) -> None:
        """`transport`: where PX4's topics are on Zenoh (the bridge's keys, or rmw_zenoh's: service.ros_transport)."""
        self.messages = messages or Px4Messages()
        self.motion = Motion()
        self.cursor = PlanCursor(reach_m)
        self.period_s = 1.0 / rate_hz
        self._lock = threading.Lock()
        self._stamp_us = 0
        self._pubs = {"odometry": transport.publisher(keys.visual_odometry, VEHICLE_ODOMETRY),
                      "setpoint": transport.publisher(keys.trajectory_setpoint, TRAJECTORY_SETPOINT),
                      "offboard": transport.publisher(keys.offboard_control_mode, OFFBOARD_CONTROL_MODE)}
        self._stop = threading.Event()
        self._timer = threading.Thread(target=self._heartbeat, name="px4-offboard", daemon=True)
        self._timer.start()

    def pose(self, est: Estimate) -> None:
        velocity = self.motion.velocity_cad(est)
        with self._lock:
            self._stamp_us = est.stamp_ns // 1000
            if est.T_cad_body is not None:
                self.cursor.advance(est.T_cad_body[:3, 3])
        if est.T_cad_body is not None and est.status in ("localized", "degraded"):
            self._pubs["odometry"].put(to_cdr(self.messages.odometry(est, velocity), VEHICLE_ODOMETRY))
        else:  # no odometry goes out, but the counter learns that the pose was lost (a re-localization follows)
            self.messages.reset.update(None, est.status)

    def waypoints(self, plan: pb.Waypoints) -> None:
        if plan.error:
            return
        points, yaws = waypoints_arrays(plan)
        with self._lock:
            self.cursor.set(points, yaws)
        self.send_setpoint()

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        pass

    def send_setpoint(self) -> bool:
        """The offboard heartbeat and the current setpoint, where a plan is active."""
        with self._lock:
            if not self.cursor.active:
                return False
            point, yaw = self.cursor.target()
            stamp_us = self._stamp_us
        self._pubs["offboard"].put(to_cdr(self.messages.offboard_mode(stamp_us), OFFBOARD_CONTROL_MODE))
        self._pubs["setpoint"].put(to_cdr(self.messages.setpoint(point, yaw, stamp_us), TRAJECTORY_SETPOINT))
        return True

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.send_setpoint()
            except Exception:  # a closed session at shutdown must not print a thread traceback
                if not self._stop.is_set():
                    log.exception("offboard heartbeat failed")

    def close(self) -> None:
        self._stop.set()
        self._timer.join(timeout=2.0)
        for pub in self._pubs.values():
            pub.undeclare()
