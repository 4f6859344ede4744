"""`macroloc demo`: the service and a simulated vehicle in a real building, the loop closed over Zenoh.

The service runs on one Zenoh session, the vehicle agent on another, connected over loopback TCP: the agent
takes off at a seeded point of the storey where most can be seen (`sim.demo_route`: any building macroloc can
read), turns on the spot to look around and then, if the service has not said LOCALIZED yet, explores (a seeded
route through the storey's free space, flown on its own odometry); once localized it sends a goal (an IfcSpace by
name, else a door, a window or a free cell of another room), follows the service's waypoints using the service's
pose, and hovers at the goal. The operator tells the service the take-off storey (graph.storey_hint). A flight
that ends 'ambiguous' (a symmetric building: two or more poses explain all that was seen) says so, with its rival
poses. Reported, as in the paper's Table 2: localization time (simulated seconds from take-off
to the first LOCALIZED pose), error at the goal (true position vs the goal point, m) and that error as a
percentage of the flown path's length. A picture of the flight is written.
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from macroloc.graph.bim import load_building
from macroloc.graph.errors import UserInputError
from macroloc.graph.rigid import apply
from macroloc.proto.recording import FlightWriter
from macroloc.service.config import MacrolocConfig, load_config
from macroloc.sim.demo_route import Route, choose_route, goal_distance_range_m, take_off_storey

if TYPE_CHECKING:  # the service's planner, imported where used: sim/ imports only service's wire and config at its top
    from macroloc.graph.planning import Planner
    from macroloc.graph.planning_grid import OccupancyGrid

log = logging.getLogger(__name__)

DEFAULT_BUILDING = Path(__file__).resolve().parents[1] / "data" / "buildings" / "office_a.ifc"


@dataclass(frozen=True)
class DemoParams:
    seed: int = 0
    rate_hz: float = 30.0  # control, IMU and odometry rate (simulated)
    speedup: float = 1.0  # simulated seconds per wall-clock second
    timeout_s: float = 150.0  # simulated
    min_goal_distance_m: float = 10.0
    max_goal_distance_m: float = 25.0
    observations: str = "perception"  # perception: rendered frames -> the service's chain; truth: noisy ground truth
    camera_rate_hz: float = 5.0  # perception mode: frames per simulated second (the loop waits for each pose)
    detector_model: Path | None = None  # perception mode: None = the building's bundled adapted one, if any
    record: Path | None = None  # perception mode: write the flight (service.recording) for `macroloc replay`
    lockstep: bool = False  # the vehicle's clock waits for the service: the same flight on any machine load
    vehicle: str = "demo"  # key prefix: macroloc/<vehicle>/..., ROS topics /<vehicle>/macroloc/...
    listen: tuple[str, ...] = ()  # extra Zenoh endpoints the service listens on, for a bridge or a subscriber
    ros: bool = False  # also publish ROS 2 messages (service.ros_out)
    px4: bool = False  # also publish PX4's fmu/in/ topics (service.px4)
    config: Path | None = None  # the service's config file (JSON or TOML): the demo's own settings above win
    storey: str | None = None  # the take-off storey; None: the config's graph.storey_hint, else chosen (demo_route)
    goal: str | None = None  # an IfcSpace name, a door's or window's GlobalId or "x,y,z" (CAD, m); None: chosen
    foxglove: int = 0  # the operator's live view: Foxglove's WebSocket server on this port ([foxglove]); 0: none


@dataclass
class DemoResult:
    seed: int
    localized: bool
    reached: bool
    localization_time_s: float
    goal_error_m: float
    path_length_m: float
    goal_error_pct: float
    start: str
    goal: str
    observations: str
    wall_time_s: float
    true_xy: list[list[float]] = field(default_factory=list, repr=False)
    estimated_xy: list[list[float]] = field(default_factory=list, repr=False)
    waypoints_xy: list[list[float]] = field(default_factory=list, repr=False)
    goal_xyz: list[float] = field(default_factory=list, repr=False)
    goal_wgs84: list[float] | None = None  # latitude, longitude (deg), altitude (m) of the goal; None: no geo-ref.
    wall_contacts_xy: list[list[float]] = field(default_factory=list)  # where the true track hit the model's solids
    storey: str = ""  # the take-off storey
    outcome: str = ""  # reached | not reached | ambiguous | not localized
    rivals_xy: list[list[float]] = field(default_factory=list)  # ambiguous: where each rival pose puts the vehicle
    pose_error_m: float = float("nan")  # the service's estimate vs the truth (horizontal) when last localized

    def table_row(self) -> dict[str, float]:
        return {"localization_time_s": self.localization_time_s, "goal_error_m": self.goal_error_m,
                "path_length_m": self.path_length_m, "goal_error_pct": self.goal_error_pct}


def wall_contacts(grid: OccupancyGrid, true_xy: np.ndarray) -> np.ndarray:
    """(K, 2) CAD points where the vehicle's true track (N, 2: x, y at flight height, its control steps) entered a
    cell the model's solids occupy at that height (the storey's section, not inflated by the vehicle's radius), one
    per contact. A wall's face runs through each such cell, so the vehicle's centre came within a cell's diagonal
    of the wall (0.28 m on the demo's 0.2 m grid), or crossed it: a vehicle of the planner's radius (0.35 m)
    touched it. This simulator does not stop a vehicle at a wall; a real one would have hit it."""
    xy = np.asarray(true_xy, float).reshape(-1, 2)
    hit = np.array([grid.contains(p) and bool(grid.occupied[grid.cell_of(p)]) for p in xy], bool)
    starts = hit & ~np.r_[False, hit[:-1]]
    return xy[starts]


def exploration_route(planner: Planner, start_xyz: np.ndarray, seed: int, length_m: float = 40.0) -> np.ndarray:
    """(N, 3) CAD points of a seeded collision-free route from the take-off point through the storey's free
    space: legs to random free cells inside the building, planned by the service's own A* planner (the cells are
    drawn from the grid's free cells outdoors too, those outside skipped: a seed explores as it did before the
    planner kept inside). A leg is 6-15 m, or a quarter to 60 % of the storey's extent where the storey is smaller
    (`sim.demo_route.goal_distance_range_m`: a house's rooms lie 2-6 m apart, no cell lies 6 m from some)."""
    from macroloc.graph.planning import GoalSpec, PlanningError

    rng = np.random.default_rng([seed, 0xE4])
    grid, free = planner.free_cells(start_xyz[2], outdoors=True)
    lo_m, hi_m = goal_distance_range_m(grid, planner.free_cells(start_xyz[2])[1], 6.0, 15.0)
    outside = planner.outside(start_xyz[2])
    cells, inside = np.argwhere(free), np.argwhere(free & ~outside)
    route, here, total = [np.asarray(start_xyz, float)[None]], np.asarray(start_xyz, float), 0.0
    for k in range(80):  # then, short of length_m (a building small in its grid), 40 draws among the inside cells
        pool = cells if k < 40 else inside
        if not len(pool):
            break
        target = grid.centre_cad(pool[rng.integers(len(pool))][None])[0]
        if outside[grid.cell_of(target)] or not lo_m <= float(np.linalg.norm((target - here)[:2])) <= hi_m:
            continue
        try:
            leg = planner.plan(here, GoalSpec(position_cad=target))
        except PlanningError:
            continue
        route.append(leg.points_cad[1:])
        total += leg.length_m
        here = leg.points_cad[-1]
        if total >= length_m:
            break
    return np.concatenate(route)


def bundled_detector(building: Path) -> Path | None:
    """The detector adapted to a bundled building (`macroloc adapt-detector`), shipped beside it as
    NAME_detector/detector.onnx, or None."""
    path = building.with_name(f"{building.stem}_detector") / "detector.onnx"
    return path if path.is_file() else None


def detector_choice(building: Path, params: DemoParams, own: MacrolocConfig) -> tuple[Path | None, str]:
    """The detector the demo's perception chain runs (None: the generic shipped one) and where it comes from:
    --detector, else the config's perception.detector_model, else the one adapted to this building and shipped
    beside it (`bundled_detector`), else the generic one."""
    if params.detector_model is not None:
        return params.detector_model, f"detector {params.detector_model} (--detector)"
    if own.perception.detector_model is not None:
        return own.perception.detector_model, f"detector {own.perception.detector_model} (the config's)"
    adapted = bundled_detector(building)
    if adapted is not None:
        return adapted, f"the detector adapted to {building.name}, {adapted}"
    return None, "the generic shipped detector (none adapted to this building lies beside it)"


def demo_config(building: Path, params: DemoParams, port: int, storey: str | None = None) -> MacrolocConfig:
    """The service's configuration for a demo flight: `params.config`'s keys (or the defaults), under the demo's
    own: its building, vehicle, endpoints and outputs; the take-off storey (`params.storey`, else the file's, else
    `storey`: the route's, else the storey with the most doors and windows) and the building's detector where the
    file names none."""
    own = load_config(params.config)
    perceive = params.observations == "perception"
    detector = detector_choice(building, params, own)[0] if perceive else own.perception.detector_model
    return load_config(params.config, service={"building": building, "vehicle": params.vehicle,
                                               "status_period_s": 1.0, "perception": perceive,
                                               "lockstep": params.lockstep},
                       zenoh={"listen": [f"tcp/127.0.0.1:{port}", *params.listen]},
                       ros={"enabled": params.ros}, px4={"enabled": params.px4},
                       foxglove={"port": params.foxglove} if params.foxglove else {},
                       graph={"storey_hint": params.storey or own.graph.storey_hint or storey
                              or take_off_storey(load_building(building))},
                       perception={"detector_model": detector})


def demo_route(building: Path, params: DemoParams, cfg: MacrolocConfig | None = None) -> Route:
    """The flight's take-off and goal (`sim.demo_route.choose_route`) on a planner of the config's planning
    settings (the service's own: the same grids); UserInputError, one line, where the building offers none."""
    from macroloc.graph.bim import MESH_SUFFIXES
    from macroloc.graph.planning import Planner

    if building.suffix.lower() in MESH_SUFFIXES:  # the planner's walls and the goals' rooms are IFC elements
        raise UserInputError(f"cannot fly in {building.name}: the demo plans on an IFC model's walls and rooms "
                             f"(.ifc, .ifczip), and {building.suffix} is a mesh (`macroloc features` and "
                             "`localize` read it)")
    own = cfg or load_config(params.config)
    p = own.planning
    planner = Planner.for_building(building, p.cell_m, p.vehicle_radius_m, p.flight_height_m)
    return choose_route(planner, params.seed, params.min_goal_distance_m, params.max_goal_distance_m,
                        storey=params.storey or own.graph.storey_hint, goal=params.goal,
                        registration_min_landmarks=own.graph.registration.registration_min_landmarks)


def run_demo(building: Path = DEFAULT_BUILDING, params: DemoParams | None = None,
             cfg: MacrolocConfig | None = None) -> DemoResult:
    """One closed-loop flight; the service and the agent each on their own Zenoh session (loopback)."""
    import zenoh

    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.service.serve import build_service
    from macroloc.service.state import NullSavedMapFile
    from macroloc.service.zenoh_io import session_config
    from macroloc.sim.agent import RenderedStereoCamera, Sensor, TruthSensor, VehicleAgent
    from macroloc.sim.vehicle import DriftingOdometry, KinematicDrone, level_pose

    params = params or DemoParams()
    wall_start = time.monotonic()
    port = _free_port()
    perceive = params.observations == "perception"
    if params.record is not None and not perceive:
        raise UserInputError("--record needs --observations perception (a recording holds the stereo frames)")
    own = cfg or load_config(params.config)
    detector_label = detector_choice(building, params, own)[1]
    route = demo_route(building, params, own)
    start_xyz = route.start_xyz
    log.info("route: take-off on %s %s (a turn shows %d doors and windows, %d asked), goal %s", route.storey,
             route.start, route.view, route.wanted_view, route.goal.label)
    cfg = cfg or demo_config(building, params, port, storey=route.storey)
    rng = np.random.default_rng([params.seed, 0xDE40])
    stop = threading.Event()
    with zenoh.open(session_config(cfg.zenoh)) as service_session, _recorder(building, params) as recorder:
        service = build_service(cfg, service_session, NullSavedMapFile())
        thread = threading.Thread(target=service.run, args=(stop,), name="service", daemon=True)
        thread.start()
        while not service.ready.wait(1.0) and thread.is_alive():
            pass  # readiness, not a budget: a cold cache on a loaded machine takes minutes
        agent_cfg = cfg.zenoh.model_copy(update={"listen": [], "connect": [f"tcp/127.0.0.1:{port}"]})
        try:
            with zenoh.open(session_config(agent_cfg)) as agent_session:
                T0 = level_pose(start_xyz, rng.uniform(-np.pi, np.pi))
                T_cad_odom = level_pose(np.r_[rng.uniform(-20, 20, 2), 0.0], rng.uniform(-np.pi, np.pi))
                grid, _ = service.planner.grid(start_xyz[2])
                sensor: Sensor = RenderedStereoCamera(building, params.seed, ground_truth=recorder is not None) \
                    if perceive else TruthSensor(service.planner.model, grid, params.seed)
                # The vehicle's own exploration, for when turning on the spot is not enough to localize: in
                # this simulation a route through the storey's free space handed over in its odometry frame
                # (a real vehicle explores with its own obstacle sensing); it flies it on its odometry.
                route_cad = exploration_route(service.planner, start_xyz, params.seed)
                route_odom = apply(np.linalg.inv(T_cad_odom), route_cad)
                agent = VehicleAgent(agent_session, cfg.service.vehicle, KinematicDrone(T0),
                                     DriftingOdometry(T_cad_odom, T0, params.seed), sensor,
                                     sensor_period_s=1.0 / params.camera_rate_hz if perceive else 0.1,
                                     lockstep_timeout_s=5.0 if perceive else 0.0, exploration_odom=route_odom,
                                     recorder=recorder, lockstep=params.lockstep)
                result = _fly(agent, route.goal.message(pb), params)
                result.wall_contacts_xy = wall_contacts(grid, np.array(result.true_xy)).tolist()
                if recorder is not None:
                    recorder.metadata.duration_s = agent.stamp_ns * 1e-9
                    recorder.metadata.storey = cfg.graph.storey_hint or ""
                agent.close()
                sensor.close()
        finally:
            stop.set()
            thread.join(timeout=30.0)
    result.seed, result.start, result.goal, result.storey = params.seed, route.start, route.goal.label, route.storey
    result.outcome, result.rivals_xy = _outcome(result, service.front_end, cfg.graph.anchor.cad_link_m)
    if result.wall_contacts_xy:
        log.warning("the vehicle touched or crossed the model's walls %d times (first at x %.1f, y %.1f m): this "
                    "simulator lets it through, a real vehicle would have hit", len(result.wall_contacts_xy),
                    *result.wall_contacts_xy[0])
    geo = service.params.geo
    if geo is not None and result.goal_xyz:  # where the goal lies on the Earth (graph.geo)
        result.goal_wgs84 = [float(v) for v in geo.wgs84(np.asarray(result.goal_xyz))[0]]
    result.observations = sensor.label + (f" ({detector_label})" if perceive else "")
    result.wall_time_s = time.monotonic() - wall_start
    return result


def _outcome(result: DemoResult, front_end, wrong_m: float) -> tuple[str, list[list[float]]]:  # noqa: ANN001
    """reached | not reached | localized wrongly | ambiguous | not localized, and (ambiguous) where each rival
    pose puts the vehicle (x, y CAD, m): its newest keyframe's pose in the map frame carried into the CAD frame by
    each rival T_cad_map. Wrongly: the estimate was last more than `wrong_m` (graph.anchor.cad_link_m, the
    distance within which a door seen is linked to a model door) from the truth, so the doors it links are the
    wrong ones (the ground truth the simulation has; a real flight does not)."""
    if result.localized:
        if result.pose_error_m > wrong_m:
            return "localized wrongly", []
        return ("reached" if result.reached else "not reached"), []
    loc = front_end.localizer
    if loc.status != "ambiguous" or not loc.rivals:
        return "not localized", []
    T_map_body = loc.graph.T_map_body(loc.graph.n_keyframes - 1)
    return "ambiguous", [(T @ T_map_body)[:2, 3].tolist() for T in loc.rivals]


def _fly(agent, goal, params: DemoParams) -> DemoResult:  # noqa: ANN001 - VehicleAgent, pb.Goal
    dt = 1.0 / params.rate_hz
    t_sim, t_loc, goal_sent, settled = 0.0, None, False, 0
    true_xy, est_xy, pose_error_m = [], [], float("nan")
    wall0 = time.monotonic()
    while t_sim < params.timeout_s:
        agent.tick(dt)
        t_sim += dt
        T_est = agent.localized_pose()
        true_xy.append(agent.drone.T_cad_body[:2, 3].tolist())
        if T_est is not None:
            est_xy.append(T_est[:2, 3].tolist())
            pose_error_m = float(np.linalg.norm(T_est[:2, 3] - agent.drone.T_cad_body[:2, 3]))
            if t_loc is None:
                t_loc = t_sim
                log.info("localized after %.2f s", t_loc)
            if not goal_sent:
                agent.send_goal(goal)
                goal_sent = True
            final = agent.follower.final_cad()
            near = final is not None and np.linalg.norm(final - T_est[:3, 3]) < 0.05 and \
                np.linalg.norm(agent.drone.velocity_cad) < 0.05
            settled = settled + 1 if near else 0
            if settled >= int(0.5 * params.rate_hz):
                break
        delay = wall0 + t_sim / params.speedup - time.monotonic()
        if delay > 0 and not params.lockstep:
            time.sleep(delay)  # real-time pacing of the simulated vehicle
    final = agent.follower.final_cad()
    reached = settled > 0 and final is not None
    err = float(np.linalg.norm(agent.drone.T_cad_body[:3, 3] - final)) if final is not None else float("nan")
    length = agent.drone.distance_m
    result = DemoResult(0, t_loc is not None, reached, t_loc if t_loc is not None else float("nan"), err, length,
                        100.0 * err / length if length > 0 else float("nan"), "", "", "", 0.0, true_xy, est_xy,
                        agent.follower.waypoints_cad[:, :2].tolist(), [] if final is None else final.tolist())
    result.pose_error_m = pose_error_m
    return result


def plot_flight(result: DemoResult, planner: Planner, path: Path) -> Path:
    """Top view: the model's cross-section at flight height, true and estimated tracks, waypoints, goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    z = (result.goal_xyz[2] if result.goal_xyz else planner.flight_height_m)
    grid, _ = planner.grid(z)
    h, w = grid.shape
    x0, y0 = grid.origin_xy_cad
    fig, ax = plt.subplots(figsize=(10, 8))
    ax.imshow(grid.occupied, origin="lower", cmap="Greys", extent=(x0, x0 + w * grid.cell_m, y0, y0 + h * grid.cell_m))
    true_xy, est_xy = np.array(result.true_xy).reshape(-1, 2), np.array(result.estimated_xy).reshape(-1, 2)
    ax.plot(true_xy[:, 0], true_xy[:, 1], "-", color="tab:blue", lw=1.5, label="true flight")
    if len(est_xy):
        ax.plot(est_xy[:, 0], est_xy[:, 1], "--", color="tab:orange", lw=1.0, label="service's estimate")
    wp = np.array(result.waypoints_xy).reshape(-1, 2)
    if len(wp):
        ax.plot(wp[:, 0], wp[:, 1], "o", color="tab:green", ms=4, label="waypoints (last plan)")
    ax.plot(*true_xy[0], "s", color="tab:blue", ms=8, label=f"take-off ({result.start})")
    if result.goal_xyz:
        ax.plot(result.goal_xyz[0], result.goal_xyz[1], "*", color="tab:red", ms=14, label=f"goal ({result.goal})")
    rivals = np.array(result.rivals_xy).reshape(-1, 2)
    if len(rivals):
        ax.plot(rivals[:, 0], rivals[:, 1], "D", mfc="none", color="tab:purple", ms=11, mew=2,
                label=f"ambiguous: the vehicle under each of the {len(rivals)} rival poses")
    contacts = np.array(result.wall_contacts_xy).reshape(-1, 2)
    if len(contacts):
        ax.plot(contacts[:, 0], contacts[:, 1], "X", color="crimson", ms=10,
                label=f"touched or crossed a wall ({len(contacts)}): a real vehicle would have hit")
    pad = 4.0
    shown = np.vstack([true_xy, rivals])
    lo, hi = shown.min(axis=0) - pad, shown.max(axis=0) + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, CAD)")
    ax.set_ylabel("y (m, CAD)")
    ax.set_title(f"seed {result.seed}: localized after {result.localization_time_s:.2f} s, "
                 f"error at goal {result.goal_error_m:.3f} m ({result.goal_error_pct:.2f} % of "
                 f"{result.path_length_m:.1f} m)" if result.outcome in ("reached", "not reached") else
                 f"seed {result.seed}: {outcome_line(result)}",
                 fontsize=10 if result.outcome in ("reached", "not reached") else 8)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def outcome_line(result: DemoResult) -> str:
    """The flight's outcome in one line a user reads."""
    if result.outcome == "ambiguous":
        return (f"ambiguous: {len(result.rivals_xy)} poses explain all the vehicle saw equally well (a symmetric "
                "building), so the service says so instead of guessing; they are drawn on the picture")
    if result.outcome == "localized wrongly":
        return (f"localized wrongly: the service's pose was last {result.pose_error_m:.2f} m from the truth "
                "(the simulation's ground truth says so; the service did not)")
    if result.outcome == "not localized":
        return f"not localized after {result.path_length_m:.1f} m of flight"
    return f"{result.outcome}: {result.goal_error_m:.3f} m from the goal"


def result_json(result: DemoResult) -> dict:
    doc = asdict(result)
    for key in ("true_xy", "estimated_xy", "waypoints_xy"):
        doc.pop(key)
    doc["wall_contacts"] = len(doc.pop("wall_contacts_xy"))
    doc["rivals"] = len(doc.pop("rivals_xy"))
    return doc


@contextlib.contextmanager
def _recorder(building: Path, params: DemoParams) -> Iterator[FlightWriter | None]:
    """The flight's recording (params.record), closed with its metadata when the flight ends, else None."""
    if params.record is None:
        yield None
        return
    from macroloc.graph.bim import file_sha256
    from macroloc.proto.recording import FlightMetadata

    meta = FlightMetadata(building=building.name, building_sha256=file_sha256(building), seed=params.seed,
                          extra={"generator": "macroloc demo", "observations": params.observations})
    with FlightWriter(params.record, meta) as writer:
        yield writer
    log.info("flight recorded: %s (%s)", params.record, writer.counts)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def default_picture_path() -> Path:
    return Path(tempfile.gettempdir()) / "macroloc-demo.png"
