"""Issue 57 item 2: the vehicle's odometry taken where the vehicle has it: a ROS nav_msgs/msg/Odometry topic and PX4's
fmu/out/vehicle_odometry become the service's odometry (frames converted, checked as every odometry is); a reset of
the vehicle's odometry (reset_counter, or a jump) is a new segment chained at the last pose, never a teleport."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import zenoh

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.ros_types import header, msg, to_cdr
from macroloc.service.config import Px4Config, RosConfig
from macroloc.service.health import DropCounter
from macroloc.service.inputs import InputLimits, InputParser
from macroloc.service.ned import T_ned_frd_from_T_enu_flu, quat_wxyz_from_matrix
from macroloc.service.odometry_in import (
    OdometrySegments,
    SegmentRule,
    TfOdometry,
    VehicleOdometryInput,
    px4_odometry,
    ros_odometry,
)
from tests.service.helpers import (
    FakeFlight,
    client,
    free_port,
    running_service,
    service_config,
    wait_for,
    wait_subscribed,
    yaw_T,
)
from tests.service.test_service import Collector, _localized_at

STEP_NS = 33_000_000


def px4_payload(stamp_ns: int, T_map_body: np.ndarray, reset_counter: int = 0, pose_frame: int = 1) -> bytes:
    """VehicleOdometry of a z-up FLU pose: NED position, FRD attitude (service.ned), timestamps in us."""
    T = T_ned_frd_from_T_enu_flu(T_map_body)
    nan3 = np.full(3, np.nan, np.float32)
    m = msg("px4_msgs/msg/VehicleOdometry")(
        timestamp=stamp_ns // 1000, timestamp_sample=stamp_ns // 1000, pose_frame=pose_frame,
        position=T[:3, 3].astype(np.float32), q=quat_wxyz_from_matrix(T[:3, :3]).astype(np.float32),
        velocity_frame=1, velocity=nan3, angular_velocity=nan3, position_variance=nan3, orientation_variance=nan3,
        velocity_variance=nan3, reset_counter=reset_counter, quality=100)
    return to_cdr(m, "px4_msgs/msg/VehicleOdometry")


def ros_payload(stamp_ns: int, T_odom_body: np.ndarray) -> bytes:
    w, x, y, z = quat_wxyz_from_matrix(T_odom_body[:3, :3])
    pose = msg("geometry_msgs/msg/Pose")(
        position=msg("geometry_msgs/msg/Point")(x=T_odom_body[0, 3], y=T_odom_body[1, 3], z=T_odom_body[2, 3]),
        orientation=msg("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))
    twist = msg("geometry_msgs/msg/Twist")(linear=msg("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0),
                                           angular=msg("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0))
    m = msg("nav_msgs/msg/Odometry")(
        header=header(stamp_ns, "odom"), child_frame_id="base_link",
        pose=msg("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.eye(6).ravel() * 1e-4),
        twist=msg("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=np.zeros(36)))
    return to_cdr(m, "nav_msgs/msg/Odometry")


def tf_payload(stamp_ns: int, links: list[tuple[str, str, np.ndarray]]) -> bytes:
    """A tf2_msgs/msg/TFMessage of (parent, child, T_parent_child) links."""
    def stamped(parent: str, child: str, T: np.ndarray) -> object:
        w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
        return msg("geometry_msgs/msg/TransformStamped")(
            header=header(stamp_ns, parent), child_frame_id=child, transform=msg("geometry_msgs/msg/Transform")(
                translation=msg("geometry_msgs/msg/Vector3")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=msg("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)))

    typename = "tf2_msgs/msg/TFMessage"
    return to_cdr(msg(typename)(transforms=[stamped(*link) for link in links]), typename)


def test_tf_odometry_is_the_odom_to_base_link_link_and_other_links_are_skipped_uncounted() -> None:
    drops = DropCounter()
    parser = InputParser(["front"], drops, InputLimits(max_odometry_m=100.0))
    tf = VehicleOdometryInput("tf", TfOdometry("vio_odom", "body_flu"))
    tf.intakes(parser)
    T_odom_body, T_map_odom = yaw_T(0.4, np.array([1.0, -2.0, 1.5])), yaw_T(-1.0, np.array([7.0, 3.0, 0.0]))
    ev = tf.take(parser, tf_payload(2 * 10**9, [("map", "vio_odom", T_map_odom), ("vio_odom", "body_flu", T_odom_body),
                                              ("body_flu", "cam", np.eye(4))]))
    assert ev is not None and ev.stamp_ns == 2 * 10**9
    assert np.allclose(ev.T_map_body, T_odom_body, atol=1e-9)  # the link as it is, not composed with map -> odom
    assert tf.take(parser, tf_payload(3 * 10**9, [("map", "vio_odom", T_map_odom)])) is None  # macroloc's own link
    assert tf.take(parser, tf_payload(3 * 10**9, [("odom", "base_link", T_odom_body)])) is None  # other frame names
    assert drops.counts() == {}


def test_px4_odometry_is_turned_from_ned_frd_to_a_z_up_flu_pose() -> None:
    """1 m north, 2 m east, 3 m up, nose to the east (PX4 yaw +90 deg): ENU (2, 1, 3), body x along ENU +x."""
    payload_msg = msg("px4_msgs/msg/VehicleOdometry")(
        timestamp=5, timestamp_sample=4_000_000, pose_frame=1, position=np.array([1.0, 2.0, -3.0], np.float32),
        q=np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], np.float32), velocity_frame=1,
        velocity=np.zeros(3, np.float32), angular_velocity=np.zeros(3, np.float32),
        position_variance=np.zeros(3, np.float32), orientation_variance=np.zeros(3, np.float32),
        velocity_variance=np.zeros(3, np.float32), reset_counter=7, quality=100)
    odometry, reset = px4_odometry(to_cdr(payload_msg, "px4_msgs/msg/VehicleOdometry"))
    assert odometry is not None and reset == 7 and odometry.header.stamp_ns == 4_000_000_000
    p, q = odometry.T_map_body.position, odometry.T_map_body
    assert np.allclose([p.x, p.y, p.z], [2.0, 1.0, 3.0], atol=1e-6)
    assert np.allclose(np.abs([q.qw, q.qx, q.qy, q.qz]), [1.0, 0.0, 0.0, 0.0], atol=1e-6)


def _stream(steps: int, start_ns: int = 10**9, speed_mps: float = 1.0) -> list[tuple[int, np.ndarray]]:
    return [(start_ns + k * STEP_NS, yaw_T(0.1 * k * STEP_NS * 1e-9, np.array([speed_mps * k * STEP_NS * 1e-9, 0, 1])))
            for k in range(steps)]


def test_a_reset_or_a_jump_starts_a_segment_chained_at_the_last_pose() -> None:
    started: list[int] = []
    segments = OdometrySegments(SegmentRule(max_speed_mps=10.0), started.append)
    truth = _stream(60, speed_mps=8.0)  # fast, within the rule: one segment
    T_reset = yaw_T(2.0, np.array([-40.0, 13.0, -1.0]))  # the VIO's new frame after its reset
    out = []
    for k, (stamp, T) in enumerate(truth):
        if k < 20:
            out.append(segments(stamp, T, reset_counter=3))
        elif k < 40:  # a reset_counter change: a new frame
            out.append(segments(stamp, T_reset @ T, reset_counter=4))
        else:  # a jump alone (no counter: a ROS VIO): yet another frame
            out.append(segments(stamp, np.linalg.inv(T_reset) @ yaw_T(-1.0, np.r_[5.0, 5.0, 0.0]) @ T))
    assert started == [truth[20][0], truth[40][0]] and segments.segments == 3
    steps = [np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(out, out[1:], strict=False)]
    assert max(steps) < 8.0 * STEP_NS * 1e-9 + 1e-9  # never a teleport: each step at most one sample's motion
    # within a segment the motion is the vehicle's: relative poses equal the truth's (the chaining is rigid)
    for a, b in ((25, 39), (41, 59)):
        assert np.allclose(np.linalg.inv(out[a]) @ out[b], np.linalg.inv(truth[a][1]) @ truth[b][1], atol=1e-9)


def test_bad_vehicle_odometry_is_refused_and_counted() -> None:
    drops = DropCounter()
    parser = InputParser(["front"], drops, InputLimits(max_odometry_m=100.0))
    px4 = VehicleOdometryInput("fmu/out/vehicle_odometry", px4_odometry)
    ros = VehicleOdometryInput("odom", ros_odometry)
    px4.intakes(parser), ros.intakes(parser)
    assert px4.take(parser, px4_payload(10**9, np.eye(4), pose_frame=0)) is None  # unknown frame
    assert px4.take(parser, px4_payload(10**9, np.diag([1.0, 1, 1, 1]) * np.nan)) is None
    assert px4.take(parser, b"\x00\x01\x00\x00garbage") is None
    far = np.eye(4)
    far[0, 3] = 1e6
    assert ros.take(parser, ros_payload(10**9, far)) is None  # beyond the odometry's plausible range
    assert ros.take(parser, ros_payload(10**9, np.eye(4))) is not None
    assert ros.take(parser, ros_payload(10**9 - 1, np.eye(4))) is None  # out of order
    assert drops.counts() == {"odometry/nan": 2, "odometry/not_cdr": 1, "odometry/out_of_bounds": 1,
                              "odometry/out_of_order": 1}


@pytest.fixture(scope="module")
def start_pose(office_model) -> np.ndarray:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    return yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])


def _fly(s: zenoh.Session, flight: FakeFlight, T: np.ndarray, steps: int, first_stamp_ns: int,
         put_odometry: Callable[[int, np.ndarray], None]) -> np.ndarray:
    """The vehicle's IMU and sightings on macroloc's keys, its odometry (T_map_body) through `put_odometry`."""
    for k in range(steps):
        stamp = first_stamp_ns + (k + 1) * STEP_NS
        s.put("macroloc/t1/imu", flight.imu(stamp, T).SerializeToString())
        put_odometry(stamp, np.linalg.inv(flight.T_cad_odom) @ T)
        if k % 5 == 0:
            s.put("macroloc/t1/observations", flight.observations(stamp, T).SerializeToString())
        T = T @ yaw_T(0.0, np.array([0.02, 0.0, 0.0]))
    return T


@pytest.mark.parametrize("source", ["ros_odometry_rmw_zenoh", "px4_vehicle_odometry_bridge", "ros_tf_bridge"])
def test_a_flight_whose_only_odometry_is_the_vehicles_localizes_through_its_reset(
        source: str, office_path, office_model, start_pose, tmp_path) -> None:
    """The service localizes on the vehicle's own odometry alone (no macroloc Odometry is sent); then the vehicle's
    odometry resets (PX4: reset_counter + 1; ROS: its frame jumps 30 m and turns 2 rad): the localized poses stay at
    the truth, within 0.3 m, none jumps. /tf carries the service's own map -> odom beside the vehicle's link."""
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    cfg.graph.surface_check = False
    T_new_frame = yaw_T(2.0, np.array([30.0, -7.0, 0.5]))
    if source == "ros_odometry_rmw_zenoh":
        from pamoja.ros2 import entity_key  # another rmw_zenoh implementation's key (tests/service/test_rmw_zenoh.py)

        from tests.service.test_rmw_zenoh import GOLDEN_RIHS01

        cfg.ros = RosConfig(enabled=True, middleware="rmw_zenoh", odometry="/vio/odometry")
        odometry_type = "nav_msgs/msg/Odometry"
        key = entity_key(0, "/vio/odometry", odometry_type, "RIHS01_" + GOLDEN_RIHS01[odometry_type])

        def payload(stamp: int, T: np.ndarray, reset: bool) -> bytes:
            return ros_payload(stamp, T_new_frame @ T if reset else T)
    elif source == "ros_tf_bridge":
        cfg.ros = RosConfig(enabled=True, odometry_tf=True)
        key = "tf"

        def payload(stamp: int, T: np.ndarray, reset: bool) -> bytes:
            return tf_payload(stamp, [("odom", "base_link", T_new_frame @ T if reset else T)])
    else:
        cfg.px4 = Px4Config(take_odometry=True)
        key = "fmu/out/vehicle_odometry"

        def payload(stamp: int, T: np.ndarray, reset: bool) -> bytes:
            return px4_payload(stamp, T_new_frame @ T if reset else T, reset_counter=1 if reset else 0)
    with running_service(cfg) as service, client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        wait_subscribed(s, key)
        wait_subscribed(s, "macroloc/t1/observations")
        flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
        T = _fly(s, flight, start_pose, 40, 0, lambda stamp, T_map: s.put(key, payload(stamp, T_map, False)))
        wait_for(lambda: _localized_at(poses, T), what="localized on the vehicle's odometry alone")
        n_before = len(poses.items)
        truth: dict[int, np.ndarray] = {}

        def put_reset(stamp: int, T_map: np.ndarray) -> None:
            truth[stamp] = flight.T_cad_odom @ T_map
            s.put(key, payload(stamp, T_map, True))

        T = _fly(s, flight, T, 40, 40 * STEP_NS, put_reset)
        wait_for(lambda: _localized_at(poses, T) and poses.last().header.stamp_ns == max(truth), 30.0,
                 "localized at the truth after the reset")
        segments = service.drops.counts().get("odometry/segment", 0)  # type: ignore[attr-defined]
        assert service.rates["odometry"].total >= 80  # type: ignore[attr-defined]
    assert segments == 1
    after = [p for p in poses.items[n_before:] if p.status == pb.PoseEstimate.LOCALIZED and p.header.stamp_ns in truth]
    assert len(after) >= 20
    errors = [np.linalg.norm(np.array([p.T_cad_body.position.x, p.T_cad_body.position.y, p.T_cad_body.position.z])
                             - truth[p.header.stamp_ns][:3, 3]) for p in after]
    assert max(errors) < 0.3, f"after the reset: largest error {max(errors):.2f} m"
