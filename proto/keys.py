"""The wire on Zenoh: the key expressions of one vehicle (DESIGN.md) and publishers of `macroloc.v1` protobuf
messages with the protobuf encoding set. Shared by the service, the simulated vehicle, replay and the benchmarks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import zenoh

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

    @property
    def initialpose(self) -> str:
        """The operator's prior (a PoseEstimate: T_cad_body and/or storey; graph.prior)."""
        return self._k("initialpose")

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


def put_message(publisher: Any, message: Any) -> None:
    """Serialize a protobuf message and put it through a publisher declared with the protobuf encoding."""
    publisher.put(message.SerializeToString())


def declare_publisher(session: zenoh.Session, key: str, express: bool = True, block: bool = False) -> zenoh.Publisher:
    """`block`: wait when the link is congested instead of dropping (Zenoh's default for puts): for a lock-step
    vehicle that waits for every answer, a dropped message would stall the loop."""
    congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
    return session.declare_publisher(key, encoding=PROTOBUF, express=express, congestion_control=congestion)
