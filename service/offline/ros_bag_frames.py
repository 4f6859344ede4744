"""A ROS 2 bag's messages, in bag order, assembled into macroloc's FlightFrames (service.offline.ros_bag reads the bag):
left and right images paired by header stamp, each pair with its IMU and odometry samples and its truth, rectified
(service.ros_in.StereoRectifier) and given the left camera's mounting; see service.offline.ros_bag's module doc."""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame, encode_image
from macroloc.service.config import CameraConfig
from macroloc.service.ros_in import (
    CameraCalibration,
    StereoRectifier,
    TransformTree,
    any_image_array,
    default_T_body_cam,
    imu_message,
    odometry_message,
    pose_message,
    stamp_ns,
)

log = logging.getLogger(__name__)

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


class FrameAssembler:
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


def _configured_calibration(c: CameraConfig, width: int, height: int) -> tuple[CameraCalibration, CameraCalibration]:
    K = np.array([[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])
    P_l = np.hstack([K, np.zeros((3, 1))])
    P_r = P_l.copy()
    P_r[0, 3] = -c.fx * c.baseline_m
    return (CameraCalibration(width, height, K, np.zeros(5), np.eye(3), P_l),
            CameraCalibration(width, height, K, np.zeros(5), np.eye(3), P_r))

