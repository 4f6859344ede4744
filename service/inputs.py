"""Parsing and checking every input on the wire before it reaches the worker: one place per message type.

Each `InputParser` method takes the raw payload bytes and returns a typed event, or None after counting the
reason in a `DropCounter` as "<key>/<kind>" (logged once per kind). The kinds: too_large (payload bytes over
the cap), not_protobuf, unknown_fields (bytes of another message type or garbage: fields this type lacks),
wrong_frame (a goal whose header frame_id is not "cad": another message type), nan (not finite, or a
quaternion not unit), out_of_bounds (a position outside the model's box grown by a margin, a sighting beyond
sensor range), implausible (an IMU sample beyond what an IMU measures), too_many (features), bad_shape,
unknown_camera, unknown_frame, bad_image, image_header (a PNG/JPEG whose header is unreadable or differs from
the declared size), image_too_large (over the pixel cap), size_mismatch (left and right images differ),
bad_camera_info (intrinsics or baseline not positive and finite, or its size not the images'), bad_depth,
empty (a goal without a target), and the stamps' kinds (`service.stamps.StampGate`: future_stamp,
out_of_order, clock_back, clock_reset). Images are sized from their headers and never decoded here. Nothing
here raises on bad input: the service never dies of what it is sent. The limits: `InputLimits` (config
section [inputs]).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from google.protobuf.message import DecodeError, Message

from macroloc.graph.planning import GoalSpec
from macroloc.perception.image_header import DEFAULT_MAX_PIXELS, ImageHeaderError, check_encoded
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose
from macroloc.service.health import DropCounter
from macroloc.service.stamps import StampGate

FEATURE_TYPES = {"door", "window"}
OBS_FRAMES = {"map", "body", "cam_left"}
MAX_IMAGE_PIXELS = DEFAULT_MAX_PIXELS


@dataclass(frozen=True)
class InputLimits:
    """What the parser takes (service.config.InputsConfig; `limits_from_config` builds one for a model).

    `bounds_cad`: (lo (3,), hi (3,)) the model's box grown by the margin, CAD frame, metres (None: unbounded);
    `max_odometry_m`: the farthest an odometry position may lie from its frame's origin, metres."""

    max_image_pixels: int = MAX_IMAGE_PIXELS
    max_stereo_bytes: int = 128 * 2**20
    max_message_bytes: int = 2**20
    max_features: int = 256
    bounds_cad: tuple[np.ndarray, np.ndarray] | None = None
    max_odometry_m: float = math.inf
    max_observation_range_m: float = 50.0
    max_accel_mps2: float = 160.0
    max_gyro_radps: float = 35.0
    clock_reset_ns: int = 2_000_000_000
    max_clock_ahead_ns: int = 86_400 * 10**9

    def inside_cad(self, xyz_cad: np.ndarray) -> bool:
        """True when the CAD point (3,) is finite and within `bounds_cad`."""
        xyz = np.asarray(xyz_cad, float)
        if not np.isfinite(xyz).all():
            return False
        if self.bounds_cad is None:
            return True
        lo, hi = self.bounds_cad
        return bool(((xyz >= lo) & (xyz <= hi)).all())


def limits_from_config(cfg, model=None) -> InputLimits:  # noqa: ANN001 - service.config.InputsConfig, BuildingModel
    """The parser's limits: the config's caps, and bounds from the model's doors and windows grown by the
    margin (odometry: the box's diagonal plus the margin from the odometry frame's origin, the take-off point)."""
    bounds, max_odometry_m = None, math.inf
    if model is not None and len(model.features):
        corners = np.concatenate([np.asarray(f.corners_cad, float).reshape(-1, 3) for f in model.features])
        lo, hi = corners.min(axis=0) - cfg.position_margin_m, corners.max(axis=0) + cfg.position_margin_m
        bounds = (lo, hi)
        max_odometry_m = float(np.linalg.norm(hi - lo))
    return InputLimits(max_image_pixels=cfg.max_image_pixels, max_stereo_bytes=cfg.max_stereo_bytes,
                       max_message_bytes=cfg.max_message_bytes, max_features=cfg.max_features, bounds_cad=bounds,
                       max_odometry_m=max_odometry_m, max_observation_range_m=cfg.max_observation_range_m,
                       max_accel_mps2=cfg.max_accel_mps2, max_gyro_radps=cfg.max_gyro_radps,
                       clock_reset_ns=int(cfg.clock_reset_s * 1e9), max_clock_ahead_ns=int(cfg.max_clock_ahead_s * 1e9))


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


@dataclass(frozen=True)
class PriorIn:
    """The operator's prior (graph.prior): the body's pose in the CAD frame at `stamp_ns` (0: now) with its
    horizontal and heading sigmas, and/or a storey's name."""

    stamp_ns: int
    T_cad_body: np.ndarray | None  # (4, 4)
    sigma_xy_m: float
    sigma_yaw_rad: float
    storey: str | None


DEFAULT_PRIOR_SIGMA_XY_M = 0.5  # rviz's 2D Pose Estimate sends these (covariance 0.25 m^2, 0.0685 rad^2)
DEFAULT_PRIOR_SIGMA_YAW_RAD = 0.2617


@dataclass(frozen=True)
class ClockReset:
    """A key's stamps moved to a new time base (vehicle clock reset): the worker forgets stamp-ordered state."""

    key: str
    stamp_ns: int


def _xyz(v: pb.Vector3) -> np.ndarray:
    return np.array([v.x, v.y, v.z], float)


def _norm(v: np.ndarray) -> float:
    """Euclidean norm of a finite vector; inf (not an overflow warning) for one such as (1e300, 0, 0)."""
    with np.errstate(over="ignore"):
        return float(np.linalg.norm(v))


def _pose_ok(pose: pb.Pose) -> bool:
    values = [pose.position.x, pose.position.y, pose.position.z, pose.qw, pose.qx, pose.qy, pose.qz]
    return bool(np.isfinite(values).all()) and abs(float(np.linalg.norm(values[3:])) - 1.0) < 1e-3


def _has_unknown_fields(msg: Message) -> bool:
    """True when parsing kept fields the message type does not define (at any depth): bytes of another type or
    garbage. protobuf keeps them; discarding them from a copy and comparing sizes finds them at every level."""
    bare = type(msg)()
    bare.CopyFrom(msg)
    bare.DiscardUnknownFields()
    return bare.ByteSize() != msg.ByteSize()


class InputParser:
    """Parses and checks the payloads of one vehicle's input keys (see the module doc)."""

    def __init__(self, cameras: list[str], drops: DropCounter, limits: InputLimits | None = None,
                 on_clock_reset: Callable[[str, int], None] | None = None) -> None:
        self.cameras = set(cameras)
        self.drops = drops
        self.limits = limits or InputLimits()
        self.stamps = StampGate(drops, self.limits.clock_reset_ns, self.limits.max_clock_ahead_ns, on_clock_reset)

    def _decode(self, key: str, cls: type, payload: bytes, frames: set[str] | None = None):  # noqa: ANN206
        """The message of type `cls`, or None (counted): too large, not protobuf, unknown fields, or a header
        frame_id outside `frames` (empty is always allowed)."""
        cap = self.limits.max_stereo_bytes if key == "stereo" else self.limits.max_message_bytes
        if len(payload) > cap:
            self.drops.drop(f"{key}/too_large", f"{len(payload)} bytes, cap {cap}")
            return None
        msg = cls()
        try:
            msg.ParseFromString(payload)
        except (DecodeError, RuntimeWarning, ValueError) as exc:
            self.drops.drop(f"{key}/not_protobuf", str(exc)[:80])
            return None
        if _has_unknown_fields(msg):
            self.drops.drop(f"{key}/unknown_fields", f"not a {cls.__name__}: fields it does not define")
            return None
        if frames is not None and msg.header.frame_id and msg.header.frame_id not in frames:
            self.drops.drop(f"{key}/wrong_frame", f"frame_id {msg.header.frame_id[:40]!r}")
            return None
        return msg

    def odometry(self, payload: bytes) -> OdometryIn | None:
        msg = self._decode("odometry", pb.Odometry, payload)
        if msg is None:
            return None
        if not msg.HasField("T_map_body") or not _pose_ok(msg.T_map_body) or \
                not np.isfinite(np.asarray(msg.covariance, float)).all():
            self.drops.drop("odometry/nan", "pose missing, not finite or quaternion not unit")
            return None
        if _norm(_xyz(msg.T_map_body.position)) > self.limits.max_odometry_m:
            self.drops.drop("odometry/out_of_bounds", f"position {_xyz(msg.T_map_body.position)} m from the origin")
            return None
        if not self.stamps.admit("odometry", msg.header.stamp_ns):
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
        if _norm(accel) > self.limits.max_accel_mps2 or _norm(gyro) > self.limits.max_gyro_radps:
            self.drops.drop("imu/implausible", f"|accel| {_norm(accel):.3g} m/s^2, |gyro| {_norm(gyro):.3g} rad/s")
            return None
        if not self.stamps.admit("imu", msg.header.stamp_ns):
            return None
        return ImuIn(msg.header.stamp_ns, accel, gyro)

    def observations(self, payload: bytes) -> ObservationsIn | None:
        msg = self._decode("observations", pb.ObservedFeatures, payload)
        if msg is None:
            return None
        frame = msg.header.frame_id or "map"
        if frame not in OBS_FRAMES:
            self.drops.drop("observations/unknown_frame", repr(frame[:40]))
            return None
        if len(msg.features) > self.limits.max_features:
            self.drops.drop("observations/too_many", f"{len(msg.features)} features, cap {self.limits.max_features}")
            return None
        reach_m = self.limits.max_odometry_m if frame == "map" else self.limits.max_observation_range_m
        features = []
        for f in msg.features:
            corners = np.array([_xyz(c) for c in f.corners], float).reshape(-1, 3)
            with np.errstate(over="ignore", invalid="ignore"):  # huge corners give inf: refused below
                centroid = corners.mean(axis=0) if len(corners) else _xyz(f.centroid)
                spread_m = float(np.ptp(corners, axis=0).max()) if len(corners) else 0.0
            if f.type not in FEATURE_TYPES or len(corners) not in (0, 4) or (not len(corners)
                                                                            and not f.HasField("centroid")):
                self.drops.drop("observations/bad_shape", f"type {f.type[:20]!r} with {len(corners)} corners")
                continue
            if not (np.isfinite(corners).all() and np.isfinite(centroid).all()):
                self.drops.drop("observations/nan")
                continue
            if _norm(centroid) > reach_m or spread_m > 20.0:  # no door or window spans 20 m
                self.drops.drop("observations/out_of_bounds", f"{f.type} at {np.round(centroid, 1)} m ({frame})")
                continue
            features.append(Observation(f.type, corners if len(corners) else None, centroid, f.id))
        if not self.stamps.admit("observations", msg.header.stamp_ns):
            return None
        return ObservationsIn(msg.header.stamp_ns, frame, features)

    def stereo(self, payload: bytes, received_ns: int) -> StereoIn | None:
        """A frame whose images may be decoded: sizes declared, bounded, equal left and right, equal to the
        PNG/JPEG headers and to the camera info where one is sent. A frame without camera info is taken (it
        still gives a pose from the odometry) but cannot be perceived (service.frames)."""
        msg = self._decode("stereo", pb.StereoFrame, payload)
        if msg is None:
            return None
        if msg.camera_id not in self.cameras:
            self.drops.drop("stereo/unknown_camera", repr(msg.camera_id[:40]))
            return None
        left, right = msg.left, msg.right
        if (left.width, left.height) != (right.width, right.height):
            self.drops.drop("stereo/size_mismatch", f"{left.width}x{left.height} / {right.width}x{right.height}")
            return None
        if not (self._image_ok("stereo", left) and self._image_ok("stereo", right)):
            return None
        if msg.HasField("info") and not _camera_info_ok(msg.info, left):
            i = msg.info
            self.drops.drop("stereo/bad_camera_info", f"{i.width}x{i.height} fx {i.fx:.4g} fy {i.fy:.4g} "
                                                      f"baseline {i.baseline_m:.4g} m for {left.width}x{left.height}")
            return None
        if msg.HasField("depth") and (msg.depth.encoding != pb.Image.RAW_DEPTH_F32 or not self._image_ok(
                "stereo", msg.depth, count=False) or (msg.depth.width, msg.depth.height) != (left.width, left.height)):
            self.drops.drop("stereo/bad_depth", f"{msg.depth.width}x{msg.depth.height} encoding {msg.depth.encoding}")
            return None
        if not self.stamps.admit(f"stereo/{msg.camera_id}", msg.header.stamp_ns):
            return None
        return StereoIn(msg.header.stamp_ns, msg, received_ns)

    def _image_ok(self, key: str, image: pb.Image, count: bool = True) -> bool:
        """Decoding it is safe and gives the declared size: positive and capped sizes; raw images carry exactly
        width x height x bytes-per-pixel; PNG/JPEG headers say the declared size (read, not decoded).
        When not, counted as `<key>/bad_image`, image_too_large or image_header (unless `count` is off)."""
        w, h, cap = image.width, image.height, self.limits.max_image_pixels
        kind = "bad_image"
        if not (w > 0 and h > 0):
            if count:
                self.drops.drop(f"{key}/{kind}", f"{w}x{h}")
            return False
        if w * h > cap:
            if count:
                self.drops.drop(f"{key}/image_too_large", f"{w}x{h} declared, cap {cap} pixels")
            return False
        if image.encoding in RAW_BYTES_PER_PIXEL:
            ok = len(image.data) == w * h * RAW_BYTES_PER_PIXEL[image.encoding]
            if not ok and count:
                self.drops.drop(f"{key}/{kind}", f"{len(image.data)} bytes for {w}x{h} raw")
            return ok
        if image.encoding not in (pb.Image.PNG, pb.Image.JPEG):
            if count:
                self.drops.drop(f"{key}/{kind}", f"encoding {image.encoding}")
            return False
        try:
            check_encoded(image.data, cap, (w, h))
        except ImageHeaderError as exc:
            if count:
                self.drops.drop(f"{key}/{'image_too_large' if 'cap' in str(exc) else 'image_header'}", str(exc))
            return False
        return True

    def goal(self, payload: bytes) -> GoalIn | None:
        """A goal (CAD frame) whose position and start lie within the model's bounds and whose stamp is not ahead
        of this machine's clock as every input's (`StampGate.not_ahead`); no stamp order (goals may come unstamped:
        stamp 0)."""
        msg = self._decode("goal", pb.Goal, payload, {"cad"})
        if msg is None or not self.stamps.not_ahead("goal", msg.header.stamp_ns):
            return None
        target = msg.WhichOneof("target")
        if target is None:
            self.drops.drop("goal/empty")
            return None
        start = _xyz(msg.start_cad) if msg.has_start else None
        position = _xyz(msg.position_cad) if target == "position_cad" else None
        for xyz in (start, position):
            if xyz is None:
                continue
            if not np.isfinite(xyz).all():
                self.drops.drop("goal/nan")
                return None
            if not self.limits.inside_cad(xyz):
                self.drops.drop("goal/out_of_bounds", f"{np.round(xyz, 1)} m outside the model")
                return None
        if target == "position_cad":
            return GoalIn(GoalSpec(position_cad=position), start)
        name = msg.feature_id if target == "feature_id" else msg.space_name
        if not name or len(name) > 256:
            self.drops.drop("goal/empty", f"{target} of {len(name)} characters")
            return None
        if target == "feature_id":
            return GoalIn(GoalSpec(feature_id=name), start)
        return GoalIn(GoalSpec(space_name=name), start)


    def prior(self, payload: bytes) -> PriorIn | None:
        """The operator's prior, a PoseEstimate (frame cad): `T_cad_body` (finite, unit quaternion, inside the model's
        bounds) with its covariance ([rot; trans] body tangent as every PoseEstimate's; the sigmas read from its
        yaw and horizontal variances, rviz's defaults where it has none), and/or `storey`; the stamp not ahead of
        this machine's clock. Neither pose nor storey: `initialpose/empty`."""
        msg = self._decode("initialpose", pb.PoseEstimate, payload, {"cad"})
        if msg is None or not self.stamps.not_ahead("initialpose", msg.header.stamp_ns):
            return None
        storey = msg.storey or None
        if storey is not None and len(storey) > 256:
            self.drops.drop("initialpose/empty", f"storey of {len(storey)} characters")
            return None
        T_cad_body = None
        if msg.HasField("T_cad_body"):
            if not _pose_ok(msg.T_cad_body):
                self.drops.drop("initialpose/nan", "pose not finite or quaternion not unit")
                return None
            T_cad_body = matrix_from_pose(msg.T_cad_body)
            if not self.limits.inside_cad(T_cad_body[:3, 3]):
                self.drops.drop("initialpose/out_of_bounds", f"{np.round(T_cad_body[:3, 3], 1)} m outside the model")
                return None
        elif storey is None:
            self.drops.drop("initialpose/empty", "neither a pose nor a storey")
            return None
        sigma_xy, sigma_yaw = DEFAULT_PRIOR_SIGMA_XY_M, DEFAULT_PRIOR_SIGMA_YAW_RAD
        if len(msg.covariance) == 36:
            cov = np.asarray(msg.covariance, float).reshape(6, 6)
            if not np.isfinite(cov).all() or (np.diag(cov) < 0).any():
                self.drops.drop("initialpose/nan", "covariance not finite or negative")
                return None
            if cov[3, 3] > 0 or cov[4, 4] > 0:
                sigma_xy = float(np.sqrt(max(cov[3, 3], cov[4, 4])))
            if cov[2, 2] > 0:
                sigma_yaw = float(np.sqrt(cov[2, 2]))
        return PriorIn(msg.header.stamp_ns, T_cad_body, sigma_xy, sigma_yaw, storey)


RAW_BYTES_PER_PIXEL = {pb.Image.RAW_MONO8: 1, pb.Image.RAW_BGR8: 3, pb.Image.RAW_DEPTH_F32: 4}


def _camera_info_ok(info: pb.CameraInfo, left: pb.Image) -> bool:
    """Intrinsics (px) and baseline (m) positive and finite, principal point on the image, the size the images'
    and T_body_cam (when given) a finite pose with a unit quaternion."""
    values = [info.fx, info.fy, info.cx, info.cy, info.baseline_m]
    if not np.isfinite(values).all() or info.fx <= 0 or info.fy <= 0 or info.baseline_m <= 0:
        return False
    if (info.width, info.height) != (left.width, left.height):
        return False
    if not (0 <= info.cx <= info.width and 0 <= info.cy <= info.height):
        return False
    return not info.HasField("T_body_cam") or _pose_ok(info.T_body_cam)
