"""ROS 2 bags as replay sources: a bag folder (`metadata.yaml` + `.db3` or `.mcap`), or one `.mcap` / `.db3` file of
ROS 2 messages (MCAP profile `ros2`, CDR), read with rosbags (no ROS installation) into `FlightFrame`s, the type the
native reader (service.recording.read_flight) yields, so the replay runs the same on both.

Topics (`RosTopics`, each named on the command line as `--topic NAME=/ros/topic`, else found by its common names):
left, right (sensor_msgs/Image or CompressedImage, required), imu (sensor_msgs/Imu, required), left_info and
right_info (sensor_msgs/CameraInfo; default: the image topic's `camera_info` beside it; none: the configured camera,
taken as rectified), odometry (nav_msgs/Odometry: the vehicle's own, optional) and truth (geometry_msgs/PoseStamped
of the body in the CAD frame, optional). Left and right are paired by equal header stamps; an image without its
partner is dropped and counted. A pair is emitted once the IMU, odometry and truth streams have reached its stamp
(or the bag ends, or MAX_PENDING pairs wait), with the IMU and odometry samples stamped in (previous pair, this
pair] and the truth pose nearest its stamp (within TRUTH_TOLERANCE_NS). The left camera's mounting: `/tf_static`
from the body frame (`base_link`) to the left camera info's (else image's) frame id, else the configuration
(service.config.CameraConfig).
"""

from __future__ import annotations

import bisect
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from graph.errors import UserInputError
from service.config import CameraConfig
from service.recording import FlightFrame, encode_image
from service.ros_in import (
    CameraCalibration,
    StereoRectifier,
    TransformTree,
    any_image_array,
    imu_message,
    odometry_message,
    pose_message,
    stamp_ns,
)
from service.wire.macroloc.v1 import macroloc_pb2 as pb

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
TOPIC_TYPES: dict[str, tuple[str, ...]] = {
    "left": IMAGE_TYPES, "right": IMAGE_TYPES, "imu": ("sensor_msgs/msg/Imu",),
    "left_info": ("sensor_msgs/msg/CameraInfo",), "right_info": ("sensor_msgs/msg/CameraInfo",),
    "odometry": ("nav_msgs/msg/Odometry",), "truth": ("geometry_msgs/msg/PoseStamped",),
}
REQUIRED = ("left", "right", "imu")
COMMON_NAMES: dict[str, tuple[str, ...]] = {
    "left": ("/camera/left/image_raw", "/cam0/image_raw", "/left/image_raw", "/stereo/left/image_raw",
             "/camera/left/image_rect", "/cam0/image_rect", "/left/image_rect", "/stereo/left/image_rect"),
    "right": ("/camera/right/image_raw", "/cam1/image_raw", "/right/image_raw", "/stereo/right/image_raw",
              "/camera/right/image_rect", "/cam1/image_rect", "/right/image_rect", "/stereo/right/image_rect"),
    "imu": ("/imu", "/imu0", "/imu/data", "/imu/data_raw", "/camera/imu"),
    "odometry": ("/odom", "/odometry"),
}
TF_STATIC = "/tf_static"
BODY_FRAME = "base_link"
TRUTH_TOLERANCE_NS = 5_000_000  # a truth pose further than 5 ms from a frame's stamp is not that frame's
MAX_PENDING = 300  # images waiting for their partner (older ones are dropped as unpaired), and pairs waiting for
#                   the other streams to reach their stamp (older ones go without: a stream that stops holds no frames)


@dataclass
class RosTopics:
    """The bag's topic of each input (None: absent)."""

    left: str | None = None
    right: str | None = None
    imu: str | None = None
    left_info: str | None = None
    right_info: str | None = None
    odometry: str | None = None
    truth: str | None = None

    @classmethod
    def parse(cls, pairs: list[str]) -> dict[str, str]:
        """`NAME=/ros/topic` strings as {NAME: topic}; a bad one is a UserInputError."""
        names = {f.name for f in fields(cls)}
        out: dict[str, str] = {}
        for pair in pairs:
            name, sep, topic = pair.partition("=")
            if not sep or name not in names or not topic:
                raise UserInputError(f"--topic takes NAME=/ros/topic with NAME one of {', '.join(sorted(names))}, "
                                     f"not {pair!r}")
            out[name] = topic if topic.startswith("/") else "/" + topic
        return out


@dataclass
class BagStats:
    """What the reader did: pairs emitted, images dropped without their partner, seconds spent reading."""

    frames: int = 0
    unpaired_left: int = 0
    unpaired_right: int = 0
    read_s: float = 0.0
    topics: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"frames": self.frames, "unpaired_left": self.unpaired_left, "unpaired_right": self.unpaired_right,
                "topics": self.topics}


def is_ros_bag(path: Path) -> bool:
    """A ROS 2 bag folder, a `.db3`, or an MCAP file whose profile is `ros2` (macroloc's own recordings are not)."""
    if path.is_dir():
        return (path / "metadata.yaml").exists()
    if path.suffix.lower() == ".db3":
        return True
    if path.suffix.lower() != ".mcap" or not path.is_file():
        return False
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        try:
            return make_reader(fh).get_header().profile == "ros2"
        except Exception:  # not MCAP: the native reader says so
            return False


def open_flight(path: Path, topics: dict[str, str] | None = None, camera: CameraConfig | None = None,
                stats: BagStats | None = None) -> Iterator[FlightFrame]:
    """The flight's frames from what `path` is: a ROS 2 bag (`read_ros_bag`; `camera`: the configured camera, for
    bags without camera info or /tf_static) or a macroloc recording."""
    if is_ros_bag(path):
        return read_ros_bag(path, topics or {}, camera, stats)
    if topics:
        raise UserInputError(f"--topic applies to ROS 2 bags; {path} is a macroloc recording")
    from service.recording import read_flight

    return read_flight(path)


def _open_reader(path: Path):  # noqa: ANN202 - rosbags' AnyReader
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:  # rosbags raises its own error types for a bag it cannot read
        raise UserInputError(f"{path} is not a readable ROS 2 bag: {exc}") from None
    return reader


def resolve_topics(bag_topics: dict[str, str], given: dict[str, str]) -> RosTopics:
    """Each input's topic: the given one (checked: present, of a type it accepts), else the first common name
    present with such a type; a required input missing is one UserInputError naming what the bag holds."""
    held = ", ".join(f"{t} ({m})" for t, m in sorted(bag_topics.items()))
    chosen: dict[str, str | None] = {}
    for name, types in TOPIC_TYPES.items():
        if name in given:
            topic = given[name]
            if bag_topics.get(topic) not in types:
                what = "not in the bag" if topic not in bag_topics else f"of type {bag_topics[topic]}"
                raise UserInputError(f"--topic {name}={topic} is {what} (wants {' or '.join(types)}); "
                                     f"the bag holds: {held}")
            chosen[name] = topic
        else:
            chosen[name] = next((t for t in _candidates(name, chosen) if bag_topics.get(t) in types), None)
    missing = [n for n in REQUIRED if chosen[n] is None]
    if missing:
        raise UserInputError(f"no {' / '.join(missing)} topic found (give --topic {missing[0]}=/ros/topic); "
                             f"the bag holds: {held}")
    return RosTopics(**chosen)


def _candidates(name: str, chosen: dict[str, str | None]) -> list[str]:
    if name in ("left_info", "right_info"):
        image = chosen[name.removesuffix("_info")]
        if image is None:
            return []
        base = image.removesuffix("/compressed").rsplit("/", 1)[0]
        return [f"{base}/camera_info"]
    names = list(COMMON_NAMES.get(name, ()))
    return names + [f"{n}/compressed" for n in names] if name in ("left", "right") else names


def read_ros_bag(path: Path, given: dict[str, str], camera: CameraConfig | None = None,
                 stats: BagStats | None = None) -> Iterator[FlightFrame]:
    """The bag's stereo pairs as FlightFrames (see module doc); `stats` is filled as it reads."""
    reader = _open_reader(path)
    try:
        bag_topics = {t: info.msgtype or "?" for t, info in reader.topics.items()}
        topics = resolve_topics(bag_topics, given)
        stats = stats if stats is not None else BagStats()
        stats.topics = {k: v for k, v in vars(topics).items() if v is not None}
        log.info("ROS 2 bag %s: %s", path.name, ", ".join(f"{k}={v}" for k, v in stats.topics.items()))
        wanted = {v for v in stats.topics.values()} | {TF_STATIC}
        connections = [c for c in reader.connections if c.topic in wanted]
        assembler = _Assembler(topics, camera or CameraConfig(), stats)
        start = time.perf_counter()
        for conn, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, conn.msgtype)
            ready = assembler.add(conn.topic, conn.msgtype, msg)
            stats.read_s += time.perf_counter() - start
            yield from ready
            start = time.perf_counter()
        yield from assembler.finish()
        stats.read_s += time.perf_counter() - start
    finally:
        reader.close()
    if stats.frames == 0:
        raise UserInputError(f"{path}: no left/right image pairs with equal stamps on {topics.left} and "
                             f"{topics.right}")
    if stats.unpaired_left or stats.unpaired_right:
        log.warning("%s: %d left and %d right images had no partner with the same stamp (dropped)", path.name,
                    stats.unpaired_left, stats.unpaired_right)


class _Assembler:
    """Messages in bag order in, complete FlightFrames out (see module doc)."""

    def __init__(self, topics: RosTopics, camera: CameraConfig, stats: BagStats) -> None:
        self.topics, self.stats, self.camera = topics, stats, camera
        self.images: dict[str, dict[int, tuple[Any, str]]] = {"left": {}, "right": {}}
        self.pairs: list[int] = []  # stamps with both images, sorted
        self.imu: list[pb.Imu] = []
        self.odometry: list[pb.Odometry] = []
        self.truth: list[tuple[int, pb.Pose]] = []
        self.reached: dict[str, int] = {}  # newest stamp seen on each stream the frames wait for
        self.calibration: dict[str, CameraCalibration] = {}
        self.tf = TransformTree()
        self.rectifier: StereoRectifier | None = None
        self.info: pb.CameraInfo | None = None
        self.seq = 0

    def add(self, topic: str, msgtype: str, msg: Any) -> list[FlightFrame]:
        t = self.topics
        if topic == TF_STATIC:
            self.tf.add(msg)
        elif topic in (t.left_info, t.right_info):
            self.calibration.setdefault("left" if topic == t.left_info else "right", CameraCalibration.from_ros(msg))
        elif topic == t.imu:
            self._stream("imu", self.imu, imu_message(msg, len(self.imu)))
        elif topic == t.odometry:
            self._stream("odometry", self.odometry, odometry_message(msg))
        elif topic == t.truth:
            s = stamp_ns(msg.header)
            bisect.insort(self.truth, (s, pose_message(msg.pose)), key=lambda p: p[0])
            self.reached["truth"] = max(s, self.reached.get("truth", s))
        elif topic in (t.left, t.right):
            self._image("left" if topic == t.left else "right", msgtype, msg)
        return self._ready(final=False)

    def finish(self) -> list[FlightFrame]:
        frames = self._ready(final=True)
        self.stats.unpaired_left += len(self.images["left"])
        self.stats.unpaired_right += len(self.images["right"])
        return frames

    def _stream(self, name: str, samples: list, sample: Any) -> None:
        bisect.insort(samples, sample, key=lambda m: m.header.stamp_ns)
        self.reached[name] = max(sample.header.stamp_ns, self.reached.get(name, 0))

    def _image(self, side: str, msgtype: str, msg: Any) -> None:
        s = stamp_ns(msg.header)
        other = "right" if side == "left" else "left"
        self.images[side][s] = (msg, msgtype)
        if s in self.images[other]:
            bisect.insort(self.pairs, s)
        for name in ("left", "right"):
            while len(self.images[name]) > MAX_PENDING:
                oldest = min(self.images[name])
                del self.images[name][oldest]
                setattr(self.stats, f"unpaired_{name}", getattr(self.stats, f"unpaired_{name}") + 1)
                if oldest in self.pairs:
                    self.pairs.remove(oldest)

    def _ready(self, final: bool) -> list[FlightFrame]:
        out = []
        while self.pairs and (final or self._streams_reached(self.pairs[0]) or len(self.pairs) > MAX_PENDING):
            out.append(self._frame(self.pairs.pop(0)))
        return out

    def _streams_reached(self, s: int) -> bool:
        t = self.topics
        waits = [n for n, topic in (("imu", t.imu), ("odometry", t.odometry), ("truth", t.truth)) if topic]
        calibrated = all(self.calibration.get(side) is not None for side, topic in
                         (("left", t.left_info), ("right", t.right_info)) if topic)
        return calibrated and all(self.reached.get(n, -1) >= s for n in waits)

    def _frame(self, s: int) -> FlightFrame:
        for side in ("left", "right"):  # an image older than this pair lost its partner
            stale = [k for k in self.images[side] if k < s]
            for k in stale:
                del self.images[side][k]
            setattr(self.stats, f"unpaired_{side}", getattr(self.stats, f"unpaired_{side}") + len(stale))
        (lmsg, ltype), (rmsg, rtype) = self.images["left"].pop(s), self.images["right"].pop(s)
        left, right = any_image_array(lmsg, ltype), any_image_array(rmsg, rtype)
        if self.info is None:
            self._calibrate(left, lmsg)
        assert self.rectifier is not None and self.info is not None
        left, right = self.rectifier(left, right)
        stereo = pb.StereoFrame(header=pb.Header(stamp_ns=s, frame_id="cam_left", seq=self.seq), camera_id="front",
                                left=encode_image(left, "raw"), right=encode_image(right, "raw"), info=self.info)
        imu, self.imu = _split(self.imu, s)
        odometry, self.odometry = _split(self.odometry, s)
        self.seq += 1
        self.stats.frames += 1
        return FlightFrame(s, stereo, imu=imu, odometry=odometry, ground_truth=self._truth(s))

    def _calibrate(self, left: np.ndarray, lmsg: Any) -> None:
        """The rectifier and the rectified left camera's CameraInfo, from the first pair."""
        t = self.topics
        cal_l, cal_r = self.calibration.get("left"), self.calibration.get("right")
        if cal_l is None or cal_r is None:
            cal_l, cal_r = _configured_calibration(self.camera, left.shape[1], left.shape[0])
            log.warning("no camera info for both cameras: taking the configured camera (service.config camera), "
                        "rectified")
        rectified = any("rect" in (topic or "") for topic in (t.left, t.right))
        self.rectifier = StereoRectifier(cal_l, cal_r, rectified_input=rectified)
        frame_id = cal_l.frame_id or str(lmsg.header.frame_id).lstrip("/")
        T_body_cam = self.tf.T_a_b(BODY_FRAME, frame_id) if frame_id else None
        if T_body_cam is None:
            T_body_cam = np.array(self.camera.T_body_cam, float) if self.camera.T_body_cam is not None else \
                default_T_body_cam(self.rectifier.baseline_m)
            if T_body_cam.shape != (4, 4):
                raise UserInputError(f"camera.T_body_cam must be 4x4, not {T_body_cam.shape}")
            log.info("camera mounting: the configuration's (no %s -> %r in %s)", BODY_FRAME, frame_id, TF_STATIC)
        else:
            log.info("camera mounting: %s -> %s from %s", BODY_FRAME, frame_id, TF_STATIC)
        self.info = self.rectifier.info(T_body_cam)
        if self.rectifier.remap:
            log.info("rectifying the images from their camera info (%s)", cal_l.distortion_model)

    def _truth(self, s: int) -> pb.GroundTruth | None:
        if not self.truth:
            return None
        k = bisect.bisect_left(self.truth, s, key=lambda p: p[0])
        near = min(self.truth[max(k - 1, 0): k + 1], key=lambda p: abs(p[0] - s))
        del self.truth[: max(k - 1, 0)]
        if abs(near[0] - s) > TRUTH_TOLERANCE_NS:
            return None
        assert self.info is not None
        return pb.GroundTruth(header=pb.Header(stamp_ns=s, frame_id="cad"), T_cad_body=near[1],
                              T_body_cam=self.info.T_body_cam)


def _split(samples: list, s: int) -> tuple[list, list]:
    """(samples stamped at or before s, the rest); both sorted by stamp."""
    k = bisect.bisect_right(samples, s, key=lambda m: m.header.stamp_ns)
    return samples[:k], samples[k:]


def default_T_body_cam(baseline_m: float) -> np.ndarray:
    """The configured mounting where a bag has no /tf_static: the simulator's forward stereo pair."""
    from sim.simulator import forward_camera_T_body_cam

    return forward_camera_T_body_cam(baseline_m)


def _configured_calibration(c: CameraConfig, width: int, height: int) -> tuple[CameraCalibration, CameraCalibration]:
    K = np.array([[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])
    P_l = np.hstack([K, np.zeros((3, 1))])
    P_r = P_l.copy()
    P_r[0, 3] = -c.fx * c.baseline_m
    return (CameraCalibration(width, height, K, np.zeros(5), np.eye(3), P_l),
            CameraCalibration(width, height, K, np.zeros(5), np.eye(3), P_r))

