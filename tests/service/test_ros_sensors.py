"""ROS 2 sensor topics into a running service over Zenoh (as zenoh-bridge-ros2dds delivers them): stereo Image
pairs with their CameraInfo and Imu become the service's frames and IMU samples; bad ones are counted."""

from __future__ import annotations

import numpy as np

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import encode_image
from macroloc.proto.ros_types import to_cdr, typestore
from macroloc.service.offline.ros_bag_write import _Messages
from tests.service.helpers import client, free_port, running_service, service_config, wait_for, wait_subscribed
from tests.service.test_service import Collector

TOPICS = {"left_image": "/cam0/image_raw", "right_image": "/cam1/image_raw", "left_info": "/cam0/camera_info",
          "right_info": "/cam1/camera_info", "imu": "/imu0"}


def _pair(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    left = rng.integers(0, 255, (48, 64), np.uint8)
    return left, np.roll(left, -4, axis=1)  # 4 px of disparity


def test_ros_images_camera_info_and_imu_enter_as_the_services_own_inputs(duplex_path, tmp_path) -> None:
    port = free_port()
    cfg = service_config(duplex_path, tmp_path, port)
    cfg.ros.enabled = True
    for name, topic in TOPICS.items():
        setattr(cfg.ros, name, topic)
    m = _Messages(typestore())
    info = pb.CameraInfo(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5, baseline_m=0.12)
    rng = np.random.default_rng(0)
    with running_service(cfg) as service, client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        for topic in TOPICS.values():  # a put sent before the service's subscription reaches us is dropped
            wait_subscribed(s, topic.lstrip("/"))
        for side, topic in (("cam0", "cam0/camera_info"), ("cam1", "cam1/camera_info")):
            s.put(topic, to_cdr(m.camera_info(info, 0, side, np.zeros(5), 0.12), "sensor_msgs/msg/CameraInfo"))
        stamps = [(k + 1) * 100_000_000 for k in range(5)]
        for stamp in stamps:
            left, right = _pair(rng)
            s.put("cam1/image_raw", to_cdr(m.image(encode_image(right, "raw"), stamp, "cam1", False, None),
                                           "sensor_msgs/msg/Image"))  # the right before the left: paired by stamp
            s.put("cam0/image_raw", to_cdr(m.image(encode_image(left, "raw"), stamp, "cam0", False, None),
                                           "sensor_msgs/msg/Image"))
            imu = pb.Imu(accel_mps2=pb.Vector3(z=9.81), gyro_radps=pb.Vector3())
            imu.header.stamp_ns = stamp
            s.put("imu0", to_cdr(m.imu(imu), "sensor_msgs/msg/Imu"))
            wait_for(lambda: service.rates["stereo"].total >= stamps.index(stamp) + 1,  # type: ignore  # noqa: B023
                     what=f"the frame of {stamp} taken")
        wait_for(lambda: {p.header.stamp_ns for p in poses.items} >= set(stamps), what="a pose for every ROS frame")
        wait_for(lambda: service.rates["imu"].total == 5, what="the IMU samples taken")  # type: ignore

        # hostile: a raw image that declares 20000 x 20000, and bytes that are not CDR
        bomb = m.image(encode_image(np.zeros((48, 64), np.uint8), "raw"), 10**9, "cam0", False, None)
        bomb.width, bomb.height, bomb.step = 20000, 20000, 20000
        s.put("cam0/image_raw", to_cdr(bomb, "sensor_msgs/msg/Image"))
        s.put("imu0", b"\x00\x01 not cdr")
        counts = service.drops.counts  # type: ignore[attr-defined]
        wait_for(lambda: counts().get("ros_image/image_too_large") == 1 and counts().get("ros_imu/not_cdr") == 1,
                 what="the bad ROS inputs counted")
        assert service.rates["stereo"].total == 5  # type: ignore[attr-defined]


def test_a_pair_before_the_camera_infos_waits_for_them_and_only_the_latest_waits() -> None:
    """Camera infos and images arrive on their own intake threads, in no fixed order: a pair completed before
    both infos enters when the second info arrives; a second such pair replaces it (counted)."""
    from macroloc.service.health import DropCounter
    from macroloc.service.inputs import InputParser
    from macroloc.service.ros_sensors import RosSensorInputs, RosSensorTopics

    drops = DropCounter()
    topics = RosSensorTopics(left="cam0/image_raw", right="cam1/image_raw", left_info="cam0/camera_info",
                             right_info="cam1/camera_info")
    ros = RosSensorInputs(topics, InputParser(["cam0"], drops), drops, "cam0", None, 10**7, lambda: 0)
    m = _Messages(typestore())
    info = pb.CameraInfo(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5, baseline_m=0.12)
    rng = np.random.default_rng(1)

    def image(side: str, stamp: int, array: np.ndarray) -> bytes:
        return to_cdr(m.image(encode_image(array, "raw"), stamp, side, False, None), "sensor_msgs/msg/Image")

    for stamp in (100_000_000, 200_000_000):
        left, right = _pair(rng)
        assert ros.image("left", image("cam0", stamp, left)) is None
        assert ros.image("right", image("cam1", stamp, right)) is None  # paired, but no camera info yet
    assert drops.counts() == {"ros_image/no_camera_info": 1}  # the first pair, replaced by the second
    assert ros.camera_info("left", to_cdr(m.camera_info(info, 0, "cam0", np.zeros(5), 0.12),
                                          "sensor_msgs/msg/CameraInfo")) is None
    waited = ros.camera_info("right", to_cdr(m.camera_info(info, 0, "cam1", np.zeros(5), 0.12),
                                             "sensor_msgs/msg/CameraInfo"))
    assert waited is not None and waited.stamp_ns == 200_000_000
    assert ros.camera_info("right", to_cdr(m.camera_info(info, 0, "cam1", np.zeros(5), 0.12),
                                           "sensor_msgs/msg/CameraInfo")) is None  # given once
    left, right = _pair(rng)
    assert ros.image("right", image("cam1", 300_000_000, right)) is None
    later = ros.image("left", image("cam0", 300_000_000, left))
    assert later is not None and later.stamp_ns == 300_000_000
