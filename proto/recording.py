"""Recorded flights: MCAP files of the wire contract's protobuf messages, written and read back.

Topics (each a `macroloc.v1` message, protobuf encoding, log time = the message's stamp in ns):
  "/stereo"                  StereoFrame   left/right images + CameraInfo (incl. T_body_cam, baseline)
  "/imu"                     Imu           body frame (x forward, y left, z up), specific force and rate
  "/odometry"                Odometry      the vehicle's own odometry (T_map_body, map frame z up), where the
                                           vehicle has one (e.g. `macroloc demo --record`); optional
  "/ground_truth"            GroundTruth   one per stereo frame, same stamp (simulated flights only)
  "/ground_truth/instances"  Image         instance mask of the left image, same stamp: 0 = none,
                                           k = features_cam[k - 1] of that frame's GroundTruth (PNG, mono8)
Metadata record "macroloc": {"building", "building_sha256", "seed", "storey", "duration_s"} (strings).

`FlightWriter` writes, `read_flight(path)` yields one `FlightFrame` per stereo frame with its ground truth
and the IMU and odometry samples since the previous frame; `read_messages` gives every message in log-time order.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer
from scipy.spatial.transform import Rotation

from macroloc.graph.errors import UserInputError
from macroloc.perception.image_header import DEFAULT_MAX_PIXELS as DEFAULT_MAX_IMAGE_PIXELS
from macroloc.perception.image_header import ImageHeaderError, check_encoded
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb

log = logging.getLogger(__name__)

TOPIC_STEREO = "/stereo"
TOPIC_IMU = "/imu"
TOPIC_ODOMETRY = "/odometry"
TOPIC_GROUND_TRUTH = "/ground_truth"
TOPIC_INSTANCES = "/ground_truth/instances"
METADATA_NAME = "macroloc"
MESSAGE_TYPES: dict[str, Any] = {
    cls.DESCRIPTOR.full_name: cls
    for cls in (pb.StereoFrame, pb.Imu, pb.GroundTruth, pb.Image, pb.Odometry, pb.ObservedFeatures,
                pb.PoseEstimate, pb.Goal, pb.Waypoints, pb.Diagnostics, pb.ServiceStatus)
}


# --- conversions between numpy and the wire messages -------------------------------------------------------


def pose_from_matrix(T_a_b: np.ndarray) -> pb.Pose:
    """A 4x4 rigid transform T_a_b as a Pose (position in metres, unit quaternion w, x, y, z)."""
    return poses_from_matrices(np.asarray(T_a_b, float)[None])[0]


def poses_from_matrices(T_a_b: np.ndarray) -> list[pb.Pose]:
    """`pose_from_matrix` of each of N transforms (N, 4, 4), the rotations converted at once."""
    T = np.asarray(T_a_b, float).reshape(-1, 4, 4)
    if len(T) == 0:
        return []
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # scipy: x, y, z, w
    return [pb.Pose(position=pb.Vector3(x=t[0], y=t[1], z=t[2]), qw=qk[3], qx=qk[0], qy=qk[1], qz=qk[2])
            for t, qk in zip(T[:, :3, 3].tolist(), q.tolist(), strict=True)]


def matrix_from_pose(pose: pb.Pose) -> np.ndarray:
    """The 4x4 transform T_a_b of a Pose (inverse of `pose_from_matrix`)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([pose.qx, pose.qy, pose.qz, pose.qw]).as_matrix()  # scipy: x, y, z, w
    T[:3, 3] = (pose.position.x, pose.position.y, pose.position.z)
    return T


def vector3(v: np.ndarray) -> pb.Vector3:
    return pb.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def encode_image(image: np.ndarray, encoding: str = "png", png_level: int = 1, jpeg_quality: int = 92) -> pb.Image:
    """An image as a wire Image.

    image: (H, W, 3) uint8 BGR, (H, W) uint8 mono, or (H, W) float32 depth in metres (always RAW_DEPTH_F32).
    encoding: "png" | "jpeg" | "raw" (RAW_BGR8 / RAW_MONO8).
    """
    h, w = image.shape[:2]
    if image.dtype == np.float32:
        return pb.Image(width=w, height=h, encoding=pb.Image.RAW_DEPTH_F32, data=image.astype("<f4").tobytes())
    if image.dtype != np.uint8:
        raise ValueError(f"images are uint8 (BGR or mono) or float32 depth, not {image.dtype}")
    if encoding == "raw":
        enc = pb.Image.RAW_BGR8 if image.ndim == 3 else pb.Image.RAW_MONO8
        return pb.Image(width=w, height=h, encoding=enc, data=np.ascontiguousarray(image).tobytes())
    if encoding == "png":
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, png_level])
        return pb.Image(width=w, height=h, encoding=pb.Image.PNG, data=buf.tobytes())
    if encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        return pb.Image(width=w, height=h, encoding=pb.Image.JPEG, data=buf.tobytes())
    raise ValueError(f"unknown image encoding {encoding!r} (png, jpeg, raw)")


def decode_image(image: pb.Image, max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> np.ndarray:
    """A wire Image as numpy: (H, W, 3) uint8 BGR, (H, W) uint8 mono, or (H, W) float32 metres for depth.

    Nothing is decoded that is larger than `max_pixels` or whose size differs from the declared one: raw data
    must hold exactly the declared pixels, and a PNG/JPEG's header (read first, perception.image_header) must
    declare them; UserInputError otherwise (a recording's image, or the service's after its input checks)."""
    h, w = image.height, image.width
    if not (w > 0 and h > 0 and w * h <= max_pixels):
        raise UserInputError(f"image of {w}x{h} pixels declared: not positive or over the cap of {max_pixels}")
    raw_bytes = {pb.Image.RAW_DEPTH_F32: 4, pb.Image.RAW_BGR8: 3, pb.Image.RAW_MONO8: 1}.get(image.encoding)
    if raw_bytes is not None and len(image.data) != w * h * raw_bytes:
        raise UserInputError(f"raw image of {len(image.data)} bytes declared {w}x{h} pixels")
    if image.encoding == pb.Image.RAW_DEPTH_F32:
        return np.frombuffer(image.data, dtype="<f4").reshape(h, w).astype(np.float32)
    if image.encoding == pb.Image.RAW_BGR8:
        return np.frombuffer(image.data, dtype=np.uint8).reshape(h, w, 3)
    if image.encoding == pb.Image.RAW_MONO8:
        return np.frombuffer(image.data, dtype=np.uint8).reshape(h, w)
    if image.encoding in (pb.Image.PNG, pb.Image.JPEG):
        try:
            check_encoded(image.data, max_pixels, (w, h))
        except ImageHeaderError as exc:
            raise UserInputError(f"recorded image refused before decoding: {exc}") from None
        out = cv2.imdecode(np.frombuffer(image.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if out is None or out.shape[:2] != (h, w):
            raise UserInputError("recorded image cannot be decoded")
        return out
    raise UserInputError(f"recorded image has unsupported encoding {image.encoding}")


# --- writing -------------------------------------------------------------------------------------------------


@dataclass
class FlightMetadata:
    """The "macroloc" metadata record of a flight (stored as strings in MCAP)."""

    building: str = ""
    building_sha256: str = ""
    seed: int = 0
    storey: str = ""
    duration_s: float = 0.0
    extra: dict[str, str] = field(default_factory=dict)

    def to_record(self) -> dict[str, str]:
        return dict(self.extra, building=self.building, building_sha256=self.building_sha256, seed=str(self.seed),
                    storey=self.storey, duration_s=f"{self.duration_s:.6f}")

    @classmethod
    def from_record(cls, record: dict[str, str]) -> FlightMetadata:
        known = {"building", "building_sha256", "seed", "storey", "duration_s"}
        return cls(building=record.get("building", ""), building_sha256=record.get("building_sha256", ""),
                   seed=int(record.get("seed", "0") or 0), storey=record.get("storey", ""),
                   duration_s=float(record.get("duration_s", "0") or 0.0),
                   extra={k: v for k, v in record.items() if k not in known})


class FlightWriter:
    """Writes a flight recording. Use as a context manager; `metadata` may be set any time before closing."""

    def __init__(self, path: str | Path, metadata: FlightMetadata | None = None, compress: bool = True) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.metadata = metadata or FlightMetadata()
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD if compress else CompressionType.NONE)
        self.counts: dict[str, int] = {}

    def write(self, topic: str, message: Any, stamp_ns: int) -> None:
        """Any protobuf message on `topic`, logged and published at `stamp_ns`."""
        seq = self.counts.get(topic, 0)
        self._writer.write_message(topic, message, log_time=int(stamp_ns), publish_time=int(stamp_ns), sequence=seq)
        self.counts[topic] = seq + 1

    def write_stereo(self, frame: pb.StereoFrame) -> None:
        self.write(TOPIC_STEREO, frame, frame.header.stamp_ns)

    def write_imu(self, sample: pb.Imu) -> None:
        self.write(TOPIC_IMU, sample, sample.header.stamp_ns)

    def write_odometry(self, odometry: pb.Odometry) -> None:
        self.write(TOPIC_ODOMETRY, odometry, odometry.header.stamp_ns)

    def write_ground_truth(self, truth: pb.GroundTruth, instances: pb.Image | None = None) -> None:
        self.write(TOPIC_GROUND_TRUTH, truth, truth.header.stamp_ns)
        if instances is not None:
            self.write(TOPIC_INSTANCES, instances, truth.header.stamp_ns)

    def close(self) -> None:
        if self._file.closed:
            return
        self._writer.add_metadata(METADATA_NAME, self.metadata.to_record())
        self._writer.finish()
        self._file.close()

    def __enter__(self) -> FlightWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def depth_image_mm(depth_m: np.ndarray) -> pb.Image:
    """A ground-truth depth image (H, W) in metres as recorded: still float32 metres, but in 1 mm steps, which the
    MCAP chunk compression shrinks ~40x."""
    return encode_image((np.round(np.asarray(depth_m) * 1000.0) / 1000.0).astype(np.float32))


def add_features_in_view(truth: pb.GroundTruth, features: list[Any]) -> None:
    """Append the simulator's features in view (sim.groundtruth.FeatureInView: type, id, box, corners in the
    left camera frame and their visibility) to a GroundTruth message, in order."""
    for f in features:
        obs = truth.features_cam.add(type=f.type, score=1.0, id=f.id, box_xyxy=[float(v) for v in f.box_xyxy])
        for c in f.corners_cam:
            obs.corners.add(x=float(c[0]), y=float(c[1]), z=float(c[2]))
        truth.corner_visible.extend(bool(v) for v in f.corner_visible)


# --- reading -------------------------------------------------------------------------------------------------


@dataclass
class RecordedMessage:
    topic: str
    stamp_ns: int
    message: Any  # a macroloc_pb2 message instance


@dataclass
class FlightFrame:
    """One stereo frame of a recording with what belongs to it.

    imu: the IMU samples with stamps in (previous frame's stamp, this frame's stamp].
    odometry: the vehicle's own odometry samples in the same interval (empty where it recorded none).
    ground_truth / instances: None in a real (non-simulated) recording.
    """

    stamp_ns: int
    stereo: pb.StereoFrame
    imu: list[pb.Imu] = field(default_factory=list)
    odometry: list[pb.Odometry] = field(default_factory=list)
    ground_truth: pb.GroundTruth | None = None
    instances: pb.Image | None = None
    _images: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def images(self) -> tuple[np.ndarray, np.ndarray]:
        """The left and right images decoded, once: later calls return the same arrays (which the frame's one SGBM,
        perception.stereo.FrameDisparity, knows the frame by)."""
        if self._images is None:
            self._images = (decode_image(self.stereo.left), decode_image(self.stereo.right))
        return self._images


def _open_reader(path: str | Path):  # noqa: ANN202 - mcap's reader type

    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"recording not found: {path}")
    fh = open(path, "rb")  # noqa: SIM115 - the caller closes it
    try:
        return fh, make_reader(fh)
    except Exception as exc:  # mcap raises its own error types for a file that is not MCAP
        fh.close()
        raise UserInputError(f"{path} is not an MCAP recording: {exc}") from None


def read_metadata(path: str | Path) -> FlightMetadata:
    """The "macroloc" metadata record of a recording (defaults when it has none)."""
    fh, reader = _open_reader(path)
    with fh:
        for record in reader.iter_metadata():
            if record.name == METADATA_NAME:
                return FlightMetadata.from_record(dict(record.metadata))
    return FlightMetadata()


def stereo_frame_count(path: str | Path) -> int | None:
    """The recording's number of stereo frames from its summary (None where it has none)."""
    fh, reader = _open_reader(path)
    with fh:
        try:
            summary = reader.get_summary()
        except Exception:  # a file without a summary section (e.g. cut short) still reads message by message
            return None
        if summary is None or summary.statistics is None:
            return None
        ids = [c.id for c in summary.channels.values() if c.topic == TOPIC_STEREO]
        return sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)


def read_messages(path: str | Path, topics: list[str] | None = None) -> Iterator[RecordedMessage]:
    """Every message of the recording (or of `topics`) in log-time order, parsed into macroloc_pb2 types."""
    fh, reader = _open_reader(path)
    with fh:
        for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=True):
            cls = MESSAGE_TYPES.get(schema.name) if schema is not None else None
            if cls is None:
                log.debug("skipping message of unknown schema on %s", channel.topic)
                continue
            msg = cls()
            msg.ParseFromString(message.data)
            yield RecordedMessage(channel.topic, int(message.log_time), msg)


def read_flight(path: str | Path) -> Iterator[FlightFrame]:
    """The recording as stereo frames, each with its IMU and odometry samples and (simulated flights) ground
    truth."""
    pending_imu: list[pb.Imu] = []
    pending_odometry: list[pb.Odometry] = []
    truths: dict[int, pb.GroundTruth] = {}
    masks: dict[int, pb.Image] = {}
    frame: FlightFrame | None = None
    for rec in read_messages(path):
        if rec.topic == TOPIC_IMU:
            pending_imu.append(rec.message)
        elif rec.topic == TOPIC_ODOMETRY:
            pending_odometry.append(rec.message)
        elif rec.topic == TOPIC_GROUND_TRUTH:
            truths[rec.stamp_ns] = rec.message
        elif rec.topic == TOPIC_INSTANCES:
            masks[rec.stamp_ns] = rec.message
        elif rec.topic == TOPIC_STEREO:
            if frame is not None:
                yield _complete(frame, truths, masks)
            frame = FlightFrame(rec.stamp_ns, rec.message, imu=pending_imu, odometry=pending_odometry)
            pending_imu, pending_odometry = [], []
    if frame is not None:
        yield _complete(frame, truths, masks)


def _complete(frame: FlightFrame, truths: dict[int, pb.GroundTruth], masks: dict[int, pb.Image]) -> FlightFrame:
    frame.ground_truth = truths.pop(frame.stamp_ns, None)
    frame.instances = masks.pop(frame.stamp_ns, None)
    return frame
