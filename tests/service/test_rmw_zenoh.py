"""Issue 57 item 1: `[ros] middleware = "rmw_zenoh"`: macroloc as an rmw_zenoh node, checked by a Zenoh session that
plays another rmw_zenoh node with keys built by an implementation this project did not write (pamoja-ros2's
`entity_key`, rmw_zenoh's documented examples) and RIHS01 hashes as rosidl generated them (GOLDEN_RIHS01: the values
published by rmw_zenoh's docs/design.md and by several independent ROS 2 clients), payloads decoded with rosbags'
own Jazzy typestore (not macroloc's)."""

from __future__ import annotations

import struct
import threading
import time
from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.service.config import Px4Config, RosConfig
from macroloc.service.ros_transport import (
    RmwZenohTransport,
    attachment,
    dds_type_name,
    mangle,
    type_hash,
)
from tests.service.helpers import FakeFlight, client, free_port, running_service, service_config, wait_for, yaw_T
from tests.service.test_service import _query, fly

ros2 = pytest.importorskip("pamoja.ros2", reason="pamoja-ros2 (dev extra) is the independent key implementation")

# RIHS01 of the standard types as rosidl generates them (Jazzy .. Lyrical), from sources outside this project:
# std_msgs/String is rmw_zenoh's docs/design.md example; the others are the values that independent ROS 2 clients
# (C, Rust, Swift, Go, Elixir) and rosbag2 metadata publish for these types.
GOLDEN_RIHS01 = {
    "std_msgs/msg/String": "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    "geometry_msgs/msg/PoseStamped": "10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "nav_msgs/msg/Odometry": "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "nav_msgs/msg/Path": "1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    "tf2_msgs/msg/TFMessage": "e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "diagnostic_msgs/msg/DiagnosticArray": "5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
    "sensor_msgs/msg/Imu": "7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    "sensor_msgs/msg/Image": "d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
}
QOS_KEYEXPR = "::,10:,:,:,,"  # reliable, volatile, keep-last 10 in rmw_zenoh's compact form (its design.md examples)
JAZZY = get_typestore(Stores.ROS2_JAZZY)  # rosbags' own definitions: not macroloc's typestore
POSE, ODOM, PATH, TF = ("geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry", "nav_msgs/msg/Path",
                        "tf2_msgs/msg/TFMessage")
GOAL, IMU = "geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/Imu"


def independent_key(topic: str, typename: str, domain_id: int = 0) -> str:
    """The data key another rmw_zenoh implementation builds (pamoja-ros2) with the published RIHS01 hash."""
    key = ros2.entity_key(domain_id, topic, typename, "RIHS01_" + GOLDEN_RIHS01[typename])
    assert key is not None, (topic, typename)
    return key


def test_type_hashes_and_key_assembly_agree_with_independent_implementations() -> None:
    for typename, digest in GOLDEN_RIHS01.items():
        assert type_hash(typename) == "RIHS01_" + digest, typename
        assert dds_type_name(typename) == ros2.dds_type_name(typename)
    # rmw_zenoh's docs/design.md examples, to the character
    assert RmwZenohTransport.key(_transport_stub(0), "chatter", "std_msgs/msg/String") == \
        "0/chatter/std_msgs::msg::dds_::String_/RIHS01_" + GOLDEN_RIHS01["std_msgs/msg/String"]
    assert RmwZenohTransport.key(_transport_stub(0), "/robot1/chatter", "std_msgs/msg/String") == \
        "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_" + GOLDEN_RIHS01["std_msgs/msg/String"]
    for topic in ("/t1/macroloc/pose", "/tf", "/ns/t1/macroloc/goal"):
        for typename in GOLDEN_RIHS01:
            for domain_id in (0, 7):
                assert RmwZenohTransport.key(_transport_stub(domain_id), topic, typename) == \
                    independent_key(topic, typename, domain_id)
        assert mangle(topic) == ros2.percent_mangle(topic)
    # the attachment: int64 LE sequence number, int64 LE source timestamp, GID length, GID (33 bytes)
    gid = bytes(range(16))
    raw = attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(raw) == 33 and raw[:8] == (7).to_bytes(8, "little") and raw[16] == 16 and raw[17:] == gid
    assert int.from_bytes(raw[8:16], "little", signed=True) == 1_700_000_000_123_456_789


def _transport_stub(domain_id: int) -> RmwZenohTransport:
    """A transport without a session, for its key assembly alone."""
    stub = RmwZenohTransport.__new__(RmwZenohTransport)
    stub.domain_id = domain_id
    return stub


class RmwSubscriber:
    """Samples of one rmw_zenoh topic: the decoded message and its attachment (sequence, timestamp ns, GID)."""

    def __init__(self, session: zenoh.Session, topic: str, typename: str) -> None:
        self.typename = typename
        self.items: list[tuple[Any, tuple[int, int, bytes]]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(independent_key(topic, typename), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        raw = sample.attachment.to_bytes() if sample.attachment is not None else b""
        assert len(raw) == 33 and raw[16] == 16, f"attachment of {len(raw)} bytes"
        seq, stamp_ns = struct.unpack_from("<qq", raw)
        message = JAZZY.deserialize_cdr(sample.payload.to_bytes(), self.typename)
        with self._lock:
            self.items.append((message, (seq, stamp_ns, raw[17:])))

    def snapshot(self) -> list[tuple[Any, tuple[int, int, bytes]]]:
        with self._lock:
            return list(self.items)


def _ros_time(stamp_ns: int) -> Any:
    return JAZZY.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)


def _header(stamp_ns: int, frame: str) -> Any:
    return JAZZY.types["std_msgs/msg/Header"](stamp=_ros_time(stamp_ns), frame_id=frame)


def _goal(xyz: np.ndarray) -> bytes:
    T = JAZZY.types
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    return bytes(JAZZY.serialize_cdr(T[GOAL](header=_header(0, "map"), pose=pose), GOAL))


def _imu(stamp_ns: int) -> bytes:
    T = JAZZY.types
    v3, q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    msg = T[IMU](header=_header(stamp_ns, "base_link"), orientation=q, orientation_covariance=np.zeros(9),
                 angular_velocity=v3(x=0.0, y=0.0, z=0.01), angular_velocity_covariance=np.zeros(9),
                 linear_acceleration=v3(x=0.0, y=0.0, z=9.81), linear_acceleration_covariance=np.zeros(9))
    return bytes(JAZZY.serialize_cdr(msg, IMU))


class PlayedNode:
    """The other side's rmw_zenoh node ('operator' in /ground): its liveliness tokens and publishers with the
    attachment, keys from pamoja-ros2."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session, self.zid = session, str(session.info.zid())
        self.tokens = [session.liveliness().declare_token(f"@ros2_lv/0/{self.zid}/0/0/NN/%/%ground/operator")]
        self.seq = 0

    def put(self, topic: str, typename: str, payload: bytes) -> None:
        self.seq += 1
        self.tokens.append(self.session.liveliness().declare_token(
            f"@ros2_lv/0/{self.zid}/0/{self.seq}/MP/%/%ground/operator/{ros2.percent_mangle(topic)}/"
            f"{ros2.dds_type_name(typename)}/RIHS01_{GOLDEN_RIHS01[typename]}/{QOS_KEYEXPR}"))
        self.session.put(independent_key(topic, typename), payload,
                         attachment=struct.pack("<qqB", self.seq, time.time_ns(), 16) + bytes(16))


def _tokens(session: zenoh.Session) -> list[list[str]]:
    return [str(r.ok.key_expr).split("/") for r in session.liveliness().get("@ros2_lv/0/**", timeout=5.0) if r.ok]


@pytest.fixture(scope="module")
def start_pose(office_model) -> np.ndarray:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    return yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])


def test_a_ros2_node_on_rmw_zenoh_hears_macroloc_and_is_heard(office_path, office_model, start_pose,
                                                              tmp_path) -> None:
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    cfg.ros = RosConfig(enabled=True, middleware="rmw_zenoh", imu="/imu0")
    cfg.px4 = Px4Config(enabled=True)
    cfg.graph.surface_check = False
    with running_service(cfg) as service, client(port) as s:
        pose, odom = RmwSubscriber(s, "/t1/macroloc/pose", POSE), RmwSubscriber(s, "/t1/macroloc/odometry", ODOM)
        path, tf = RmwSubscriber(s, "/t1/macroloc/path", PATH), RmwSubscriber(s, "/tf", TF)
        bridge_pose: list[zenoh.Sample] = []  # the bridge's keys stay silent in this mode
        bridge_sub = s.declare_subscriber("t1/macroloc/pose", bridge_pose.append)
        tokens = _tokens(s)
        flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: len(pose.snapshot()) >= 3 and len(tf.snapshot()) >= 3 and odom.snapshot(), what="ROS poses")
        # the reverse: a goal from the played node, on its own keys with its attachment and tokens
        reachable = _query(s, "macroloc/t1/plan", pb.Waypoints, pb.Goal(space_name="MENS RR").SerializeToString())
        goal_cad = np.array([reachable.points_cad[-1].x, reachable.points_cad[-1].y, reachable.points_cad[-1].z])
        node = PlayedNode(s)
        node.put("/t1/macroloc/goal", GOAL, _goal(goal_cad))
        fly(s, flight, T, 3, first_stamp_ns=10**9)
        wait_for(lambda: path.snapshot(), what="a Path planned to the goal the rmw_zenoh node sent")
        imu_before = service.rates["imu"].total  # type: ignore[attr-defined]
        for k in range(5):
            node.put("/imu0", IMU, _imu(5 * 10**9 + k * 10**7))
        wait_for(lambda: service.rates["imu"].total >= imu_before + 5,  # type: ignore[attr-defined]
                 what="the rmw_zenoh node's IMU taken")
        seen_from_macroloc = _tokens(s)
        bridge_sub.undeclare()
    assert not bridge_pose

    # liveliness: the node and one token per publisher and subscription, as rmw_zenoh's Entity::make parses them
    ours = [t for t in tokens if t[8] == "macroloc"]
    assert [t[5:9] for t in ours if t[5] == "NN"] == [["NN", "%", "%t1", "macroloc"]]
    endpoints = {(t[5], t[9], t[10], t[11], t[12]) for t in ours if t[5] != "NN"}
    assert len({t[4] for t in ours if t[5] != "NN"}) == len(endpoints)  # entity ids unique
    for kind, topic, typename in [("MP", "/t1/macroloc/pose", POSE), ("MP", "/t1/macroloc/odometry", ODOM),
                                  ("MP", "/t1/macroloc/path", PATH), ("MP", "/tf", TF),
                                  ("MP", "/t1/macroloc/status", "diagnostic_msgs/msg/DiagnosticArray"),
                                  ("MS", "/t1/macroloc/goal", GOAL), ("MS", "/imu0", IMU)]:
        assert (kind, ros2.percent_mangle(topic), ros2.dds_type_name(typename), "RIHS01_" + GOLDEN_RIHS01[typename],
                QOS_KEYEXPR) in endpoints, (kind, topic)
    assert ("MP", "%fmu%in%vehicle_visual_odometry") in {(k, t) for k, t, *_ in endpoints}
    assert {t[2] for t in ours} == {t[2] for t in seen_from_macroloc if t[8] == "macroloc"}  # one session id
    assert any(t[5:9] == ["NN", "%", "%ground", "operator"] for t in seen_from_macroloc)

    # samples: decoded by rosbags' Jazzy types; attachment sequence numbers count up per publisher from 1, source
    # timestamps are this machine's clock, the GID is one per publisher
    for sub, frame in ((pose, "map"), (odom, "map"), (path, "map")):
        items = sub.snapshot()
        assert all(m.header.frame_id == frame for m, _ in items)
        seqs = [a[0] for _, a in items]
        assert seqs == sorted(seqs) and seqs[0] >= 1 and len(set(seqs)) == len(seqs)
        assert all(abs(a[1] - time.time_ns()) < 600 * 10**9 for _, a in items)
        assert len({a[2] for _, a in items}) == 1
    gids = {sub.snapshot()[0][1][2] for sub in (pose, odom, path, tf)}
    assert len(gids) == 4
    assert all({(t.header.frame_id, t.child_frame_id) for t in m.transforms} <= {("map", "odom"), ("odom", "base_link")}
               for m, _ in tf.snapshot())
    assert np.isfinite(pose.snapshot()[-1][0].pose.covariance).all()
    last = path.snapshot()[-1][0].poses[-1].pose.position
    assert np.linalg.norm(np.array([last.x, last.y]) - goal_cad[:2]) < 0.3
