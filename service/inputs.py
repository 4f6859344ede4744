"""Parsing and checking every input on the wire before it reaches the worker.

Each `parse_*` takes the raw payload bytes and returns a typed event, or None after counting the reason in a
`DropCounter` ("<key>/<kind>": not_protobuf, nan, bad_shape, bad_image, out_of_order, unknown_camera,
unknown_frame, empty). Nothing here raises on bad input: the service never dies of what it is sent.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from google.protobuf.message import DecodeError

from service.health import DropCounter
from service.planning import GoalSpec
from service.recording import matrix_from_pose
from service.wire.macroloc.v1 import macroloc_pb2 as pb

FEATURE_TYPES = {"door", "window"}
OBS_FRAMES = {"map", "body", "cam_left"}
MAX_IMAGE_PIXELS = 4096 * 4096


@dataclass(frozen=True)
class OdometryIn:
    stamp_ns: int
    T_map_body: np.ndarray  # (4, 4)


@dataclass(frozen=True)
class Observation:
    """One observed door/window: corners (4, 3) or only a centroid (3,), in the event's frame, metres."""

    type: str
    corners: np.ndarray | None
    centroid: np.ndarray
    id: str = ""


@dataclass(frozen=True)
class ObservationsIn:
    stamp_ns: int
    frame_id: str  # "map" | "body" | "cam_left"
    features: list[Observation] = field(default_factory=list)


@dataclass(frozen=True)
class StereoIn:
    stamp_ns: int
    frame: pb.StereoFrame
    received_ns: int  # time.monotonic_ns() when it arrived, for frame-in -> pose-out latency


@dataclass(frozen=True)
class ImuIn:
    stamp_ns: int
    accel_mps2: np.ndarray  # (3,) body frame
    gyro_radps: np.ndarray  # (3,) body frame


@dataclass(frozen=True)
class GoalIn:
    goal: GoalSpec
    start_cad: np.ndarray | None = None


def _xyz(v: pb.Vector3) -> np.ndarray:
    return np.array([v.x, v.y, v.z], float)


def _pose_ok(pose: pb.Pose) -> bool:
    values = [pose.position.x, pose.position.y, pose.position.z, pose.qw, pose.qx, pose.qy, pose.qz]
    return bool(np.isfinite(values).all()) and abs(float(np.linalg.norm(values[3:])) - 1.0) < 1e-3


class InputParser:
    """Parses the payloads of one vehicle's input keys; keeps the last stamp per key to reject reordering."""

    def __init__(self, cameras: list[str], drops: DropCounter) -> None:
        self.cameras = set(cameras)
        self.drops = drops
        self._last_stamp: dict[str, int] = {}

    def _decode(self, key: str, cls: type, payload: bytes):  # noqa: ANN206 - the message class given
        msg = cls()
        try:
            msg.ParseFromString(payload)
        except (DecodeError, RuntimeWarning, ValueError) as exc:
            self.drops.drop(f"{key}/not_protobuf", str(exc)[:80])
            return None
        return msg

    def _in_order(self, key: str, stamp_ns: int) -> bool:
        last = self._last_stamp.get(key)
        if last is not None and stamp_ns <= last:
            self.drops.drop(f"{key}/out_of_order", f"stamp {stamp_ns} after {last}")
            return False
        self._last_stamp[key] = stamp_ns
        return True

    def odometry(self, payload: bytes) -> OdometryIn | None:
        msg = self._decode("odometry", pb.Odometry, payload)
        if msg is None:
            return None
        if not msg.HasField("T_map_body") or not _pose_ok(msg.T_map_body):
            self.drops.drop("odometry/nan", "pose missing, not finite or quaternion not unit")
            return None
        if not self._in_order("odometry", msg.header.stamp_ns):
            return None
        return OdometryIn(msg.header.stamp_ns, matrix_from_pose(msg.T_map_body))

    def imu(self, payload: bytes) -> ImuIn | None:
        msg = self._decode("imu", pb.Imu, payload)
        if msg is None:
            return None
        accel, gyro = _xyz(msg.accel_mps2), _xyz(msg.gyro_radps)
        if not (np.isfinite(accel).all() and np.isfinite(gyro).all()):
            self.drops.drop("imu/nan")
            return None
        if not self._in_order("imu", msg.header.stamp_ns):
            return None
        return ImuIn(msg.header.stamp_ns, accel, gyro)

    def observations(self, payload: bytes) -> ObservationsIn | None:
        msg = self._decode("observations", pb.ObservedFeatures, payload)
        if msg is None:
            return None
        frame = msg.header.frame_id or "map"
        if frame not in OBS_FRAMES:
            self.drops.drop("observations/unknown_frame", repr(frame))
            return None
        features = []
        for f in msg.features:
            corners = np.array([_xyz(c) for c in f.corners], float).reshape(-1, 3)
            centroid = corners.mean(axis=0) if len(corners) else _xyz(f.centroid)
            if f.type not in FEATURE_TYPES or len(corners) not in (0, 4) or (not len(corners)
                                                                            and not f.HasField("centroid")):
                self.drops.drop("observations/bad_shape", f"type {f.type!r} with {len(corners)} corners")
                continue
            if not (np.isfinite(corners).all() and np.isfinite(centroid).all()):
                self.drops.drop("observations/nan")
                continue
            features.append(Observation(f.type, corners if len(corners) else None, centroid, f.id))
        if not self._in_order("observations", msg.header.stamp_ns):
            return None
        return ObservationsIn(msg.header.stamp_ns, frame, features)

    def stereo(self, payload: bytes, received_ns: int) -> StereoIn | None:
        msg = self._decode("stereo", pb.StereoFrame, payload)
        if msg is None:
            return None
        if msg.camera_id not in self.cameras:
            self.drops.drop("stereo/unknown_camera", repr(msg.camera_id))
            return None
        if not (_image_ok(msg.left) and _image_ok(msg.right)) or \
                (msg.left.width, msg.left.height) != (msg.right.width, msg.right.height):
            self.drops.drop("stereo/bad_image", f"{msg.left.width}x{msg.left.height} / "
                                                f"{msg.right.width}x{msg.right.height}")
            return None
        if msg.HasField("depth") and (msg.depth.encoding != pb.Image.RAW_DEPTH_F32 or not _image_ok(msg.depth)):
            self.drops.drop("stereo/bad_depth", f"{msg.depth.width}x{msg.depth.height} encoding {msg.depth.encoding}")
            return None
        if not self._in_order(f"stereo/{msg.camera_id}", msg.header.stamp_ns):
            return None
        return StereoIn(msg.header.stamp_ns, msg, received_ns)

    def goal(self, payload: bytes) -> GoalIn | None:
        msg = self._decode("goal", pb.Goal, payload)
        if msg is None:
            return None
        target = msg.WhichOneof("target")
        if target is None:
            self.drops.drop("goal/empty")
            return None
        start = _xyz(msg.start_cad) if msg.has_start else None
        if start is not None and not np.isfinite(start).all():
            self.drops.drop("goal/nan")
            return None
        if target == "position_cad":
            position = _xyz(msg.position_cad)
            if not np.isfinite(position).all():
                self.drops.drop("goal/nan")
                return None
            return GoalIn(GoalSpec(position_cad=position), start)
        if target == "feature_id":
            return GoalIn(GoalSpec(feature_id=msg.feature_id), start)
        return GoalIn(GoalSpec(space_name=msg.space_name), start)


RAW_BYTES_PER_PIXEL = {pb.Image.RAW_MONO8: 1, pb.Image.RAW_BGR8: 3, pb.Image.RAW_DEPTH_F32: 4}


def _image_ok(image: pb.Image) -> bool:
    """Plausible sizes: positive and bounded; raw images carry exactly width x height x bytes-per-pixel."""
    if not (image.width > 0 and image.height > 0 and image.width * image.height <= MAX_IMAGE_PIXELS):
        return False
    if image.encoding in RAW_BYTES_PER_PIXEL:
        return len(image.data) == image.width * image.height * RAW_BYTES_PER_PIXEL[image.encoding]
    return image.encoding in (pb.Image.PNG, pb.Image.JPEG) and len(image.data) > 0
