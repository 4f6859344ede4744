"""Offline replay of a recorded flight through the localizer, as fast as it runs, scored against truth.

`replay()` reads the MCAP recording, turns each frame into inputs (an `ObservationSource`: ground truth with
realistic errors, or the perception chain), runs them through the `LocalizationSession` the service runs too
(service.session: the keyframe rule, the `Localizer`), and scores the poses in
the CAD frame against ground truth without alignment (evo's APE/RPE, translation part). The frames go through
`FrameSink`s (a null one by default): the seam where `--over-zenoh` publishes instead of running in-process.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from queue import Full, Queue
from typing import Protocol, TypeVar

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel
from macroloc.graph.localizer import Estimate, Localizer, Sighting
from macroloc.graph.rigid import rotation_angle_deg
from macroloc.graph.surfaces import SurfaceIndex
from macroloc.graph.trajectory_metrics import ErrorStats, ape_translation, rpe_translation
from macroloc.proto.recording import FlightFrame
from macroloc.service.front_end import FrontEnd
from macroloc.service.health import DropCounter
from macroloc.service.inputs import ClockReset, InputLimits, InputParser, ObservationsIn
from macroloc.service.offline.replay_sources import AHEAD_FRAMES, FrameInput, ObservationSource, TruthSource, gravity_at
from macroloc.service.offline.vehicle import RecordedVehicle
from macroloc.service.places import KeyframePlaces
from macroloc.service.saved_map import SavedMap
from macroloc.service.session import FrameIn, LocalizationSession, SessionSettings, make_session

log = logging.getLogger(__name__)
T = TypeVar("T")
U = TypeVar("U")

WRONG_TRANS_M = 1.0  # a localization whose pose is further off than this (or WRONG_ROT_DEG) is wrong
WRONG_ROT_DEG = 10.0


class FrameSink(Protocol):
    def __call__(self, estimate: Estimate) -> None: ...


def null_sink(estimate: Estimate) -> None:
    """Receives every estimate and does nothing (a publisher can take its place)."""


class FrameRecorder(Protocol):
    """Keeps each frame with its inputs and estimate (service.offline.foxglove_out.ReplayRecorder), and the end
    state."""

    def frame(self, frame: FlightFrame, inputs: FrameInput | FrameSeen, estimate: Estimate) -> None: ...

    def finish(self, localizer: Localizer) -> None: ...


class NullRecorder:
    """Records nothing."""

    def frame(self, frame: FlightFrame, inputs: FrameInput | FrameSeen, estimate: Estimate) -> None:
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
                "position_sigma_final_m": _round(self.position_sigma_final_m)}


def _round(v: float | None, nd: int = 4) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), nd)


def replay(flight: Path | Iterable[FlightFrame], model: BuildingModel, source: ObservationSource | None = None,
           saved: SavedMap | None = None, sink: FrameSink = null_sink, surfaces: SurfaceIndex | None = None,
           places: KeyframePlaces | None = None, recorder: FrameRecorder | None = None,
           settings: SessionSettings | None = None,
           make: Callable[[np.ndarray], LocalizationSession] | None = None,
           one_thread: bool = False) -> ReplayResult:
    """Run `flight` (a macroloc MCAP recording, or its frames from any reader: service.offline.ros_bag.open_flight)
    through a new localization session (service.session) in `model`; see module doc. `make`: the session for the
    flight's camera (T_body_cam, 4x4), as the CLI and the benchmarks build it (`service.session.session_from_config`);
    else one from `settings` (the defaults without), with `saved` (the saved map to start from: service.saved_map)
    and `surfaces` where given. `places`: place recognition on the frames (service.places: views kept for the
    saved map, frames placed in the saved map's views). `recorder`: keeps every frame (e.g. for Foxglove:
    service.offline.foxglove_out.ReplayRecorder).

    Three threads, as a SLAM system runs its tracking beside its mapping: one reads the recording and decodes the
    images, one runs the source's `ahead` (the visual odometry), each up to AHEAD_FRAMES frames ahead of the next;
    this one runs the rest (the perception chain, the session) in frame order. The results are those of one
    thread: each part sees the frames in order, and nothing ahead depends on the session. `one_thread`, or a
    source that must not run ahead (`runs_ahead` False), does it all here, in turn. `processing_fps` counts the
    wall time from the first frame asked for to the last estimate, reading included."""
    import scipy.spatial.transform  # noqa: F401 - a one-off import (0.5 s here) kept out of the timed loop

    from macroloc.proto.recording import matrix_from_pose, read_flight

    source = source or TruthSource()
    settings = settings or SessionSettings()
    make = make or (lambda T_body_cam: make_session(
        model, settings, surfaces=surfaces, T_body_cam=T_body_cam,
        registrar=None if saved is None else saved.registrar(model, surfaces is not None)(settings)))
    places = places or KeyframePlaces(None, keep_views=False)
    recorder = recorder or NullRecorder()
    trace = ReplayTrace()
    session: LocalizationSession | None = None
    t0 = None
    busy_at_localized: float | None = None
    frames = read_flight(flight) if isinstance(flight, Path) else flight
    start = time.perf_counter()
    ahead_frames = 0 if one_thread or not source.runs_ahead else AHEAD_FRAMES
    for frame, ahead in _read_ahead(frames, source, ahead_frames):
        if session is None:
            session = make(source.T_body_cam(frame))
        inputs: FrameInput = source(frame, ahead, gravity_at(session, frame, ahead))
        t0 = frame.stamp_ns if t0 is None else t0
        placed = places.at_frame(frame, inputs.T_odom_body, inputs.T_body_cam, inputs.up_body, session.status)
        est = session.frame(FrameIn(inputs.stamp_ns, inputs.T_odom_body, inputs.sightings, inputs.up_body,
                                    inputs.points_body, inputs.dead_reckoned_s, placed, inputs.measure_depth))
        if busy_at_localized is None and est.status == "localized":
            busy_at_localized = time.perf_counter() - start
        sink(est)
        recorder.frame(frame, inputs, est)
        trace.stamp_ns.append(frame.stamp_ns)
        _record(trace, (frame.stamp_ns - t0) * 1e-9, est,
                matrix_from_pose(frame.ground_truth.T_cad_body) if frame.ground_truth else None, session.keyframe,
                len(inputs.sightings))
    if session is None:
        from macroloc.graph.errors import UserInputError

        raise UserInputError(f"recording {flight if isinstance(flight, Path) else 'given'} holds no stereo frames")
    busy_s = time.perf_counter() - start
    recorder.finish(session.localizer)
    return _score(trace, session.localizer, busy_s, busy_at_localized)


def replay_as_service(flight: Path | Iterable[FlightFrame], front_end: FrontEnd, vehicle: RecordedVehicle,
                      limits: InputLimits, cameras: Sequence[str] = ("front",),
                      sink: FrameSink = null_sink, recorder: FrameRecorder | None = None) -> ReplayResult:
    """Run `flight` through the service's own per-frame path: each recorded frame becomes the messages its vehicle
    sends (`vehicle`, service.offline.vehicle), parsed as the service parses them (service.inputs, with its `limits`
    and `cameras`: [inputs], [service] cameras) and handed to its `front_end` in the order sent, on one thread, as a
    lock-step `macroloc serve` takes them from Zenoh; scored as `replay` scores. A frame's estimate is its stereo
    frame's (what the service publishes for it last). `recorder` keeps each frame with what was seen in it (the
    doors the vehicle sent and those the service perceived) and its estimate."""
    from macroloc.proto.recording import matrix_from_pose, read_flight

    recorder = recorder or NullRecorder()
    trace = ReplayTrace()
    t0: int | None = None
    busy_at_localized: float | None = None
    resets: list[ClockReset] = []
    parser = InputParser(list(cameras), DropCounter(), limits,
                         on_clock_reset=lambda key, stamp_ns: resets.append(ClockReset(key, stamp_ns)))
    parse = {"imu": parser.imu, "odometry": parser.odometry, "observations": parser.observations,
             "stereo": lambda payload: parser.stereo(payload, time.monotonic_ns())}
    frames = read_flight(flight) if isinstance(flight, Path) else flight
    start = time.perf_counter()
    for frame in frames:
        t0 = frame.stamp_ns if t0 is None else t0
        est: Estimate | None = None
        keyframe = False
        sent: list[Sighting] = []  # the doors and windows the vehicle sent with the frame, body frame
        for m in vehicle.messages(frame):
            event = parse[m.key](m.message.SerializeToString())
            for reset in resets:
                front_end.handle(reset)
            resets.clear()
            if event is None:
                continue
            answer = front_end.handle(event)
            keyframe |= answer is not None and front_end.session.keyframe
            if isinstance(event, ObservationsIn) and event.frame_id == "body":
                sent += [Sighting(o.type, o.corners) for o in event.features if o.corners is not None]
            if m.key == "stereo":
                est = answer or Estimate(frame.stamp_ns, front_end.status, np.eye(4))
        est = est or Estimate(frame.stamp_ns, front_end.status, np.eye(4))
        if busy_at_localized is None and est.status == "localized":
            busy_at_localized = time.perf_counter() - start
        sink(est)
        seen = [*sent, *front_end.sightings]
        recorder.frame(frame, FrameSeen(_T_body_cam(frame), seen), est)
        trace.stamp_ns.append(frame.stamp_ns)
        _record(trace, (frame.stamp_ns - t0) * 1e-9, est,
                matrix_from_pose(frame.ground_truth.T_cad_body) if frame.ground_truth else None, keyframe, len(seen))
    if t0 is None:
        raise UserInputError(f"recording {flight if isinstance(flight, Path) else 'given'} holds no stereo frames")
    busy_s = time.perf_counter() - start
    recorder.finish(front_end.localizer)
    return _score(trace, front_end.localizer, busy_s, busy_at_localized)


@dataclass(frozen=True)
class FrameSeen:
    """What a replayed frame's recorder draws: the left camera in the body frame (4x4) and the doors and windows
    seen (corners in the body frame)."""

    T_body_cam: np.ndarray
    sightings: list[Sighting]


def _T_body_cam(frame: FlightFrame) -> np.ndarray:
    from macroloc.common.geometry import forward_stereo_T_body_cam
    from macroloc.proto.recording import matrix_from_pose

    info = frame.stereo.info
    return matrix_from_pose(info.T_body_cam) if info.HasField("T_body_cam") else forward_stereo_T_body_cam()


def _read_ahead(frames: Iterable[FlightFrame], source: ObservationSource,
                ahead_frames: int) -> Iterator[tuple[FlightFrame, object]]:
    """(frame, source.ahead(frame)) in frame order. `ahead_frames` > 0: two threads of their own, each at most that
    many frames ahead of the next: one reads the recording and decodes the images (where the source uses them),
    one runs `ahead`. 0: here, in turn. An error there is raised here, in its frame's turn; the caller stopping
    early stops the threads."""
    if ahead_frames <= 0:
        for frame in frames:
            yield frame, source.ahead(frame)
        return

    def decoded(frame: FlightFrame) -> FlightFrame:
        if source.uses_images:
            frame.images()
        return frame

    read = _in_thread(_mapped(iter(frames), decoded), ahead_frames, "replay-read")
    yield from _in_thread(_mapped(read, lambda frame: (frame, source.ahead(frame))), ahead_frames, "replay-ahead")


def _mapped(items: Iterator[T], fn: Callable[[T], U]) -> Iterator[U]:
    """fn of each item; closing it closes `items` (a generator expression would not)."""
    try:
        for item in items:
            yield fn(item)
    finally:
        _close(items)


def _close(items: Iterator[object]) -> None:
    """End a generator where it stands (its own `finally` runs); other iterators need nothing."""
    close = getattr(items, "close", None)
    if close is not None:
        close()


def _in_thread(items: Iterator[T], depth: int, name: str) -> Iterator[T]:
    """`items`, taken on a thread of their own at most `depth` ahead of the caller; its error raised here in
    turn; the caller closing this (or stopping with an error) stops the thread and closes `items`."""
    done = object()
    queue: Queue[object] = Queue(maxsize=depth)
    stop = threading.Event()

    def put(item: object) -> bool:
        while not stop.is_set():
            try:
                queue.put(item, timeout=0.1)
                return True
            except Full:
                continue
        return False

    def run() -> None:
        try:
            for item in items:
                if not put(item):
                    return
            put(done)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread, raised there
            put(exc)
        finally:
            _close(items)

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    try:
        while (item := queue.get()) is not done:
            if isinstance(item, BaseException):
                raise item
            yield item  # type: ignore[misc]
    finally:
        stop.set()
        thread.join()


def _record(trace: ReplayTrace, t_s: float, est: Estimate, T_true: np.ndarray | None, is_kf: bool,
            n_sightings: int) -> None:
    trace.t_s.append(t_s)
    trace.status.append(est.status)
    trace.T_true.append(T_true if T_true is not None else np.full((4, 4), np.nan))
    trace.T_est.append(est.T_cad_body)
    trace.keyframe.append(is_kf)
    trace.update_ms.append(est.update_ms if is_kf else 0.0)
    trace.n_sightings.append(n_sightings)


def _score(trace: ReplayTrace, localizer: Localizer, busy_s: float, busy_at_localized: float | None) -> ReplayResult:
    t = np.array(trace.t_s)
    localized_mask = np.array([s in ("localized", "degraded", "lost") and T is not None
                               for s, T in zip(trace.status, trace.T_est, strict=True)])
    first = int(np.argmax(localized_mask)) if localized_mask.any() else None
    idx = np.flatnonzero(localized_mask)
    P_true = np.array([trace.T_true[k] for k in idx]).reshape(-1, 4, 4)
    P_est = np.array([trace.T_est[k] for k in idx]).reshape(-1, 4, 4)
    ape = ErrorStats.of(ape_translation(P_true, P_est)) if len(idx) else ErrorStats.of(np.zeros(0))
    rate = max(1, int(round(1.0 / np.median(np.diff(t))))) if len(t) > 1 else 1
    rpe = ErrorStats.of(rpe_translation(P_true, P_est, delta=rate)) if len(idx) else ErrorStats.of(np.zeros(0))
    kf_ms = [m for m, k in zip(trace.update_ms, trace.keyframe, strict=True) if k]
    links = localizer.links
    truth_of = _truth_ids(localizer)
    return ReplayResult(
        frames=len(t), processing_fps=len(t) / max(busy_s, 1e-9), localized=first is not None,
        time_to_localize_s=None if first is None else float(t[first]),
        processing_to_localize_s=busy_at_localized, ape=ape, rpe_1s=rpe,
        wrong_localizations=_wrong_localizations(trace), wrong_while_localized_s=_wrong_while_localized_s(trace),
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
