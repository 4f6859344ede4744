"""ROS 2 messages in: rosbags-deserialized `sensor_msgs`, `nav_msgs`, `geometry_msgs` and `tf2_msgs` messages as
macroloc's own types (numpy images, wire `Imu`, `Odometry`, `Pose`, `CameraInfo`).

The messages are read by attribute (the classes rosbags generates, or any object with the same fields), so the
same functions serve a bag today and ROS topics arriving over Zenoh (CDR payloads deserialized by rosbags)
later. Frames: ROS's `base_link` (REP-103: x forward, y left, z up) is macroloc's `body`; camera frames are
optical (x right, y down, z forward), as in macroloc; the IMU's frame is taken to be the body's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.graph.errors import UserInputError
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import pose_from_matrix, vector3

log = logging.getLogger(__name__)

IMAGE_ENCODINGS = ("mono8", "mono16", "bgr8", "rgb8")


def stamp_ns(header: Any) -> int:
    """A std_msgs/Header's stamp (builtin_interfaces/Time: sec, nanosec) in ns."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_array(msg: Any) -> np.ndarray:
    """A sensor_msgs/Image as (H, W) uint8 mono or (H, W, 3) uint8 BGR; mono16 keeps its 8 high bits."""
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), str(msg.encoding).lower()
    data = np.asarray(msg.data, np.uint8)
    if enc == "mono8":
        return data.reshape(h, step)[:, :w].copy()
    if enc == "mono16":
        dtype = ">u2" if msg.is_bigendian else "<u2"
        return (data.reshape(h, step).view(dtype)[:, :w] >> 8).astype(np.uint8)
    if enc in ("bgr8", "rgb8"):
        image = data.reshape(h, step)[:, : 3 * w].reshape(h, w, 3)
        return image[:, :, ::-1].copy() if enc == "rgb8" else image.copy()
    raise UserInputError(f"image encoding {msg.encoding!r} is not supported (use one of {', '.join(IMAGE_ENCODINGS)})")


def compressed_image_array(msg: Any) -> np.ndarray:
    """A sensor_msgs/CompressedImage (jpeg, png) as (H, W) uint8 mono or (H, W, 3) uint8 BGR."""
    image = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise UserInputError(f"a compressed image (format {msg.format!r}) cannot be decoded")
    if image.dtype == np.uint16:
        image = (image // 256).astype(np.uint8)
    return image[:, :, :3] if image.ndim == 3 else image


def any_image_array(msg: Any, msgtype: str) -> np.ndarray:
    """An Image or CompressedImage (by its type name) as `image_array` gives it."""
    return compressed_image_array(msg) if msgtype.endswith("CompressedImage") else image_array(msg)


def imu_message(msg: Any, seq: int = 0) -> pb.Imu:
    """A sensor_msgs/Imu as a wire Imu: specific force (m/s^2) and rate (rad/s), in the IMU's frame taken as body."""
    a, g = msg.linear_acceleration, msg.angular_velocity
    return pb.Imu(header=pb.Header(stamp_ns=stamp_ns(msg.header), frame_id="body", seq=seq),
                  accel_mps2=vector3(np.array([a.x, a.y, a.z])), gyro_radps=vector3(np.array([g.x, g.y, g.z])))


def pose_message(pose: Any) -> pb.Pose:
    """A geometry_msgs/Pose (position, orientation x, y, z, w) as a wire Pose (qw, qx, qy, qz)."""
    p, q = pose.position, pose.orientation
    return pb.Pose(position=pb.Vector3(x=p.x, y=p.y, z=p.z), qw=q.w, qx=q.x, qy=q.y, qz=q.z)


def odometry_message(msg: Any, seq: int = 0) -> pb.Odometry:
    """A nav_msgs/Odometry as a wire Odometry: T_map_body (ROS `odom` = macroloc `map`), covariance reordered from
    ROS's (x, y, z, rot x, rot y, rot z) to the wire's [rot; trans]."""
    cov = np.asarray(msg.pose.covariance, float).reshape(6, 6)
    order = [3, 4, 5, 0, 1, 2]
    return pb.Odometry(header=pb.Header(stamp_ns=stamp_ns(msg.header), frame_id="map", seq=seq),
                       T_map_body=pose_message(msg.pose.pose), covariance=cov[np.ix_(order, order)].ravel().tolist())


def transform_matrix(transform: Any) -> np.ndarray:
    """A geometry_msgs/Transform (of a TransformStamped: T_parent_child) as a 4x4 matrix."""
    t, q = transform.translation, transform.rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()  # scipy: x, y, z, w
    T[:3, 3] = (t.x, t.y, t.z)
    return T


def default_T_body_cam(baseline_m: float) -> np.ndarray:
    """The configured mounting where a bag has no /tf_static: the simulator's forward stereo pair."""
    return forward_stereo_T_body_cam(baseline_m)


@dataclass
class TransformTree:
    """Static transforms (tf2_msgs/TFMessage of /tf_static): T_parent_child by child frame id."""

    parent_of: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)

    def add(self, msg: Any) -> None:
        for ts in msg.transforms:
            self.parent_of[str(ts.child_frame_id).lstrip("/")] = (str(ts.header.frame_id).lstrip("/"),
                                                                  transform_matrix(ts.transform))

    def T_a_b(self, a: str, b: str) -> np.ndarray | None:
        """4x4 T_a_b through the tree (both frames' chains to their common root), or None when not connected."""
        up_a, up_b = self._to_root(a.lstrip("/")), self._to_root(b.lstrip("/"))
        common = next((f for f in up_b if f in up_a), None)
        if common is None:
            return None
        return np.linalg.inv(up_a[common]) @ up_b[common]

    def _to_root(self, frame: str) -> dict[str, np.ndarray]:
        """{ancestor: T_ancestor_frame} for the frame itself and each ancestor."""
        chain = {frame: np.eye(4)}
        T = np.eye(4)
        while frame in self.parent_of and len(chain) < 64:
            frame, T_parent_child = self.parent_of[frame]
            T = T_parent_child @ T
            chain[frame] = T
        return chain


@dataclass(eq=False)
class CameraCalibration:
    """One camera's sensor_msgs/CameraInfo: K (3x3), D, R (3x3 rectifying rotation), P (3x4), image size.
    Two are equal when every field is (a driver repeats its camera info with every image)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    distortion_model: str = "plumb_bob"
    frame_id: str = ""

    @classmethod
    def from_ros(cls, msg: Any) -> CameraCalibration:
        P = np.asarray(msg.p, float).reshape(3, 4)
        if P[0, 0] <= 0:
            raise UserInputError(f"camera info of {msg.header.frame_id!r} has no projection matrix P")
        return cls(int(msg.width), int(msg.height), np.asarray(msg.k, float).reshape(3, 3),
                   np.asarray(msg.d, float).ravel(), np.asarray(msg.r, float).reshape(3, 3), P,
                   str(msg.distortion_model or "plumb_bob"), str(msg.header.frame_id).lstrip("/"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraCalibration):
            return NotImplemented
        return ((self.width, self.height, self.distortion_model, self.frame_id)
                == (other.width, other.height, other.distortion_model, other.frame_id)
                and all(np.array_equal(a, b) for a, b in ((self.K, other.K), (self.D, other.D), (self.R, other.R),
                                                           (self.P, other.P))))

    __hash__ = None  # type: ignore[assignment]  # mutable arrays: equal, never hashed

    @property
    def is_rectified(self) -> bool:
        """No distortion and no rectifying rotation: the images are already the pinhole P describes."""
        return not np.any(self.D) and np.allclose(self.R, np.eye(3)) and np.allclose(self.K, self.P[:, :3])


class StereoRectifier:
    """Rectified left/right images and the rectified left camera's wire CameraInfo from two CameraInfo.

    The rectified cameras are the projections P (fx = P[0,0], cx = P[0,2], ...); the baseline is -P_right[0,3] /
    P_right[0,0] (ROS's convention, metres). Images are remapped (OpenCV, bilinear) unless both calibrations are
    already rectified or `rectified_input` says the topics carry rectified images (`image_rect`). The rectified
    left camera is the raw one turned by R_left (p_rect = R p_raw): T_body_camrect = T_body_camraw @ R_left^T.
    """

    def __init__(self, left: CameraCalibration, right: CameraCalibration, rectified_input: bool = False) -> None:
        self.left, self.right = left, right
        self.baseline_m = round(float(-right.P[0, 3] / right.P[0, 0]), 9)  # to the nanometre: P holds fx * b
        if not self.baseline_m > 0:
            raise UserInputError(f"the right camera info's P gives a baseline of {self.baseline_m:.4f} m "
                                 "(P[0,3] = -fx * baseline, negative for the right camera)")
        self.remap = not rectified_input and not (left.is_rectified and right.is_rectified)
        self._maps = [self._maps_of(c) for c in (left, right)] if self.remap else []

    @staticmethod
    def _maps_of(c: CameraCalibration) -> tuple[np.ndarray, np.ndarray]:
        size = (c.width, c.height)
        if c.distortion_model == "equidistant":
            return cv2.fisheye.initUndistortRectifyMap(c.K, c.D[:4], c.R, c.P[:, :3], size, cv2.CV_16SC2)
        return cv2.initUndistortRectifyMap(c.K, c.D, c.R, c.P[:, :3], size, cv2.CV_16SC2)

    def __call__(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.remap:
            return left, right
        return tuple(cv2.remap(img, m1, m2, cv2.INTER_LINEAR)  # type: ignore[return-value]
                     for img, (m1, m2) in zip((left, right), self._maps, strict=True))

    def info(self, T_body_camraw: np.ndarray) -> pb.CameraInfo:
        """The rectified left camera as a wire CameraInfo, mounted at T_body_camraw @ R_left^T when remapping."""
        P = self.left.P
        T_body_cam = T_body_camraw.copy()
        if self.remap:
            T_body_cam[:3, :3] = T_body_camraw[:3, :3] @ self.left.R.T
        return pb.CameraInfo(width=self.left.width, height=self.left.height, fx=P[0, 0], fy=P[1, 1], cx=P[0, 2],
                             cy=P[1, 2], baseline_m=self.baseline_m, T_body_cam=pose_from_matrix(T_body_cam))
