"""The demo's route in any building macroloc can read: the take-off storey, the take-off point and the goal.

What the building offers decides, not figures fitted to one building:

- **Storey.** The storeys are tried in the order of what a vehicle can see there: the most doors and windows
  first, then the most free space at flight height. A storey without doors and windows (nothing to localize
  from) or without free space at flight height (nowhere to fly) is not tried.
- **Take-off point.** 1.2 m in front of a door, in free space (a second pass also tries the inner side of the
  windows). A turn on the spot there (12 headings, ground truth, nothing dropped) must show `wanted_view` doors and
  windows: what the registration answers 'localized' from (graph.localizer.registration_min_landmarks, 4) plus one
  for a detection the camera misses. Where no point of the storey shows that many (a house's rooms hold two or
  three doors and windows, an office corridor ten), the best view the storey offers is the threshold: the vehicle
  then localizes from fewer doors and the walls, or explores.
- **Goal.** A named IfcSpace of the storey where the model has one, else a door or a window, else a free cell,
  always in another room (no free straight line from the take-off point: a goal in view is no flight through the
  building), between a quarter and 60 % of the storey's extent (the diagonal of its free space's box) from the
  take-off point, capped at the demo's 10-25 m where the storey is larger (a longer flight costs wall time and
  shows nothing more). Each goal must be connected to the take-off point by the service's own planner.

The user may name the storey (`storey`) and the goal (`goal`: a space name, a door's or window's GlobalId, or
CAD coordinates "x,y,z" in metres); a named goal is taken at any distance, on its own storey.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.planning import GoalSpec, PlanningError
from macroloc.sim.agent import TruthSensor, ray_free
from macroloc.sim.vehicle import level_pose

if TYPE_CHECKING:  # the service's planner, imported where used: sim/ imports only service's wire and config at its top
    from macroloc.graph.features import BuildingModel, MacroFeature
    from macroloc.graph.planning import GoalSpec, Planner
    from macroloc.graph.planning_grid import OccupancyGrid

FRONT_M = 1.2  # the take-off point's distance in front of a door or window, m
TURN_HEADINGS = 12  # the turn on the spot: headings looked at, evenly spaced
MAX_CANDIDATES = 150  # take-off points tried per pass and storey


@dataclass(frozen=True)
class DemoGoal:
    """Where the demo flies once localized: exactly one of an IfcSpace name, a feature GlobalId or a CAD point."""

    label: str  # what the user reads: "space 121 (Office)", "door 2O2Fr$...", "free cell (3.1, 4.2, 1.4) m"
    space_name: str | None = None
    feature_id: str | None = None
    position_cad: tuple[float, float, float] | None = None  # m, CAD frame

    def spec(self) -> GoalSpec:
        """The goal as the service's planner takes it."""
        pos = None if self.position_cad is None else np.asarray(self.position_cad, float)
        return GoalSpec(position_cad=pos, feature_id=self.feature_id, space_name=self.space_name)

    def message(self, pb: Any) -> Any:  # noqa: ANN401 - the wire module and its pb.Goal
        """The goal as the vehicle sends it (pb.Goal)."""
        if self.space_name is not None:
            return pb.Goal(space_name=self.space_name)
        if self.feature_id is not None:
            return pb.Goal(feature_id=self.feature_id)
        x, y, z = self.position_cad or (np.nan, np.nan, np.nan)
        return pb.Goal(position_cad=pb.Vector3(x=x, y=y, z=z))


@dataclass(frozen=True)
class Route:
    """The take-off (a CAD point at flight height, m) on `storey`, the goal, and what the take-off point shows."""

    storey: str
    start: str  # "in front of door <id>"
    start_xyz: np.ndarray  # (3,) CAD, m
    goal: DemoGoal
    view: int  # doors and windows a turn on the spot shows from the take-off point
    wanted_view: int  # the view asked for on that storey (see the module doc)


@dataclass
class StoreyTried:
    """What one storey offered, for the one line that says why no route was found."""

    name: str
    features: int
    free_m2: float
    best_view: int = 0
    take_offs: int = 0  # take-off points with the view asked for
    goals_tried: int = 0

    def summary(self) -> str:
        return (f"{self.name}: {self.features} doors/windows, {self.free_m2:.0f} m² free, best view "
                f"{self.best_view}, {self.take_offs} take-off points, {self.goals_tried} goals tried")


def wanted_view(registration_min_landmarks: int = 4) -> int:
    """Doors and windows a take-off point's turn should show: the registration's need plus one missed."""
    return registration_min_landmarks + 1


def choose_route(planner: Planner, seed: int, min_goal_distance_m: float = 10.0, max_goal_distance_m: float = 25.0,
                 storey: str | None = None, goal: str | None = None, registration_min_landmarks: int = 4) -> Route:
    """A seeded take-off point and goal (see the module doc), CAD frame; UserInputError with one line saying why
    and the figure behind it where the building offers none."""
    model = planner.model
    user_goal = parse_goal(planner, goal) if goal is not None else None
    if user_goal is not None and storey is None:
        storey = storey_of(planner, goal_z_cad(planner, user_goal))
    storeys = ranked_storeys(planner, model.checked_storey(storey))
    rng = np.random.default_rng(seed)
    tried = []
    for name, floor_z, features, free_m2 in storeys:
        stats = StoreyTried(name, features, free_m2)
        tried.append(stats)
        route = _route_on_storey(planner, name, floor_z, rng, seed, stats, min_goal_distance_m, max_goal_distance_m,
                                 user_goal, wanted_view(registration_min_landmarks))
        if route is not None:
            return route
    raise UserInputError(f"no take-off point with a view and a connected goal in {model.source}: "
                         + "; ".join(s.summary() for s in tried))


def ranked_storeys(planner: Planner, only: str | None = None) -> list[tuple[str, float, int, float]]:
    """(name, floor z m, doors and windows, free m² at flight height) of the storeys a route may take off on,
    the most doors and windows first, then the most free space; UserInputError where none can be flown."""
    model = planner.model
    counts: dict[str, int] = {}
    for f in model.features:
        if f.storey:
            counts[f.storey] = counts.get(f.storey, 0) + 1
    if not counts:
        raise UserInputError(f"cannot fly in {model.source}: no doors or windows on any of its "
                             f"{len(model.storey_elevations_m)} storeys (the vehicle localizes from them)")
    rows = []
    for name, n in counts.items():
        if only is not None and name != only:
            continue
        floor_z = model.storey_elevations_m.get(name, 0.0)
        grid, free = planner.free_cells(floor_z + planner.flight_height_m)
        rows.append((name, floor_z, n, float(free.sum()) * grid.cell_m ** 2))
    flyable = [r for r in rows if r[3] > 0.0]
    if not flyable:
        raise UserInputError(
            f"cannot fly in {model.source}: no free space {planner.flight_height_m:.1f} m above the floor (flight "
            "height, the vehicle's radius kept from the walls) on any storey with doors or windows: "
            + ", ".join(f"{name} 0 m² ({n} doors/windows)" for name, _, n, _ in rows))
    return sorted(flyable, key=lambda r: (-r[2], -r[3], r[1]))


def _route_on_storey(planner: Planner, name: str, floor_z: float, rng: np.random.Generator, seed: int,
                     stats: StoreyTried, min_goal_m: float, max_goal_m: float, user_goal: DemoGoal | None,
                     wanted: int) -> Route | None:
    z = floor_z + planner.flight_height_m
    grid, free = planner.free_cells(z)
    sensor = TruthSensor(planner.model, grid, seed, drop_fraction=0.0)
    lo, hi = goal_distance_range_m(grid, free, min_goal_m, max_goal_m)
    doors = [f for f in planner.model.features if f.type == "door" and f.storey == name]
    windows = [f for f in planner.model.features if f.type == "window" and f.storey == name]
    # pass 1: doors, the view the registration wants; pass 2: doors and windows, the best view pass 1 found
    for kind, candidates in (("door", doors), ("door or window", doors + windows)):
        threshold = wanted if kind == "door" else max(1, min(wanted, stats.best_view))
        if kind != "door" and stats.best_view >= wanted and not windows:
            break  # pass 2 would try the same points with the same threshold
        for feature, xyz in _take_off_points(candidates, free, grid, z, rng):
            seen = _turn_view(sensor, xyz)
            stats.best_view = max(stats.best_view, seen)
            if seen < threshold:
                continue
            stats.take_offs += 1
            for goal in _goals(planner, name, xyz, free, grid, rng, lo, hi, user_goal):
                stats.goals_tried += 1
                if _connected(planner, xyz, goal):
                    return Route(name, f"in front of {feature.type} {feature.id}", xyz, goal, seen, threshold)
    return None


def _take_off_points(features: list[MacroFeature], free: np.ndarray, grid: OccupancyGrid, z: float,
                     rng: np.random.Generator) -> Iterator[tuple[MacroFeature, np.ndarray]]:
    """Seeded points FRONT_M in front of (or behind) each feature at height z, in free space."""
    for k in rng.permutation(len(features))[:MAX_CANDIDATES]:
        f = features[k]
        xyz = np.r_[f.centroid_cad[:2] + rng.choice([-FRONT_M, FRONT_M]) * f.normal_cad[:2], z]
        if free[grid.cell_of(xyz)]:
            yield f, xyz


def _turn_view(sensor: Any, xyz: np.ndarray) -> int:  # noqa: ANN401 - sim.agent.TruthSensor
    """Doors and windows a turn on the spot at xyz shows (ground truth: in range, in view, in line of sight)."""
    yaws = np.linspace(-np.pi, np.pi, TURN_HEADINGS)
    return len(set().union(*(sensor.visible(level_pose(xyz, yaw)) for yaw in yaws)))


def _goals(planner: Planner, storey: str, start_xyz: np.ndarray, free: np.ndarray, grid: OccupancyGrid,
           rng: np.random.Generator, lo_m: float, hi_m: float, user_goal: DemoGoal | None) -> Iterator[DemoGoal]:
    """Goal candidates from start_xyz: the user's; else the storey's named spaces where it has any, else its doors
    and windows, then its free cells; lo_m-hi_m away (horizontally) and in another room (no free straight line)."""
    if user_goal is not None:
        yield user_goal
        return

    def fits(xy: np.ndarray) -> bool:
        d = float(np.hypot(*(np.asarray(xy, float)[:2] - start_xyz[:2])))
        return lo_m <= d <= hi_m and not _in_view(free, grid, start_xyz, xy)

    floor_z = planner.model.storey_elevations_m.get(storey, 0.0)
    spaces = [s for s in planner.solids.spaces if abs(s.floor_z_cad - floor_z) < 0.5 and s.name]
    for j in rng.permutation(len(spaces)):
        s = spaces[j]
        if fits(np.asarray(s.centroid_xy_cad)):
            yield DemoGoal(f"space {s.name} ({s.long_name})", space_name=s.name)
    if spaces:
        return  # the model names this storey's rooms: a room is the goal
    features = [f for f in planner.model.features if f.storey == storey]
    for j in rng.permutation(len(features)):
        f = features[j]
        if fits(f.centroid_cad):
            yield DemoGoal(f"{f.type} {f.id}", feature_id=f.id)
    cells = np.argwhere(free)
    for j in rng.permutation(len(cells))[:MAX_CANDIDATES]:
        xyz = grid.centre_cad(cells[j][None])[0]
        if fits(xyz):
            x, y = (float(v) for v in xyz[:2])
            yield DemoGoal(f"free cell ({x:.1f}, {y:.1f}) m", position_cad=(x, y, float(start_xyz[2])))


def _in_view(free: np.ndarray, grid: OccupancyGrid, a_xyz: np.ndarray, b_xy: np.ndarray) -> bool:
    """Whether the straight line from a to b (CAD, m) runs through free cells only: b is in a's room."""
    return ray_free(free, grid.cell_of(a_xyz), grid.cell_of(b_xy))


def _connected(planner: Planner, start_xyz: np.ndarray, goal: DemoGoal) -> bool:
    try:
        planner.plan(start_xyz, goal.spec())
    except PlanningError:
        return False
    return True


def goal_distance_range_m(grid: OccupancyGrid, free: np.ndarray, min_m: float, max_m: float) -> tuple[float, float]:
    """How far (m, horizontally) a goal lies from the take-off point: a quarter to 60 % of the storey's extent
    (the diagonal of its free cells' box: on any plan that crosses a room or two and stays clear of the far
    walls), capped at min_m-max_m where the storey is larger."""
    cells = np.argwhere(free)
    extent_m = float(np.hypot(*((cells.max(axis=0) - cells.min(axis=0) + 1) * grid.cell_m))) if len(cells) else 0.0
    return min(min_m, 0.25 * extent_m), min(max_m, 0.6 * extent_m)


def parse_goal(planner: Planner, text: str) -> DemoGoal:
    """The user's goal: CAD coordinates "x,y,z" (m), a door's or window's GlobalId, or an IfcSpace's Name or
    LongName; UserInputError where it is none of these."""
    parts = text.split(",")
    if len(parts) == 3:
        try:
            xyz = tuple(float(p) for p in parts)
        except ValueError:
            xyz = ()
        if len(xyz) == 3:
            if not np.isfinite(xyz).all():
                raise UserInputError(f"--goal {text!r}: coordinates must be finite")
            return DemoGoal(f"point ({xyz[0]:.2f}, {xyz[1]:.2f}, {xyz[2]:.2f}) m", position_cad=xyz)  # type: ignore[arg-type]
    by_id = {f.id: f for f in planner.model.features}
    if text in by_id:
        return DemoGoal(f"{by_id[text].type} {text}", feature_id=text)
    key = text.strip().casefold()
    found = [s for s in planner.solids.spaces if key in (s.name.casefold(), s.long_name.casefold())]
    if found:
        return DemoGoal(f"space {found[0].name} ({found[0].long_name})", space_name=text.strip())
    named = [f"{s.name} ({s.long_name})" if s.long_name else s.name for s in planner.solids.spaces if s.name]
    listed = ", ".join(named[:6]) + (f", ... {len(named) - 6} more" if len(named) > 6 else "")
    raise UserInputError(f"--goal {text!r} is no space name, door or window GlobalId, or x,y,z in "
                         f"{planner.model.source}: {len(planner.model.features)} doors and windows "
                         f"(`macroloc features` lists them), {len(named)} named spaces"
                         + (f": {listed}" if named else ""))


def goal_z_cad(planner: Planner, goal: DemoGoal) -> float:
    """The CAD height of the user's goal (its space's floor, its feature's centroid or its point), m."""
    if goal.position_cad is not None:
        return float(goal.position_cad[2])
    if goal.feature_id is not None:
        return float(planner.goals.feature(goal.feature_id)[2])
    key = (goal.space_name or "").casefold()
    return next(s.floor_z_cad for s in planner.solids.spaces if key in (s.name.casefold(), s.long_name.casefold()))


def storey_of(planner: Planner, z_cad: float) -> str:
    """The storey whose floor is the highest at or below z_cad (+0.3 m), by name; UserInputError if unnamed."""
    floor = planner.floor_z(z_cad)
    names = [n for n, e in planner.model.storey_elevations_m.items() if e == floor]
    if not names:
        raise UserInputError(f"no storey at height {z_cad:.2f} m in {planner.model.source}")
    return names[0]


def take_off_storey(model: BuildingModel) -> str | None:
    """The storey with the most doors and windows (what a vehicle can see), or None where there are none; the
    demo's route decides its own storey (`choose_route`), this is the guess without a planner."""
    counts: dict[str, int] = {}
    for f in model.features:
        if f.storey:
            counts[f.storey] = counts.get(f.storey, 0) + 1
    return max(counts, key=lambda n: (counts[n], -model.storey_elevations_m.get(n, 0.0))) if counts else None
