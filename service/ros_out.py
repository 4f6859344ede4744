"""ROS 2 through Zenoh without ROS: macroloc's estimates and plans as CDR messages on ROS 2 topics, and the ROS goal
in. Where a topic lives on Zenoh is the `service.ros_transport` strategy's: the keys `zenoh-bridge-ros2dds` maps
(ROS topic `/<ns>/<vehicle>/macroloc/pose` <-> Zenoh key `<ns>/<vehicle>/macroloc/pose`, the default), or
rmw_zenoh's own keys, attachment and liveliness tokens (`[ros] middleware = "rmw_zenoh"`). Topics below are
given as the bridge's keys (the ROS topic without its leading slash).

Frames (REP-105): `map` is macroloc's `cad` (the building model's frame), `odom` is macroloc's `map` (the flight's
odometry frame), `base_link` is `body` (FLU). Out:
- `<vehicle>/macroloc/pose`      geometry_msgs/msg/PoseWithCovarianceStamped, frame `map` (localized poses only)
- `<vehicle>/macroloc/odometry`  nav_msgs/msg/Odometry, frame `map`, child `base_link`; twist in `base_link`
- `<vehicle>/macroloc/path`      nav_msgs/msg/Path, frame `map`: the waypoints with their yaws
- `tf`                           tf2_msgs/msg/TFMessage: `map -> odom` (T_cad_map, once localized), `odom -> base_link`
- `<vehicle>/macroloc/status`    diagnostic_msgs/msg/DiagnosticArray
Covariances are in ROS order: x, y, z (m^2), rotation about x, y, z (rad^2), about the header frame's axes
(`service.ned.cov_ros_from_gtsam`); an unknown twist has covariance[0] = -1 (ROS's "unknown").
In: `<vehicle>/macroloc/goal` geometry_msgs/msg/PoseStamped, frame `map` (= CAD): a goal position.
ROS sensor inputs (Image, CameraInfo, Imu) plug in through `RosInputs.intakes` (service.ros_in converts them).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from macroloc.graph.localizer import Estimate
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.ros_types import from_cdr, header, msg, stamp_ns_of, to_cdr
from macroloc.service.inputs import GoalIn, InputParser, PriorIn
from macroloc.service.ned import cov_ros_from_gtsam, quat_wxyz_from_matrix
from macroloc.service.ros_transport import RosTransport
from macroloc.service.vehicle_out import Motion, waypoints_arrays

log = logging.getLogger(__name__)

POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
PATH = "nav_msgs/msg/Path"
TF = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
STRING = "std_msgs/msg/String"
UNKNOWN_COV = np.diag([-1.0, 0, 0, 0, 0, 0])  # ROS: covariance[0] = -1 means the value is unknown


@dataclass(frozen=True)
class RosFrames:
    """REP-105 frame ids: `map` = macroloc's cad, `odom` = macroloc's map, `base_link` = body."""

    map: str = "map"
    odom: str = "odom"
    base_link: str = "base_link"


@dataclass(frozen=True)
class RosKeys:
    """Zenoh keys of the ROS topics, as zenoh-bridge-ros2dds names them (the topic without its leading slash)."""

    vehicle: str
    namespace: str = ""

    def _k(self, leaf: str) -> str:
        ns = self.namespace.strip("/")
        return f"{ns}/{leaf}" if ns else leaf

    def topic(self, name: str) -> str:
        return self._k(f"{self.vehicle}/macroloc/{name}")

    def of(self, ros_topic: str) -> str:
        """The Zenoh key of any ROS topic (e.g. /cam0/image_raw); "" for none."""
        return self._k(ros_topic.lstrip("/")) if ros_topic else ""

    @property
    def tf(self) -> str:
        return self._k("tf")


def _pose(T: np.ndarray) -> Any:
    w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
    return msg("geometry_msgs/msg/Pose")(position=msg("geometry_msgs/msg/Point")(x=float(T[0, 3]), y=float(T[1, 3]),
                                                                                 z=float(T[2, 3])),
                                         orientation=msg("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))


def _transform(stamp_ns: int, parent: str, child: str, T: np.ndarray) -> Any:
    w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
    tr = msg("geometry_msgs/msg/Transform")(
        translation=msg("geometry_msgs/msg/Vector3")(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        rotation=msg("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))
    return msg("geometry_msgs/msg/TransformStamped")(header=header(stamp_ns, parent), child_frame_id=child,
                                                     transform=tr)


def _vector3(v: np.ndarray) -> Any:
    return msg("geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _yaw_R(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class RosMessages:
    """Estimates, plans and status as ROS 2 messages (rosbags' classes); no transport."""

    def __init__(self, vehicle: str, frames: RosFrames | None = None, odom_tf: bool = False) -> None:
        """`odom_tf`: also `odom -> base_link` on /tf (REP-105: the vehicle's VIO usually owns it; off unless
        `[ros] odom_tf`)."""
        self.vehicle = vehicle
        self.frames = frames or RosFrames()
        self.odom_tf = odom_tf

    def pose_with_covariance(self, est: Estimate) -> Any:
        """PoseWithCovarianceStamped of T_cad_body (frame `map`); requires a localized estimate."""
        assert est.T_cad_body is not None
        cov = self.covariance_ros(est)
        pwc = msg("geometry_msgs/msg/PoseWithCovariance")(pose=_pose(est.T_cad_body), covariance=cov.ravel())
        return msg(POSE_COV)(header=header(est.stamp_ns, self.frames.map), pose=pwc)

    def covariance_ros(self, est: Estimate) -> np.ndarray:
        """6x6 ROS-order covariance of T_cad_body (module doc); zeros where the estimate has none."""
        assert est.T_cad_body is not None
        if est.covariance is None:
            return np.zeros((6, 6))
        return cov_ros_from_gtsam(np.asarray(est.covariance, float), est.T_cad_body[:3, :3])

    def odometry(self, est: Estimate, velocity_cad: np.ndarray | None) -> Any:
        """Odometry: pose as `pose_with_covariance`, twist in `base_link` (linear only, from `Motion`)."""
        assert est.T_cad_body is not None
        pose = self.pose_with_covariance(est).pose
        if velocity_cad is None:
            twist_cov, v_body = UNKNOWN_COV, np.zeros(3)
        else:
            twist_cov, v_body = np.zeros((6, 6)), est.T_cad_body[:3, :3].T @ velocity_cad
        twist = msg("geometry_msgs/msg/Twist")(linear=_vector3(v_body), angular=_vector3(np.zeros(3)))
        twc = msg("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=twist_cov.ravel())
        return msg(ODOMETRY)(header=header(est.stamp_ns, self.frames.map), child_frame_id=self.frames.base_link,
                             pose=pose, twist=twc)

    def tf(self, est: Estimate) -> Any:
        """`map -> odom` (T_cad_map) where localized (REP-105: a localizer publishes map -> odom), and
        `odom -> base_link` (T_map_body) only with `odom_tf`; None where that leaves nothing."""
        f = self.frames
        transforms = [_transform(est.stamp_ns, f.odom, f.base_link, est.T_map_body)] if self.odom_tf else []
        if est.T_cad_map is not None:
            transforms.insert(0, _transform(est.stamp_ns, f.map, f.odom, est.T_cad_map))
        return msg(TF)(transforms=transforms) if transforms else None

    def path(self, plan: pb.Waypoints) -> Any:
        """The waypoints as a Path in `map`, each pose turned to its yaw, stamped with the plan's stamp."""
        points, yaws = waypoints_arrays(plan)
        stamp_ns = plan.header.stamp_ns
        poses = []
        for p, yaw in zip(points, yaws, strict=True):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = _yaw_R(float(yaw)), p
            poses.append(msg(POSE_STAMPED)(header=header(stamp_ns, self.frames.map), pose=_pose(T)))
        return msg(PATH)(header=header(stamp_ns, self.frames.map), poses=poses)

    def diagnostics(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> Any:
        """One DiagnosticStatus: OK when localized, WARN while exploring, ambiguous or degraded, ERROR when lost."""
        Status = msg("diagnostic_msgs/msg/DiagnosticStatus")
        KeyValue = msg("diagnostic_msgs/msg/KeyValue")
        level = {pb.PoseEstimate.LOCALIZED: Status.OK, pb.PoseEstimate.LOST: Status.ERROR}.get(status.status,
                                                                                              Status.WARN)
        values = [KeyValue(key="status", value=diag.state), KeyValue(key="keyframes", value=str(status.keyframes)),
                  KeyValue(key="landmarks", value=str(status.landmarks))]
        values += [KeyValue(key=f"rate_hz/{k}", value=f"{v:.2f}") for k, v in sorted(diag.rates_hz.items())]
        values += [KeyValue(key=f"latency_ms/{k}", value=f"{v:.2f}") for k, v in sorted(diag.latencies_ms.items())]
        values += [KeyValue(key=f"dropped/{k}", value=str(v)) for k, v in sorted(diag.dropped.items())]
        entry = Status(level=level, name=f"macroloc: {self.vehicle}", message=diag.state,
                       hardware_id=self.vehicle, values=values)
        return msg(DIAGNOSTICS)(header=header(diag.header.stamp_ns, ""), status=[entry])


TOPIC_TYPES = {"pose": POSE_COV, "odometry": ODOMETRY, "path": PATH, "status": DIAGNOSTICS}


class RosOutput:
    """Publishes `RosMessages` as CDR through a `RosTransport` (the bridge's keys or rmw_zenoh's; a
    `service.vehicle_out.VehicleOutput`)."""

    def __init__(self, transport: RosTransport, keys: RosKeys, frames: RosFrames | None = None,
                 odom_tf: bool = False) -> None:
        self.keys = keys
        self.messages = RosMessages(keys.vehicle, frames, odom_tf)
        self.motion = Motion()
        self._pubs = {name: transport.publisher(keys.topic(name), typename) for name, typename in TOPIC_TYPES.items()}
        self._pubs["tf"] = transport.publisher(keys.tf, TF)

    def _put(self, name: str, message: Any, typename: str) -> None:
        self._pubs[name].put(to_cdr(message, typename))

    def pose(self, est: Estimate) -> None:
        velocity = self.motion.velocity_cad(est)
        if est.T_cad_body is not None and est.status in ("localized", "degraded"):
            self._put("pose", self.messages.pose_with_covariance(est), POSE_COV)
            self._put("odometry", self.messages.odometry(est, velocity), ODOMETRY)
        tf = self.messages.tf(est)
        if tf is not None:
            self._put("tf", tf, TF)

    def waypoints(self, plan: pb.Waypoints) -> None:
        if not plan.error:
            self._put("path", self.messages.path(plan), PATH)

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        self._put("status", self.messages.diagnostics(diag, status), DIAGNOSTICS)

    def close(self) -> None:
        for pub in self._pubs.values():
            pub.undeclare()


def goal_from_pose_stamped(payload: bytes, frames: RosFrames | None = None) -> pb.Goal | None:
    """A ROS goal (geometry_msgs/msg/PoseStamped in `map` = CAD) as the service's wire Goal (frame `cad`, the
    header's stamp in ns), to be checked by `InputParser.goal` as a goal on the protobuf key is; None in another
    frame. Raises on a payload that is not CDR of that type."""
    m = from_cdr(payload, POSE_STAMPED)
    if m.header.frame_id not in ("", (frames or RosFrames()).map):
        return None
    p = m.pose.position
    goal = pb.Goal(position_cad=pb.Vector3(x=p.x, y=p.y, z=p.z))
    goal.header.frame_id, goal.header.stamp_ns = "cad", stamp_ns_of(m.header.stamp)
    return goal


def prior_from_initialpose(payload: bytes, frames: RosFrames | None = None) -> pb.PoseEstimate | None:
    """Nav2's /initialpose (geometry_msgs/msg/PoseWithCovarianceStamped in `map` = CAD, rviz's 2D Pose Estimate)
    as the service's wire prior (a PoseEstimate, frame `cad`; the ROS covariance, x y z rotx roty rotz about `map`'s
    axes, read for its x, y and yaw variances into the wire's [rot; trans] diagonal: a prior's gate uses no more),
    to be checked by `InputParser.prior`; None in another frame. Raises on a payload that is not CDR of that type."""
    m = from_cdr(payload, POSE_COV)
    if m.header.frame_id not in ("", (frames or RosFrames()).map):
        return None
    p, q = m.pose.pose.position, m.pose.pose.orientation
    cov_ros = np.asarray(m.pose.covariance, float).reshape(6, 6)
    prior = pb.PoseEstimate(T_cad_body=pb.Pose(position=pb.Vector3(x=p.x, y=p.y, z=p.z), qw=q.w, qx=q.x, qy=q.y,
                                               qz=q.z))
    prior.covariance.extend(np.diag([cov_ros[3, 3], cov_ros[4, 4], cov_ros[5, 5],
                                     cov_ros[0, 0], cov_ros[1, 1], cov_ros[2, 2]]).ravel())
    prior.header.frame_id, prior.header.stamp_ns = "cad", stamp_ns_of(m.header.stamp)
    return prior


class RosInputs:
    """The ROS topics the service takes: the goal, checked by the service's `InputParser` like its protobuf twin
    (ROS sensor inputs: service.ros_sensors; the operator's prior: `RosPriorInputs`)."""

    def __init__(self, keys: RosKeys, frames: RosFrames | None = None, transport: RosTransport | None = None) -> None:
        """`transport`: where the goal topic is (and announces its subscription); the bridge's keys by default."""
        self.keys = keys
        self.frames = frames or RosFrames()
        self.goal_key = transport.subscription(keys.topic("goal"), POSE_STAMPED) if transport is not None else \
            keys.topic("goal")

    def intakes(self, parser: InputParser) -> dict[str, tuple[Any, str, bool, int]]:
        """key -> (parse(payload) -> event | None, rate name, heavy, ring size), as service.node's intakes."""
        return {self.goal_key: (lambda payload: self.goal(parser, payload), "goal", False, 8)}

    def goal(self, parser: InputParser, payload: bytes) -> GoalIn | None:
        """The ROS goal through `parser.goal` (bounds, finite, stamp not ahead); another frame counts as
        ros_goal/wrong_frame."""
        goal = goal_from_pose_stamped(payload, self.frames)
        if goal is None:
            parser.drops.drop("ros_goal/wrong_frame")
            return None
        return parser.goal(goal.SerializeToString())


class RosPriorInputs:
    """The operator's prior from ROS (graph.prior): Nav2's /initialpose and a storey's name (std_msgs/msg/String on
    `<vehicle>/macroloc/storey`), each checked by `InputParser.prior` like the protobuf `initialpose` key."""

    def __init__(self, keys: RosKeys, frames: RosFrames | None = None, transport: RosTransport | None = None,
                 initialpose: str = "/initialpose") -> None:
        """`transport`: where the topics are (and announces the subscriptions); the bridge's keys by default.
        `initialpose`: the initial pose's topic (Nav2's and rviz's `/initialpose`, under `[ros] namespace`; ''
        for none)."""
        self.frames = frames or RosFrames()

        def key(topic: str, typename: str) -> str:
            return transport.subscription(topic, typename) if transport is not None else topic

        self.initialpose_key = key(keys.of(initialpose), POSE_COV) if initialpose else ""
        self.storey_key = key(keys.topic("storey"), STRING)

    def intakes(self, parser: InputParser) -> dict[str, tuple[Any, str, bool, int]]:
        """key -> (parse(payload) -> event | None, rate name, heavy, ring size), as service.node's intakes."""
        intakes: dict[str, tuple[Any, str, bool, int]] = {
            self.storey_key: (lambda payload: self.storey(parser, payload), "initialpose", False, 8)}
        if self.initialpose_key:
            intakes[self.initialpose_key] = (lambda payload: self.initialpose(parser, payload), "initialpose",
                                             False, 8)
        return intakes

    def initialpose(self, parser: InputParser, payload: bytes) -> PriorIn | None:
        """/initialpose through `parser.prior`; another frame counts as ros_initialpose/wrong_frame."""
        prior = prior_from_initialpose(payload, self.frames)
        if prior is None:
            parser.drops.drop("ros_initialpose/wrong_frame")
            return None
        return parser.prior(prior.SerializeToString())

    def storey(self, parser: InputParser, payload: bytes) -> PriorIn | None:
        """A storey's name (std_msgs/msg/String) through `parser.prior`, as a prior with no pose."""
        prior = pb.PoseEstimate(storey=str(from_cdr(payload, STRING).data))
        prior.header.frame_id = "cad"
        return parser.prior(prior.SerializeToString())


class RosIntakes(Protocol):
    def intakes(self, parser: InputParser) -> dict[str, tuple[Any, str, bool, int]]:
        """key -> (parse(payload) -> event | None, rate name, heavy, ring size), as service.node's intakes."""


class AllRosIntakes:
    """Several ROS inputs as one (the goal, the vehicle's odometry topics)."""

    def __init__(self, parts: list[RosIntakes]) -> None:
        self.parts = parts

    def intakes(self, parser: InputParser) -> dict[str, tuple[Any, str, bool, int]]:
        return {key: intake for part in self.parts for key, intake in part.intakes(parser).items()}


class NullRosInputs:
    def intakes(self, parser: InputParser) -> dict[str, tuple[Any, str, bool, int]]:
        return {}
