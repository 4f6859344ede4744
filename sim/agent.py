"""The reference onboard vehicle agent: subscribes to its poses and waypoints, flies, publishes its sensors.

`VehicleAgent` is what runs on a drone beside the service: it takes the latest `PoseEstimate` (CAD frame) and
`Waypoints` from Zenoh, steers towards the next waypoint using the *estimated* pose (as a real vehicle must),
and publishes IMU, odometry and what its cameras see. In simulation the vehicle is `sim.vehicle.KinematicDrone`
with a `DriftingOdometry`; the sensor is pluggable (`Sensor`): `TruthSensor` publishes the doors and windows in
view from the model's ground truth, with noise and drop-outs, in the body frame (the stand-in for the
rendering + perception chain, always labelled as such in the demo's output).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import zenoh

from macroloc.graph.features import BuildingModel
from macroloc.proto.keys import Keys, declare_publisher
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import (
    TOPIC_GROUND_TRUTH,
    TOPIC_STEREO,
    FlightWriter,
    add_features_in_view,
    depth_image_mm,
    encode_image,
    matrix_from_pose,
    pose_from_matrix,
    vector3,
)
from macroloc.sim.groundtruth import features_in_view
from macroloc.sim.simulator import SimulationParams, Simulator
from macroloc.sim.vehicle import DriftingOdometry, KinematicDrone, yaw_of

if TYPE_CHECKING:
    from macroloc.graph.planning_grid import OccupancyGrid

log = logging.getLogger(__name__)

GRAVITY_MPS2 = 9.81
RECORDED_TOPICS = {"stereo": TOPIC_STEREO, "ground_truth": TOPIC_GROUND_TRUTH}  # a sensor's keys -> recording's


class Sensor(Protocol):
    """What the vehicle's sensor produces at its true pose: messages and the input key (leaf) each goes on."""

    label: str

    def measure(self, stamp_ns: int, T_cad_body: np.ndarray) -> list[tuple[str, Any]]: ...

    def close(self) -> None: ...


class TruthSensor:
    """Doors/windows in the camera's field of view, in range and in line of sight through the model's walls,
    from ground truth: corners in the body frame with noise sigma = a + b x range (m); a fraction dropped."""

    label = "ground-truth observations with noise (rendering + perception not in the loop)"

    def __init__(self, model: BuildingModel, grid: OccupancyGrid, seed: int, range_m: float = 7.0,
                 half_fov_rad: float = np.radians(33.0), noise_m: tuple[float, float] = (0.02, 0.005),
                 drop_fraction: float = 0.1) -> None:
        self.features = [f for f in model.features if f.orientation == "vertical"]
        self.centroids = np.array([f.centroid_cad for f in self.features])
        self.grid = grid
        self.rng = np.random.default_rng([seed, 0x5E4])
        self.range_m = range_m
        self.half_fov_rad = half_fov_rad
        self.noise_m = noise_m
        self.drop_fraction = drop_fraction

    def visible(self, T_cad_body: np.ndarray) -> list[int]:
        """Indices of features in range, in the forward field of view, same storey, with a free line of sight."""
        eye = T_cad_body[:3, 3]
        d = self.centroids - eye
        dist = np.linalg.norm(d[:, :2], axis=1)
        bearing = np.arctan2(d[:, 1], d[:, 0]) - yaw_of(T_cad_body)
        bearing = np.abs((bearing + np.pi) % (2 * np.pi) - np.pi)
        near = np.nonzero((dist < self.range_m) & (dist > 0.5) & (bearing < self.half_fov_rad)
                          & (np.abs(d[:, 2]) < 1.5))[0]
        free = ~self.grid.occupied
        out = []
        for k in near:
            end = self.centroids[k] - 0.3 * d[k] / max(float(np.linalg.norm(d[k])), 1e-9)  # stop short of its wall
            if ray_free(free, self.grid.cell_of(eye), self.grid.cell_of(end)):
                out.append(int(k))
        return out

    def measure(self, stamp_ns: int, T_cad_body: np.ndarray) -> list[tuple[str, Any]]:
        return [("observations", self.observe(stamp_ns, T_cad_body))]

    def close(self) -> None:
        """Nothing to release."""

    def observe(self, stamp_ns: int, T_cad_body: np.ndarray) -> pb.ObservedFeatures:
        msg = pb.ObservedFeatures()
        msg.header.stamp_ns = stamp_ns
        msg.header.frame_id = "body"
        T_body_cad = np.linalg.inv(T_cad_body)
        for k in self.visible(T_cad_body):
            if self.rng.random() < self.drop_fraction:
                continue
            f = self.features[k]
            rng_m = float(np.linalg.norm(f.centroid_cad - T_cad_body[:3, 3]))
            corners = f.corners_cad @ T_body_cad[:3, :3].T + T_body_cad[:3, 3]
            corners = corners + self.rng.normal(0.0, self.noise_m[0] + self.noise_m[1] * rng_m, corners.shape)
            msg.features.add(type=f.type, id=f.id, score=1.0).corners.extend(vector3(c) for c in corners)
        return msg


class RenderedStereoCamera:
    """The simulator's stereo camera (sim/): renders the building at the true pose and publishes the frames;
    the service's perception chain finds the doors and windows in them."""

    label = "rendered stereo frames -> the service's perception chain"

    def __init__(self, building: Path, seed: int, ground_truth: bool = False) -> None:
        """`ground_truth`: also give each frame's GroundTruth (key "ground_truth": the true pose, the doors and
        windows in view and the depth), for a recording; it is not published."""
        self.ground_truth = ground_truth
        self.sim = Simulator(building, SimulationParams(seed=seed))
        cam = self.sim.params.camera
        self.info = pb.CameraInfo(width=cam.width, height=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                                  baseline_m=cam.baseline_m, T_body_cam=pose_from_matrix(self.sim.T_body_cam))
        self._k = 0

    def measure(self, stamp_ns: int, T_cad_body: np.ndarray) -> list[tuple[str, Any]]:
        self._k += 1
        left, right = self.sim.renderer.render_stereo(T_cad_body @ self.sim.T_body_cam, self.sim.lighting,
                                                      frame_seed=float(self._k))
        frame = pb.StereoFrame(camera_id="front", left=encode_image(left.image_bgr), right=encode_image(right),
                               info=self.info)
        frame.header.stamp_ns = stamp_ns
        frame.header.frame_id = "cam_left"
        if not self.ground_truth:
            return [("stereo", frame)]
        return [("stereo", frame), ("ground_truth", self._truth(stamp_ns, T_cad_body, left))]

    def _truth(self, stamp_ns: int, T_cad_body: np.ndarray, left: Any) -> pb.GroundTruth:  # noqa: ANN401 - a render
        """The frame's ground truth as `macroloc simulate` records it (its depth in 1 mm steps)."""
        truth = pb.GroundTruth(header=pb.Header(stamp_ns=stamp_ns, frame_id="cam_left", seq=self._k),
                               T_cad_body=pose_from_matrix(T_cad_body), T_body_cam=self.info.T_body_cam,
                               depth=depth_image_mm(left.depth_m))
        add_features_in_view(truth, features_in_view(self.sim.features, self.sim.half_depths,
                                                     T_cad_body @ self.sim.T_body_cam, self.sim.params.camera,
                                                     left.depth_m, left.instance))
        return truth

    def close(self) -> None:
        self.sim.close()


def ray_free(free: np.ndarray, a_rc: tuple[int, int], b_rc: tuple[int, int]) -> bool:
    """True when the thin segment between two cell centres crosses only free cells (sampled at 1/4 cell)."""
    a, b = np.asarray(a_rc, float), np.asarray(b_rc, float)
    n = max(2, int(np.ceil(np.abs(b - a).max() * 4)) + 1)
    cells = np.unique(np.floor(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a) + 0.5).astype(int), axis=0)
    return bool(free[cells[:, 0], cells[:, 1]].all())


@dataclass(frozen=True)
class FollowerParams:
    cruise_mps: float = 1.0
    reach_m: float = 0.25  # an intermediate waypoint counts as reached within this
    slow_radius_m: float = 1.0  # decelerate linearly within this of the final waypoint
    yaw_gain: float = 1.5
    explore_yaw_rate_radps: float = 0.7


class WaypointFollower:
    """Body-frame velocity and yaw-rate commands from the estimated pose toward the next waypoint (CAD)."""

    def __init__(self, params: FollowerParams | None = None) -> None:
        self.params = params or FollowerParams()
        self.waypoints_cad = np.zeros((0, 3))
        self.index = 0

    def set_waypoints(self, points_cad: np.ndarray) -> None:
        """New plan (from the current pose): follow it from its first point beyond reach."""
        self.waypoints_cad = np.asarray(points_cad, float).reshape(-1, 3)
        self.index = min(1, len(self.waypoints_cad) - 1) if len(self.waypoints_cad) else 0

    def final_cad(self) -> np.ndarray | None:
        return self.waypoints_cad[-1] if len(self.waypoints_cad) else None

    def command(self, T_cad_body_est: np.ndarray) -> tuple[np.ndarray, float]:
        """(velocity_body (3,), yaw rate) to fly toward the current waypoint; hover with no waypoints."""
        p = self.params
        if not len(self.waypoints_cad):
            return np.zeros(3), 0.0
        position = T_cad_body_est[:3, 3]
        while self.index < len(self.waypoints_cad) - 1 and \
                np.linalg.norm((self.waypoints_cad[self.index] - position)[:2]) < p.reach_m:
            self.index += 1
        target = self.waypoints_cad[self.index]
        delta = target - position
        dist = float(np.linalg.norm(delta))
        last = self.index == len(self.waypoints_cad) - 1
        speed = p.cruise_mps * (min(1.0, dist / p.slow_radius_m) if last else 1.0)
        v_cad = delta / max(dist, 1e-9) * speed
        heading_error = np.arctan2(delta[1], delta[0]) - yaw_of(T_cad_body_est)
        heading_error = (heading_error + np.pi) % (2 * np.pi) - np.pi
        yaw_rate = p.yaw_gain * heading_error if dist > 0.3 else 0.0
        return T_cad_body_est[:3, :3].T @ v_cad, float(yaw_rate)

    def explore(self) -> tuple[np.ndarray, float]:
        """Before localization: turn on the spot to look around."""
        return np.zeros(3), self.params.explore_yaw_rate_radps

    def remaining_m(self, position_cad: np.ndarray) -> float:
        """Length of the plan still to fly from `position_cad` (m): to the current waypoint, then along the rest."""
        points = self.waypoints_cad[self.index:]
        if not len(points):
            return 0.0
        return float(np.linalg.norm(points[0] - position_cad) + np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


@dataclass(frozen=True)
class ProgressParams:
    window_s: float = 15.0  # no shorter way left to the goal for this long (at 1 m/s: 15 m not gained) = no progress
    gain_m: float = 0.5  # the way left must shrink by this to count as progress (twice the waypoint reach)
    max_replans: int = 2  # new plans asked for in a row without progress; then the vehicle holds and says so


class ProgressMonitor:
    """Detects a vehicle that makes no progress toward its goal (circling a room, oscillating between two
    waypoints): the length of the plan left to fly has not reached a new minimum, by `gain_m`, for `window_s`.
    `update` answers "ok", "replan" (ask the service for a new plan) or, after `max_replans` of those, "hold"
    (once; "held" after that)."""

    def __init__(self, params: ProgressParams | None = None) -> None:
        self.params = params or ProgressParams()
        self.reset(0.0)

    def reset(self, t_s: float) -> None:
        self.best_m, self.best_at_s, self.replans, self.holding = float("inf"), t_s, 0, False

    def update(self, t_s: float, remaining_m: float) -> str:
        p = self.params
        if self.holding:
            return "held"
        if remaining_m < self.best_m - p.gain_m or remaining_m <= p.gain_m:
            self.best_m, self.best_at_s, self.replans = min(remaining_m, self.best_m), t_s, 0
            return "ok"
        if t_s - self.best_at_s < p.window_s:
            return "ok"
        self.best_at_s = t_s
        if self.replans >= p.max_replans:
            self.holding = True
            return "hold"
        self.replans += 1
        return "replan"


class VehicleAgent:
    """The onboard side of the loop (see module doc). `tick(dt)` advances the vehicle by one control step."""

    def __init__(self, session: zenoh.Session, vehicle: str, drone: KinematicDrone, odometry: DriftingOdometry,
                 sensor: Sensor, follower: WaypointFollower | None = None, sensor_period_s: float = 0.1,
                 lockstep_timeout_s: float = 0.0, exploration_odom: np.ndarray | None = None,
                 explore_after_s: float = 10.0, recorder: FlightWriter | None = None, lockstep: bool = False) -> None:
        """`exploration_odom`: (N, 3) the vehicle's own exploration route in its odometry frame, flown on its
        odometry while the service is not localized yet, after `explore_after_s` of turning on the spot. Once
        localized, the route is dropped: a vehicle the service loses later turns on the spot where it is (the
        route was drawn from the take-off point, and this simulator does not stop a vehicle at a wall).
        `recorder`: also write what the vehicle sends (IMU, odometry, stereo frames) and the sensor's ground truth
        to this recording (service.recording), a flight `macroloc replay` can run again.
        `lockstep`: the vehicle's clock waits for the service (with `ServiceParams.lockstep`): after each tick
        until every message that gives a pose has been answered, after a goal until its waypoints came; one
        seed then flies the same flight on an idle or a loaded machine."""
        self.keys = Keys(vehicle)
        self.drone = drone
        self.odometry = odometry
        self.sensor = sensor
        self.follower = follower or WaypointFollower()
        self.explorer = WaypointFollower(self.follower.params)
        if exploration_odom is not None:
            self.explorer.set_waypoints(exploration_odom)
        self.explore_after_s = explore_after_s
        self._T_odom_body = odometry.T_odom_body
        self.sensor_period_s = sensor_period_s
        self.lockstep_timeout_s = lockstep_timeout_s  # > 0: after a measurement, wait for its pose (slow sensors)
        self.stamp_ns = 0
        self._next_sensor_ns = 0
        self._lock = threading.Lock()
        self.pose: pb.PoseEstimate | None = None
        self.plans = 0
        self.lockstep = lockstep
        self._pose_producers = 0  # odometry, sightings and frames sent: each is answered by one pose (lock-step)
        self._waypoint_answers = 0  # waypoint messages received, errors included
        self.progress = ProgressMonitor()
        self._goal: pb.Goal | None = None
        self.recorder = recorder
        self._pubs = {name: declare_publisher(session, getattr(self.keys, name), block=lockstep)
                      for name in ("imu", "odometry", "observations", "stereo", "goal")}
        self._subs: list[zenoh.Subscriber[Any]] = []
        if lockstep:  # the service's answers in the order it sent them (a plan goes out before its pose)
            answers = session.declare_subscriber(f"macroloc/{vehicle}/*", zenoh.handlers.FifoChannel(4096),
                                                 allowed_origin=zenoh.Locality.REMOTE)
            self._subs = [answers]
            threading.Thread(target=self._ordered_answers, args=(answers,), name="answers", daemon=True).start()
        else:
            self._subs = [session.declare_subscriber(self.keys.pose, self._on_pose),
                          session.declare_subscriber(self.keys.waypoints, self._on_waypoints)]

    def _ordered_answers(self, answers: zenoh.Subscriber[Any]) -> None:
        """Lock-step: poses and waypoints from one FIFO channel, handled in arrival order. On two subscribers
        each has its own callback thread, and a vehicle that has its pose could tick once more on the plan
        before the one planned from that pose."""
        handlers = {self.keys.pose: self._on_pose, self.keys.waypoints: self._on_waypoints}
        for sample in answers:
            handler = handlers.get(str(sample.key_expr))
            if handler is not None:
                handler(sample)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        msg = pb.PoseEstimate.FromString(sample.payload.to_bytes())
        with self._lock:
            self.pose = msg

    def _on_waypoints(self, sample: zenoh.Sample) -> None:
        msg = pb.Waypoints.FromString(sample.payload.to_bytes())
        with self._lock:
            self._waypoint_answers += 1
        if msg.error or not msg.points_cad:
            log.warning("no waypoints: %s", msg.error)
            return
        with self._lock:
            self.follower.set_waypoints(np.array([[p.x, p.y, p.z] for p in msg.points_cad]))
            self.plans += 1

    def localized_pose(self) -> np.ndarray | None:
        """The latest estimated T_cad_body when the service says LOCALIZED (or DEGRADED), else None."""
        with self._lock:
            pose = self.pose
        if pose is None or pose.status not in (pb.PoseEstimate.LOCALIZED, pb.PoseEstimate.DEGRADED) \
                or not pose.HasField("T_cad_body"):
            return None
        return matrix_from_pose(pose.T_cad_body)

    def send_goal(self, goal: pb.Goal) -> None:
        if self._goal is not goal:
            self.progress.reset(self.stamp_ns * 1e-9)
        self._goal = goal
        goal.header.stamp_ns = self.stamp_ns
        with self._lock:
            answered = self._waypoint_answers
        self._pubs["goal"].put(goal.SerializeToString())
        if self.lockstep:
            self._wait(lambda: self._waypoint_answers > answered, "the goal's waypoints")

    def tick(self, dt_s: float) -> None:
        """Control from the estimate, move the true vehicle, publish IMU, odometry and (periodically) sightings."""
        T_est = self.localized_pose()
        if T_est is not None and len(self.explorer.waypoints_cad):
            self.explorer.set_waypoints(np.zeros((0, 3)))  # localized once: the take-off's exploration is over
        if T_est is not None and self._goal is not None and len(self.follower.waypoints_cad):
            self._watch_progress(T_est)
        with self._lock:
            if self.progress.holding:
                v_body, yaw_rate = np.zeros(3), 0.0
            else:
                v_body, yaw_rate = self.follower.command(T_est) if T_est is not None else self._explore()
        self.drone.step(dt_s, v_body, yaw_rate)
        self.stamp_ns += int(round(dt_s * 1e9))
        T_true = self.drone.T_cad_body
        imu = pb.Imu(accel_mps2=vector3(self.drone.specific_force_body(GRAVITY_MPS2)),
                     gyro_radps=pb.Vector3(z=yaw_rate))
        imu.header.stamp_ns = self.stamp_ns
        imu.header.frame_id = "body"
        self._pubs["imu"].put(imu.SerializeToString())
        self._T_odom_body = self.odometry.update(T_true)
        odo = pb.Odometry(T_map_body=pose_from_matrix(self._T_odom_body))
        odo.header.stamp_ns = self.stamp_ns
        odo.header.frame_id = "map"
        self._pubs["odometry"].put(odo.SerializeToString())
        self._pose_producers += 1
        if self.recorder is not None:
            self.recorder.write_imu(imu)
            self.recorder.write_odometry(odo)
        if self.stamp_ns >= self._next_sensor_ns:
            self._next_sensor_ns = self.stamp_ns + int(self.sensor_period_s * 1e9)
            for key, message in self.sensor.measure(self.stamp_ns, T_true):
                if key in self._pubs:
                    self._pubs[key].put(message.SerializeToString())
                    self._pose_producers += key in ("observations", "stereo")
                if self.recorder is not None and key in RECORDED_TOPICS:
                    self.recorder.write(RECORDED_TOPICS[key], message, self.stamp_ns)
            if self.lockstep_timeout_s > 0 and not self.lockstep:
                self._wait_for_pose(self.stamp_ns, self.lockstep_timeout_s)
        if self.lockstep:
            n = self._pose_producers
            self._wait(lambda: self.pose is not None and self.pose.header.seq >= n - 1, f"pose {n}")

    def _watch_progress(self, T_est: np.ndarray) -> None:
        """No progress toward the goal: ask for a new plan (the goal again), then hold; each said in the log."""
        with self._lock:
            remaining = self.follower.remaining_m(T_est[:3, 3])
        action = self.progress.update(self.stamp_ns * 1e-9, remaining)
        if action == "replan" and self._goal is not None:
            log.warning("no progress toward the goal for %.0f s (%.1f m of the plan left, %.1f m at best): asking "
                        "for a new plan", self.progress.params.window_s, remaining, self.progress.best_m)
            self.send_goal(self._goal)
        elif action == "hold":
            log.warning("still no progress toward the goal after %d new plans: holding position",
                        self.progress.replans)

    def _explore(self) -> tuple[np.ndarray, float]:
        """Not localized: turn on the spot, then fly the exploration route on odometry (if any is left), then turn."""
        route = self.explorer.waypoints_cad  # in the odometry frame here
        if self.stamp_ns * 1e-9 < self.explore_after_s or not len(route) or \
                np.linalg.norm((route[-1] - self._T_odom_body[:3, 3])[:2]) < self.explorer.params.reach_m:
            return self.follower.explore()
        return self.explorer.command(self._T_odom_body)

    def _wait_for_pose(self, stamp_ns: int, timeout_s: float) -> None:
        """Simulated time waits for the service to answer this measurement (a sensor slower than real time)."""
        self._until(lambda: self.pose is not None and self.pose.header.stamp_ns >= stamp_ns, timeout_s, 0.002)

    def _wait(self, answered: Any, what: str, timeout_s: float = 120.0) -> None:
        """Lock-step: block the vehicle's clock until `answered()` (checked under the lock) or the timeout."""
        if not self._until(answered, timeout_s, 0.0005):
            log.warning("lock-step: no answer for %s within %.0f s; the vehicle goes on", what, timeout_s)

    def _until(self, condition: Any, timeout_s: float, poll_s: float) -> bool:
        """Poll `condition()` under the lock until it holds (True) or `timeout_s` passed (False)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if condition():
                    return True
            time.sleep(poll_s)
        return False

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        for pub in self._pubs.values():
            pub.undeclare()
