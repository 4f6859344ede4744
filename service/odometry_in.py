"""The vehicle's odometry taken where the vehicle has it (issue 57 item 2): a ROS 2 `nav_msgs/msg/Odometry` topic
(a VIO: OpenVINS, VINS-Fusion, Isaac ROS Visual SLAM) and PX4's `fmu/out/vehicle_odometry`
(`px4_msgs/msg/VehicleOdometry`) or the `odom -> base_link` link of ROS's `/tf` (`tf2_msgs/msg/TFMessage`), each
turned into the service's own odometry event and checked by
`InputParser.odometry` (finite, unit quaternion, plausible position, stamps in order) like a macroloc `Odometry` on
`macroloc/<vehicle>/odometry`.

Frames. macroloc's `map` frame (REP-105's `odom`) is the odometry's world frame, `body` is FLU:
- ROS Odometry: `pose` is the child frame (`base_link`, FLU, REP-103) in the header's frame (the VIO's `odom`), taken
  as T_map_body as it is; header stamp in ns; the pose covariance reordered to the wire's [rot; trans].
- ROS /tf: the TransformStamped whose header frame is `[ros] frame_odom` and child `[ros] frame_base_link`
  (T_odom_base_link, the VIO's, REP-105) taken as T_map_body as it is, at its own header stamp; no covariance (the
  wire's "unknown": none given). A /tf message without that link (the rest of the tree, macroloc's own
  `map -> odom`) is not odometry: skipped, not counted.
- PX4 VehicleOdometry: `position` (m) and `q` (w, x, y, z: the FRD body in the world frame) in NED (`pose_frame` 1)
  or FRD-world (2, arbitrary heading), both z down, turned into a z-up frame by `service.ned`
  (T_map_body = T_enu_flu_from_T_ned_frd: x<->y swapped, z flipped; body FRD -> FLU); stamp = `timestamp_sample`
  (us, PX4's clock) x 1000, so the cameras must be stamped on PX4's clock. A sample with an unknown pose frame or a
  NaN position or attitude (PX4's "invalid") is refused as `odometry/nan`.

Segments. A VIO that resets (PX4's `reset_counter` changes, or a pose jumps further between consecutive samples than
`max_speed_mps` x dt + 0.25 m, or turns more than `max_rate_radps` x dt + 10 deg) starts a new odometry frame: its
poses are not a motion of the vehicle. `OdometrySegments` places each new segment so that its first pose is the
last pose of the previous one (the vehicle does not move across a reset: the error is the motion of one sample
interval), T_map_body = T_map_segment @ T_segment_body, so that the pose graph sees one continuous odometry and
never a teleport; each new segment is counted as `odometry/segment` in the diagnostics (not a drop).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from macroloc.graph.rigid import rotation_angle_rad
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import pose_from_matrix
from macroloc.proto.ros_types import from_cdr, stamp_ns_of
from macroloc.service.inputs import InputParser, OdometryIn
from macroloc.service.ned import T_enu_flu_from_T_ned_frd, matrix_from_quat_wxyz
from macroloc.service.ros_in import odometry_message, transform_matrix

log = logging.getLogger(__name__)

ROS_ODOMETRY = "nav_msgs/msg/Odometry"
PX4_ODOMETRY = "px4_msgs/msg/VehicleOdometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
PX4_POSE_FRAMES = (1, 2)  # NED, FRD-world: both z down
JUMP_SLACK_M = 0.25
JUMP_SLACK_RAD = float(np.deg2rad(10.0))


@dataclass(frozen=True)
class SegmentRule:
    """A pose change between consecutive samples beyond what the vehicle can move is a reset (module doc)."""

    max_speed_mps: float = 10.0
    max_rate_radps: float = float(np.deg2rad(400.0))

    def is_jump(self, T_prev: np.ndarray, T_next: np.ndarray, dt_s: float) -> bool:
        """Whether T_prev -> T_next (4x4, one frame, metres) over dt_s seconds is beyond the vehicle's motion."""
        moved_m = float(np.linalg.norm(T_next[:3, 3] - T_prev[:3, 3]))
        turned_rad = rotation_angle_rad(T_prev[:3, :3].T @ T_next[:3, :3])
        return moved_m > JUMP_SLACK_M + self.max_speed_mps * dt_s or \
            turned_rad > JUMP_SLACK_RAD + self.max_rate_radps * dt_s


class OdometrySegments:
    """One continuous `map` frame from a vehicle odometry that resets (module doc)."""

    def __init__(self, rule: SegmentRule, on_segment: Callable[[int], None] | None = None) -> None:
        """`on_segment(stamp_ns)`: told at the first sample of each new segment after the first."""
        self.rule, self.on_segment = rule, on_segment
        self.T_map_segment = np.eye(4)
        self.segments = 1
        self._last: tuple[int, np.ndarray, np.ndarray, int | None] | None = None  # stamp, T_seg_body, T_map_body, reset

    def __call__(self, stamp_ns: int, T_segment_body: np.ndarray, reset_counter: int | None = None) -> np.ndarray:
        """T_map_body of a sample (stamps increase: the parser ordered them), T_segment_body in its own segment."""
        if self._last is not None:
            last_ns, T_seg_prev, T_map_prev, last_reset = self._last
            counter_reset = reset_counter is not None and last_reset is not None and reset_counter != last_reset
            if counter_reset or self.rule.is_jump(T_seg_prev, T_segment_body, (stamp_ns - last_ns) * 1e-9):
                self.T_map_segment = T_map_prev @ np.linalg.inv(T_segment_body)  # first pose = the last one
                self.segments += 1
                log.warning("vehicle odometry reset (%s) at %d ns: segment %d chained at the last pose",
                            "reset_counter" if counter_reset else "jump", stamp_ns, self.segments)
                if self.on_segment is not None:
                    self.on_segment(stamp_ns)
        T_map_body = self.T_map_segment @ T_segment_body
        self._last = (stamp_ns, T_segment_body, T_map_body, reset_counter)
        return T_map_body


def ros_odometry(payload: bytes) -> tuple[pb.Odometry, None]:
    """A nav_msgs/msg/Odometry CDR payload as a wire Odometry (module doc); no reset counter."""
    return odometry_message(from_cdr(payload, ROS_ODOMETRY)), None


class TfOdometry:
    """/tf's `odom_frame -> base_frame` link as the vehicle's odometry (module doc)."""

    def __init__(self, odom_frame: str = "odom", base_frame: str = "base_link") -> None:
        self.odom_frame, self.base_frame = odom_frame.lstrip("/"), base_frame.lstrip("/")

    def __call__(self, payload: bytes) -> tuple[pb.Odometry, None] | None:
        """A tf2_msgs/msg/TFMessage CDR payload as a wire Odometry (T_map_body = T_odom_base_link, the last such
        link in the message), or None where the message holds no such link."""
        links = [t for t in from_cdr(payload, TF_MESSAGE).transforms if t.header.frame_id.lstrip("/") ==
                 self.odom_frame and t.child_frame_id.lstrip("/") == self.base_frame]
        if not links:
            return None
        msg = pb.Odometry(T_map_body=pose_from_matrix(transform_matrix(links[-1].transform)))
        msg.header.stamp_ns, msg.header.frame_id = stamp_ns_of(links[-1].header.stamp), "map"
        return msg, None


def px4_odometry(payload: bytes) -> tuple[pb.Odometry | None, int]:
    """A px4_msgs/msg/VehicleOdometry CDR payload as a wire Odometry (T_map_body: z-up world, FLU body; module doc)
    and its reset_counter; None for an unknown pose frame or an invalid (NaN) pose."""
    m = from_cdr(payload, PX4_ODOMETRY)
    position_ned, q_wxyz = np.asarray(m.position, float), np.asarray(m.q, float)
    if int(m.pose_frame) not in PX4_POSE_FRAMES or not (np.isfinite(position_ned).all() and np.isfinite(q_wxyz).all()):
        return None, int(m.reset_counter)
    T_ned_frd = np.eye(4)
    T_ned_frd[:3, :3] = matrix_from_quat_wxyz(q_wxyz / np.linalg.norm(q_wxyz))  # float32 on the wire
    T_ned_frd[:3, 3] = position_ned
    msg = pb.Odometry(T_map_body=pose_from_matrix(T_enu_flu_from_T_ned_frd(T_ned_frd)))
    msg.header.stamp_ns, msg.header.frame_id = int(m.timestamp_sample) * 1000, "map"
    return msg, int(m.reset_counter)


class VehicleOdometryInput:
    """One odometry topic as an intake of `service.node`: converted, checked by the parser, stitched into segments."""

    def __init__(self, key: str, convert: Callable[[bytes], tuple[pb.Odometry | None, int | None] | None],
                 rule: SegmentRule | None = None) -> None:
        """`convert`: a payload as (wire Odometry or None where invalid, reset counter or None), or None where the
        payload carries no odometry (a /tf message of other links: skipped, not counted)."""
        self.key, self.convert, self.rule = key, convert, rule or SegmentRule()
        self.segments: OdometrySegments | None = None

    def intakes(self, parser: InputParser) -> dict[str, tuple[Any, str, bool, int]]:
        self.segments = OdometrySegments(self.rule, lambda _: parser.drops.drop("odometry/segment"))
        return {self.key: (lambda payload: self.take(parser, payload), "odometry", False, 256)}

    def take(self, parser: InputParser, payload: bytes) -> OdometryIn | None:
        """The service's odometry event of a payload, or None (counted): not CDR of the type (`odometry/not_cdr`),
        invalid (`odometry/nan`), or refused by the parser."""
        assert self.segments is not None, "intakes() first"
        try:
            converted = self.convert(payload)
        except Exception as exc:  # noqa: BLE001 - rosbags raises several types for bytes that are not this CDR
            parser.drops.drop("odometry/not_cdr", str(exc)[:80])
            return None
        if converted is None:
            return None
        msg, reset_counter = converted
        if msg is None:
            parser.drops.drop("odometry/nan", "PX4 odometry with an unknown frame or an invalid pose")
            return None
        ev = parser.odometry(msg.SerializeToString())
        if ev is None:
            return None
        return replace(ev, T_map_body=self.segments(ev.stamp_ns, ev.T_map_body, reset_counter))
