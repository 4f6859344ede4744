"""ROS 2 sensor topics as the service's inputs, through Zenoh (zenoh-bridge-ros2dds): stereo images, their camera
info and the IMU arrive as CDR and enter the service as the wire messages its own keys carry.

Each ROS message is converted with the same code that reads ROS 2 bags (`service.ros_in`): left and right
`sensor_msgs/msg/Image` or `CompressedImage` are paired by header stamp (a pair waits for its partner at most
`PAIR_WAIT` frames), rectified from the two `CameraInfo` (OpenCV) unless already rectified, and become one
`StereoFrame` that goes through `InputParser.stereo` like any frame on `macroloc/<vehicle>/stereo` (every check of
`service.inputs` applies); `sensor_msgs/msg/Imu` becomes an `Imu` through `InputParser.imu`. Sizes are checked
before anything is decoded: a raw image whose declared size exceeds the pixel cap or disagrees with its data, or
a compressed one whose header does (`perception.image_header`), is dropped and counted
(`ros_image/image_too_large`, `ros_image/bad_image`), as is a payload that is not CDR of the topic's type
(`ros_<name>/not_cdr`). The two camera infos and the images arrive on their own intake threads, in no fixed order:
a pair completed before both camera infos waits for them and enters the service when the second arrives (the
latest such pair only; one it replaces is counted, `ros_image/no_camera_info`).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.perception.image_header import ImageHeaderError, check_encoded
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import encode_image
from macroloc.proto.ros_types import from_cdr
from macroloc.service.health import DropCounter
from macroloc.service.inputs import ImuIn, InputParser, StereoIn
from macroloc.service.ros_in import (
    CameraCalibration,
    StereoRectifier,
    any_image_array,
    default_T_body_cam,
    imu_message,
    stamp_ns,
)

log = logging.getLogger(__name__)

IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
CAMERA_INFO, IMU = "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/Imu"
PAIR_WAIT = 8  # unpaired images kept per side: a partner later than 8 frames is not coming
RAW_BYTES = {"mono8": 1, "mono16": 2, "bgr8": 3, "rgb8": 3}


@dataclass(frozen=True)
class RosSensorTopics:
    """Zenoh keys of the ROS sensor topics (the ROS topic without its leading slash); "" = not taken."""

    left: str = ""
    right: str = ""
    left_info: str = ""
    right_info: str = ""
    imu: str = ""
    compressed: bool = False  # the image topics carry CompressedImage (else Image)
    rectified: bool = False  # the image topics carry rectified images (image_rect): no remapping


class RosSensorInputs:
    """Intakes for `service.node` (key -> (parse, rate name, heavy, ring size)) that turn ROS sensor messages
    into the service's own input events (see the module doc)."""

    def __init__(self, topics: RosSensorTopics, parser: InputParser, drops: DropCounter, camera_id: str,
                 T_body_cam: np.ndarray | None, max_pixels: int, clock_ns: Any) -> None:
        """`T_body_cam`: the left camera's mounting (4x4); None: the simulator's forward pair at the camera info's
        baseline (`service.ros_in.default_T_body_cam`), as for a bag without /tf_static."""
        self.topics, self.parser, self.drops = topics, parser, drops
        self.camera_id, self.T_body_cam, self.max_pixels = camera_id, T_body_cam, max_pixels
        self.clock_ns = clock_ns  # time.monotonic_ns, for the frame-in -> pose-out latency
        self._lock = threading.Lock()
        self._info: dict[str, CameraCalibration] = {}
        self._rectifier: StereoRectifier | None = None
        self._waiting: dict[str, dict[int, np.ndarray]] = {"left": {}, "right": {}}
        self._unready: tuple[int, np.ndarray, np.ndarray] | None = None  # a pair waiting for the camera infos

    def intakes(self) -> dict[str, tuple[Any, str, bool, int]]:
        t = self.topics
        out: dict[str, tuple[Any, str, bool, int]] = {}
        if t.left and t.right and t.left_info and t.right_info:
            out[t.left] = (lambda p: self.image("left", p), "stereo", True, 4)
            out[t.right] = (lambda p: self.image("right", p), "stereo", True, 4)
            # heavy like the images: a camera info returns the pair that waited for it, if any
            out[t.left_info] = (lambda p: self.camera_info("left", p), "stereo", True, 4)
            out[t.right_info] = (lambda p: self.camera_info("right", p), "stereo", True, 4)
        if t.imu:
            out[t.imu] = (self.imu, "imu", False, 1024)
        return out

    def _decode(self, name: str, payload: bytes, typename: str) -> Any:
        try:
            return from_cdr(payload, typename)
        except Exception as exc:  # noqa: BLE001 - rosbags raises several types for bytes that are not this CDR
            self.drops.drop(f"ros_{name}/not_cdr", str(exc)[:80])
            return None

    def imu(self, payload: bytes) -> ImuIn | None:
        msg = self._decode("imu", payload, IMU)
        return None if msg is None else self.parser.imu(imu_message(msg).SerializeToString())

    def camera_info(self, side: str, payload: bytes) -> StereoIn | None:
        """Keep a side's calibration; the pair that waited for it, once both sides are known."""
        msg = self._decode(f"{side}_info", payload, CAMERA_INFO)
        if msg is None:
            return None
        try:
            calibration = CameraCalibration.from_ros(msg)
        except UserInputError as exc:
            self.drops.drop("ros_camera_info/bad_camera_info", str(exc)[:80])
            return None
        with self._lock:
            if self._info.get(side) != calibration:
                self._info[side] = calibration
                self._rectifier = None  # rebuilt from both at the next pair
            if self._unready is None:
                return None
            rectifier = self._rectifier_now()
            if rectifier is None:
                return None
            (stamp, left, right), self._unready = self._unready, None
            return self._frame(stamp, left, right, rectifier)

    def _sized(self, msg: Any) -> bool:
        """Whether the image may be converted: its size read without decoding, within the cap, consistent."""
        if self.topics.compressed:
            try:
                check_encoded(bytes(msg.data), self.max_pixels)
            except ImageHeaderError as exc:
                self.drops.drop("ros_image/image_too_large" if "cap" in str(exc) else "ros_image/bad_image",
                                str(exc)[:80])
                return False
            return True
        h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding).lower()
        if not (w > 0 and h > 0 and w * h <= self.max_pixels):
            self.drops.drop("ros_image/image_too_large", f"{w}x{h}")
            return False
        if enc not in RAW_BYTES or step < w * RAW_BYTES[enc] or len(msg.data) != h * step:
            self.drops.drop("ros_image/bad_image", f"{w}x{h} {enc} step {step}, {len(msg.data)} bytes")
            return False
        return True

    def image(self, side: str, payload: bytes) -> StereoIn | None:
        msg = self._decode("image", payload, COMPRESSED if self.topics.compressed else IMAGE)
        if msg is None or not self._sized(msg):
            return None
        stamp = stamp_ns(msg.header)
        try:
            array = any_image_array(msg, COMPRESSED if self.topics.compressed else IMAGE)
        except UserInputError as exc:
            self.drops.drop("ros_image/bad_image", str(exc)[:80])
            return None
        other = "right" if side == "left" else "left"
        with self._lock:
            partner = self._waiting[other].pop(stamp, None)
            if partner is None:
                waiting = self._waiting[side]
                waiting[stamp] = array
                while len(waiting) > PAIR_WAIT:
                    waiting.pop(min(waiting))
                    self.drops.drop("ros_image/unpaired")
                return None
            left, right = (array, partner) if side == "left" else (partner, array)
            rectifier = self._rectifier_now()
            if rectifier is None:
                if self._unready is not None:
                    self.drops.drop("ros_image/no_camera_info")
                self._unready = (stamp, left, right)
                return None
            return self._frame(stamp, left, right, rectifier)  # under the lock: stamps reach the parser in order

    def _frame(self, stamp: int, left: np.ndarray, right: np.ndarray, rectifier: StereoRectifier) -> StereoIn | None:
        left, right = rectifier(left, right)
        T_body_cam = self.T_body_cam if self.T_body_cam is not None else default_T_body_cam(rectifier.baseline_m)
        frame = pb.StereoFrame(camera_id=self.camera_id, left=encode_image(left, "raw"),
                               right=encode_image(right, "raw"), info=rectifier.info(T_body_cam))
        frame.header.stamp_ns = stamp
        return self.parser.stereo(frame.SerializeToString(), self.clock_ns())

    def _rectifier_now(self) -> StereoRectifier | None:
        if self._rectifier is None and {"left", "right"} <= self._info.keys():
            try:
                self._rectifier = StereoRectifier(self._info["left"], self._info["right"], self.topics.rectified)
            except UserInputError as exc:
                self.drops.drop("ros_camera_info/bad_camera_info", str(exc)[:80])
        return self._rectifier
