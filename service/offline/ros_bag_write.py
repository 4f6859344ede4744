"""A macroloc recording written as a ROS 2 bag (rosbags, no ROS installation): what a ROS 2 drone's `ros2 bag
record` would hold for the same flight, for the bag reader's tests and benchmark.

Per stereo frame: left/right images (sensor_msgs/Image bgr8, or CompressedImage carrying the recorded JPEG/PNG
bytes), their CameraInfo (K, D, R = I, P; the right P's P[0,3] = -fx * baseline), the IMU samples
(sensor_msgs/Imu), the vehicle's odometry (nav_msgs/Odometry) where recorded, and ground truth as
geometry_msgs/PoseStamped of the body in the CAD frame; `/tf_static` holds base_link -> the left camera's optical
frame. With `distortion` (OpenCV's k1, k2, p1, p2, k3), the images are distorted with those coefficients (the
pinhole K kept) and the CameraInfo says so: the reader must rectify them back.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import decode_image, matrix_from_pose, read_flight

LEFT_FRAME = "cam0_optical_frame"
RIGHT_FRAME = "cam1_optical_frame"


@dataclass(frozen=True)
class BagTopics:
    left: str = "/cam0/image_raw"
    right: str = "/cam1/image_raw"
    left_info: str = "/cam0/camera_info"
    right_info: str = "/cam1/camera_info"
    imu: str = "/imu0"
    odometry: str = "/vio/odom"
    truth: str = "/ground_truth/pose"


def write_ros_bag(flight: Path, out: Path, storage: str = "sqlite3", topics: BagTopics | None = None,
                  compressed: bool = False, distortion: np.ndarray | None = None, max_frames: int | None = None
                  ) -> Path:
    """Write the recording `flight` as a ROS 2 bag folder `out` (storage "sqlite3" or "mcap"); returns `out`."""
    ts = get_typestore(Stores.LATEST)
    tp = topics or BagTopics()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    make = _Messages(ts)
    distorter: _Distorter | None = None
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        conn = {name: writer.add_connection(topic, msgtype, typestore=ts) for name, topic, msgtype in (
            ("left", tp.left, image_type), ("right", tp.right, image_type),
            ("left_info", tp.left_info, "sensor_msgs/msg/CameraInfo"),
            ("right_info", tp.right_info, "sensor_msgs/msg/CameraInfo"), ("imu", tp.imu, "sensor_msgs/msg/Imu"),
            ("odometry", tp.odometry, "nav_msgs/msg/Odometry"), ("truth", tp.truth, "geometry_msgs/msg/PoseStamped"),
            ("tf_static", "/tf_static", "tf2_msgs/msg/TFMessage"))}

        def put(name: str, msg: Any, stamp: int) -> None:
            writer.write(conn[name], stamp, ts.serialize_cdr(msg, msg.__msgtype__))

        for k, frame in enumerate(read_flight(flight)):
            if max_frames is not None and k >= max_frames:
                break
            info = frame.stereo.info
            s = frame.stamp_ns
            if k == 0:
                put("tf_static", make.tf_static(matrix_from_pose(info.T_body_cam), s), s)
                if distortion is not None:
                    distorter = _Distorter(info, np.asarray(distortion, float))
            for sample in frame.imu:
                put("imu", make.imu(sample), sample.header.stamp_ns)
            for odom in frame.odometry:
                put("odometry", make.odometry(odom), odom.header.stamp_ns)
            D = np.zeros(5) if distortion is None else np.asarray(distortion, float)
            put("left_info", make.camera_info(info, s, LEFT_FRAME, D, 0.0), s)
            put("right_info", make.camera_info(info, s, RIGHT_FRAME, D, info.baseline_m), s)
            for side, image, frame_id in (("left", frame.stereo.left, LEFT_FRAME),
                                          ("right", frame.stereo.right, RIGHT_FRAME)):
                put(side, make.image(image, s, frame_id, compressed, distorter), s)
            if frame.ground_truth is not None:
                put("truth", make.pose_stamped(frame.ground_truth.T_cad_body, s), s)
    return out


class _Distorter:
    """Maps that turn a pinhole image into what a lens with distortion D (OpenCV's model) would have taken: each
    distorted pixel samples the pinhole image where its undistorted ray lands."""

    def __init__(self, info: pb.CameraInfo, D: np.ndarray) -> None:
        K = _K(info)
        u, v = np.meshgrid(np.arange(info.width, dtype=np.float32), np.arange(info.height, dtype=np.float32))
        pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        undist = cv2.undistortPoints(pts, K, D, P=K).reshape(info.height, info.width, 2)
        self.map_x, self.map_y = undist[..., 0].astype(np.float32), undist[..., 1].astype(np.float32)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _K(info: pb.CameraInfo) -> np.ndarray:
    return np.array([[info.fx, 0.0, info.cx], [0.0, info.fy, info.cy], [0.0, 0.0, 1.0]])


class _Messages:
    """rosbags message objects from macroloc's types."""

    def __init__(self, ts: Any) -> None:
        self.ts = ts
        self.T = ts.types

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        Time, Header = self.T["builtin_interfaces/msg/Time"], self.T["std_msgs/msg/Header"]
        return Header(stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), frame_id=frame_id)

    def image(self, image: pb.Image, stamp_ns: int, frame_id: str, compressed: bool,
              distorter: _Distorter | None) -> Any:
        if compressed and distorter is None and image.encoding in (pb.Image.JPEG, pb.Image.PNG):
            fmt = "jpeg" if image.encoding == pb.Image.JPEG else "png"
            return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(stamp_ns, frame_id), format=fmt,
                                                             data=np.frombuffer(image.data, np.uint8))
        array = decode_image(image)
        if distorter is not None:
            array = distorter(array)
        if compressed:
            ok, buf = cv2.imencode(".png", array)
            return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(stamp_ns, frame_id), format="png",
                                                             data=buf.ravel())
        mono = array.ndim == 2
        return self.T["sensor_msgs/msg/Image"](header=self.header(stamp_ns, frame_id), height=array.shape[0],
                                               width=array.shape[1], encoding="mono8" if mono else "bgr8",
                                               is_bigendian=0, step=array.shape[1] * (1 if mono else 3),
                                               data=np.ascontiguousarray(array).ravel())

    def camera_info(self, info: pb.CameraInfo, stamp_ns: int, frame_id: str, D: np.ndarray, baseline_m: float) -> Any:
        K = _K(info)
        P = np.hstack([K, [[-info.fx * baseline_m], [0.0], [0.0]]])
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, frame_id), height=info.height, width=info.width,
            distortion_model="plumb_bob", d=np.asarray(D, float), k=K.ravel(), r=np.eye(3).ravel(), p=P.ravel(),
            binning_x=0, binning_y=0, roi=roi)

    def _vec(self, v: pb.Vector3) -> Any:
        return self.T["geometry_msgs/msg/Vector3"](x=v.x, y=v.y, z=v.z)

    def imu(self, sample: pb.Imu) -> Any:
        q = self.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        cov = np.zeros(9)
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(sample.header.stamp_ns, "base_link"), orientation=q,
            orientation_covariance=np.r_[-1.0, np.zeros(8)], angular_velocity=self._vec(sample.gyro_radps),
            angular_velocity_covariance=cov, linear_acceleration=self._vec(sample.accel_mps2),
            linear_acceleration_covariance=cov)

    def pose(self, pose: pb.Pose) -> Any:
        return self.T["geometry_msgs/msg/Pose"](
            position=self.T["geometry_msgs/msg/Point"](x=pose.position.x, y=pose.position.y, z=pose.position.z),
            orientation=self.T["geometry_msgs/msg/Quaternion"](x=pose.qx, y=pose.qy, z=pose.qz, w=pose.qw))

    def pose_stamped(self, pose: pb.Pose, stamp_ns: int) -> Any:
        return self.T["geometry_msgs/msg/PoseStamped"](header=self.header(stamp_ns, "cad"), pose=self.pose(pose))

    def odometry(self, odom: pb.Odometry) -> Any:
        T = self.T
        order = [3, 4, 5, 0, 1, 2]  # wire [rot; trans] -> ROS (x, y, z, rot x, rot y, rot z)
        cov = np.asarray(odom.covariance, float).reshape(6, 6) if len(odom.covariance) == 36 else np.zeros((6, 6))
        zero = self._vec(pb.Vector3())
        return T["nav_msgs/msg/Odometry"](
            header=self.header(odom.header.stamp_ns, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(odom.T_map_body),
                                                           covariance=cov[np.ix_(order, order)].ravel()),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)))

    def tf_static(self, T_body_cam: np.ndarray, stamp_ns: int) -> Any:
        T = self.T
        q = Rotation.from_matrix(T_body_cam[:3, :3]).as_quat()  # x, y, z, w
        t = T_body_cam[:3, 3]
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        stamped = T["geometry_msgs/msg/TransformStamped"](header=self.header(stamp_ns, "base_link"),
                                                         child_frame_id=LEFT_FRAME, transform=transform)
        return T["tf2_msgs/msg/TFMessage"](transforms=[stamped])


