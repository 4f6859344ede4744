"""The reference vehicle agent's exploration, the demo's exploration route and its check that the true track kept
out of the walls (no service: nobody answers)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from macroloc.cli.demo import exploration_route, wall_contacts
from macroloc.graph.planning import Planner, line_of_sight
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import pose_from_matrix
from macroloc.service.zenoh_io import session_config
from macroloc.sim.agent import VehicleAgent
from macroloc.sim.vehicle import DriftingOdometry, KinematicDrone, level_pose
from tests.service.helpers import loopback


class Blind:
    """A sensor that sees nothing: the vehicle never hears it is localized."""

    label = "blind"

    def measure(self, stamp_ns: int, T_cad_body: np.ndarray) -> list:
        return []

    def close(self) -> None:
        pass


def _distance_to_polyline(p: np.ndarray, line: np.ndarray) -> float:
    a, b = line[:-1, :2], line[1:, :2]
    ab = b - a
    t = np.clip(((p[:2] - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p[:2], axis=1)))


def test_unlocalized_the_vehicle_turns_then_flies_its_exploration_route_on_odometry() -> None:
    T0 = level_pose(np.array([2.0, 1.0, 1.4]), 0.4)
    T_cad_odom = level_pose(np.array([5.0, -3.0, 0.0]), 1.1)  # the odometry frame is anywhere
    route_cad = np.array([[2.0, 1.0, 1.4], [6.0, 1.0, 1.4], [6.0, 5.0, 1.4]])
    T_odom_cad = np.linalg.inv(T_cad_odom)
    route_odom = route_cad @ T_odom_cad[:3, :3].T + T_odom_cad[:3, 3]
    odometry = DriftingOdometry(T_cad_odom, T0, seed=0, drift_per_m=0.0, yaw_drift_rad_per_m=0.0)
    with zenoh.open(session_config(loopback())) as session:
        agent = VehicleAgent(session, "explore-test", KinematicDrone(T0), odometry, Blind(),
                             exploration_odom=route_odom, explore_after_s=2.0)
        for _ in range(60):  # 2 s: turning on the spot
            agent.tick(1 / 30)
        assert np.linalg.norm(agent.drone.T_cad_body[:3, 3] - T0[:3, 3]) < 0.05
        track = []
        for _ in range(30 * 25):
            agent.tick(1 / 30)
            track.append(agent.drone.T_cad_body[:3, 3].copy())
        agent.close()
    assert np.linalg.norm(track[-1][:2] - route_cad[-1, :2]) < 0.3  # flew the route to its end ...
    assert max(_distance_to_polyline(p, route_cad) for p in track) < 0.5  # ... along it


def test_a_vehicle_lost_after_localizing_turns_where_it_is() -> None:
    """The exploration route was drawn from the take-off point: a vehicle the service loses later (its status
    `lost`) turns on the spot where it is instead of flying the rest of that route, through whatever walls lie
    between (this simulator does not stop a vehicle at one)."""
    T0 = level_pose(np.array([2.0, 1.0, 1.4]), 0.4)
    route_cad = np.array([[2.0, 1.0, 1.4], [6.0, 1.0, 1.4], [6.0, 5.0, 1.4]])
    odometry = DriftingOdometry(np.eye(4), T0, seed=0, drift_per_m=0.0, yaw_drift_rad_per_m=0.0)
    with zenoh.open(session_config(loopback())) as session:
        agent = VehicleAgent(session, "lost-test", KinematicDrone(T0), odometry, Blind(), exploration_odom=route_cad,
                             explore_after_s=0.0)

        def hear(status: int) -> None:
            msg = pb.PoseEstimate(status=status, T_cad_body=pose_from_matrix(agent.drone.T_cad_body))
            session.put(agent.keys.pose, msg.SerializeToString())
            deadline = time.monotonic() + 5.0
            while (agent.pose is None or agent.pose.status != status) and time.monotonic() < deadline:
                time.sleep(0.01)

        hear(pb.PoseEstimate.LOCALIZED)
        for _ in range(30):
            agent.tick(1 / 30)
        hear(pb.PoseEstimate.LOST)
        here = agent.drone.T_cad_body[:3, 3].copy()
        for _ in range(90):  # 3 s lost: with the route, 3 m along it
            agent.tick(1 / 30)
        agent.close()
    assert agent.pose is not None and agent.pose.status == pb.PoseEstimate.LOST
    assert np.linalg.norm(agent.drone.T_cad_body[:3, 3] - here) < 0.05
    assert np.linalg.norm(agent.drone.T_cad_body[:3, 3] - T0[:3, 3]) < 0.05


@pytest.fixture(scope="module")
def planner(office_path) -> Planner:
    return Planner.for_building(office_path, cell_m=0.2, vehicle_radius_m=0.35, flight_height_m=1.4)


def _in_front_of_a_door(planner: Planner) -> np.ndarray:
    """1.2 m in front of Office_A's first door on Level 1, on its free side, at flight height."""
    door = next(f for f in planner.model.features if f.type == "door" and f.storey == "Level 1")
    grid, free = planner.free_cells(1.4)
    start = np.r_[door.centroid_cad[:2] + 1.2 * door.normal_cad[:2], 1.4]
    return start if free[grid.cell_of(start)] else np.r_[door.centroid_cad[:2] - 1.2 * door.normal_cad[:2], 1.4]


@pytest.mark.parametrize("seed", [0, 1])
def test_the_demo_exploration_route_is_long_and_stays_in_free_space(planner: Planner, seed: int) -> None:
    start = _in_front_of_a_door(planner)
    grid, free = planner.free_cells(start[2])
    route = exploration_route(planner, start, seed, length_m=30.0)
    assert np.allclose(route[0], start)
    assert np.linalg.norm(np.diff(route, axis=0), axis=1).sum() >= 30.0
    cells = [grid.cell_of(p) for p in route[1:]]
    assert all(free[c] for c in cells)
    assert all(line_of_sight(free, a, b) for a, b in zip(cells[:-1], cells[1:], strict=True))


def test_a_track_into_the_walls_is_counted_once_per_wall(planner: Planner) -> None:
    """Two walls across a 10 m x 10 m grid: a track across both goes into the walls twice, one along the free
    space never, one into a wall and back out on its side once. On Office_A at flight height the demo's
    exploration route keeps out of the walls, and a straight 20 m line across the storey does not."""
    from macroloc.graph.planning_grid import OccupancyGrid

    occupied = np.zeros((100, 100), bool)
    occupied[30:32, :] = occupied[70:72, :] = True  # walls at y = 3.0-3.2 m and 7.0-7.2 m
    grid = OccupancyGrid(occupied, np.zeros(2), 0.1, 1.4)
    ys = np.linspace(0.5, 9.5, 400)
    assert len(wall_contacts(grid, np.c_[np.full_like(ys, 5.0), ys])) == 2
    assert len(wall_contacts(grid, np.c_[ys, np.full_like(ys, 5.0)])) == 0
    into_and_back = np.r_[np.linspace(2.0, 3.1, 50), np.linspace(3.1, 2.0, 50)]
    assert np.allclose(wall_contacts(grid, np.c_[np.full_like(into_and_back, 5.0), into_and_back]), [[5.0, 3.0]],
                       atol=0.05)

    start = _in_front_of_a_door(planner)
    office, _ = planner.grid(start[2])
    route = exploration_route(planner, start, 0, length_m=30.0)
    steps = np.vstack([a + np.linspace(0.0, 1.0, 60)[:, None] * (b - a)
                       for a, b in zip(route, route[1:], strict=False)])
    assert len(wall_contacts(office, steps[:, :2])) == 0
    assert len(wall_contacts(office, start[:2] + np.linspace(0.0, 1.0, 2000)[:, None] * [0.0, 20.0])) >= 1


def test_the_vehicles_imu_measures_its_acceleration_and_gravity_is_recovered() -> None:
    """The simulated vehicle's accelerometer reports gravity's reaction plus its acceleration (as a real one
    does); perception.gravity, given the odometry, takes the acceleration back out of it."""
    from macroloc.perception.gravity import GravityEstimator

    drone = KinematicDrone(level_pose(np.zeros(3), 0.0))
    estimator = GravityEstimator()
    dt_s, leans, errors = 1.0 / 30.0, [], []
    for k in range(150):  # speed up along x, turn while cruising, brake
        command = (np.array([1.0, 0.0, 0.0]), 0.0) if k < 60 else (np.array([1.0, 0.0, 0.0]), 1.0) if k < 110 \
            else (np.zeros(3), 0.0)
        drone.step(dt_s, *command)
        f_body = drone.specific_force_body()
        assert np.allclose(drone.T_cad_body[:3, :3] @ f_body, drone.accel_cad + [0.0, 0.0, 9.81])
        up = estimator.update(int(k * dt_s * 1e9), drone.T_cad_body, f_body[None, :])
        if k >= 30:
            leans.append(np.degrees(np.arccos(f_body[2] / np.linalg.norm(f_body))))
            errors.append(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))  # the drone flies level: up = z
    assert max(leans) > 5.0  # 1-1.5 m/s^2 lean the specific force by 6-9 degrees
    assert np.median(errors) < 0.5 and max(errors) < 0.3 * max(leans)


class StampCamera:
    """A sensor giving a small stereo frame and its ground truth (the true pose) at each measurement."""

    label = "stamp camera"

    def __init__(self) -> None:
        self.stamps_ns: list[int] = []

    def measure(self, stamp_ns: int, T_cad_body: np.ndarray) -> list:
        self.stamps_ns.append(stamp_ns)
        from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
        from macroloc.proto.recording import encode_image, pose_from_matrix

        image = encode_image(np.full((8, 10, 3), stamp_ns % 251, np.uint8))
        frame = pb.StereoFrame(header=pb.Header(stamp_ns=stamp_ns, frame_id="cam_left"), left=image, right=image)
        truth = pb.GroundTruth(header=pb.Header(stamp_ns=stamp_ns), T_cad_body=pose_from_matrix(T_cad_body))
        return [("stereo", frame), ("ground_truth", truth)]

    def close(self) -> None:
        pass


def test_a_recorded_flight_holds_what_the_vehicle_sent_and_replays_frame_by_frame(tmp_path) -> None:  # noqa: ANN001
    """`recorder`: every IMU and odometry sample the vehicle publishes, and its camera's frames with their ground
    truth; read back, each frame carries the odometry of its own stamp (the pose the service placed it at)."""
    from macroloc.proto.recording import FlightWriter, matrix_from_pose, read_flight

    T0 = level_pose(np.array([2.0, 1.0, 1.4]), 0.4)
    odometry = DriftingOdometry(level_pose(np.array([5.0, -3.0, 0.0]), 1.1), T0, seed=3)
    published, camera = {}, StampCamera()
    with zenoh.open(session_config(loopback())) as session, FlightWriter(tmp_path / "f.mcap") as writer:
        agent = VehicleAgent(session, "record-test", KinematicDrone(T0), odometry, camera,
                             sensor_period_s=0.2, recorder=writer)
        for _ in range(45):  # 1.5 s at 30 Hz, turning on the spot
            agent.tick(1 / 30)
            published[agent.stamp_ns] = (agent._T_odom_body.copy(), agent.drone.T_cad_body.copy())
        agent.close()
    frames = list(read_flight(tmp_path / "f.mcap"))
    assert [f.stamp_ns for f in frames] == camera.stamps_ns and len(frames) == 7  # every 0.2 s, on a 30 Hz tick
    n_ticks = round(camera.stamps_ns[-1] * 30e-9)  # IMU and odometry samples up to the last frame
    assert sum(len(f.imu) for f in frames) == sum(len(f.odometry) for f in frames) == n_ticks
    for f in frames:
        assert f.odometry[-1].header.stamp_ns == f.stamp_ns == f.imu[-1].header.stamp_ns
        T_odom_body, T_cad_body = published[f.stamp_ns]
        assert np.allclose(matrix_from_pose(f.odometry[-1].T_map_body), T_odom_body, atol=1e-9)
        assert f.ground_truth is not None
        assert np.allclose(matrix_from_pose(f.ground_truth.T_cad_body), T_cad_body, atol=1e-9)
