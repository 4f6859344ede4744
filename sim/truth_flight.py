"""Ground-truth-only flights: a smooth trajectory through a storey's free space with every door and window
in view, recorded in the flight MCAP format (no images), for `macroloc replay --observations truth`.

A stand-in until the simulator's rendered flights exist, and a fast fixture for tests. The building's walls
(and columns, curtain walls) are cut by horizontal planes: the cut at flight height decides what the camera
can see (a 2D line of sight to each corner; walls are vertical), the cut at 0.5 m where the drone may fly
(window openings closed there). Waypoints are points in front of doors (both sides) and inside windows; the
drone flies a random walk over the clear straight edges between them, smoothed, at a steady speed, looking
along its path with a gentle look-around.

Frames: cad (model, z up), body (x forward, y left, z up), cam (optical, x right, y down, z forward).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import ifcopenshell.geom
import numpy as np
import trimesh

from macroloc.graph.bim import cache_dir, cache_key, load_building
from macroloc.graph.bim_ifc import geometry_settings, open_ifc
from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightMetadata, FlightWriter, pose_from_matrix, vector3
from macroloc.sim.render import CameraModel  # the simulator's camera: one camera model for rendered and truth flights

log = logging.getLogger(__name__)

R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # cam x = -body y, y = -z, z = x
T_BODY_CAM = np.eye(4)
T_BODY_CAM[:3, :3] = R_BODY_CAM
T_BODY_CAM[:3, 3] = (0.10, 0.0, 0.0)  # camera 10 cm ahead of the body centre
FLIGHT_HEIGHT_M = 1.4  # above the storey's floor
MAX_RANGE_M = 8.0  # features further than this are not reported in view
WALL_TYPES = ("IfcWall", "IfcColumn", "IfcCurtainWall", "IfcPlate", "IfcMember")


RATE_HZ = 30.0  # ground-truth frames per second


@dataclass
class FloorPlan:
    """Wall segments (N, 2, 2) in CAD xy, metres, at eye height (sight) and at 0.5 m (flight)."""

    floor_z: float
    sight: np.ndarray
    flight: np.ndarray


# --- the building's walls as 2D segments ---------------------------------------------------------------------


def wall_mesh(path: Path):  # noqa: ANN201 - trimesh.Trimesh
    """Walls, columns and curtain walls of an IFC file as one trimesh (CAD frame, metres)."""
    ifc = open_ifc(path)
    elements = [e for t in WALL_TYPES for e in ifc.by_type(t)]
    verts, faces, n = [], [], 0
    iterator = ifcopenshell.geom.iterator(geometry_settings(), ifc, 2, include=elements)
    if elements and iterator.initialize():
        while True:
            shape = iterator.get()
            v = np.asarray(shape.geometry.verts, float).reshape(-1, 3)
            faces.append(np.asarray(shape.geometry.faces, int).reshape(-1, 3) + n)
            verts.append(v)
            n += len(v)
            if not iterator.next():
                break
    return trimesh.Trimesh(np.vstack(verts), np.vstack(faces), process=False)


def floor_plan(path: Path, model: BuildingModel, storey: str) -> FloorPlan:
    """The storey's wall cuts, cached beside the feature cache (by file hash and storey)."""
    # cache_key hashes the storey name with SHA-256: Python's hash() of a str changes from process to process
    cached = cache_dir() / f"floorplan-{cache_key(model.sha256, {'storey': storey})}.npz"
    floor_z = storey_floor_z(model, storey)
    if cached.exists():
        data = np.load(cached)
        return FloorPlan(float(data["floor_z"]), data["sight"], data["flight"])
    mesh = wall_mesh(path)
    cuts = [trimesh.intersections.mesh_plane(mesh, [0, 0, 1], [0, 0, floor_z + h])[:, :, :2]
            for h in (FLIGHT_HEIGHT_M, 0.5)]
    np.savez(cached, floor_z=floor_z, sight=cuts[0], flight=cuts[1])
    return FloorPlan(floor_z, cuts[0], cuts[1])


def storey_floor_z(model: BuildingModel, storey: str) -> float:
    """The floor under the storey's doors (their lowest corners), else its elevation."""
    doors = [f for f in model.features if f.storey == storey and f.type == "door" and f.orientation == "vertical"]
    if doors:
        return float(np.median([f.corners_cad[:, 2].min() for f in doors]))
    return float(model.storey_elevations_m.get(storey, 0.0))


def segments_blocked(a: np.ndarray, b: np.ndarray, walls: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N,) bool: does the 2D segment a[k] -> b[k] cross any wall segment? a, b (N, 2); walls (W, 2, 2).

    `margin` shortens the segment at its far end (a corner lying on its own wall is still visible)."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    d = b - a
    length = np.linalg.norm(d, axis=1, keepdims=True)
    b = a + d * np.clip(1 - margin / np.maximum(length, 1e-9), 0, 1)
    p, q = walls[:, 0], walls[:, 1]

    def orient(u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
        return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (w[..., 0] - u[..., 0])

    A, B = a[:, None], b[:, None]
    o1, o2 = orient(A, B, p[None]), orient(A, B, q[None])
    o3, o4 = orient(p[None], q[None], A), orient(p[None], q[None], B)
    return np.any((o1 * o2 < 0) & (o3 * o4 < 0), axis=1)


# --- the trajectory ------------------------------------------------------------------------------------------


def waypoints(model: BuildingModel, plan: FloorPlan, storey: str) -> np.ndarray:
    """(N, 2) candidate points: 0.9 m either side of each door, 1.2 m inside each window; indoors only."""
    pts = []
    for f in model.features:
        if f.storey != storey or f.orientation != "vertical":
            continue
        n = f.normal_cad[:2]
        offsets = (0.9, -0.9) if f.type == "door" else (-1.2,)
        pts += [f.centroid_cad[:2] + s * n for s in offsets]
    pts_arr = np.array(pts).reshape(-1, 2)
    return pts_arr[[_indoors(p, plan.flight) and _clearance(p, plan.flight) > 0.35 for p in pts_arr]]


def _indoors(p: np.ndarray, walls: np.ndarray) -> bool:
    dirs = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
    free = ~segments_blocked(np.repeat(p[None], 8, 0), p + 40.0 * dirs, walls)
    return int(free.sum()) <= 1


def _clearance(p: np.ndarray, walls: np.ndarray) -> float:
    a, b = walls[:, 0], walls[:, 1]
    t = np.clip(np.einsum("ij,ij->i", p - a, b - a) / np.maximum(np.einsum("ij,ij->i", b - a, b - a), 1e-12), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * (b - a) - p, axis=1))) if len(walls) else np.inf


def random_walk(points: np.ndarray, walls: np.ndarray, length_m: float, rng: np.random.Generator,
                start_score: np.ndarray | None = None) -> np.ndarray:
    """A polyline (M, 2) over clear edges (< 10 m, 0.25 m either side free) of at least `length_m`; it starts
    at a random point, or at one of the three best by `start_score` (N,) when given."""
    n = len(points)
    ii, jj = np.triu_indices(n, 1)
    dist = np.linalg.norm(points[ii] - points[jj], axis=1)
    keep = (dist < 10.0) & (dist > 0.5)
    ii, jj = ii[keep], jj[keep]
    d = points[jj] - points[ii]
    side = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True) * 0.25
    clear = ~(segments_blocked(points[ii], points[jj], walls) | segments_blocked(points[ii] + side, points[jj] + side,
                                                                                walls)
              | segments_blocked(points[ii] - side, points[jj] - side, walls))
    adj: dict[int, list[int]] = {k: [] for k in range(n)}
    for a, b in zip(ii[clear], jj[clear], strict=True):
        adj[int(a)].append(int(b))
        adj[int(b)].append(int(a))
    starts = [k for k in _largest_component(adj) if len(adj[k]) >= 2]
    if not starts:
        raise ValueError("no clear path between waypoints on this storey")
    if start_score is not None:
        starts = sorted(starts, key=lambda k: -start_score[k])[:3]
    path = [int(rng.choice(starts))]
    travelled, visits = 0.0, np.zeros(n)
    while travelled < length_m:
        here = path[-1]
        nbrs = [k for k in adj[here] if len(path) < 2 or k != path[-2]] or adj[here]
        weights = np.exp(-visits[nbrs])
        nxt = int(rng.choice(nbrs, p=weights / weights.sum()))
        visits[nxt] += 1
        travelled += float(np.linalg.norm(points[nxt] - points[here]))
        path.append(nxt)
    return points[path]


def _largest_component(adj: dict[int, list[int]]) -> list[int]:
    seen: set[int] = set()
    best: list[int] = []
    for start in adj:
        if start in seen:
            continue
        comp, stack = [], [start]
        seen.add(start)
        while stack:
            k = stack.pop()
            comp.append(k)
            for m in adj[k]:
                if m not in seen:
                    seen.add(m)
                    stack.append(m)
        if len(comp) > len(best):
            best = comp
    return sorted(best)


def smooth_trajectory(polyline: np.ndarray, speed_mps: float, rate_hz: float, duration_s: float,
                      start_s: float = 0.0) -> np.ndarray:
    """(N, 2) positions at `rate_hz`: Chaikin-smoothed polyline walked at `speed_mps` from `start_s` on
    (1 s ramp from rest), hovering at its start before."""
    pts = polyline
    for _ in range(4):
        q, r = 0.75 * pts[:-1] + 0.25 * pts[1:], 0.25 * pts[:-1] + 0.75 * pts[1:]
        pts = np.vstack([pts[:1], np.column_stack([q, r]).reshape(-1, 2), pts[-1:]])
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    t = np.maximum(np.arange(int(duration_s * rate_hz)) / rate_hz - start_s, 0.0)
    s = speed_mps * np.where(t < 1.0, 0.5 * t * t, t - 0.5)  # accelerate over the first second
    s = np.minimum(s, arc[-1])
    return np.column_stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])])


def body_poses(xy: np.ndarray, z: float, rate_hz: float, rng: np.random.Generator, spin_s: float = 0.0) -> np.ndarray:
    """(N, 4, 4) T_cad_body: level, yaw along the path (low-passed) plus a slow +-35 deg look-around; during the
    first `spin_s` seconds (hovering) one full smooth turn on the spot, to look around before setting off."""
    t = np.arange(len(xy)) / rate_hz
    v = np.gradient(xy, axis=0)
    heading = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    moving = np.linalg.norm(v, axis=1) > 1e-4
    if moving.any():
        first = int(np.argmax(moving))
        heading[:first] = heading[first]
    kernel = np.ones(int(rate_hz)) / int(rate_hz)
    heading = np.convolve(np.pad(heading, len(kernel) // 2, mode="edge"), kernel, mode="same")[
        len(kernel) // 2: len(kernel) // 2 + len(xy)]
    look = np.radians(35.0) * np.sin(2 * np.pi * 0.1 * np.maximum(t - spin_s, 0.0))
    u = np.clip(t / spin_s, 0.0, 1.0) if spin_s > 0 else np.ones_like(t)
    yaw = heading + look + 2 * np.pi * u * u * (3 - 2 * u)  # smoothstep: the turn starts and ends at rest
    T = np.tile(np.eye(4), (len(xy), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, :2, 3], T[:, 2, 3] = xy, z
    return T


# --- what the camera sees -----------------------------------------------------------------------------------


def features_in_view(features: list[MacroFeature], T_cad_cam: np.ndarray, camera: CameraModel,
                     walls: np.ndarray) -> list[tuple[MacroFeature, np.ndarray, np.ndarray]]:
    """(feature, corners_cam (4, 3), corner_visible (4,)) for each feature with a corner in the image,
    in front of the camera, within MAX_RANGE_M, facing it, and not hidden behind a wall (2D line of sight)."""
    T_cam_cad = np.linalg.inv(T_cad_cam)
    out = []
    eye = T_cad_cam[:2, 3]
    for f in features:
        to_f = f.centroid_cad - T_cad_cam[:3, 3]
        dist = float(np.linalg.norm(to_f))
        if dist > MAX_RANGE_M or abs(float(np.dot(to_f, f.normal_cad))) < 0.17 * dist:  # > 80 deg oblique
            continue
        corners_cam = (T_cam_cad[:3, :3] @ f.corners_cad.T).T + T_cam_cad[:3, 3]
        z = corners_cam[:, 2]
        u = camera.fx * corners_cam[:, 0] / np.maximum(z, 1e-6) + camera.cx
        v = camera.fy * corners_cam[:, 1] / np.maximum(z, 1e-6) + camera.cy
        inside = (z > 0.3) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        if not inside.any():
            continue
        # the opening's corners sit mid-wall: the last 0.4 m of the line of sight may cross its own reveal
        shrunk = f.centroid_cad[:2] + 0.8 * (f.corners_cad[:, :2] - f.centroid_cad[:2])
        seen = inside & ~segments_blocked(np.repeat(eye[None], 4, 0), shrunk, walls, margin=0.4)
        if seen.any():
            out.append((f, corners_cam, seen))
    return out


def _features_in_sight(p: np.ndarray, feats: list[MacroFeature], walls: np.ndarray) -> int:
    """How many features lie within MAX_RANGE_M of the 2D point p with a clear line of sight."""
    near = [f.centroid_cad[:2] for f in feats if np.linalg.norm(f.centroid_cad[:2] - p) < MAX_RANGE_M]
    if not near:
        return 0
    return int((~segments_blocked(np.repeat(p[None], len(near), 0), np.array(near), walls, margin=0.2)).sum())


# --- the recording --------------------------------------------------------------------------------------------


def default_storey(model: BuildingModel) -> str:
    """The storey with the most vertical doors and windows."""
    counts = {s: sum(f.orientation == "vertical" for f in fs) for s, fs in model.by_storey().items() if s}
    return max(counts, key=lambda s: counts[s])


def write_truth_flight(building: Path, out: Path, seed: int = 0, duration_s: float = 60.0,
                       storey: str | None = None, speed_mps: float = 1.0, camera: CameraModel | None = None,
                       rate_hz: float = RATE_HZ, spin_s: float = 4.0, start: str = "open") -> Path:
    """Plan a flight through `storey` of `building` (IFC) and record its ground truth as MCAP at `out`: it
    hovers and turns once on the spot for `spin_s` seconds, then flies at `speed_mps`. `start`: "random" (any
    waypoint) or "open" (one of the three waypoints with the most features in line of sight: taking off in a
    corridor or hall rather than in a closet)."""
    camera = camera or CameraModel()
    model = load_building(building)
    storey = storey or default_storey(model)
    plan = floor_plan(Path(building), model, storey)
    rng = np.random.default_rng(seed)
    feats = [f for f in model.features if f.storey == storey and f.orientation == "vertical"]
    points = waypoints(model, plan, storey)
    score = np.array([_features_in_sight(p, feats, plan.sight) for p in points]) if start == "open" else None
    polyline = random_walk(points, plan.flight, speed_mps * duration_s + 5.0, rng, score)
    xy = smooth_trajectory(polyline, speed_mps, rate_hz, duration_s, start_s=spin_s)
    T_cad_body = body_poses(xy, plan.floor_z + FLIGHT_HEIGHT_M, rate_hz, rng, spin_s)
    info = pb.CameraInfo(width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy, cx=camera.cx,
                         cy=camera.cy, baseline_m=camera.baseline_m, T_body_cam=pose_from_matrix(T_BODY_CAM))
    dt = 1.0 / rate_hz
    velocity = np.gradient(T_cad_body[:, :3, 3], dt, axis=0)
    accel = np.gradient(velocity, dt, axis=0)
    yaw = np.unwrap(np.arctan2(T_cad_body[:, 1, 0], T_cad_body[:, 0, 0]))
    yaw_rate = np.gradient(yaw, dt)
    meta = FlightMetadata(building=Path(building).name, building_sha256=model.sha256, seed=seed, storey=storey,
                          duration_s=duration_s, extra={"kind": "truth-only"})
    with FlightWriter(out, meta) as writer:
        for k, T in enumerate(T_cad_body):
            stamp_ns = int(round(k * dt * 1e9))
            header = pb.Header(stamp_ns=stamp_ns, frame_id="cam_left", seq=k)
            writer.write_stereo(pb.StereoFrame(header=header, camera_id="front", info=info))
            specific_force = T[:3, :3].T @ (accel[k] + np.array([0.0, 0.0, 9.81]))  # body frame, includes -g
            writer.write_imu(pb.Imu(header=pb.Header(stamp_ns=stamp_ns, frame_id="body", seq=k),
                                    accel_mps2=vector3(specific_force),
                                    gyro_radps=vector3(np.array([0.0, 0.0, yaw_rate[k]]))))
            truth = pb.GroundTruth(header=pb.Header(stamp_ns=stamp_ns, frame_id="cad", seq=k),
                                   T_cad_body=pose_from_matrix(T), T_body_cam=pose_from_matrix(T_BODY_CAM))
            for f, corners_cam, seen in features_in_view(feats, T @ T_BODY_CAM, camera, plan.sight):
                truth.features_cam.append(pb.ObservedFeature(type=f.type, id=f.id, score=1.0,
                                                             corners=[vector3(c) for c in corners_cam]))
                truth.corner_visible.extend(bool(s) for s in seen)
            writer.write_ground_truth(truth)
    log.info("wrote %s: %d frames on %s", out, len(T_cad_body), storey)
    return out
