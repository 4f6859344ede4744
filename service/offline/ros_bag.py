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

import logging
import time
from collections.abc import Iterator
from pathlib import Path

from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from macroloc.graph.errors import UserInputError
from macroloc.proto.recording import FlightFrame, read_flight
from macroloc.service.config import CameraConfig
from macroloc.service.offline.ros_bag_frames import TF_STATIC, BagStats, FrameAssembler, RosTopics

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
}  # odometry and truth only where named: a bag's /odom may be anything but the vehicle's VIO


def is_ros_bag(path: Path) -> bool:
    """A ROS 2 bag folder, a `.db3`, or an MCAP file whose profile is `ros2` (macroloc's own recordings are not)."""
    if path.is_dir():
        return (path / "metadata.yaml").exists()
    if path.suffix.lower() == ".db3":
        return True
    if path.suffix.lower() != ".mcap" or not path.is_file():
        return False

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

    return read_flight(path)


def _open_reader(path: Path):  # noqa: ANN202 - rosbags' AnyReader
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
        assembler = FrameAssembler(topics, camera or CameraConfig(), stats)
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
