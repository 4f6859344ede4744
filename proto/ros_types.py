"""ROS 2 message types without a ROS installation: rosbags' typestore (CDR with the encapsulation header).

`typestore()` is ROS 2 Humble's standard messages (geometry_msgs, nav_msgs, tf2_msgs, diagnostic_msgs,
sensor_msgs) plus the px4_msgs definitions shipped as `.msg` text in `proto/px4_msgs/msg/` (BSD-3, PX4
Development Team; see the LICENSE beside them), registered at run time as `px4_msgs/msg/<Name>`.
`to_cdr` / `from_cdr` are the little-endian CDR payloads `zenoh-bridge-ros2dds` carries between Zenoh and DDS.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

PX4_MSG_DIR = Path(__file__).resolve().parent / "px4_msgs" / "msg"
NS_PER_S = 1_000_000_000


@cache
def typestore() -> Typestore:
    """Humble's message types and px4_msgs' VehicleOdometry, TrajectorySetpoint and OffboardControlMode."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for path in sorted(PX4_MSG_DIR.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"px4_msgs/msg/{path.stem}"))
    store.register(types)
    return store


def msg(typename: str) -> Any:
    """The message class of a type name, e.g. msg('geometry_msgs/msg/PoseStamped')."""
    return typestore().types[typename]


def to_cdr(message: Any, typename: str) -> bytes:
    """A message as a CDR payload (little endian, with its 4-byte encapsulation header)."""
    return bytes(typestore().serialize_cdr(message, typename))


def from_cdr(payload: bytes, typename: str) -> Any:
    return typestore().deserialize_cdr(payload, typename)


def ros_time(stamp_ns: int) -> Any:
    """builtin_interfaces/msg/Time of a stamp in nanoseconds."""
    return msg("builtin_interfaces/msg/Time")(sec=int(stamp_ns // NS_PER_S), nanosec=int(stamp_ns % NS_PER_S))


def stamp_ns_of(time_msg: Any) -> int:
    return int(time_msg.sec) * NS_PER_S + int(time_msg.nanosec)


def header(stamp_ns: int, frame_id: str) -> Any:
    return msg("std_msgs/msg/Header")(stamp=ros_time(stamp_ns), frame_id=frame_id)
