"""Zenoh plumbing shared by the service, the vehicle agent, replay and the benchmarks.

`open_session(cfg)` builds a session config from an optional JSON5 file plus the typed overrides (peer mode on
loopback, multicast and gossip scouting off by default); `Keys` names every key expression of one vehicle.
Payloads are `macroloc.v1` protobuf messages with the protobuf encoding set.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import zenoh

from service.config import ZenohConfig

PROTOBUF = zenoh.Encoding.APPLICATION_PROTOBUF


@dataclass(frozen=True)
class Keys:
    """Key expressions under macroloc/<vehicle>/ (DESIGN.md)."""

    vehicle: str

    def _k(self, leaf: str) -> str:
        return f"macroloc/{self.vehicle}/{leaf}"

    # inputs
    @property
    def stereo(self) -> str:
        return self._k("stereo")

    @property
    def imu(self) -> str:
        return self._k("imu")

    @property
    def odometry(self) -> str:
        return self._k("odometry")

    @property
    def observations(self) -> str:
        return self._k("observations")

    @property
    def goal(self) -> str:
        return self._k("goal")

    # outputs
    @property
    def pose(self) -> str:
        return self._k("pose")

    @property
    def waypoints(self) -> str:
        return self._k("waypoints")

    @property
    def features(self) -> str:
        return self._k("features")

    @property
    def diagnostics(self) -> str:
        return self._k("diagnostics")

    @property
    def status(self) -> str:
        return self._k("status")

    @property
    def alive(self) -> str:
        return self._k("alive")

    # queryables
    @property
    def map(self) -> str:
        return self._k("map")

    @property
    def plan(self) -> str:
        return self._k("plan")


def session_config(cfg: ZenohConfig) -> zenoh.Config:
    """A zenoh.Config: the JSON5 file (if any), then mode, endpoints and scouting from the typed config."""
    conf = zenoh.Config.from_file(str(cfg.config_file)) if cfg.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.connect:
        conf.insert_json5("connect/endpoints", json.dumps(cfg.connect))
    if cfg.listen:
        conf.insert_json5("listen/endpoints", json.dumps(cfg.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(cfg.gossip_scouting))
    return conf


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    return zenoh.open(session_config(cfg))


def put_message(publisher: Any, message: Any) -> None:
    """Serialize a protobuf message and put it through a publisher declared with the protobuf encoding."""
    publisher.put(message.SerializeToString())


def declare_publisher(session: zenoh.Session, key: str, express: bool = True) -> zenoh.Publisher:
    return session.declare_publisher(key, encoding=PROTOBUF, express=express)
