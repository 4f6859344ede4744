"""Collision-free flights through one storey, planned on the model's own free space.

1. `FreeSpace.from_scene`: an occupancy grid of the storey (CAD x, y; `cell_m`): the inside of the building
   (its IfcSpace volumes, else cells with a floor below and a ceiling above) minus every triangle that crosses
   the flight band, eroded by the vehicle radius; the largest connected region is kept.
2. `plan_route`: shortest paths (Dijkstra, preferring clearance) between seeded random goals, shortcut by line
   of sight, smoothed, then timed with speed limited by curvature and acceleration (velocity never jumps).
3. `Trajectory`: poses T_cad_body sampled at `rate_hz` (body: x forward, y left, z up), height 1.0-1.8 m above
   the floor, yaw mostly along the velocity with slow natural glances, roll/pitch as a multirotor tilts to
   accelerate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d, minimum_filter1d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial.transform import Rotation, Slerp

from macroloc.graph.errors import BuildingError
from macroloc.graph.features import MacroFeature
from macroloc.sim.scene import COVERING, DOOR, SLAB, WINDOW, SceneGeometry

log = logging.getLogger(__name__)

GRAVITY_MPS2 = 9.81
HOVER_AT_START_S = 0.5
MAX_YAW_RATE_RADPS = 0.9
MAX_TILT_RAD = 0.25  # roll/pitch saturate smoothly here


@dataclass
class FlightParams:
    """What shapes a flight. Heights are above the storey's elevation, metres; speeds m/s; accelerations m/s^2."""

    duration_s: float = 60.0
    speed_mps: float = 1.0
    min_height_m: float = 1.0
    max_height_m: float = 1.8
    vehicle_radius_m: float = 0.25
    cell_m: float = 0.10
    lateral_accel_mps2: float = 0.8
    accel_mps2: float = 0.5
    yaw_glance_rad: float = 0.3
    rate_hz: float = 200.0


@dataclass
class FreeSpace:
    """Where the vehicle's centre may be: grid[i, j] over cells (x = x0 + (j + .5) cell, y = y0 + (i + .5) cell).

    safe: (H, W) bool; clearance_m: (H, W) distance to the nearest obstacle or outside cell, metres.
    """

    origin_xy: np.ndarray
    cell_m: float
    safe: np.ndarray
    clearance_m: np.ndarray
    floor_z_m: float

    def to_xy(self, ij: np.ndarray) -> np.ndarray:
        """(N, 2) cell indices (row, col) -> (N, 2) CAD x, y of the cell centres, metres."""
        ij = np.asarray(ij, float)
        return self.origin_xy + (ij[:, ::-1] + 0.5) * self.cell_m

    def to_ij(self, xy: np.ndarray) -> np.ndarray:
        return np.floor((np.asarray(xy, float) - self.origin_xy) / self.cell_m).astype(int)[:, ::-1]

    def is_safe(self, xy: np.ndarray) -> np.ndarray:
        ij = self.to_ij(np.atleast_2d(xy))
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.safe.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.safe.shape[1])
        out = np.zeros(len(ij), bool)
        out[inside] = self.safe[ij[inside, 0], ij[inside, 1]]
        return out

    @classmethod
    def from_scene(cls, scene: SceneGeometry, floor_z_m: float, params: FlightParams,
                   ceiling_z_m: float | None = None) -> FreeSpace:
        cell = params.cell_m
        lo, hi = scene.bounds_cad[0, :2] - 1.0, scene.bounds_cad[1, :2] + 1.0
        shape = (int(np.ceil((hi[1] - lo[1]) / cell)), int(np.ceil((hi[0] - lo[0]) / cell)))
        # the band the vehicle's body sweeps; its top stays under door heads (~2 m) so doorways stay open
        band = (floor_z_m + params.min_height_m - 0.3, floor_z_m + params.max_height_m + 0.12)
        tri = scene.triangles_cad
        zmin, zmax = tri[:, :, 2].min(axis=1), tri[:, :, 2].max(axis=1)
        # doors do not block: the simulator opens (draws without its leaf) every door the flight passes through
        crossing = (zmin < band[1]) & (zmax > band[0]) & (scene.tri_class != DOOR)
        obstacle = _rasterise(tri[crossing], lo, cell, shape, fill=True)
        inside = _inside_mask(scene, floor_z_m, ceiling_z_m, lo, cell, shape)
        doors = (scene.tri_class == DOOR) & (zmin < band[1]) & (zmax > band[0])
        inside |= cv2.dilate(_rasterise(tri[doors], lo, cell, shape, fill=True).astype(np.uint8),
                             np.ones((3, 3), np.uint8)).astype(bool)  # door openings lie between spaces
        free = (inside & ~obstacle).astype(np.uint8)
        clearance = cv2.distanceTransform(free, cv2.DIST_L2, 5) * cell
        safe = (clearance >= params.vehicle_radius_m + cell).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(safe, connectivity=8)
        if n <= 1:
            raise BuildingError(f"no free space to fly at {floor_z_m:.2f} m + {params.min_height_m}-"
                                f"{params.max_height_m} m in {scene.source}")
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        return cls(lo, cell, labels == largest, clearance, floor_z_m)


def _rasterise(triangles: np.ndarray, lo: np.ndarray, cell: float, shape: tuple[int, int], fill: bool) -> np.ndarray:
    """Cells touched by the triangles' xy projections (vertical faces become their footprint lines)."""
    img = np.zeros(shape, np.uint8)
    if len(triangles) == 0:
        return img.astype(bool)
    pts = np.round((triangles[:, :, :2] - lo) / cell * 4).astype(np.int32)  # 2 fractional bits
    polys = list(pts)
    if fill:
        cv2.fillPoly(img, polys, 1, lineType=cv2.LINE_8, shift=2)
    cv2.polylines(img, polys, True, 1, lineType=cv2.LINE_8, shift=2)
    return img.astype(bool)


def _inside_mask(scene: SceneGeometry, floor_z: float, ceiling_z: float | None, lo: np.ndarray, cell: float,
                 shape: tuple[int, int]) -> np.ndarray:
    spaces = scene.space_triangles_cad
    in_spaces = np.zeros(shape, bool)
    if len(spaces):  # the bottom faces of the storey's IfcSpace volumes
        zmin, zmax = spaces[:, :, 2].min(axis=1), spaces[:, :, 2].max(axis=1)
        bottoms = spaces[(zmax - zmin < 0.05) & (np.abs(zmin - floor_z) < 0.5)]
        in_spaces = _rasterise(bottoms, lo, cell, shape, fill=True)
    return in_spaces | _covered(scene, floor_z, ceiling_z, lo, cell, shape)


def _covered(scene: SceneGeometry, floor_z: float, ceiling_z: float | None, lo: np.ndarray, cell: float,
             shape: tuple[int, int]) -> np.ndarray:
    """Cells with a floor below and a ceiling above (models whose spaces are missing or partial)."""
    tri, normals = scene.triangles_cad, scene.normals_cad()
    horizontal = np.isin(scene.tri_class, (SLAB, COVERING)) | (np.abs(normals[:, 2]) > 0.9)
    horizontal &= ~np.isin(scene.tri_class, (DOOR, WINDOW))
    zc = tri[:, :, 2].mean(axis=1)
    top = ceiling_z if ceiling_z is not None else floor_z + 8.0
    floor = _rasterise(tri[horizontal & (np.abs(zc - floor_z) < 0.6)], lo, cell, shape, fill=True)
    roof = _rasterise(tri[horizontal & (zc > floor_z + 2.2) & (zc < top + 0.6)], lo, cell, shape, fill=True)
    hull = _hull_mask(tri[:, :, :2].reshape(-1, 2), lo, cell, shape)
    if floor.sum() < 0.3 * hull.sum():  # walls only (a mesh of one floor plan): inside their convex hull
        return hull
    if (floor & roof).sum() < 0.5 * floor.sum():  # a model without ceilings (meshes): the floor's footprint
        return floor
    return floor & roof


def _hull_mask(points_xy: np.ndarray, lo: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    img = np.zeros(shape, np.uint8)
    if len(points_xy) >= 3:
        pts = np.round((points_xy - lo) / cell).astype(np.int32)
        cv2.fillConvexPoly(img, cv2.convexHull(pts), 1)
    return img.astype(bool)


# --- routes ------------------------------------------------------------------------------------------------


def plan_route(space: FreeSpace, length_m: float, rng: np.random.Generator) -> np.ndarray:
    """(N, 2) CAD x, y of a collision-free polyline at least `length_m` long (when the space allows), metres."""
    graph, cells = _grid_graph(space)
    index = -np.ones(space.safe.shape, int)
    index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    clear = space.clearance_m[cells[:, 0], cells[:, 1]]
    start = int(rng.choice(np.flatnonzero(clear >= np.quantile(clear, 0.5))))
    route = [space.to_xy(cells[[start]])]
    total = 0.0
    for _ in range(64):
        dist, pred = dijkstra(graph, indices=start, return_predecessors=True)
        finite = np.isfinite(dist)
        reachable = finite & (dist > min(3.0, 0.5 * float(dist[finite].max())))  # small spaces: shorter hops
        if not reachable.any():
            break
        weight = np.where(reachable, np.sqrt(np.maximum(dist, 0)) * clear, 0.0)
        goal = int(rng.choice(len(cells), p=weight / weight.sum()))
        path = [goal]
        while path[-1] != start:
            path.append(int(pred[path[-1]]))
        xy = space.to_xy(cells[path[::-1]])
        route.append(xy[1:])
        total += float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
        start = goal
        if total >= length_m:
            break
    return np.concatenate(route)


def _grid_graph(space: FreeSpace):  # noqa: ANN202 - (csr_matrix, (N, 2) cells)

    cells = np.argwhere(space.safe)
    index = -np.ones(space.safe.shape, int)
    index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    rows, cols, costs = [], [], []
    clear = space.clearance_m
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = cells
        b = a + (di, dj)
        ok = (b[:, 0] < space.safe.shape[0]) & (b[:, 1] >= 0) & (b[:, 1] < space.safe.shape[1])
        a, b = a[ok], b[ok]
        ok = space.safe[b[:, 0], b[:, 1]]
        a, b = a[ok], b[ok]
        step = space.cell_m * np.hypot(di, dj)
        penalty = 1.0 + 0.5 / np.maximum(np.minimum(clear[a[:, 0], a[:, 1]], clear[b[:, 0], b[:, 1]]), 0.1)
        rows.append(index[a[:, 0], a[:, 1]])
        cols.append(index[b[:, 0], b[:, 1]])
        costs.append(step * penalty)
    r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(costs)
    n = len(cells)
    return coo_matrix((np.r_[w, w], (np.r_[r, c], np.r_[c, r])), shape=(n, n)).tocsr(), cells


def smooth_route(space: FreeSpace, route_xy: np.ndarray, step_m: float = 0.05) -> np.ndarray:
    """(M, 2) the route resampled every `step_m` and smoothed as much as stays collision-free."""
    pts = _resample(route_xy, step_m)
    best = pts
    for sigma_m in (1.2, 0.8, 0.5, 0.3, 0.15):
        sm = gaussian_filter1d(pts, sigma_m / step_m, axis=0, mode="nearest")
        if space.is_safe(sm).all():
            best = sm
            break
    return _resample(best, step_m)


def _resample(xy: np.ndarray, step_m: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.r_[True, seg > 1e-9]
    xy = xy[keep]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    if s[-1] <= 0:
        return xy[:1]
    q = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step_m)) + 1))
    return np.stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])], axis=1)


# --- timing and attitude ------------------------------------------------------------------------------------


@dataclass
class Trajectory:
    """Poses sampled uniformly in time. stamps_s: (N,); positions_cad: (N, 3) metres; R_cad_body: (N, 3, 3)."""

    stamps_s: np.ndarray
    positions_cad: np.ndarray
    R_cad_body: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.stamps_s[-1] - self.stamps_s[0])

    def T_cad_body(self, t_s: float) -> np.ndarray:
        """4x4 pose at time t (linear position, slerp rotation between samples)."""
        t = float(np.clip(t_s, self.stamps_s[0], self.stamps_s[-1]))
        k = int(np.clip(np.searchsorted(self.stamps_s, t) - 1, 0, len(self.stamps_s) - 2))
        t0, t1 = self.stamps_s[k], self.stamps_s[k + 1]
        a = (t - t0) / (t1 - t0)
        T = np.eye(4)
        T[:3, 3] = (1 - a) * self.positions_cad[k] + a * self.positions_cad[k + 1]
        T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(self.R_cad_body[k:k + 2]))([a]).as_matrix()[0]
        return T


def time_route(path_xy: np.ndarray, params: FlightParams, rng: np.random.Generator, floor_z_m: float) -> Trajectory:
    """Trajectory along the smoothed path: curvature- and acceleration-limited speed from rest, heights and yaw."""
    step = float(np.linalg.norm(path_xy[1] - path_xy[0])) if len(path_xy) > 1 else 0.05
    s = np.arange(len(path_xy)) * step
    v = _speed_profile(path_xy, step, params)
    dt_seg = 2 * step / np.maximum(v[1:] + v[:-1], 1e-3)
    t_of_s = HOVER_AT_START_S + np.r_[0.0, np.cumsum(dt_seg)]  # hover a moment: the flight starts at rest
    duration = min(params.duration_s, float(t_of_s[-1]))
    dt = 1.0 / params.rate_hz
    pad = int(params.rate_hz)  # one second either side, so the smoothing sees the motion go on (or rest before)
    stamps_ext = np.arange(-pad, int(round(duration * params.rate_hz)) + 1 + pad) * dt
    s_t = gaussian_filter1d(np.interp(stamps_ext, t_of_s, s), 0.1 * params.rate_hz, mode="nearest")  # smooth accel
    xy = np.stack([np.interp(s_t, s, path_xy[:, 0]), np.interp(s_t, s, path_xy[:, 1])], axis=1)
    xy = gaussian_filter1d(xy, 0.1 * params.rate_hz, axis=0, mode="nearest")  # velocity continuous at corners
    z = floor_z_m + _height_profile(np.maximum(stamps_ext, 0.0), params, rng)
    pos_ext = np.column_stack([xy, z])
    vel = np.gradient(pos_ext, dt, axis=0)
    acc = gaussian_filter1d(np.gradient(vel, dt, axis=0), 0.05 * params.rate_hz, axis=0, mode="nearest")
    inner = slice(pad, len(stamps_ext) - pad)
    stamps, pos, vel, acc = stamps_ext[inner] - stamps_ext[pad], pos_ext[inner], vel[inner], acc[inner]
    yaw = _yaw_profile(stamps, vel, path_xy, params, rng)
    # a multirotor tilts its thrust toward its horizontal acceleration (in the yaw frame)
    c, sn = np.cos(yaw), np.sin(yaw)
    a_fwd = c * acc[:, 0] + sn * acc[:, 1]
    a_left = -sn * acc[:, 0] + c * acc[:, 1]
    pitch = MAX_TILT_RAD * np.tanh(np.arctan2(a_fwd, GRAVITY_MPS2) / MAX_TILT_RAD)  # + about y: nose down
    roll = -MAX_TILT_RAD * np.tanh(np.arctan2(a_left, GRAVITY_MPS2) / MAX_TILT_RAD)  # - about x: lean left
    R = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()  # Rz(yaw) Ry(pitch) Rx(roll)
    return Trajectory(stamps, pos, R)


def _speed_profile(path_xy: np.ndarray, step: float, params: FlightParams) -> np.ndarray:
    n = len(path_xy)
    if n < 3:
        return np.full(n, 1e-3)
    seg = np.diff(path_xy, axis=0)
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    turn = np.abs(np.angle(np.exp(1j * np.diff(heading))))  # rad between successive segments (pi: a U-turn)
    kappa = np.r_[0.0, turn / step, 0.0]  # curvature, 1/m (a cross-product formula misses reversals)

    kappa = gaussian_filter1d(maximum_filter1d(kappa, max(3, int(0.6 / step))), 3)  # keep the peaks of turns
    v = np.minimum(params.speed_mps, np.sqrt(params.lateral_accel_mps2 / np.maximum(kappa, 1e-6)))
    v[0] = v[-1] = 0.0
    for i in range(1, n):  # forward pass: accelerate at most accel_mps2
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * params.accel_mps2 * step))
    for i in range(n - 2, -1, -1):  # backward pass: brake at most accel_mps2
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * params.accel_mps2 * step))
    return np.maximum(v, 0.02)


def _height_profile(t: np.ndarray, params: FlightParams, rng: np.random.Generator) -> np.ndarray:
    mid = 0.5 * (params.min_height_m + params.max_height_m)
    amp = 0.5 * (params.max_height_m - params.min_height_m)
    p1, p2 = rng.uniform(12, 25), rng.uniform(4, 8)
    f1, f2 = rng.uniform(0, 2 * np.pi, 2)
    wave = 1.1 * np.sin(2 * np.pi * t / p1 + f1) + 0.35 * np.sin(2 * np.pi * t / p2 + f2)
    ramp = _smoothstep(t / 3.0)  # take off at the middle height, level: no vertical speed at t = 0
    return mid + amp * np.tanh(ramp * wave)  # tanh: a smooth saturation, never a kink (velocity jump)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)  # C2: zero first and second derivative at 0 and 1


def _yaw_profile(t: np.ndarray, vel: np.ndarray, path_xy: np.ndarray, params: FlightParams,
                 rng: np.random.Generator) -> np.ndarray:
    speed = np.linalg.norm(vel[:, :2], axis=1)
    k0 = min(len(path_xy) - 1, 10)
    d0 = path_xy[k0] - path_xy[0]
    heading = np.empty(len(t))
    last = float(np.arctan2(d0[1], d0[0]))
    for i in range(len(t)):  # hold the last heading while (nearly) hovering
        if speed[i] > 0.15:
            last = float(np.arctan2(vel[i, 1], vel[i, 0]))
        heading[i] = last
    heading = np.unwrap(heading)
    rate = params.rate_hz
    max_step = MAX_YAW_RATE_RADPS / rate
    for i in range(1, len(heading)):  # turn no faster than a pilot would (U-turns take a few seconds)
        heading[i] = heading[i - 1] + np.clip(heading[i] - heading[i - 1], -max_step, max_step)
    heading = gaussian_filter1d(heading, 0.3 * rate, mode="nearest")
    p1, p2 = rng.uniform(6, 12), rng.uniform(2.5, 4.5)
    f1, f2 = rng.uniform(0, 2 * np.pi, 2)
    glance = params.yaw_glance_rad * (0.8 * np.sin(2 * np.pi * t / p1 + f1) + 0.2 * np.sin(2 * np.pi * t / p2 + f2))
    return heading + glance


def doors_crossed(traj: Trajectory, features: list[MacroFeature]) -> set[int]:
    """Indices of the vertical door features whose opening (bottom edge, in x, y) the flight's path crosses."""
    xy = traj.positions_cad[:, :2]
    a, b = xy[:-1], xy[1:]
    out = set()
    for k, f in enumerate(features):
        if f.type != "door" or f.orientation != "vertical":
            continue
        c, d = f.corners_cad[0, :2], f.corners_cad[1, :2]
        if _segments_cross(a, b, c, d).any():
            out.add(k)
    return out


def _segments_cross(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(N,) whether segments a[i]-b[i] cross the segment c-d (2D, proper intersections)."""
    def orient(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    o1, o2 = orient(a, b, c), orient(a, b, d)
    o3, o4 = orient(c, d, a), orient(c, d, b)
    return (o1 * o2 < 0) & (o3 * o4 < 0)


def duck_under_doors(traj: Trajectory, features: list[MacroFeature], floor_z_m: float,
                     params: FlightParams, clearance_m: float = 0.35, reach_m: float = 1.2) -> Trajectory:
    """The trajectory with its height lowered smoothly near every door it passes through, to stay
    `clearance_m` under the door head (never under `params.min_height_m`)."""
    crossed = doors_crossed(traj, features)
    if not crossed:
        return traj
    limit = np.full(len(traj.stamps_s), np.inf)
    for k in crossed:
        f = features[k]
        near = np.linalg.norm(traj.positions_cad[:, :2] - f.centroid_cad[:2], axis=1) < reach_m
        limit[near] = np.minimum(limit[near], float(f.corners_cad[:, 2].max()) - clearance_m)
    softness = 0.03  # m: soft minimum, so the descent has no kink (no velocity jump)
    floor_limit = floor_z_m + params.min_height_m + softness
    limit = np.maximum(np.minimum(limit, traj.positions_cad[:, 2]), floor_limit)
    window = int(params.rate_hz)  # widen, then smooth: the descent starts about a second early

    smooth_limit = gaussian_filter1d(minimum_filter1d(limit, window), window / 4)
    z = traj.positions_cad[:, 2]
    z = -softness * np.logaddexp(-z / softness, -smooth_limit / softness)  # soft min(z, limit)
    pos = traj.positions_cad.copy()
    pos[:, 2] = np.maximum(z, floor_z_m + params.min_height_m)
    return Trajectory(traj.stamps_s, pos, traj.R_cad_body)


def plan_flight(scene: SceneGeometry, floor_z_m: float, params: FlightParams, seed: int,
                ceiling_z_m: float | None = None,
                features: list[MacroFeature] | None = None) -> tuple[Trajectory, FreeSpace]:
    """A seeded flight of `params.duration_s` (shorter when the route cannot be longer) on the storey at
    `floor_z_m`, with the free space it was planned in."""
    rng = np.random.default_rng(seed)
    space = FreeSpace.from_scene(scene, floor_z_m, params, ceiling_z_m)
    route = plan_route(space, length_m=params.speed_mps * params.duration_s * 1.3 + 5.0, rng=rng)
    path = smooth_route(space, route)
    traj = time_route(path, params, rng, floor_z_m)
    if features is not None:
        traj = duck_under_doors(traj, features, floor_z_m, params)
    log.info("flight: %.1f s, %.1f m of path, %d safe cells", traj.duration_s,
             float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()), int(space.safe.sum()))
    return traj, space
