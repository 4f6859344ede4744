"""`macroloc replay FLIGHT.mcap --over-zenoh`: play a recording into a running service, as a vehicle would.

Each recorded frame goes out on the service's input keys at the recording's pace (times `speed`; 0 = as fast
as possible): the IMU samples since the previous frame, the stereo frame, and, with a `TruthSource`
(ground truth with realistic errors: the service's perception is then not needed), the odometry and the
doors/windows seen (body frame) with the frame's stamp. The service's poses are collected and scored against
the recording's ground truth (CAD frame, no alignment), with the frame-in -> pose-out latency.

`odometry_out`: where the vehicle's odometry goes instead of macroloc's own `Odometry` on
`macroloc/<vehicle>/odometry` (bench.bench_odometry_sources plays it as a ROS `nav_msgs/msg/Odometry` or PX4's
`vehicle_odometry`): the same poses at the same stamps, only the message and key differ.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zenoh

from macroloc.graph.errors import UserInputError
from macroloc.proto.keys import Keys, declare_publisher
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame, matrix_from_pose, read_flight
from macroloc.service.config import ZenohConfig
from macroloc.service.offline.replay import ReplayTrace, TraceScore
from macroloc.service.offline.replay_sources import TruthSource
from macroloc.service.offline.vehicle import RecordedVehicle

if TYPE_CHECKING:
    from macroloc.service.offline.run import ReplayOptions
from macroloc.service.offline.run import vehicle_for
from macroloc.service.zenoh_io import session_config

log = logging.getLogger(__name__)


@dataclass
class ZenohReplayResult:
    """The service's poses of each frame's stamp scored as the offline replay scores its own
    (service.offline.replay.TraceScore), and what the service's status, map and last pose say."""

    frames: int = 0
    poses: int = 0
    duration_s: float = 0.0  # wall clock of the playback
    localized: bool = False
    time_to_localize_s: float | None = None  # recording time of the first pose in the model
    processing_to_localize_s: float | None = None  # wall time from the first frame sent to that pose's arrival
    ape_rmse_m: float | None = None  # poses in the model vs ground truth, CAD frame, no alignment
    ape_max_m: float | None = None
    rpe_1s_rmse_m: float | None = None
    latency_ms: dict[str, float] = field(default_factory=dict)  # frame published -> its pose received
    odometry: str = "none"  # what the vehicle's odometry was: source, recorded, simulated or none
    wrong_localizations: int = 0  # entries into LOCALIZED with a pose WRONG_TRANS_M / WRONG_ROT_DEG off the truth
    wrong_while_localized_s: float = 0.0  # flight time LOCALIZED that far off
    keyframes: int | None = None  # the service's last status: keyframes in its graph
    landmarks: int | None = None  # ... its landmarks
    status_final: str | None = None  # ... and its localization status
    cad_links: int | None = None  # the service's map at the end: landmarks linked to a CAD feature
    wrong_links: int | None = None  # ... linked to another feature than the one its vehicle's sighting named
    isam_update_ms_mean: float | None = None  # the service's last diagnostics: its pose graph's update at keyframes
    dropped: dict[str, int] = field(default_factory=dict)  # ... and the inputs it dropped, by kind
    position_sigma_final_m: float | None = None  # the last pose's covariance: largest position sigma
    # the service's last pose of each frame's stamp: (status, T_cad_body or None), for comparing runs (not in JSON)
    poses_cad: dict[int, tuple[str, np.ndarray | None]] = field(default_factory=dict, repr=False)

    def to_json(self) -> dict:
        return {"frames": self.frames, "poses": self.poses, "duration_s": round(self.duration_s, 3),
                "processing_fps": round(self.frames / self.duration_s, 1) if self.duration_s > 0 else None,
                "odometry": self.odometry,
                "localized": self.localized, "time_to_localize_s": self.time_to_localize_s,
                "processing_to_localize_s": self.processing_to_localize_s,
                "ape_rmse_m": self.ape_rmse_m, "ape_max_m": self.ape_max_m, "rpe_1s_rmse_m": self.rpe_1s_rmse_m,
                "wrong_localizations": self.wrong_localizations,
                "wrong_while_localized_s": round(self.wrong_while_localized_s, 3),
                "keyframes": self.keyframes, "landmarks": self.landmarks, "cad_links": self.cad_links,
                "wrong_links": self.wrong_links, "isam_update_ms_mean": self.isam_update_ms_mean,
                "status_final": self.status_final, "position_sigma_final_m": self.position_sigma_final_m,
                "dropped": {k: n for k, n in sorted(self.dropped.items()) if n},
                "latency_ms": {k: round(v, 3) for k, v in self.latency_ms.items()}}


class PoseCollector:
    """The service's poses by stamp, with the wall time each arrived."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.poses: dict[int, tuple[pb.PoseEstimate, float]] = {}
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on_pose)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        msg = pb.PoseEstimate.FromString(sample.payload.to_bytes())
        with self._lock:
            self.poses[msg.header.stamp_ns] = (msg, time.perf_counter())

    def has(self, stamp_ns: int) -> bool:
        with self._lock:
            return stamp_ns in self.poses


class LastStatus:
    """The service's last ServiceStatus."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.status: pb.ServiceStatus | None = None
        self._sub = session.declare_subscriber(key, self._on_status)

    def _on_status(self, sample: zenoh.Sample) -> None:
        self.status = pb.ServiceStatus.FromString(sample.payload.to_bytes())


class ServiceIdle:
    """The service's diagnostics: whether one sent after a given moment found its queue empty and its worker idle
    (frames are answered on arrival; what they change comes as the worker gets through them)."""

    IDLE_BUSY_MS = 150.0  # an idle worker looks for work every 100 ms

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self._idle_ns: list[int] = []  # wall-clock stamps of the diagnostics that found the service idle
        self.last: pb.Diagnostics | None = None
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on_diagnostics)

    def _on_diagnostics(self, sample: zenoh.Sample) -> None:
        msg = pb.Diagnostics.FromString(sample.payload.to_bytes())
        self.last = msg
        if msg.counts.get("queued", 1) == 0 and msg.latencies_ms.get("worker_busy", np.inf) < self.IDLE_BUSY_MS:
            with self._lock:
                self._idle_ns.append(msg.header.stamp_ns)

    def wait(self, after_ns: int, timeout_s: float) -> bool:
        """Block until a diagnostics message stamped after `after_ns` (time.time_ns()) found the service idle."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if any(t > after_ns for t in self._idle_ns):
                    return True
            time.sleep(0.02)
        return False


def wait_for_service(session: zenoh.Session, keys: Keys, timeout_s: float) -> None:
    """Block until the service's liveliness token is visible, or raise UserInputError."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(r.ok is not None for r in session.liveliness().get(keys.alive, timeout=1.0)):
            return
    raise UserInputError(f"no macroloc service answers on {keys.alive} (is `macroloc serve` running and "
                         "reachable with these Zenoh settings?)")


def replay_over_zenoh(flight: Path | Iterable[FlightFrame], zenoh_cfg: ZenohConfig, vehicle: str,
                      source: TruthSource | None, speed: float = 1.0, wait_s: float = 30.0,
                      seed: int = 0,
                      odometry_out: Callable[[zenoh.Session], Callable[[pb.Odometry], None]] | None = None,
                      answered: bool = False, odometry: str = "auto",
                      sender: RecordedVehicle | None = None) -> ZenohReplayResult:
    """Publish the recording (a macroloc MCAP, or its frames from any reader:
    service.offline.ros_bag.open_flight) to the service of `vehicle` and score what it sends back (see module doc).
    `seed`: of the simulated odometry's drift, where the vehicle's odometry is simulated. `odometry_out(session)`:
    the vehicle's odometry sender, in place of macroloc's own Odometry message (module doc). `answered`: each
    frame's pose is waited for (up to 10 s) before the next frame goes out, as a lock-step vehicle does, and the
    messages wait where the link is congested instead of being dropped (with `[service] lockstep` and speed 0, a
    run that does not depend on the machine's load). `odometry`: the vehicle's odometry (service.offline.vehicle:
    auto, recorded, simulated, visual), chosen as the offline replay's `--odometry`; `sender`: the vehicle whole
    instead (service.offline.run.vehicle_for), `source`, `seed` and `odometry` then unused."""
    keys = Keys(vehicle)
    result = ZenohReplayResult()
    sender = sender or RecordedVehicle(odometry, source, seed)
    sent_at: dict[int, float] = {}
    truth: dict[int, np.ndarray] = {}
    with zenoh.open(session_config(zenoh_cfg)) as session:
        wait_for_service(session, keys, wait_s)
        pubs = {name: declare_publisher(session, getattr(keys, name), express=True, block=answered)
                for name in ("stereo", "imu", "odometry", "observations", "initialpose")}
        put_odometry = odometry_out(session) if odometry_out is not None else \
            (lambda odo: pubs["odometry"].put(odo.SerializeToString()))
        poses = PoseCollector(session, keys.pose)
        last_status = LastStatus(session, keys.status)
        idle = ServiceIdle(session, keys.diagnostics)
        start_wall, first_stamp = time.perf_counter(), None
        frame: FlightFrame
        for frame in (read_flight(flight) if isinstance(flight, Path) else flight):
            first_stamp = frame.stamp_ns if first_stamp is None else first_stamp
            if speed > 0:
                delay = start_wall + (frame.stamp_ns - first_stamp) * 1e-9 / speed - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)  # the recording's pace
            for m in sender.messages(frame):
                if m.key == "stereo":
                    sent_at[frame.stamp_ns] = time.perf_counter()
                if m.key == "odometry":
                    put_odometry(m.message)
                else:
                    pubs[m.key].put(m.message.SerializeToString())
            if answered:
                deadline = time.monotonic() + 10.0
                while not poses.has(frame.stamp_ns) and time.monotonic() < deadline:
                    time.sleep(0.0005)
            if frame.ground_truth is not None:
                truth[frame.stamp_ns] = matrix_from_pose(frame.ground_truth.T_cad_body)
            result.frames += 1
        result.odometry = "source" if sender.sightings is not None and sender.odometry == "simulated" else \
            sender.odometry or "none"
        last = max(sent_at, default=None)
        deadline = time.monotonic() + 10.0
        while last is not None and not poses.has(last) and time.monotonic() < deadline:
            time.sleep(0.01)  # the last frame's pose, or give up after 10 s
        if idle.wait(time.time_ns(), timeout_s=max(deadline - time.monotonic(), 0.0)):
            time.sleep(0.1)  # the poses of its last events, on their way
        result.duration_s = time.perf_counter() - start_wall
        time.sleep(0.3)  # a status sent after the last event (every [service] status_period_s)
        if last_status.status is not None:
            result.keyframes = last_status.status.keyframes
            result.landmarks = last_status.status.landmarks
            result.status_final = pb.PoseEstimate.Status.Name(last_status.status.status).lower()
        for reply in session.get(keys.map, timeout=5.0):  # the service's map: its landmarks linked to the model
            if reply.ok is not None:
                snapshot = pb.MapSnapshot.FromString(reply.ok.payload.to_bytes())
                result.cad_links = sum(1 for lm in snapshot.landmarks_map if lm.id)
                result.wrong_links = sum(1 for lm in snapshot.landmarks_map
                                         if lm.id and lm.source_id and lm.id != lm.source_id)
        if idle.last is not None:
            result.isam_update_ms_mean = round(idle.last.latencies_ms.get("isam_update_mean", 0.0), 3)
            result.dropped = dict(idle.last.dropped)
        for pub in pubs.values():
            pub.undeclare()
    _score(result, poses.poses, sent_at, truth, first_stamp or 0, start_wall)
    return result


def _score(result: ZenohReplayResult, poses: dict[int, tuple[pb.PoseEstimate, float]], sent_at: dict[int, float],
           truth: dict[int, np.ndarray], first_stamp: int, start_wall: float) -> None:
    result.poses = len(poses)
    result.poses_cad = {stamp: (pb.PoseEstimate.Status.Name(p.status).lower(),
                                matrix_from_pose(p.T_cad_body) if p.HasField("T_cad_body") else None)
                        for stamp, (p, _) in poses.items()}
    latencies = [(arrived - sent_at[stamp]) * 1e3 for stamp, (_, arrived) in poses.items() if stamp in sent_at]
    if latencies:
        result.latency_ms = {"p50": float(np.percentile(latencies, 50)), "p99": float(np.percentile(latencies, 99)),
                             "n": float(len(latencies))}
    # each answered frame's last pose at its stamp, as the offline replay records its own (a frame the service did
    # not answer, pushed out of its queue when not in lock-step, is left out rather than counted as exploring)
    frames = sorted(stamp for stamp in sent_at if stamp in poses)
    trace = ReplayTrace()
    for stamp in frames:
        pose = poses[stamp][0]
        trace.t_s.append((stamp - first_stamp) * 1e-9)
        trace.status.append(pb.PoseEstimate.Status.Name(pose.status).lower())
        trace.T_est.append(matrix_from_pose(pose.T_cad_body) if pose.HasField("T_cad_body") else None)
        trace.T_true.append(truth.get(stamp, np.full((4, 4), np.nan)))
    if not frames:
        return
    score = TraceScore.of(trace)
    result.localized = score.first is not None
    if score.first is not None:
        result.time_to_localize_s = round(trace.t_s[score.first], 3)
        result.processing_to_localize_s = round(poses[frames[score.first]][1] - start_wall, 3)
    if score.ape.n:
        result.ape_rmse_m, result.ape_max_m = round(score.ape.rmse, 4), round(score.ape.max, 4)
    if score.rpe_1s.n:
        result.rpe_1s_rmse_m = round(score.rpe_1s.rmse, 4)
    result.wrong_localizations, result.wrong_while_localized_s = score.wrong_localizations, \
        score.wrong_while_localized_s
    last = poses.get(frames[-1])
    if last is not None and len(last[0].covariance) == 36:  # 6x6, [rot; trans]: the lower right 3x3
        cov = np.asarray(last[0].covariance, float).reshape(6, 6)
        result.position_sigma_final_m = round(float(np.sqrt(np.max(np.linalg.eigvalsh(cov[3:, 3:])))), 4)


def replay_command(flight: Iterable[FlightFrame], options: ReplayOptions, connect: list[str], vehicle: str,
                   speed: float) -> dict:
    """The CLI's `--over-zenoh` branch: a client-less peer connecting to the service's endpoint(s); the result's
    JSON document (the CLI prints it). The vehicle sends what the offline replay's would
    (service.offline.run.vehicle_for); `visual` odometry is the service's to run ([service] odometry). At `speed` 0
    the vehicle is lock-step: each frame waits for its answer and nothing is dropped on a congested link
    (`replay_over_zenoh`'s `answered`)."""
    if speed < 0:
        raise UserInputError("--speed must be >= 0")
    sender = vehicle_for(options.checked(), None, visual_if_none=False)  # `auto`: decided at the first frame
    cfg = ZenohConfig(mode="peer", connect=connect or ["tcp/127.0.0.1:7447"], listen=[])
    return replay_over_zenoh(flight, cfg, vehicle, None, speed, answered=speed == 0, sender=sender).to_json()
