"""How macroloc's ROS 2 topics travel on Zenoh: one strategy, picked once by `make_ros_transport` from
`[ros] middleware`, used by every ROS and PX4 publisher and subscription (service.ros_out, service.px4,
service.ros_sensors, service.odometry_in); no branch in the hot path.

- `BridgeTransport` ("bridge", the default): the keys `zenoh-bridge-ros2dds` maps to ROS 2 topics: ROS topic
  `/a/b` is Zenoh key `a/b`; CDR payloads, nothing else.
- `RmwZenohTransport` ("rmw_zenoh"): what a ROS 2 node running `rmw_zenoh_cpp` puts on Zenoh itself, following
  rmw_zenoh's `docs/design.md` (RMW_ZENOH_FOLLOWED below):
  - data key `<domain_id>/<fully qualified topic without its leading slash>/<DDS type name>/<RIHS01 type hash>`,
    e.g. `0/drone1/macroloc/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_26432f98...`; the
    hash is REP-2016's RIHS01 of the type's description, computed by rosbags from the same definitions the CDR
    payloads are written with (service.ros_types);
  - on every sample an attachment of 33 bytes: sequence number (int64, little endian, from 1 per publisher), source
    timestamp (int64 LE, ns since the UNIX epoch on this machine's clock), the GID's length (one byte, 16) and the
    publisher's 16-byte GID;
  - liveliness tokens: the node's `@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node name>`, and
    for each publisher (MP) and subscription (MS)
    `@ros2_lv/<domain>/<zid>/<nid>/<eid>/<MP|MS>/<enclave>/<namespace>/<node name>/<topic>/<type>/<hash>/<qos>`,
    names mangled (`/` -> `%`, `%` alone for an empty enclave or the root namespace), QoS reliable, volatile,
    keep-last 10 (rmw_zenoh's compact form `::,10:,:,:,,`: the defaults left empty), held while the service runs.
  The GID is the first 16 bytes of BLAKE2b of the entity's liveliness key (rmw_zenoh hashes the same key with
  XXH3-128; a GID is opaque to its readers, only unique).
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import struct
import time
from functools import cache
from typing import Protocol

import zenoh

from macroloc.proto.ros_types import typestore

log = logging.getLogger(__name__)

RMW_ZENOH_FOLLOWED = ("rmw_zenoh docs/design.md at ros2/rmw_zenoh commit 99a6a2bd (2025): the 33-byte attachment "
                      "of rmw_zenoh PR #601 (Humble 0.1.2 and the Jazzy/Kilted/Rolling releases after it)")
ADMIN_SPACE = "@ros2_lv"
QOS_DEPTH = 10
QOS_KEYEXPR = f"::,{QOS_DEPTH}:,:,:,,"  # reliable, volatile, keep-last (rmw_zenoh's defaults: left empty), depth 10
GID_BYTES = 16
_ATTACHMENT_HEAD = struct.Struct("<qqB")  # sequence number, source timestamp (ns), GID length


def dds_type_name(typename: str) -> str:
    """The DDS type name of a ROS type: 'geometry_msgs/msg/Pose' -> 'geometry_msgs::msg::dds_::Pose_'."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@cache
def type_hash(typename: str) -> str:
    """REP-2016's RIHS01 hash of a type ('RIHS01_' + 64 hex digits), from service.ros_types' definitions."""
    return typestore().hash_rihs01(typename)


def mangle(name: str) -> str:
    """rmw_zenoh's mangling of a name inside a liveliness key: every '/' becomes '%'; empty is '%'."""
    return name.replace("/", "%") or "%"


def fully_qualified(topic: str) -> str:
    """'/a/b' for 'a/b', '/a/b' or '/a/b/'."""
    return "/" + topic.strip("/")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment (module doc): 8 + 8 + 1 + 16 = 33 bytes."""
    return _ATTACHMENT_HEAD.pack(sequence_number, source_timestamp_ns, len(gid)) + gid


class RosPublisher(Protocol):
    def put(self, payload: bytes) -> None: ...

    def undeclare(self) -> None: ...


class RosTransport(Protocol):
    """Where a ROS topic of a type lives on Zenoh, and what announces it."""

    def publisher(self, topic: str, typename: str) -> RosPublisher:
        """A publisher of CDR payloads on the topic ('/a/b' or 'a/b')."""

    def subscription(self, topic: str, typename: str) -> str:
        """The Zenoh key to subscribe to for the topic (announced as this node's subscription where the middleware
        has announcements); the caller declares the subscriber."""

    def close(self) -> None:
        """Withdraw the announcements (before the session closes); publishers are undeclared by their owners."""


class BridgeTransport:
    """zenoh-bridge-ros2dds's keys: ROS topic `/a/b` is Zenoh key `a/b`; no attachment, no announcement."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session

    def key(self, topic: str, typename: str) -> str:
        return topic.strip("/")

    def publisher(self, topic: str, typename: str) -> RosPublisher:
        return self.session.declare_publisher(self.key(topic, typename), express=True)

    def subscription(self, topic: str, typename: str) -> str:
        return self.key(topic, typename)

    def close(self) -> None:
        pass


class RmwPublisher:
    """A Zenoh publisher whose samples carry rmw_zenoh's attachment (module doc), with its liveliness token."""

    def __init__(self, publisher: zenoh.Publisher, token: zenoh.LivelinessToken, gid: bytes) -> None:
        self._publisher, self._token, self.gid = publisher, token, gid
        self._sequence = itertools.count(1)

    def put(self, payload: bytes) -> None:
        self._publisher.put(payload, attachment=attachment(next(self._sequence), time.time_ns(), self.gid))

    def undeclare(self) -> None:
        self._publisher.undeclare()
        self._token.undeclare()


class RmwZenohTransport:
    """macroloc as one rmw_zenoh node (module doc): `node_namespace` '/' or '/a/b', `domain_id` ROS_DOMAIN_ID."""

    def __init__(self, session: zenoh.Session, domain_id: int = 0, node_namespace: str = "/",
                 node_name: str = "macroloc", enclave: str = "") -> None:
        self.session, self.domain_id = session, domain_id
        self.zid = str(session.info.zid())  # the session id as rmw_zenoh writes it (hex)
        self.node_id = 0
        self._node = (f"{mangle(enclave)}/{mangle(fully_qualified(node_namespace).rstrip('/'))}/"
                      f"{mangle(node_name)}")
        self.node_token_key = f"{self._head(self.node_id, 'NN')}/{self._node}"
        self._entity_ids = itertools.count(self.node_id + 1)
        self._tokens = [session.liveliness().declare_token(self.node_token_key)]
        self.token_keys = [self.node_token_key]

    def _head(self, entity_id: int, kind: str) -> str:
        return f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}"

    def key(self, topic: str, typename: str) -> str:
        """`<domain>/<topic without its leading slash>/<DDS type name>/<RIHS01 hash>`."""
        return f"{self.domain_id}/{topic.strip('/')}/{dds_type_name(typename)}/{type_hash(typename)}"

    def _entity_token(self, kind: str, topic: str, typename: str) -> str:
        key = (f"{self._head(next(self._entity_ids), kind)}/{self._node}/{mangle(fully_qualified(topic))}/"
               f"{dds_type_name(typename)}/{type_hash(typename)}/{QOS_KEYEXPR}")
        self.token_keys.append(key)
        return key

    def publisher(self, topic: str, typename: str) -> RosPublisher:
        token_key = self._entity_token("MP", topic, typename)
        gid = hashlib.blake2b(token_key.encode(), digest_size=GID_BYTES).digest()
        return RmwPublisher(self.session.declare_publisher(self.key(topic, typename), express=True),
                            self.session.liveliness().declare_token(token_key), gid)

    def subscription(self, topic: str, typename: str) -> str:
        self._tokens.append(self.session.liveliness().declare_token(self._entity_token("MS", topic, typename)))
        return self.key(topic, typename)

    def close(self) -> None:
        for token in reversed(self._tokens):  # the node's last
            token.undeclare()
        self._tokens.clear()


def make_ros_transport(middleware: str, session: zenoh.Session, domain_id: int = 0,
                       node_namespace: str = "/") -> RosTransport:
    """The strategy `[ros] middleware` names: "bridge" or "rmw_zenoh"."""
    if middleware == "rmw_zenoh":
        transport = RmwZenohTransport(session, domain_id, node_namespace)
        log.info("ROS 2 as an rmw_zenoh node: domain %d, node %s, %s", domain_id, transport.node_token_key,
                 RMW_ZENOH_FOLLOWED)
        return transport
    return BridgeTransport(session)
