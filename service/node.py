"""The long-running localization service on Zenoh: sensor streams in, pose and waypoints out.

Threads: one intake thread per input key reads its subscriber's ring channel, parses and checks the payload
(`service.inputs`) and hands a typed event to the worker through `WorkQueue` (bounded: stereo frames beyond
`queue_size` push out the oldest frame); the worker is the only thread that touches the localizer: it perceives
the stereo frames and adds them to the pose graph. Each stereo frame is answered with its pose at once by its
intake thread, from the newest keyframe's estimate and the odometry (`service.frame_answers`), so that a frame's
answer never waits for perception or a registration (in lock-step the worker answers each frame after perceiving
it); a queryable thread answers map and plan queries; the caller's thread publishes status and diagnostics and
saves the map periodically. `run()` returns after `stop` is set: intake stops, the worker
drains what was queued, the map is saved, and every publisher, subscriber, queryable and the liveliness
token is undeclared before the caller closes the session.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from macroloc.graph.geo import GeoReference
from macroloc.graph.localizer import Estimate
from macroloc.graph.planning import GoalSpec, Planner, PlanningError
from macroloc.proto.keys import PROTOBUF, Keys, declare_publisher
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose
from macroloc.service.foxglove_live import LiveView, NullLiveView
from macroloc.service.frame_answers import OdometryBuffer
from macroloc.service.frames import depth_points_body
from macroloc.service.front_end import STATUS_TO_WIRE, FrontEnd, plausible, pose_message
from macroloc.service.health import DropCounter, LatencyWindow, RateMeter
from macroloc.service.inputs import (
    ClockReset,
    GoalIn,
    ImuIn,
    InputLimits,
    InputParser,
    ObservationsIn,
    OdometryIn,
    PriorIn,
    StereoIn,
)
from macroloc.service.ros_out import NullRosInputs, RosIntakes
from macroloc.service.ros_sensors import RosSensorInputs, RosSensorTopics
from macroloc.service.state import SavedMapFile
from macroloc.service.systemd import Notifier, NullNotifier
from macroloc.service.vehicle_out import NullVehicleOutput, VehicleOutput
from macroloc.service.workqueue import CountingRing, WorkQueue

log = logging.getLogger(__name__)

VERSION = "0.1.0"


@dataclass
class ServiceParams:
    """The running service's settings, from the config (service.serve.build_service): [service]'s and
    [planning]'s have no defaults here, the config's are the only ones."""

    vehicle: str
    building: str
    building_sha256: str
    cameras: list[str]
    ring_size: int
    queue_size: int
    status_period_s: float
    save_period_s: float
    replan_period_s: float
    stall_after_s: float  # a handler busy this long is a stall: liveliness withdrawn, watchdog not fed
    drain_timeout_s: float  # at stop, the queued events get this long; then the map is saved and we exit
    lockstep: bool  # inputs handled in the order sent (one FIFO intake, nothing dropped), replans first
    geo: GeoReference | None = None  # the model's geo-reference: poses also in ENU and WGS84
    limits: InputLimits = field(default_factory=InputLimits)  # what the input keys take (service.inputs)
    ros_sensors: RosSensorTopics = field(default_factory=RosSensorTopics)  # ROS sensor topics taken ([ros])
    T_body_cam: np.ndarray | None = None  # the camera's mounting for ROS images (None: the simulator's)


class LocalizationService:
    """One vehicle's service on an open Zenoh session (see module doc)."""

    def __init__(self, session: zenoh.Session, front_end: FrontEnd, planner: Planner, store: SavedMapFile,
                 params: ServiceParams,
                 vehicle_out: VehicleOutput | None = None, ros_inputs: RosIntakes | None = None,
                 notifier: Notifier | None = None, live: LiveView | None = None) -> None:
        """`vehicle_out`: ROS 2 / PX4 messages beside the protobuf keys (service.ros_out, service.px4), none by
        default; `ros_inputs`: the ROS topics taken beside the protobuf inputs (the goal, the vehicle's odometry);
        `notifier`: systemd's notification socket (service.systemd), none outside systemd; `live`: the operator's
        live view (service.foxglove_live: it only queues, never waits), none by default; closed at stop."""
        self.session = session
        self.live: LiveView = live or NullLiveView()
        self.vehicle_out: VehicleOutput = vehicle_out or NullVehicleOutput()
        self.ros_inputs: RosIntakes = ros_inputs or NullRosInputs()
        self.front_end = front_end  # the one per-frame path (service.front_end), the replay's too
        self.planner = planner
        self.store = store
        self.params = params
        self.keys = Keys(params.vehicle)
        self.drops = DropCounter()
        self.queue = WorkQueue(params.queue_size)
        self.parser = InputParser(params.cameras, self.drops, params.limits, on_clock_reset=self._clock_reset_seen)
        self.ros_sensors = RosSensorInputs(params.ros_sensors, self.parser, self.drops, params.cameras[0],
                                           params.T_body_cam, params.limits.max_image_pixels, time.monotonic_ns)
        self.rates = {name: RateMeter() for name in ("stereo", "imu", "odometry", "observations", "goal", "initialpose",
                                                   "pose")}
        # frame_perceived: a stereo frame's arrival -> perceived and in the pose graph (the worker's delay)
        self.latency = {name: LatencyWindow() for name in ("frame_to_pose", "odometry_to_pose", "keyframe",
                                                           "frame_perceived")}
        self._odometry = OdometryBuffer()  # for answering frames on their intake thread
        self._publish_lock = threading.Lock()  # poses go out from the worker and the stereo intake
        self.ready = threading.Event()  # everything declared: inputs are being taken
        self._lock = threading.Lock()  # the front end and planner are used by the worker and the queryables
        self._goal: GoalIn | None = None
        self._last_plan_ns: int | None = None  # the pose stamp the last plan started from (vehicle clock)
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._worker_done = threading.Event()
        self._abandon = threading.Event()  # set at stop once the drain is over (or has timed out)
        self._last_pose_ns = -1
        self.notifier = notifier or NullNotifier()
        self._worker_beat_s = time.monotonic()  # the worker's last sign of progress (between events)
        self._stalled = False
        self._token: zenoh.LivelinessToken | None = None
        self._last_status = pb.ServiceStatus(version=VERSION, vehicle=params.vehicle, building=params.building)

    # --- the process --------------------------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        """Serve until `stop` is set, then drain, save and undeclare (the session stays open)."""
        k = self.keys
        self._pubs = {name: declare_publisher(self.session, getattr(k, name), block=self.params.lockstep)
                      for name in ("pose", "waypoints", "features", "diagnostics", "status")}
        queryables = [self.session.declare_queryable(k.map, self._answer_map),
                      self.session.declare_queryable(k.plan, self._answer_plan)]
        intakes = {
            k.stereo: (lambda s: self.parser.stereo(s, time.monotonic_ns()), "stereo", True, self.params.ring_size),
            k.odometry: (lambda s: self.parser.odometry(s), "odometry", False, 256),
            k.imu: (lambda s: self.parser.imu(s), "imu", False, 1024),
            k.observations: (lambda s: self.parser.observations(s), "observations", False, 64),
            k.goal: (lambda s: self.parser.goal(s), "goal", False, 8),
            k.initialpose: (lambda s: self.parser.prior(s), "initialpose", False, 8),
            **self.ros_inputs.intakes(self.parser),
            **self.ros_sensors.intakes(),
        }
        subs: list[Any] = []  # every subscriber, undeclared at stop
        threads: list[threading.Thread] = []
        prefix = f"macroloc/{self.params.vehicle}/"
        if self.params.lockstep:  # one channel for the vehicle's keys: handled in the order the vehicle sent them
            ordered = {key: intake for key, intake in intakes.items() if key.startswith(prefix)}
            intakes = {key: intake for key, intake in intakes.items() if key not in ordered}
            sub = self.session.declare_subscriber(prefix + "*", zenoh.handlers.FifoChannel(4096))
            subs.append(sub)
            threads.append(threading.Thread(target=self._ordered_intake, args=(sub, ordered), name="intake",
                                            daemon=True))
        rings = []
        for key, (parse, name, heavy, ring) in intakes.items():
            channel = CountingRing(ring, self._overflow_counter(name))
            subs.append(self.session.declare_subscriber(key, channel))
            rings.append(channel)
            threads.append(threading.Thread(target=self._intake, args=(channel, parse, name, heavy),
                                            name=f"intake-{name}", daemon=True))
        worker = threading.Thread(target=self._work, args=(stop,), name="worker", daemon=True)
        saver = threading.Thread(target=self._save_periodically, args=(stop,), name="saver", daemon=True)
        for t in [*threads, worker, saver]:
            t.start()
        log.info("serving vehicle %s on macroloc/%s/** (building %s)", self.params.vehicle, self.params.vehicle,
                 self.params.building)
        # the readiness signal: the token appears once every input is taken (a launch file waits on it)
        self._token = self.session.liveliness().declare_token(k.alive)
        self.ready.set()
        self.notifier.ready()
        try:
            while not stop.wait(self.params.status_period_s):
                self._watch_worker()
                self._publish_status()
                self._publish_features()
        finally:
            self.notifier.stopping()
            log.info("stopping: draining %d queued events", len(self.queue))
            for sub in subs:
                sub.undeclare()  # ends the intake threads' iterations (the FIFO's; the rings at close)
            for channel in rings:
                channel.close()
            for t in threads:
                t.join(timeout=5.0)
            # bounded so that a stalled worker cannot hold the exit past systemd's TimeoutStopSec (30 s)
            if not self._worker_done.wait(timeout=self.params.drain_timeout_s):
                log.warning("stopping: the drain took longer than %.0f s; %d queued events are dropped",
                            self.params.drain_timeout_s, len(self.queue))
            self._abandon.set()  # a worker still busy stops after its current event, before outputs close
            worker.join(timeout=1.0)
            saver.join(timeout=5.0)
            self._save(lock_timeout_s=2.0)
            self._publish_status()
            for q in queryables:
                q.undeclare()
            for pub in self._pubs.values():
                pub.undeclare()
            self.vehicle_out.close()
            self.live.close()
            if self._token is not None:
                self._token.undeclare()
            if self.front_end.supersedes_saved():
                log.info("stopped; map saved to %s", self.store.path)
            else:
                log.info("stopped before localizing; the saved map %s is kept as it was", self.store.path)

    def _overflow_counter(self, name: str) -> Callable[[], None]:
        return lambda: self.drops.drop(f"{name}/ring_overflow")

    def _intake(self, samples: Iterable[Any], parse: Callable[[bytes], Any], name: str, heavy: bool) -> None:
        for sample in samples:
            self._take(sample, parse, name, heavy)

    def _ordered_intake(self, sub: zenoh.Subscriber, intakes: dict[str, tuple]) -> None:
        """Lock-step: the input keys' samples from one FIFO channel, parsed and queued in arrival order (the
        service's own outputs on the same prefix are skipped); none is heavy: never pushed out, the vehicle waits
        for each answer."""
        for sample in sub:
            intake = intakes.get(str(sample.key_expr))
            if intake is not None:
                parse, name, _, _ = intake
                self._take(sample, parse, name, False)

    def _take(self, sample: Any, parse: Callable[[bytes], Any], name: str, heavy: bool) -> None:
        """Parse one sample and queue its event; a parser bug must not kill the intake: counted, skipped."""
        try:
            event = parse(sample.payload.to_bytes())
        except Exception:
            log.exception("parsing %s failed", name)
            self.drops.drop(f"{name}/parse_error")
            return
        if event is None:
            return
        self.rates[name].tick()
        if isinstance(event, OdometryIn):
            self._odometry.add(event.stamp_ns, event.T_map_body)
        if isinstance(event, StereoIn) and not self.params.lockstep:
            self._answer_frame(event)  # before queueing: the worker, woken, would hold the GIL meanwhile
        self.queue.put(event, heavy)

    def _clock_reset_seen(self, key: str, stamp_ns: int) -> None:
        """A key's stamps went back (the parser saw it on an intake thread): the odometry kept for answering
        frames is forgotten, and the worker is told in order."""
        self._odometry.clear()
        self.queue.put(ClockReset(key, stamp_ns), False)

    def _answer_frame(self, ev: StereoIn) -> None:
        """The frame's pose at once, on its intake thread (service.frame_answers); the worker perceives it later."""
        snapshot, T_odom_body = self.front_end.loop.snapshot, self._odometry.at(ev.stamp_ns, newest_if_later=True)
        est = snapshot.at(ev.stamp_ns, T_odom_body) if snapshot is not None and T_odom_body is not None else \
            Estimate(ev.stamp_ns, self.front_end.status, np.eye(4))
        self._publish_pose(est)
        self.latency["frame_to_pose"].add_ms((time.monotonic_ns() - ev.received_ns) * 1e-6)

    def _work(self, stop: threading.Event) -> None:
        """Handle events until stopped and the queue is empty (the drain)."""
        handlers: dict[type, Callable[[Any], None]] = {
            OdometryIn: self._on_odometry, ObservationsIn: self._on_observations, StereoIn: self._on_stereo,
            ImuIn: self._on_imu, GoalIn: self._on_goal, PriorIn: self._on_prior, ClockReset: self._on_clock_reset}
        while not self._abandon.is_set():
            self._worker_beat_s = time.monotonic()
            event = self.queue.get(timeout_s=0.1)
            if event is None:
                if stop.is_set() and not len(self.queue):
                    break
                continue
            try:
                handlers[type(event)](event)
            except Exception:  # one bad event must not kill the service
                if self._abandon.is_set():  # its outputs were closed under it at the end of the drain
                    self.drops.drop(f"{type(event).__name__}/shutdown")
                    continue
                log.exception("handling %s failed", type(event).__name__)
                self.drops.drop(f"{type(event).__name__}/handler_error")
        self._worker_done.set()

    # --- events -------------------------------------------------------------------------------------------------

    def _on_clock_reset(self, ev: ClockReset) -> None:
        """A key's stamps restarted from a new time base: poses go out again from the new stamps on, and the
        front end forgets what it keeps by stamp (its odometry buffer, pending sightings)."""
        if ev.stamp_ns < self._last_pose_ns:
            log.warning("clock reset on %s: poses restart from stamp %d ns", ev.key, ev.stamp_ns)
            self._last_pose_ns = -1
            with self._lock:
                self.front_end.handle(ev)

    def _on_imu(self, ev: ImuIn) -> None:
        with self._lock:
            self.front_end.handle(ev)

    def _on_odometry(self, ev: OdometryIn) -> None:
        start = time.perf_counter()
        with self._lock:
            est = self.front_end.handle(ev)
        assert est is not None  # an odometry sample is a frame of its own
        self._publish_worker(est)
        self.latency["odometry_to_pose"].add_ms((time.perf_counter() - start) * 1e3)

    def _on_observations(self, ev: ObservationsIn) -> None:
        start = time.perf_counter()
        with self._lock:
            est = self.front_end.handle(ev)
        if est is None:
            return  # waiting for the odometry of its stamp (or counted as unmatched by the front end)
        self.latency["keyframe"].add_ms((time.perf_counter() - start) * 1e3)
        self._publish_worker(est)

    def _on_stereo(self, ev: StereoIn) -> None:
        """The front end perceives the frame and adds it to the pose graph (service.front_end). In lock-step its
        pose goes out now; otherwise it went out on arrival, and what the frame changed goes out at the last
        answer's stamp (`_publish_worker`)."""
        with self._lock:
            est = self.front_end.handle(ev)
            sightings, status = self.front_end.sightings, self.front_end.status
        self.live.frame(ev.frame, ev.stamp_ns, sightings)
        if est is None:
            est = Estimate(ev.stamp_ns, status, np.eye(4))
        self.latency["frame_perceived"].add_ms((time.monotonic_ns() - ev.received_ns) * 1e-6)
        if self.params.lockstep:
            self._publish_pose(est)
            self.latency["frame_to_pose"].add_ms((time.monotonic_ns() - ev.received_ns) * 1e-6)
        else:
            self._publish_worker(est)
        if est.T_cad_body is not None and ev.frame.HasField("depth"):
            self._add_obstacles(ev.frame, est.T_cad_body)

    def _add_obstacles(self, frame: pb.StereoFrame, T_cad_body: np.ndarray) -> None:
        """Depth seen by the vehicle (CAD frame) into the planner's obstacle layer of the current storey."""
        points_body = depth_points_body(frame)
        if len(points_body):
            with self._lock:
                self.planner.add_obstacle_points(points_body @ T_cad_body[:3, :3].T + T_cad_body[:3, 3],
                                                 float(T_cad_body[2, 3]))

    def _on_prior(self, ev: PriorIn) -> None:
        """The operator's prior to the localizer (graph.prior: it picks among poses the registration leaves tied);
        a storey the model lacks, or a pose before any odometry, is counted and dropped."""
        with self._lock:
            refused = self.front_end.prior(ev)
        if refused is not None:
            self.drops.drop(refused)

    def _on_goal(self, ev: GoalIn) -> None:
        try:  # a feature or space the model does not have: refused and counted, the current goal is kept
            self.planner.resolve(ev.goal, np.zeros(3))
        except PlanningError as exc:
            self.drops.drop("goal/unknown_target", str(exc)[:80])
            return
        self._goal = ev
        self._last_plan_ns = None
        log.info("new goal: %s", ev.goal)
        if ev.start_cad is not None:
            self._plan_and_publish(ev.start_cad)
        elif self.front_end.last is not None:
            self._maybe_replan(self.front_end.last)

    # --- outputs ------------------------------------------------------------------------------------------------

    def _publish(self, est: Estimate) -> None:
        """The pose, and a new plan when one is due: in lock-step the plan goes out first, so that a vehicle that
        waits for this pose has the waypoints planned from it too (one session's puts arrive in order)."""
        if self.params.lockstep:
            self._maybe_replan(est)
            self._publish_pose(est)
        else:
            self._publish_pose(est)
            self._maybe_replan(est)

    def _publish_worker(self, est: Estimate) -> None:
        """An estimate of the worker. Where a newer pose already went out (frames are answered on arrival; a
        keyframe's sightings come late), a keyframe's change goes out again at that pose's stamp: the newest
        keyframe's estimate moved by the odometry there (not at a newer stamp: a frame still being answered would
        then be older than the last pose, and withheld)."""
        if est.stamp_ns >= self._last_pose_ns:
            self._publish(est)
            return
        stamp_ns, snapshot = self._last_pose_ns, self.front_end.loop.snapshot
        T_odom_body = self._odometry.at(stamp_ns, newest_if_later=True)
        if self.front_end.loop.keyframe and snapshot is not None and T_odom_body is not None:
            self._publish(snapshot.at(stamp_ns, T_odom_body))

    def _publish_pose(self, est: Estimate) -> None:
        """Publish the estimate unless a newer one already went out (keys arrive through separate channels)."""
        with self._publish_lock:
            if est.stamp_ns < self._last_pose_ns:
                return
            est = self._plausible(est)
            self._last_pose_ns = est.stamp_ns
            msg = pose_message(est, geo=self.params.geo)
            msg.header.seq = self.rates["pose"].total
            self._pubs["pose"].put(msg.SerializeToString())
            self.vehicle_out.pose(est)
            self.live.pose(est)
            self.rates["pose"].tick()

    def _plausible(self, est: Estimate) -> Estimate:
        """The estimate, or LOST without a pose where it is implausible (`front_end.plausible`): no garbage pose
        goes out, least of all as LOCALIZED (counted as pose/implausible)."""
        if plausible(est, self.params.limits):
            return est
        self.drops.drop("pose/implausible", f"{est.status} pose withheld")
        return Estimate(est.stamp_ns, "lost", np.eye(4))

    def _maybe_replan(self, est: Estimate) -> None:
        if self._goal is None or est.T_cad_body is None or est.status not in ("localized", "degraded"):
            return
        if self._last_plan_ns is not None and est.stamp_ns - self._last_plan_ns < self.params.replan_period_s * 1e9:
            return  # on the vehicle's clock: a replay or a lock-step flight replans at the same moments
        self._last_plan_ns = est.stamp_ns
        self._plan_and_publish(est.T_cad_body[:3, 3], est.stamp_ns)

    def _plan_and_publish(self, start_cad: np.ndarray, stamp_ns: int | None = None) -> None:
        assert self._goal is not None
        msg = self._plan(self._goal.goal, start_cad, stamp_ns)
        self._pubs["waypoints"].put(msg.SerializeToString())
        self.vehicle_out.waypoints(msg)
        self.live.waypoints(msg)

    def _plan(self, goal: GoalSpec, start_cad: np.ndarray, stamp_ns: int | None = None) -> pb.Waypoints:
        """Waypoints from start_cad to the goal, stamped with the stamp of the pose they start from (`stamp_ns`;
        by default the last pose published, the vehicle's clock like every pose), with a yaw per waypoint."""
        msg = pb.Waypoints()
        msg.header.frame_id = "cad"
        msg.header.stamp_ns = max(self._last_pose_ns, 0) if stamp_ns is None else stamp_ns
        try:
            with self._lock:
                plan = self.planner.plan(start_cad, goal)
        except PlanningError as exc:
            msg.error = str(exc)
            log.warning("no plan: %s", exc)
            return msg
        msg.points_cad.extend(pb.Vector3(x=p[0], y=p[1], z=p[2]) for p in plan.points_cad)
        msg.yaw_rad.extend(float(y) for y in plan.yaw_rad)
        msg.path_length_m = plan.length_m
        msg.goal_description = plan.description
        return msg

    def _answer_map(self, query: zenoh.Query) -> None:
        with self._lock:
            snap = self.front_end.snapshot(self.params.building, self.params.building_sha256)
        query.reply(query.key_expr, snap.SerializeToString(), encoding=PROTOBUF)

    def _answer_plan(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        goal = self.parser.goal(payload) if payload else None
        if goal is None:
            msg = pb.Waypoints(error="the query's payload must be a macroloc.v1.Goal")
        else:
            start, last = goal.start_cad, self.front_end.last  # read once: the worker replaces it meanwhile
            if start is None and last is not None and last.T_cad_body is not None:
                start = last.T_cad_body[:3, 3]
            msg = self._plan(goal.goal, start) if start is not None else \
                pb.Waypoints(error="not localized yet: give Goal.start_cad")
        query.reply(query.key_expr, msg.SerializeToString(), encoding=PROTOBUF)

    def _watch_worker(self) -> None:
        """Stall detection: a worker busy beyond `stall_after_s` withdraws the liveliness token and stops feeding
        systemd's watchdog (which then restarts the process); the token returns when the worker moves again."""
        busy_s = time.monotonic() - self._worker_beat_s
        stalled = busy_s > self.params.stall_after_s
        if stalled and not self._stalled:
            log.warning("worker stalled: one event has been handled for %.1f s; liveliness withdrawn", busy_s)
            if self._token is not None:
                self._token.undeclare()
                self._token = None
            self.notifier.status(f"stalled for {busy_s:.0f} s")
        elif not stalled and self._stalled:
            log.warning("worker moving again; liveliness restored")
            self._token = self.session.liveliness().declare_token(self.keys.alive)
        if not stalled:
            self.notifier.watchdog()
        self._stalled = stalled

    def diagnostics(self) -> pb.Diagnostics:
        msg = pb.Diagnostics(state=self.front_end.status)
        msg.header.stamp_ns = time.time_ns()
        for name, meter in self.rates.items():
            msg.rates_hz[name] = meter.rate_hz()
            msg.counts[name] = meter.total
        for name, window in self.latency.items():
            for stat, value in window.percentiles().items():
                msg.latencies_ms[f"{name}_{stat}"] = value
        for kind, n in self.drops.counts().items():
            msg.dropped[kind] = n
        msg.dropped["queue_overrun"] = self.queue.dropped
        msg.dropped["observations/no_odometry"] = self.front_end.unmatched
        msg.dropped["graph/restarted"] = self.front_end.graph_restarts
        msg.latencies_ms["isam_update_mean"] = self.front_end.isam_update_ms_mean  # at keyframes, since the start
        msg.counts["queued"] = len(self.queue)
        msg.latencies_ms["worker_busy"] = (time.monotonic() - self._worker_beat_s) * 1e3  # > stall_after_s: stalled
        return msg

    def _publish_status(self) -> None:
        diag = self.diagnostics()
        if self._lock.acquire(timeout=0.2):  # a stalled worker holds the lock: publish what was last known
            try:
                loc = self.front_end.localizer
                self._last_status = pb.ServiceStatus(
                    version=VERSION, vehicle=self.params.vehicle, building=self.params.building,
                    status=STATUS_TO_WIRE[loc.status], keyframes=loc.graph.n_keyframes, landmarks=len(loc.landmarks))
            finally:
                self._lock.release()
        status = self._last_status
        status.header.stamp_ns = diag.header.stamp_ns
        self._pubs["diagnostics"].put(diag.SerializeToString())
        self._pubs["status"].put(status.SerializeToString())
        self.vehicle_out.status(diag, status)
        self.live.status(diag, status)
        state = diag.state
        log.info("status %s: rates %s, latencies %s, dropped %s", state,
                 {k: round(v, 1) for k, v in diag.rates_hz.items()},
                 {k: round(v, 2) for k, v in diag.latencies_ms.items()}, dict(diag.dropped),
                 extra={"data": {"status": state, "rates_hz": dict(diag.rates_hz),
                                 "latencies_ms": dict(diag.latencies_ms), "dropped": dict(diag.dropped)}})

    def _publish_features(self) -> None:
        """The reconstructed doors/windows: CAD frame once localized (id = the linked model feature), else map."""
        if not self._lock.acquire(timeout=0.2):  # the worker is busy: the next period publishes them
            return
        try:
            snap = self.front_end.snapshot(self.params.building, self.params.building_sha256)
            rivals_cad_body = self.front_end.rival_poses()
        finally:
            self._lock.release()
        msg = pb.ObservedFeatures()
        msg.header.stamp_ns = snap.header.stamp_ns
        localized = snap.status == pb.PoseEstimate.LOCALIZED and snap.HasField("T_cad_map")
        msg.header.frame_id = "cad" if localized else "map"
        T = matrix_from_pose(snap.T_cad_map) if localized else np.eye(4)
        for lm in snap.landmarks_map:
            corners = np.array([[c.x, c.y, c.z] for c in lm.corners]).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
            msg.features.add(type=lm.type, id=lm.id).corners.extend(
                pb.Vector3(x=c[0], y=c[1], z=c[2]) for c in corners)
        self._pubs["features"].put(msg.SerializeToString())
        self.live.landmarks(msg, rivals_cad_body)

    def _save_periodically(self, stop: threading.Event) -> None:
        """Every save_period_s, on its own thread: a slow disk (fsync) never delays status or poses."""
        while not stop.wait(self.params.save_period_s):
            self._save(lock_timeout_s=0.2)

    def _save(self, lock_timeout_s: float = -1.0) -> bool:
        """Save the map (False when the worker held the lock past `lock_timeout_s`; -1: wait as long as it takes)."""
        if not self._lock.acquire(timeout=lock_timeout_s):
            log.warning("worker stalled: the map saved last is kept (a snapshot mid-update would be inconsistent)")
            return False
        try:
            if not self.front_end.supersedes_saved():
                log.debug("not localized yet: the saved map this run restarted from is kept")
                return True
            snap = self.front_end.snapshot(self.params.building, self.params.building_sha256)
            views = self.front_end.saved_views()
        finally:
            self._lock.release()
        self.store.save(snap, views)  # off the lock: the worker goes on meanwhile
        return True
