"""Fake data and loopback Zenoh helpers for the service tests (no mocks: real sessions on 127.0.0.1)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import pose_from_matrix, vector3
from macroloc.service.config import MacrolocConfig, ZenohConfig, load_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback(mode: str = "peer", listen: list[str] | None = None, connect: list[str] | None = None) -> ZenohConfig:
    return ZenohConfig(mode=mode, listen=listen if listen is not None else [], connect=connect or [])


def wait_for(condition: Callable[[], object], timeout_s: float = 20.0, what: str = "condition") -> object:
    """Poll `condition` until it is truthy (returned) or fail after timeout_s: no fixed sleeps."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def wait_subscribed(session: zenoh.Session, key: str, timeout_s: float = 20.0) -> None:
    """Wait until a subscriber (the service's) matches `key` as seen from `session`: a put sent before the
    service's declarations reach a newly connected session is dropped on the way."""
    publisher = session.declare_publisher(key)
    try:
        wait_for(lambda: publisher.matching_status.matching, timeout_s, f"a subscriber on {key}")
    finally:
        publisher.undeclare()


def yaw_T(yaw: float, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


@dataclass
class FakeFlight:
    """A vehicle hovering/moving in the model; odometry in its own frame (T_cad_odom unknown to the service)."""

    model: object
    T_cad_odom: np.ndarray
    range_m: float = 9.0
    noise_m: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def odometry(self, stamp_ns: int, T_cad_body: np.ndarray) -> pb.Odometry:
        msg = pb.Odometry(T_map_body=pose_from_matrix(np.linalg.inv(self.T_cad_odom) @ T_cad_body))
        msg.header.stamp_ns = stamp_ns
        msg.header.frame_id = "map"
        return msg

    def imu(self, stamp_ns: int, T_cad_body: np.ndarray) -> pb.Imu:
        """A hovering vehicle's specific force (gravity reaction, +z up in the CAD frame) in the body frame."""
        accel_body = T_cad_body[:3, :3].T @ np.array([0.0, 0.0, 9.81])
        msg = pb.Imu(accel_mps2=vector3(accel_body), gyro_radps=pb.Vector3())
        msg.header.stamp_ns = stamp_ns
        msg.header.frame_id = "body"
        return msg

    def observations(self, stamp_ns: int, T_cad_body: np.ndarray) -> pb.ObservedFeatures:
        """Every vertical door/window within range_m on the body's storey (|dz| < 2 m), corners in the body frame."""
        msg = pb.ObservedFeatures()
        msg.header.stamp_ns = stamp_ns
        msg.header.frame_id = "body"
        T_body_cad = np.linalg.inv(T_cad_body)
        for f in self.model.features:  # type: ignore[attr-defined]
            d = f.centroid_cad - T_cad_body[:3, 3]
            if f.orientation != "vertical" or np.linalg.norm(d[:2]) > self.range_m or abs(d[2]) > 2.0:
                continue
            corners = f.corners_cad @ T_body_cad[:3, :3].T + T_body_cad[:3, 3]
            corners = corners + self.rng.normal(0, self.noise_m, corners.shape)
            msg.features.add(type=f.type, id=f.id).corners.extend(vector3(c) for c in corners)
        return msg


def service_config(building: Path, state_dir: Path, port: int, vehicle: str = "t1") -> MacrolocConfig:
    return load_config(None, service={"building": building, "state_dir": state_dir, "vehicle": vehicle,
                                      "status_period_s": 0.2, "save_period_s": 0.5, "perception": False},
                       zenoh=loopback(listen=[f"tcp/127.0.0.1:{port}"]).model_dump())


@contextmanager
def running_service(cfg: MacrolocConfig, notifier: object | None = None) -> Iterator[object]:
    """The service in a thread on its own loopback session; yields it once ready, stops and joins on exit."""
    from macroloc.service.serve import build_service
    from macroloc.service.zenoh_io import open_session

    stop = threading.Event()
    box: dict[str, object] = {}

    def run() -> None:
        with open_session(cfg.zenoh) as session:
            service = build_service(cfg, session, notifier=notifier)  # type: ignore[arg-type]
            box["service"] = service
            service.run(stop)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    # readiness, not a budget: a cold building cache on a loaded machine takes minutes; a dead thread fails at once
    wait_for(lambda: ("service" in box and box["service"].ready.is_set()) or not thread.is_alive(),  # type: ignore
             600.0, "service ready")
    assert thread.is_alive(), "the service thread died while starting"
    try:
        yield box["service"]
    finally:
        stop.set()
        thread.join(timeout=30.0)
        assert not thread.is_alive(), "service did not stop"


@contextmanager
def client(port: int, mode: str = "peer") -> Iterator[zenoh.Session]:
    with zenoh.open(_session_conf(loopback(mode=mode, connect=[f"tcp/127.0.0.1:{port}"]))) as session:
        yield session


def _session_conf(cfg: ZenohConfig) -> zenoh.Config:
    from macroloc.service.zenoh_io import session_config

    return session_config(cfg)
