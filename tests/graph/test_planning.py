"""Planning (paper §3.3): A* against a graph-search oracle, line of sight, and plans in a real building."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.planning import GoalSpec, Planner, PlanningError, astar, line_of_sight, simplify


def _grid_graph(free: np.ndarray) -> nx.Graph:
    g = nx.Graph()
    h, w = free.shape
    for r in range(h):
        for c in range(w):
            if not free[r, c]:
                continue
            for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
                nr, nc = r + dr, c + dc
                if 0 <= nr < h and 0 <= nc < w and free[nr, nc] and (not (dr and dc) or
                                                                     (free[r, nc] and free[nr, c])):
                    g.add_edge((r, c), (nr, nc), weight=float(np.hypot(dr, dc)))
    return g


def _length(path: list[tuple[int, int]]) -> float:
    return float(sum(np.hypot(a[0] - b[0], a[1] - b[1]) for a, b in zip(path, path[1:], strict=False)))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_astar_finds_the_shortest_path_that_dijkstra_finds(seed: int) -> None:
    rng = np.random.default_rng(seed)
    free = rng.random((14, 17)) > 0.3
    free[0, 0] = free[-1, -1] = True
    path = astar(free, (0, 0), (13, 16))
    g = _grid_graph(free)
    try:
        best = nx.dijkstra_path_length(g, (0, 0), (13, 16))
    except (nx.NetworkXNoPath, nx.NodeNotFound):
        assert path == []
        return
    assert path[0] == (0, 0) and path[-1] == (13, 16)
    assert all(free[r, c] for r, c in path)
    assert _length(path) == pytest.approx(best)
    for a, b in zip(simplify(path, free), simplify(path, free)[1:], strict=False):
        assert line_of_sight(free, a, b)


def test_line_of_sight_is_blocked_by_a_wall() -> None:
    free = np.ones((10, 10), bool)
    free[:, 5] = False
    assert not line_of_sight(free, (2, 1), (2, 8))
    assert line_of_sight(free, (1, 1), (8, 4))


@pytest.fixture(scope="module")
def planner(office_path) -> Planner:
    return Planner.for_building(office_path, cell_m=0.2, vehicle_radius_m=0.35, flight_height_m=1.4)


def _start(planner: Planner, space: str) -> np.ndarray:
    return planner.goals.space(space, np.zeros(2)) + np.array([0.0, 0.0, 1.4])


def test_plan_between_rooms_passes_doors_and_stays_free(planner: Planner) -> None:
    start = _start(planner, "111")
    plan = planner.plan(start, GoalSpec(space_name="MENS RR"))
    grid, free = planner.free_cells(start[2])
    assert len(plan.points_cad) >= 2 and plan.length_m > 3.0
    assert np.allclose(plan.points_cad[:, 2], grid.z_cad)
    cells = [grid.cell_of(p) for p in plan.points_cad]
    for a, b in zip(cells, cells[1:], strict=False):
        assert line_of_sight(free, a, b), "a waypoint segment crosses an obstacle"


def test_goal_by_feature_id_and_by_position(planner: Planner) -> None:
    start = _start(planner, "121")
    door = next(f for f in planner.model.features if f.type == "door" and f.storey == "Level 1")
    by_id = planner.plan(start, GoalSpec(feature_id=door.id))
    assert np.linalg.norm(by_id.points_cad[-1, :2] - door.centroid_cad[:2]) < 0.5
    target = by_id.points_cad[-1]
    by_xyz = planner.plan(start, GoalSpec(position_cad=target))
    assert np.allclose(by_xyz.points_cad[-1, :2], target[:2])


def test_unknown_goals_are_refused(planner: Planner) -> None:
    start = _start(planner, "121")
    with pytest.raises(PlanningError):
        planner.plan(start, GoalSpec(space_name="no such room"))
    with pytest.raises(PlanningError):
        planner.plan(start, GoalSpec(feature_id="nonexistent"))


def test_goals_and_starts_outside_the_model_are_refused(planner: Planner) -> None:
    """A goal at 1e300 m once got an error-free plan (its cell clipped into the grid's corner)."""
    start = _start(planner, "121")
    far = np.array([1e300, 0.0, 1.0])
    for goal, begin in ((far, start), (start + [200.0, 0.0, 0.0], start), (start + [0.0, 0.0, 500.0], start),
                        (start, far), (start, np.array([np.nan, 0.0, 0.0]))):
        with pytest.raises(PlanningError, match="outside"):
            planner.plan(begin, GoalSpec(position_cad=goal))
    assert len(planner.plan(start, GoalSpec(position_cad=start + [0.5, 0.0, 0.0])).points_cad) >= 2


def _block_leg(planner: Planner, plan, leg: int, z_cad: float) -> np.ndarray:  # noqa: ANN001 - Plan
    """A wall of points 3 m wide across the plan's leg, at flight height (an obstacle the model lacks): its middle."""
    a, b = plan.points_cad[leg], plan.points_cad[leg + 1]
    mid = a + 0.5 * (b - a)
    normal = np.array([-(b - a)[1], (b - a)[0], 0.0]) / np.linalg.norm((b - a)[:2])
    wall = mid + np.linspace(-1.5, 1.5, 200)[:, None] * normal
    assert planner.add_obstacle_points(np.repeat(wall, 5, axis=0), z_cad) == 1000
    return mid


def test_seen_obstacles_change_the_plan(office_path) -> None:
    planner = Planner.for_building(office_path, cell_m=0.2, vehicle_radius_m=0.35, flight_height_m=1.4)
    start = _start(planner, "121")
    goal = GoalSpec(space_name="MENS RR")
    before = planner.plan(start, goal)
    mid = _block_leg(planner, before, 1, start[2])  # the corridor's leg: a way round inside is longer
    grid, free = planner.free_cells(start[2])
    assert not free[grid.cell_of(mid)]
    after = planner.plan(start, goal)
    assert after.length_m > before.length_m + 1.0
    cells = [grid.cell_of(p) for p in after.points_cad]
    assert all(line_of_sight(free, p, q) for p, q in zip(cells, cells[1:], strict=False))


def test_a_room_whose_door_is_blocked_has_no_way_out_through_a_window(office_path) -> None:
    """Room 121's first leg blocked: the only way round leaves the building (a window or an exterior door); the
    plan is refused rather than flown outside."""
    planner = Planner.for_building(office_path, cell_m=0.2, vehicle_radius_m=0.35, flight_height_m=1.4)
    start = _start(planner, "121")
    goal = GoalSpec(space_name="MENS RR")
    _block_leg(planner, planner.plan(start, goal), 0, start[2])
    with pytest.raises(PlanningError, match="no free path"):
        planner.plan(start, goal)


def test_lines_of_sight_pass_doorways_not_the_walls_beside_them(fzk_path) -> None:
    """The model's walls as voxels for the surface check (graph.building_assets.surfaces_for): through every door
    of FZK-Haus, 1.5 m either side of it, the line of sight is free (IFC openings are cut from the walls); 0.4 m
    beside the door it crosses the wall. `line_of_sight=False` leaves the voxels out."""
    from macroloc.graph.bim import load_building
    from macroloc.graph.building_assets import surfaces_for

    surfaces = surfaces_for(fzk_path)
    assert surfaces is not None and surfaces.walls is not None and len(surfaces.walls) > 10_000
    doors = [f for f in load_building(fzk_path).features if f.type == "door" and f.orientation == "vertical"]
    assert len(doors) >= 5
    for door in doors:
        c, n = door.centroid_cad, door.normal_cad
        along = np.cross([0.0, 0.0, 1.0], n) / np.linalg.norm(np.cross([0.0, 0.0, 1.0], n))
        beside = c + (door.width_m / 2 + 0.4) * along
        origins, points = np.array([c + 1.5 * n, beside + 1.5 * n]), np.array([c - 1.5 * n, beside - 1.5 * n])
        assert surfaces.walls.seen_through(origins, points).tolist() == [False, True]
    unchecked = surfaces_for(fzk_path, line_of_sight=False)
    assert unchecked is not None and unchecked.walls is None


def test_the_surfaces_read_from_the_cache_are_those_built(fzk_path, tmp_path, monkeypatch) -> None:
    """surfaces_for caches the seeded samples per file and parameters: the second call reads them (the hidden-face
    test and the sampling are not repeated) and gets the same index, sample for sample; another setting (no lines
    of sight, so no hidden faces dropped) is cached apart."""
    import macroloc.graph.bim as bim
    import macroloc.graph.surfaces as surfaces
    from macroloc.graph.building_assets import surfaces_for

    monkeypatch.setattr(bim, "cache_dir", lambda: tmp_path)
    monkeypatch.setattr("macroloc.graph.building_assets.cache_dir", lambda: tmp_path)
    built = surfaces_for(fzk_path)
    assert built is not None and len(list(tmp_path.glob("surfaces-*.npz"))) == 1
    monkeypatch.setattr(surfaces.SurfaceIndex, "from_mesh", None)  # a rebuild would fail
    cached = surfaces_for(fzk_path)
    assert cached is not None and cached.walls is not None and cached.horizontal is not None
    assert built.horizontal is not None and built.normals_cad is not None and cached.normals_cad is not None
    assert np.array_equal(cached.samples_cad, built.samples_cad) and np.array_equal(cached.normals_cad,
                                                                                   built.normals_cad)
    assert np.array_equal(cached.horizontal[1], built.horizontal[1])
    assert np.array_equal(cached.walls.keys, built.walls.keys)
    monkeypatch.undo()
    monkeypatch.setattr("macroloc.graph.building_assets.cache_dir", lambda: tmp_path)
    unchecked = surfaces_for(fzk_path, line_of_sight=False)
    assert unchecked is not None and len(unchecked) > len(built)  # its hidden faces are kept
    assert len(list(tmp_path.glob("surfaces-*.npz"))) == 2


def test_the_model_s_triangles_come_in_the_elements_order(fzk_path) -> None:
    """The geometry iterator's two threads hand the shapes over in whichever order they finish; the mesh (and so
    the surface samples drawn on it, and every replay's figures) must not depend on that: the shapes come in the
    elements' id order, and two reads give the same mesh."""
    import ifcopenshell

    from macroloc.graph.building_assets import NOT_SEEN, _iterate_shapes

    first, again = ([(element.id(), verts, faces) for element, verts, faces in
                     _iterate_shapes(ifcopenshell.open(str(fzk_path)), exclude=list(NOT_SEEN))] for _ in range(2))
    ids = [element_id for element_id, _, _ in first]
    assert len(ids) > 10 and ids == sorted(ids) == [element_id for element_id, _, _ in again]
    assert all(np.array_equal(v1, v2) and np.array_equal(f1, f2)
               for (_, v1, f1), (_, v2, f2) in zip(first, again, strict=True))


def test_outside_is_what_the_border_reaches_without_passing_a_wall_or_an_opening() -> None:
    """A room of walls with a door gap in its south wall: without the door given, the outside leaks in through
    the gap; with it, the room is inside and only the ring around it is outside."""
    from macroloc.graph.planning_grid import OccupancyGrid, outside_cells

    occupied = np.zeros((30, 30), bool)
    occupied[5, 5:25] = occupied[24, 5:25] = occupied[5:25, 5] = occupied[5:25, 24] = True
    occupied[5, 12:16] = False  # the door: x 1.2-1.6 m (cells 12-15) in the wall at y = 0.5 m
    grid = OccupancyGrid(occupied, np.zeros(2), 0.1, 1.4)
    door = np.array([[1.2, 0.55, 0.0], [1.6, 0.55, 0.0], [1.6, 0.55, 2.1], [1.2, 0.55, 2.1]])
    leaked = outside_cells(grid, [])
    assert leaked[15, 15]  # the room's middle, reached through the door gap
    outside = outside_cells(grid, [door])
    assert not outside[6:24, 6:24].any() and outside[0, 0] and outside[29, 29] and outside[2, 14]
    assert outside_cells(grid, [door + [0.0, 0.0, 3.0]])[15, 15]  # an opening above the cut closes nothing


def test_plans_stay_inside_the_building(planner: Planner) -> None:
    """From Office_A's south-east corner to the CHAPLAIN room (the demo's seed 5 flew it): the shortest way leaves
    through an exterior door and runs along the south façade, where the model knows no floor; the plan keeps
    inside. Outdoors allowed, the path goes outside (so the test would see a plan that leaves)."""
    start = np.array([48.5, -34.5, 1.4])
    grid = planner.grid(start[2])[0]
    outside = planner.outside(start[2])

    def cells_along(points: np.ndarray) -> list[tuple[int, int]]:
        out = []
        for a, b in zip(points, points[1:], strict=False):
            for t in np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / 0.05))):
                out.append(grid.cell_of(a + t * (b - a)))
        return out

    plan = planner.plan(start, GoalSpec(space_name="129"))
    assert not any(outside[c] for c in cells_along(plan.points_cad))
    grid_o, free_o = planner.free_cells(start[2], outdoors=True)
    from macroloc.graph.planning import astar

    path = astar(free_o, grid_o.cell_of(start), grid_o.cell_of(planner.goals.space("129", start[:2])))
    assert any(outside[c] for c in path)
