"""Offline replay of a recorded flight through the service's own per-frame path, as fast as it runs, scored
against truth.

`replay_as_service` turns each recorded frame into the messages its vehicle sends (service.offline.vehicle), parses
them as the service does (service.inputs) and hands them to the service's front end (service.front_end), then
scores the poses in the CAD frame against ground truth without alignment (evo's APE/RPE, translation part).
service.offline.run.replay_flight builds the front end from the config, as `macroloc serve` does. Every frame's
estimate goes to a `FrameSink` (a null one by default) and a `FrameRecorder`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.localizer import Estimate, Localizer, Sighting
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.rigid import rotation_angle_deg
from macroloc.graph.trajectory_metrics import ErrorStats, ape_translation, rpe_translation
from macroloc.proto.recording import FlightFrame, matrix_from_pose, read_flight
from macroloc.service.frames import stereo_T_body_cam
from macroloc.service.front_end import FrontEnd
from macroloc.service.health import DropCounter
from macroloc.service.inputs import ClockReset, InputLimits, InputParser, ObservationsIn
from macroloc.service.offline.vehicle import RecordedVehicle

log = logging.getLogger(__name__)

WRONG_TRANS_M = 1.0  # a localization whose pose is further off than this (or WRONG_ROT_DEG) is wrong
WRONG_ROT_DEG = 10.0


class FrameSink(Protocol):
    def __call__(self, estimate: Estimate) -> None: ...


def null_sink(estimate: Estimate) -> None:
    """Receives every estimate and does nothing (a publisher can take its place)."""


class FrameRecorder(Protocol):
    """Keeps each frame with its inputs and estimate (service.offline.foxglove_out.ReplayRecorder), and the end
    state."""

    def frame(self, frame: FlightFrame, inputs: FrameSeen, estimate: Estimate) -> None: ...

    def finish(self, localizer: Localizer) -> None: ...


class NullRecorder:
    """Records nothing."""

    def frame(self, frame: FlightFrame, inputs: FrameSeen, estimate: Estimate) -> None:
        pass

    def finish(self, localizer: Localizer) -> None:
        pass


@dataclass
class ReplayTrace:
    """Per-frame record: stamps (s from the first frame), truth and estimates (NaN before localization)."""

    t_s: list[float] = field(default_factory=list)
    stamp_ns: list[int] = field(default_factory=list)  # the frames' own stamps
    status: list[str] = field(default_factory=list)
    T_true: list[np.ndarray] = field(default_factory=list)
    T_est: list[np.ndarray | None] = field(default_factory=list)
    keyframe: list[bool] = field(default_factory=list)
    update_ms: list[float] = field(default_factory=list)
    n_sightings: list[int] = field(default_factory=list)


@dataclass
class ReplayResult:
    frames: int
    processing_fps: float
    localized: bool
    time_to_localize_s: float | None
    processing_to_localize_s: float | None
    ape: ErrorStats
    rpe_1s: ErrorStats
    wrong_localizations: int
    wrong_while_localized_s: float  # flight time spent `localized` with the pose WRONG_TRANS_M / WRONG_ROT_DEG off
    status_final: str
    keyframes: int
    landmarks: int
    cad_links: int
    wrong_links: int
    isam_update_ms_mean: float
    position_sigma_final_m: float | None  # sqrt of the largest translation variance of the last keyframe (marginals)
    trace: ReplayTrace
    localizer: Localizer
    dropped: dict[str, int] = field(default_factory=dict)  # inputs the service's checks refused, by key/kind

    def to_json(self) -> dict:
        return {"frames": self.frames, "processing_fps": round(self.processing_fps, 1), "localized": self.localized,
                "time_to_localize_s": _round(self.time_to_localize_s),
                "processing_to_localize_s": _round(self.processing_to_localize_s),
                "ape_rmse_m": _round(self.ape.rmse), "ape_max_m": _round(self.ape.max),
                "rpe_1s_rmse_m": _round(self.rpe_1s.rmse), "wrong_localizations": self.wrong_localizations,
                "wrong_while_localized_s": round(self.wrong_while_localized_s, 3),
                "status_final": self.status_final, "keyframes": self.keyframes, "landmarks": self.landmarks,
                "cad_links": self.cad_links, "wrong_links": self.wrong_links,
                "isam_update_ms_mean": round(self.isam_update_ms_mean, 3),
                "position_sigma_final_m": _round(self.position_sigma_final_m),
                "dropped": {k: n for k, n in sorted(self.dropped.items()) if n}}


def _round(v: float | None, nd: int = 4) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), nd)


def replay_as_service(flight: Path | Iterable[FlightFrame], front_end: FrontEnd, vehicle: RecordedVehicle,
                      limits: InputLimits, cameras: Sequence[str] = ("front",),
                      sink: FrameSink = null_sink, recorder: FrameRecorder | None = None) -> ReplayResult:
    """Run `flight` through the service's own per-frame path: each recorded frame becomes the messages its vehicle
    sends (`vehicle`, service.offline.vehicle), parsed as the service parses them (service.inputs, with its `limits`
    and `cameras`: [inputs], [service] cameras) and handed to its `front_end` in the order sent, on one thread, as a
    lock-step `macroloc serve` takes them from Zenoh; scored against the frames' ground truth (module doc). A
    frame's estimate is the last the service gives at the frame's stamp (its stereo frame's; the doors' or the
    odometry's where the stereo frame gives none, e.g. a truth flight's frames without images, which the parser
    drops), as replay_zenoh scores a lock-step `serve`'s. `recorder` keeps each frame with what was seen in it
    (the doors the vehicle sent and those the service perceived) and its estimate."""
    recorder = recorder or NullRecorder()
    trace = ReplayTrace()
    t0: int | None = None
    busy_at_localized: float | None = None
    resets: list[ClockReset] = []
    drops = DropCounter()
    parser = InputParser(list(cameras), drops, limits,
                         on_clock_reset=lambda key, stamp_ns: resets.append(ClockReset(key, stamp_ns)))
    parse = {"imu": parser.imu, "odometry": parser.odometry, "observations": parser.observations,
             "initialpose": parser.prior, "stereo": lambda payload: parser.stereo(payload, time.monotonic_ns())}
    frames = read_flight(flight) if isinstance(flight, Path) else flight
    start = time.perf_counter()
    for frame in frames:
        t0 = frame.stamp_ns if t0 is None else t0
        est: Estimate | None = None
        keyframe, update_ms = False, 0.0  # whether one of the frame's messages made a keyframe; its iSAM2 update
        sent: list[Sighting] = []  # the doors and windows the vehicle sent with the frame, body frame
        for m in vehicle.messages(frame):
            event = parse[m.key](m.message.SerializeToString())
            for reset in resets:
                front_end.handle(reset)
            resets.clear()
            if event is None:
                continue
            answer = front_end.handle(event)
            if answer is not None and front_end.loop.keyframe:
                keyframe, update_ms = True, max(update_ms, answer.update_ms)
            if isinstance(event, ObservationsIn) and event.frame_id == "body":
                sent += [Sighting(o.type, o.corners) for o in event.features if o.corners is not None]
            if answer is not None and answer.stamp_ns == frame.stamp_ns:
                est = answer  # the last pose the service publishes at the frame's stamp, as a lock-step serve's
        est = est or Estimate(frame.stamp_ns, front_end.status, np.eye(4))
        if busy_at_localized is None and est.status == "localized":
            busy_at_localized = time.perf_counter() - start
        sink(est)
        seen = [*sent, *front_end.sightings]
        recorder.frame(frame, FrameSeen(stereo_T_body_cam(frame.stereo), seen, front_end.localizer.graph), est)
        trace.stamp_ns.append(frame.stamp_ns)
        _record(trace, (frame.stamp_ns - t0) * 1e-9, est,
                matrix_from_pose(frame.ground_truth.T_cad_body) if frame.ground_truth else None, keyframe, len(seen),
                update_ms)
    if t0 is None:
        raise UserInputError(f"recording {flight if isinstance(flight, Path) else 'given'} holds no stereo frames")
    busy_s = time.perf_counter() - start
    recorder.finish(front_end.localizer)
    result = _score(trace, front_end.localizer, busy_s, busy_at_localized)
    result.dropped = drops.counts()
    return result


@dataclass(frozen=True)
class FrameSeen:
    """What a replayed frame's recorder draws: the left camera in the body frame (4x4) and the doors and windows
    seen (corners in the body frame)."""

    T_body_cam: np.ndarray
    sightings: list[Sighting]
    graph: PoseGraph | None = None  # the service's pose graph, as it stands after the frame



def _record(trace: ReplayTrace, t_s: float, est: Estimate, T_true: np.ndarray | None, is_kf: bool,
            n_sightings: int, update_ms: float) -> None:
    trace.t_s.append(t_s)
    trace.status.append(est.status)
    trace.T_true.append(T_true if T_true is not None else np.full((4, 4), np.nan))
    trace.T_est.append(est.T_cad_body)
    trace.keyframe.append(is_kf)
    trace.update_ms.append(update_ms if is_kf else 0.0)
    trace.n_sightings.append(n_sightings)


@dataclass(frozen=True)
class TraceScore:
    """What a trace's poses score against its truth, the same for a replay and for a service's poses
    (service.offline.replay_zenoh): the first frame with a pose in the model (`localized`, `degraded` or `lost`),
    APE and RPE over the frames with one (CAD frame, no alignment), wrong entries and time."""

    first: int | None
    ape: ErrorStats
    rpe_1s: ErrorStats
    wrong_localizations: int
    wrong_while_localized_s: float

    @classmethod
    def of(cls, trace: ReplayTrace) -> TraceScore:
        t = np.array(trace.t_s)
        localized_mask = np.array([s in ("localized", "degraded", "lost") and T is not None
                                   for s, T in zip(trace.status, trace.T_est, strict=True)], dtype=bool)
        first = int(np.argmax(localized_mask)) if localized_mask.any() else None
        idx = np.flatnonzero(localized_mask)
        P_true = np.array([trace.T_true[k] for k in idx]).reshape(-1, 4, 4)
        P_est = np.array([trace.T_est[k] for k in idx]).reshape(-1, 4, 4)
        ape = ErrorStats.of(ape_translation(P_true, P_est)) if len(idx) else ErrorStats.of(np.zeros(0))
        rate = max(1, int(round(1.0 / np.median(np.diff(t))))) if len(t) > 1 else 1
        rpe = ErrorStats.of(rpe_translation(P_true, P_est, delta=rate)) if len(idx) else ErrorStats.of(np.zeros(0))
        return cls(first, ape, rpe, _wrong_localizations(trace), _wrong_while_localized_s(trace))


def _score(trace: ReplayTrace, localizer: Localizer, busy_s: float, busy_at_localized: float | None) -> ReplayResult:
    t = np.array(trace.t_s)
    score = TraceScore.of(trace)
    kf_ms = [m for m, k in zip(trace.update_ms, trace.keyframe, strict=True) if k]
    links = localizer.links
    truth_of = _truth_ids(localizer)
    return ReplayResult(
        frames=len(t), processing_fps=len(t) / max(busy_s, 1e-9), localized=score.first is not None,
        time_to_localize_s=None if score.first is None else float(t[score.first]),
        processing_to_localize_s=busy_at_localized, ape=score.ape, rpe_1s=score.rpe_1s,
        wrong_localizations=score.wrong_localizations, wrong_while_localized_s=score.wrong_while_localized_s,
        status_final=trace.status[-1],
        keyframes=localizer.graph.n_keyframes, landmarks=len(localizer.landmarks), cad_links=len(links),
        wrong_links=sum(1 for j, fid in links.items() if truth_of.get(j) not in (None, fid)),
        isam_update_ms_mean=float(np.mean(kf_ms)) if kf_ms else 0.0,
        position_sigma_final_m=_position_sigma(localizer), trace=trace, localizer=localizer)


def _position_sigma(localizer: Localizer) -> float | None:
    """Largest position standard deviation (m) of the last keyframe's T_cad_body, from the marginals."""
    if not localizer.graph.has_anchor:
        return None
    cov = localizer.graph.covariance_cad_body(localizer.graph.n_keyframes - 1)
    return float(np.sqrt(np.max(np.linalg.eigvalsh(cov[3:, 3:]))))  # [rot; trans]: the lower right 3x3


def _truth_ids(localizer: Localizer) -> dict[int, str]:
    """Ground-truth id of each landmark (from the sighting that created it), when known."""
    return {j: lm.truth_id for j, lm in localizer.landmarks.items() if lm.truth_id is not None}


def _is_wrong(T_est: np.ndarray, T_true: np.ndarray) -> bool:
    d = np.linalg.inv(T_true) @ T_est
    return bool(np.linalg.norm(d[:3, 3]) > WRONG_TRANS_M or rotation_angle_deg(d[:3, :3]) > WRONG_ROT_DEG)


def _wrong_while_localized_s(trace: ReplayTrace) -> float:
    """Flight time (s) during which the status said `localized` and the pose was WRONG_TRANS_M / WRONG_ROT_DEG
    off: a correct entry followed by a drift away is counted here, not by `_wrong_localizations`."""
    t = np.asarray(trace.t_s)
    dt = np.diff(t, append=t[-1] + (np.median(np.diff(t)) if len(t) > 1 else 0.0)) if len(t) else t
    return float(sum(step for step, status, T_est, T_true in zip(dt, trace.status, trace.T_est, trace.T_true,
                                                                 strict=True)
                     if status == "localized" and T_est is not None and np.isfinite(T_true).all()
                     and _is_wrong(T_est, T_true)))


def _wrong_localizations(trace: ReplayTrace) -> int:
    """Times the status entered 'localized' with a pose more than WRONG_TRANS_M / WRONG_ROT_DEG off."""
    wrong, before = 0, "exploring"
    for status, T_est, T_true in zip(trace.status, trace.T_est, trace.T_true, strict=True):
        if status == "localized" and before != "localized" and T_est is not None and np.isfinite(T_true).all():
            wrong += int(_is_wrong(T_est, T_true))
        before = status
    return wrong
