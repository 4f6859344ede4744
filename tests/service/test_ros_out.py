"""ROS 2 and PX4 through Zenoh: a plain Zenoh session subscribes to the ROS keys while the service flies a fake
flight, deserializes every message with rosbags' CDR deserializer and checks it against the protobuf messages of
the same stamps (frames, covariance order, path vs Waypoints, TF chain vs T_cad_map, PX4 NED pose and yaw)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
import zenoh

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose
from macroloc.proto.ros_types import from_cdr, msg, stamp_ns_of, to_cdr
from macroloc.service.config import Px4Config, RosConfig
from macroloc.service.ned import cov_ros_from_gtsam, matrix_from_quat_wxyz
from macroloc.service.px4 import ResetCounter
from macroloc.service.ros_in import pose_message as ros_pose
from macroloc.service.ros_in import transform_matrix
from tests.service.helpers import FakeFlight, client, free_port, running_service, service_config, wait_for, yaw_T
from tests.service.test_service import Collector, _query, fly


class CdrCollector:
    """Every CDR message on a key, deserialized with rosbags."""

    def __init__(self, session: zenoh.Session, key: str, typename: str) -> None:
        self.items: list[Any] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on)
        self.typename = typename

    def _on(self, sample: zenoh.Sample) -> None:
        m = from_cdr(sample.payload.to_bytes(), self.typename)
        with self._lock:
            self.items.append(m)

    def snapshot(self) -> list[Any]:
        with self._lock:
            return list(self.items)


def _T_of(pose: Any) -> np.ndarray:
    """A geometry_msgs/Pose as 4x4, through the bag reader's conversion."""
    return matrix_from_pose(ros_pose(pose))


@pytest.fixture(scope="module")
def start_pose(office_model) -> np.ndarray:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    return yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])


def test_ros_and_px4_messages_match_the_protobuf_ones(office_path, office_model, start_pose, tmp_path) -> None:
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    cfg.ros = RosConfig(enabled=True, odom_tf=True)  # the chain map -> odom -> base_link below
    cfg.px4 = Px4Config(enabled=True, namespace="px4_1")
    cfg.graph.surface_check = False  # four doors in range register without the walls' check (faster to start)
    with running_service(cfg), client(port) as s:
        poses_pb = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        waypoints_pb = Collector(s, "macroloc/t1/waypoints", pb.Waypoints)
        pose = CdrCollector(s, "t1/macroloc/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")
        odom = CdrCollector(s, "t1/macroloc/odometry", "nav_msgs/msg/Odometry")
        path = CdrCollector(s, "t1/macroloc/path", "nav_msgs/msg/Path")
        tf = CdrCollector(s, "tf", "tf2_msgs/msg/TFMessage")
        status = CdrCollector(s, "t1/macroloc/status", "diagnostic_msgs/msg/DiagnosticArray")
        vio = CdrCollector(s, "px4_1/fmu/in/vehicle_visual_odometry", "px4_msgs/msg/VehicleOdometry")
        setpoint = CdrCollector(s, "px4_1/fmu/in/trajectory_setpoint", "px4_msgs/msg/TrajectorySetpoint")
        offboard = CdrCollector(s, "px4_1/fmu/in/offboard_control_mode", "px4_msgs/msg/OffboardControlMode")
        flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: len(pose.snapshot()) >= 3, what="ROS poses")
        # the goal through ROS: a PoseStamped in `map` (= CAD) where a protobuf plan query says it is reachable
        reachable = _query(s, "macroloc/t1/plan", pb.Waypoints, pb.Goal(space_name="MENS RR").SerializeToString())
        goal_cad = np.array([reachable.points_cad[-1].x, reachable.points_cad[-1].y, reachable.points_cad[-1].z])
        goal = msg("geometry_msgs/msg/PoseStamped")(
            header=msg("std_msgs/msg/Header")(stamp=msg("builtin_interfaces/msg/Time")(sec=1, nanosec=0),
                                              frame_id="map"),
            pose=msg("geometry_msgs/msg/Pose")(position=msg("geometry_msgs/msg/Point")(x=goal_cad[0], y=goal_cad[1],
                                                                                       z=goal_cad[2]),
                                               orientation=msg("geometry_msgs/msg/Quaternion")(x=0, y=0, z=0, w=1)))
        s.put("t1/macroloc/goal", to_cdr(goal, "geometry_msgs/msg/PoseStamped"))
        fly(s, flight, T, 3, first_stamp_ns=10**9)
        wait_for(lambda: path.snapshot() and waypoints_pb.items, what="a path from the ROS goal")
        wait_for(lambda: len(offboard.snapshot()) >= 3 and setpoint.snapshot(), what="offboard heartbeats")
        wait_for(lambda: status.snapshot(), what="a DiagnosticArray")

    by_stamp: dict[int, list] = {}  # a keyframe may publish a second estimate at its stamp
    for p in poses_pb.items:  # ROS and PX4 get a pose where it is localized or degraded (service.ros_out, px4)
        if p.status in (pb.PoseEstimate.LOCALIZED, pb.PoseEstimate.DEGRADED):
            by_stamp.setdefault(p.header.stamp_ns, []).append(p)
    received = {p.header.stamp_ns for p in poses_pb.items}

    def same(T: np.ndarray, refs: list, field: str = "T_cad_body", tol: float = 1e-6):  # noqa: ANN202
        found = [r for r in refs if np.abs(matrix_from_pose(getattr(r, field)) - T)[:3].max() < tol]
        assert found, f"no protobuf pose of that stamp has this {field}"
        return found[0]

    checked = 0
    for m in pose.snapshot():  # pose: frame map = CAD; covariance in ROS order, finite
        assert m.header.frame_id == "map"
        stamp_ns = stamp_ns_of(m.header.stamp)
        if stamp_ns not in received:
            continue  # its protobuf twin was dropped on the way (poses go out with CongestionControl.DROP)
        assert stamp_ns in by_stamp, "a ROS pose where the protobuf one is neither localized nor degraded"
        ref = same(_T_of(m.pose.pose), by_stamp[stamp_ns])
        T_cad_body = matrix_from_pose(ref.T_cad_body)
        # Office_A's IfcSite geo-reference (no TrueNorth: ENU = CAD axes at the origin): ENU and WGS84 beside CAD
        assert np.allclose(matrix_from_pose(ref.T_enu_body), T_cad_body, atol=1e-9)
        assert abs(ref.wgs84.latitude_deg - (42.358428955 + T_cad_body[1, 3] / 111_080)) < 1e-6
        cov = m.pose.covariance.reshape(6, 6)
        assert np.isfinite(cov).all() and np.allclose(cov, cov.T)
        if len(ref.covariance) == 36:
            expected = cov_ros_from_gtsam(np.array(ref.covariance).reshape(6, 6), T_cad_body[:3, :3])
            assert np.allclose(cov, expected, rtol=1e-9, atol=1e-15)
            # ROS order: the position block is GTSAM's translation block, rotated into the map frame
            R = T_cad_body[:3, :3]
            assert np.allclose(cov[:3, :3], R @ np.array(ref.covariance).reshape(6, 6)[3:, 3:] @ R.T)
            checked += 1
    assert checked >= 3
    for m in odom.snapshot():
        assert (m.header.frame_id, m.child_frame_id) == ("map", "base_link")
    # TF: map -> odom is T_cad_map, and map -> odom -> base_link is T_cad_body, to 1 mm
    chains = 0
    for m in tf.snapshot():
        frames = {(t.header.frame_id, t.child_frame_id): t for t in m.transforms}
        assert ("odom", "base_link") in frames
        if ("map", "odom") not in frames:
            continue
        stamp = stamp_ns_of(frames["map", "odom"].header.stamp)
        if stamp not in by_stamp:
            continue
        T_map_odom = transform_matrix(frames["map", "odom"].transform)
        T_odom_base = transform_matrix(frames["odom", "base_link"].transform)
        ref = same(T_map_odom, by_stamp[stamp], "T_cad_map", 1e-3)
        assert np.abs(T_map_odom @ T_odom_base - matrix_from_pose(ref.T_cad_body))[:3].max() < 1e-3
        chains += 1
    assert chains >= 3
    # path: the Waypoints' points and yaws, stamped with the pose the plan started from
    plan, ros_path = waypoints_pb.items[-1], path.snapshot()[-1]
    assert ros_path.header.frame_id == "map" and stamp_ns_of(ros_path.header.stamp) == plan.header.stamp_ns
    assert plan.header.stamp_ns in {p.header.stamp_ns for p in poses_pb.items}  # the vehicle's clock
    points = np.array([[p.x, p.y, p.z] for p in plan.points_cad])
    assert np.linalg.norm(points[-1, :2] - goal_cad[:2]) < 0.3
    assert len(ros_path.poses) == len(points) == len(plan.yaw_rad)
    for ps, p, yaw in zip(ros_path.poses, points, plan.yaw_rad, strict=True):
        T = _T_of(ps.pose)
        assert np.allclose(T[:3, 3], p, atol=1e-9)
        assert abs(np.arctan2(T[1, 0], T[0, 0]) - yaw) < 1e-9
    diag = status.snapshot()[-1].status[0]
    assert diag.name == "macroloc: t1" and diag.level == 0  # OK: localized
    # PX4: the visual odometry is the CAD pose through the NED conversion (float32 on the wire)
    vios = [v for v in vio.snapshot() if v.timestamp_sample * 1000 in by_stamp]
    assert len(vios) >= 3
    assert {v.reset_counter for v in vio.snapshot()} == {0}  # no re-localization in this flight: no reset
    for v in vios:
        p_cad = np.array([v.position[1], v.position[0], -v.position[2]])  # NED -> ENU (CAD)
        refs = [r for r in by_stamp[v.timestamp_sample * 1000]
                if np.linalg.norm(matrix_from_pose(r.T_cad_body)[:3, 3] - p_cad) < 1e-3]
        assert refs, "the visual odometry's position is a CAD pose of its stamp, through NED, to 1 mm"
        T_cad_body = matrix_from_pose(refs[0].T_cad_body)
        assert v.pose_frame == 2  # FRD: Office_A's CAD frame is not geo-referenced to true north here
        R_frd = matrix_from_quat_wxyz(v.q.astype(float))
        R_expected = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]]) @ T_cad_body[:3, :3] @ np.diag([1, -1, -1])
        assert np.abs(R_frd - R_expected).max() < 1e-6
        assert np.isfinite(v.position_variance).all() and (v.position_variance > 0).all()
    # the setpoint's yaw follows the path's direction (NED: from north, clockwise)
    sp = setpoint.snapshot()[-1]
    sp_xyz = np.array([sp.position[1], sp.position[0], -sp.position[2]])  # NED -> CAD
    i = int(np.argmin(np.linalg.norm(points - sp_xyz, axis=1)))
    assert np.linalg.norm(points[i] - sp_xyz) < 1e-3
    leg = points[min(i + 1, len(points) - 1)] - points[i] if i < len(points) - 1 else points[i] - points[i - 1]
    assert abs(np.angle(np.exp(1j * (sp.yaw - np.arctan2(leg[0], leg[1]))))) < 1e-5 or \
        (i == len(points) - 1)
    assert all(o.position and not o.velocity for o in offboard.snapshot())


def test_reset_counter_counts_anchor_jumps_not_refinements() -> None:
    """T_cad_map refined by millimetres keeps the counter; a re-localization that moves it 0.5 m (or 5 deg) adds
    one, exactly at that estimate."""
    rng = np.random.default_rng(0)
    counter = ResetCounter(jump_m=0.10, jump_rad=np.deg2rad(2.0))
    T = yaw_T(0.4, np.array([2.0, 1.0, 0.0]))
    counts = []
    for k in range(40):
        if k in (15, 30):
            T = T @ (yaw_T(0.0, np.array([0.5, 0.0, 0.0])) if k == 15 else yaw_T(np.deg2rad(5.0), np.zeros(3)))
        else:
            T = T @ yaw_T(float(rng.normal(0, 1e-4)), rng.normal(0, 0.002, 3))
        counts.append(counter.update(T if k != 20 else None))  # one estimate without an anchor (lost)
    assert counts[:15] == [0] * 15 and counts[15:30] == [1] * 15 and counts[30:] == [2] * 10


@pytest.mark.slow
def test_the_demo_can_be_watched_live_through_listen(tmp_path) -> None:
    """`macroloc demo --listen ENDPOINT --ros`: a session connected to that endpoint (as zenoh-bridge-ros2dds would
    be) receives the demo's ROS poses in `map` while it flies; the goal's latitude/longitude come back. In real
    time: at 3x and 4x the simulated clock (with the ROS outputs) the vehicle circled its waypoints and gave up
    (2026-12-03), the localization itself on track."""
    from macroloc.cli.demo import DemoParams, run_demo

    port = free_port()
    poses: list[Any] = []
    result: dict[str, Any] = {}
    demo = threading.Thread(target=lambda: result.setdefault("r", run_demo(params=DemoParams(
        seed=0, speedup=1.0, vehicle="drone1", listen=(f"tcp/127.0.0.1:{port}",), ros=True, observations="truth"))),
        daemon=True)
    demo.start()
    from tests.service.helpers import loopback

    conf = loopback(connect=[f"tcp/127.0.0.1:{port}"])
    from macroloc.service.zenoh_io import session_config

    deadline_s = 120.0
    wait_for(lambda: _can_connect(port), deadline_s, "the demo's listening endpoint")
    with zenoh.open(session_config(conf)) as s:
        s.declare_subscriber("drone1/macroloc/pose", lambda smp: poses.append(
            from_cdr(smp.payload.to_bytes(), "geometry_msgs/msg/PoseWithCovarianceStamped")))
        demo.join(timeout=300.0)
    assert "r" in result and result["r"].reached
    assert len(poses) > 10 and all(p.header.frame_id == "map" for p in poses)
    lat, lon, _ = result["r"].goal_wgs84
    assert abs(lat - 42.358) < 0.01 and abs(lon + 71.060) < 0.01  # Office_A's IfcSite is in Boston


def _can_connect(port: int) -> bool:
    import socket

    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def test_reset_counter_increments_exactly_at_a_re_localization_in_a_flight(office_model) -> None:
    """A flight through the service's front end: localized, then the pose graph fails (an odometry sample at
    x = 1e300 let through past the edge checks) and restarts LOST, then the vehicle flies on and is localized
    again. VehicleOdometry's reset_counter is 0 throughout the first localization and 1 from the first pose after
    the re-localization on, while T_cad_map itself barely moved (same odometry frame)."""
    from macroloc.service.front_end import FrontEnd
    from macroloc.service.health import DropCounter
    from macroloc.service.inputs import InputParser, OdometryIn
    from macroloc.service.px4 import Px4Messages
    from tests.service.helpers import FakeFlight

    backend = FrontEnd.fresh_or_restored(office_model, None)
    parser, messages = InputParser(["front"], DropCounter()), Px4Messages()
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    T = yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])
    flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
    counts: list[tuple[str, int]] = []

    def step(k: int, T_cad_body: np.ndarray) -> None:
        stamp = (k + 1) * 33_000_000
        est = backend.odometry(parser.odometry(flight.odometry(stamp, T_cad_body).SerializeToString()))
        if k % 5 == 0:
            est = backend.observations(parser.observations(flight.observations(stamp, T_cad_body)
                                                           .SerializeToString())) or est
        if est.T_cad_body is not None and est.status in ("localized", "degraded"):
            counts.append((est.status, int(messages.odometry(est, None).reset_counter)))
        else:
            messages.reset.update(None, est.status)
            counts.append((est.status, -1))

    for k in range(40):
        step(k, T)
        T = T @ yaw_T(0.0, np.array([0.02, 0.0, 0.0]))
    assert counts[-1] == ("localized", 0)
    lost = backend.odometry(OdometryIn(41 * 33_000_000, yaw_T(0.0, np.array([1e300, 0.0, 1.4]))))
    assert lost.status == "lost" and backend.graph_restarts == 1
    messages.reset.update(None, lost.status)
    n = len(counts)
    for k in range(42, 120):
        step(k, T)
        T = T @ yaw_T(0.0, np.array([0.02, 0.0, 0.0]))
    after = [c for _, c in counts[n:] if c >= 0]
    assert after and set(after) == {1}, counts[n:]
    assert all(c == 0 for _, c in counts[:n] if c >= 0)


def test_a_ros_goal_is_checked_as_the_protobuf_goal_is() -> None:
    """Issue 57 item 6: the ROS goal goes through InputParser.goal: a stamp a day and more ahead (here the largest a
    builtin_interfaces/Time holds, 2038), a position outside the model or not finite is refused and counted; another
    frame than `map` counts as ros_goal/wrong_frame; a goal in the model, stamped now or unstamped, is taken."""
    from macroloc.service.health import DropCounter
    from macroloc.service.inputs import InputLimits, InputParser
    from macroloc.service.ros_out import RosInputs, RosKeys

    drops = DropCounter()
    parser = InputParser(["front"], drops, InputLimits(bounds_cad=(np.full(3, -10.0), np.full(3, 30.0))))
    parser.stamps.now_ns = lambda: 1_800_000_000 * 10**9
    inputs = RosInputs(RosKeys("t1"))
    (key, (parse, name, _, _)), = inputs.intakes(parser).items()
    assert (key, name) == ("t1/macroloc/goal", "goal")

    def goal(x: float, sec: int, frame: str = "map") -> bytes:
        m = msg("geometry_msgs/msg/PoseStamped")(
            header=msg("std_msgs/msg/Header")(stamp=msg("builtin_interfaces/msg/Time")(sec=sec, nanosec=999_999_999),
                                              frame_id=frame),
            pose=msg("geometry_msgs/msg/Pose")(position=msg("geometry_msgs/msg/Point")(x=x, y=1.0, z=1.0),
                                               orientation=msg("geometry_msgs/msg/Quaternion")(x=0, y=0, z=0, w=1)))
        return to_cdr(m, "geometry_msgs/msg/PoseStamped")

    assert parse(goal(5.0, 2**31 - 1)) is None
    assert parse(goal(1e300, 0)) is None
    assert parse(goal(float("nan"), 0)) is None
    assert parse(goal(5.0, 0, "odom")) is None
    taken = parse(goal(5.0, 1_800_000_000))
    assert taken is not None and np.allclose(taken.goal.position_cad, [5.0, 1.0, 1.0])
    assert parse(goal(5.0, 0)) is not None
    assert drops.counts() == {"goal/future_stamp": 1, "goal/out_of_bounds": 1, "goal/nan": 1,
                              "ros_goal/wrong_frame": 1}
