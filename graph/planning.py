"""Path planning to a goal in the building model (paper §3.3): occupancy grid, A*, waypoints in the CAD frame.

`Planner.plan(start_cad, goal)` picks the storey under the start, cuts the model at flight height
(`planning_grid`), adds the obstacles seen in depth, blocks the cells outside the building (unless the start is
outside), inflates by the vehicle's radius, runs A* on the 8-connected grid and returns waypoints at cell
centres, simplified where the line of sight is free, ending exactly at the goal. Goals are CAD coordinates, a
door/window GlobalId, or an IfcSpace's name.
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from macroloc.graph.building_assets import BuildingSolids, Space
from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel
from macroloc.graph.planning_grid import ObstacleLayer, OccupancyGrid, inflate, outside_cells, section_grid

log = logging.getLogger(__name__)

SQRT2 = math.sqrt(2.0)
NEIGHBOURS_8 = ((-1, -1, SQRT2), (-1, 0, 1.0), (-1, 1, SQRT2), (0, -1, 1.0), (0, 1, 1.0),
                (1, -1, SQRT2), (1, 0, 1.0), (1, 1, SQRT2))


class PlanningError(UserInputError):
    """No plan: unknown goal, or no free path between start and goal."""


@dataclass(frozen=True)
class Plan:
    """Waypoints (N, 3) in the CAD frame, metres, from the start to the goal; their polyline length, m; a heading
    per waypoint (N,), radians about the CAD frame's +z from +x (`waypoint_yaws`)."""

    points_cad: np.ndarray
    length_m: float
    description: str
    yaw_rad: np.ndarray = field(default_factory=lambda: np.zeros(0))


def waypoint_yaws(points_cad: np.ndarray, facing_cad: np.ndarray | None = None) -> np.ndarray:
    """A heading per waypoint (radians about +z from +x, CAD frame): the direction of travel of the leg that leaves
    it; at the last one, `facing_cad` (a horizontal direction, e.g. into the goal's door) when given, else the last
    leg's direction. Legs shorter than 1 mm keep the heading before them (0 for a plan that never moves)."""
    points = np.asarray(points_cad, float).reshape(-1, 3)
    yaws = np.zeros(len(points))
    heading = 0.0
    legs = np.diff(points[:, :2], axis=0)
    first = next((leg for leg in legs if np.hypot(*leg) > 1e-3), None)
    if first is not None:
        heading = float(np.arctan2(first[1], first[0]))
    for i, leg in enumerate(legs):
        if np.hypot(*leg) > 1e-3:
            heading = float(np.arctan2(leg[1], leg[0]))
        yaws[i] = heading
    if len(points):
        yaws[-1] = heading
        if facing_cad is not None and np.hypot(facing_cad[0], facing_cad[1]) > 1e-9:
            yaws[-1] = float(np.arctan2(facing_cad[1], facing_cad[0]))
    return yaws


def astar(free: np.ndarray, start_rc: tuple[int, int], goal_rc: tuple[int, int]) -> list[tuple[int, int]]:
    """A* on an 8-connected grid (free: (H, W) bool), octile heuristic, no corner cutting; [] if unreachable."""
    h, w = free.shape
    goal_r, goal_c = goal_rc

    def heuristic(r: int, c: int) -> float:  # octile distance: admissible and consistent on this grid
        dr, dc = abs(r - goal_r), abs(c - goal_c)
        return (SQRT2 - 1.0) * min(dr, dc) + max(dr, dc)

    cost = {start_rc: 0.0}
    parent: dict[tuple[int, int], tuple[int, int]] = {}
    heap = [(heuristic(*start_rc), 0.0, start_rc)]
    closed: set[tuple[int, int]] = set()
    while heap:
        _, g, cell = heapq.heappop(heap)
        if cell == goal_rc:
            path = [cell]
            while cell in parent:
                cell = parent[cell]
                path.append(cell)
            return path[::-1]
        if cell in closed:
            continue
        closed.add(cell)
        r, c = cell
        for dr, dc, step in NEIGHBOURS_8:
            nr, nc = r + dr, c + dc
            if not (0 <= nr < h and 0 <= nc < w) or not free[nr, nc]:
                continue
            if dr and dc and not (free[r, nc] and free[nr, c]):
                continue  # no squeezing diagonally between two occupied cells
            ng = g + step
            if ng < cost.get((nr, nc), math.inf):
                cost[(nr, nc)] = ng
                parent[(nr, nc)] = cell
                heapq.heappush(heap, (ng + heuristic(nr, nc), ng, (nr, nc)))
    return []


def line_of_sight(free: np.ndarray, a_rc: tuple[int, int], b_rc: tuple[int, int]) -> bool:
    """True when every cell the segment between two cell centres touches is free (sampled at 1/4 cell)."""
    a, b = np.asarray(a_rc, float), np.asarray(b_rc, float)
    n = max(2, int(np.ceil(np.abs(b - a).max() * 4)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = a + t * (b - a)
    cells = np.unique(np.concatenate([np.floor(pts + 0.5 + d) for d in (-0.2, 0.2)]).astype(int), axis=0)
    cells = np.clip(cells, 0, np.array(free.shape) - 1)
    return bool(free[cells[:, 0], cells[:, 1]].all())


def simplify(path_rc: list[tuple[int, int]], free: np.ndarray) -> list[tuple[int, int]]:
    """Greedy string pulling: from each kept cell, jump to the farthest later cell still in line of sight."""
    if len(path_rc) <= 2:
        return list(path_rc)
    kept, i = [path_rc[0]], 0
    while i < len(path_rc) - 1:
        j = len(path_rc) - 1
        while j > i + 1 and not line_of_sight(free, path_rc[i], path_rc[j]):
            j -= 1
        kept.append(path_rc[j])
        i = j
    return kept


def nearest_free(free: np.ndarray, cell_rc: tuple[int, int]) -> tuple[int, int] | None:
    """The free cell nearest to cell_rc (itself when free); None when the grid has no free cell."""
    if free[cell_rc]:
        return cell_rc
    rows, cols = np.nonzero(free)
    if not len(rows):
        return None
    k = int(np.argmin((rows - cell_rc[0]) ** 2 + (cols - cell_rc[1]) ** 2))
    return int(rows[k]), int(cols[k])


class GoalResolver:
    """Turns a goal (CAD point, feature GlobalId, or space name) into a CAD point, metres."""

    def __init__(self, model: BuildingModel, spaces: list[Space]) -> None:
        self._features = {f.id: f for f in model.features}
        for f in model.features:
            for dup in f.duplicates:
                self._features.setdefault(dup, f)
        self._spaces = spaces

    def feature(self, feature_id: str) -> np.ndarray:
        if feature_id not in self._features:
            raise PlanningError(f"unknown feature id {feature_id!r}")
        return np.asarray(self._features[feature_id].centroid_cad, float)

    def facing(self, feature_id: str, from_cad: np.ndarray) -> np.ndarray | None:
        """The horizontal direction (unit, CAD frame) that faces the feature's plane from `from_cad`: its normal,
        signed to point from that side towards the feature; None for a feature without a horizontal normal."""
        f = self._features[feature_id]
        n = np.array([f.normal_cad[0], f.normal_cad[1], 0.0], float)
        if np.linalg.norm(n) < 1e-6:
            return None
        n /= np.linalg.norm(n)
        return n if float(n @ (np.asarray(f.centroid_cad, float) - from_cad)) >= 0 else -n

    def space(self, name: str, near_xy_cad: np.ndarray) -> np.ndarray:
        """An IfcSpace by Name, else by LongName (case-insensitive); of several, the one nearest near_xy_cad."""
        key = name.strip().casefold()
        found = [s for s in self._spaces if s.name.casefold() == key] or \
                [s for s in self._spaces if s.long_name.casefold() == key]
        if not found:
            raise PlanningError(f"no space named {name!r} in the building")
        best = min(found, key=lambda s: float(np.hypot(*(np.array(s.centroid_xy_cad) - near_xy_cad[:2]))))
        return np.array([*best.centroid_xy_cad, best.floor_z_cad], float)


class Planner:
    """Plans on the storey under the start; grids are built once per storey and kept with their obstacles."""

    def __init__(self, model: BuildingModel, solids: BuildingSolids, cell_m: float, vehicle_radius_m: float,
                 flight_height_m: float) -> None:
        self.model = model
        self.solids = solids
        self.cell_m = cell_m
        self.vehicle_radius_m = vehicle_radius_m
        self.flight_height_m = flight_height_m
        self.goals = GoalResolver(model, solids.spaces)
        self._grids: dict[float, tuple[OccupancyGrid, ObstacleLayer]] = {}
        self._outside: dict[float, np.ndarray] = {}  # per storey: its grid's cells outside the building
        v = solids.vertices_cad
        self._box_cad = (v.min(axis=0), v.max(axis=0)) if len(v) else None  # the solids' box, CAD frame, m

    @classmethod
    def for_building(cls, path: Path, cell_m: float, vehicle_radius_m: float, flight_height_m: float) -> Planner:
        from macroloc.graph.bim import load_building
        from macroloc.graph.building_assets import load_solids

        return cls(load_building(path), load_solids(Path(path)), cell_m, vehicle_radius_m, flight_height_m)

    def inside(self, xyz_cad: np.ndarray, margin_m: float = 1.0) -> bool:
        """True when the CAD point (3,) is finite and within the model's solids' box grown by margin_m."""
        xyz = np.asarray(xyz_cad, float)
        if not np.isfinite(xyz).all() or self._box_cad is None:
            return bool(np.isfinite(xyz).all())
        lo, hi = self._box_cad
        return bool(((xyz >= lo - margin_m) & (xyz <= hi + margin_m)).all())

    def floor_z(self, z_cad: float) -> float:
        """Elevation (CAD z, m) of the storey the point at height z_cad is in (the highest floor below it)."""
        below = [e for e in self.model.storey_elevations_m.values() if e <= z_cad + 0.3]
        return max(below) if below else min(self.model.storey_elevations_m.values(), default=0.0)

    def grid(self, z_cad: float) -> tuple[OccupancyGrid, ObstacleLayer]:
        """The grid (and its seen-obstacle layer) of the storey at height z_cad, cut at flight height."""
        floor = self.floor_z(z_cad)
        if floor not in self._grids:
            grid = section_grid(self.solids, floor + self.flight_height_m, self.cell_m)
            self._grids[floor] = (grid, ObstacleLayer(grid.shape))
            self._outside[floor] = outside_cells(grid, [f.corners_cad for f in self.model.features])
        return self._grids[floor]

    def outside(self, z_cad: float) -> np.ndarray:
        """(H, W) bool: the cells of the storey's grid (at height z_cad) outside the building (`outside_cells`)."""
        self.grid(z_cad)
        return self._outside[self.floor_z(z_cad)]

    def add_obstacle_points(self, points_cad: np.ndarray, z_cad: float) -> int:
        """Depth points (N, 3) in the CAD frame seen from height z_cad: obstacles the model may lack."""
        grid, layer = self.grid(z_cad)
        return layer.add_points(grid, points_cad)

    def free_cells(self, z_cad: float, outdoors: bool = False) -> tuple[OccupancyGrid, np.ndarray]:
        """The storey's grid and its free cells (the vehicle's radius kept from every obstacle): inside the
        building only, unless `outdoors`."""
        grid, layer = self.grid(z_cad)
        blocked = grid.occupied | layer.occupied() | (False if outdoors else self.outside(z_cad))
        return grid, inflate(blocked, self.vehicle_radius_m, self.cell_m)

    def resolve(self, goal: GoalSpec, start_cad: np.ndarray) -> tuple[np.ndarray, str]:
        """The goal's CAD point and a description of it."""
        if goal.feature_id is not None:
            return self.goals.feature(goal.feature_id), f"feature {goal.feature_id}"
        if goal.space_name is not None:
            return self.goals.space(goal.space_name, start_cad), f"space {goal.space_name}"
        if goal.position_cad is None or not np.isfinite(goal.position_cad).all():
            raise PlanningError("goal has no finite position, feature id or space name")
        return np.asarray(goal.position_cad, float), "position"

    def plan(self, start_cad: np.ndarray, goal: GoalSpec) -> Plan:
        """Waypoints from start_cad (3,) to the goal, at flight height over the start's storey, CAD frame."""
        start_cad = np.asarray(start_cad, float)
        if not self.inside(start_cad):
            raise PlanningError(f"start {np.round(start_cad, 1).tolist()} lies outside the building model")
        target_cad, description = self.resolve(goal, start_cad)
        if not self.inside(target_cad):
            raise PlanningError(f"goal {np.round(target_cad, 1).tolist()} lies outside the building model")
        grid, _ = self.grid(start_cad[2])
        outdoors = bool(self.outside(start_cad[2])[grid.cell_of(start_cad)])  # a start outside: the way in may too
        grid, free = self.free_cells(start_cad[2], outdoors)
        if not grid.contains(target_cad):
            raise PlanningError(f"goal {np.round(target_cad, 1).tolist()} lies outside this storey's plan")
        start_rc = nearest_free(free, grid.cell_of(start_cad))
        goal_rc = nearest_free(free, grid.cell_of(target_cad))
        if start_rc is None or goal_rc is None:
            raise PlanningError("no free cell on this storey")
        cells = astar(free, start_rc, goal_rc)
        if not cells:
            raise PlanningError(f"no free path to {description}")
        points = grid.centre_cad(np.array(simplify(cells, free)))
        if grid.cell_of(target_cad) == goal_rc:  # the goal itself is free: end exactly there
            points[-1, :2] = target_cad[:2]
        points[0, :2] = start_cad[:2] if grid.cell_of(start_cad) == start_rc else points[0, :2]
        length = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
        before_last = points[-2] if len(points) > 1 else start_cad
        facing = self.goals.facing(goal.feature_id, before_last) if goal.feature_id is not None else None
        return Plan(points, length, description, waypoint_yaws(points, facing))


@dataclass(frozen=True)
class GoalSpec:
    """One of: a CAD position (3,) in metres, a feature GlobalId, or an IfcSpace name."""

    position_cad: np.ndarray | None = None
    feature_id: str | None = None
    space_name: str | None = None
