"""The demo's route in any building (`sim.demo_route`): every shared and bundled building gets a take-off and a
goal; a building that cannot be flown says why in one line; the user's storey and goal are taken; a flight in
each building in lock-step (slow)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from macroloc.graph.errors import UserInputError
from tests.conftest import BUILDINGS, SHARED_DATA

SHARED = sorted((SHARED_DATA / "bim").glob("*.ifc"))
BUNDLED = sorted(BUILDINGS.glob("*.ifc"))
SYMMETRIC = {"duplex"}  # the duplex's two flats are each other's image under a 180° turn: 'ambiguous' is honest
_PLANNERS: dict[Path, object] = {}


def planner_for(path: Path):  # noqa: ANN201 - service.planning.Planner, imported lazily
    from macroloc.graph.planning import Planner

    if path not in _PLANNERS:
        _PLANNERS[path] = Planner.for_building(path, 0.2, 0.35, 1.4)  # the default planning settings
    return _PLANNERS[path]


def _check_route(path: Path, seed: int) -> None:
    from macroloc.graph.planning import Planner
    from macroloc.sim.agent import ray_free
    from macroloc.sim.demo_route import choose_route, goal_distance_range_m

    planner: Planner = planner_for(path)  # type: ignore[assignment]
    route = choose_route(planner, seed)
    floor_z = planner.model.storey_elevations_m[route.storey]
    assert route.start_xyz[2] == pytest.approx(floor_z + planner.flight_height_m)
    grid, free = planner.free_cells(route.start_xyz[2])
    assert free[grid.cell_of(route.start_xyz)], "the take-off point lies in free space"
    assert 1 <= route.wanted_view <= route.view, "a turn there shows what was asked"
    planner.plan(route.start_xyz, route.goal.spec())  # connected, or PlanningError fails the test
    goal_xy = planner.resolve(route.goal.spec(), route.start_xyz)[0][:2]
    lo, hi = goal_distance_range_m(grid, free, 10.0, 25.0)
    assert 0.0 < lo <= float(np.hypot(*(goal_xy - route.start_xyz[:2]))) <= hi
    assert not ray_free(free, grid.cell_of(route.start_xyz), grid.cell_of(goal_xy)), "the goal is in another room"
    names = [s.name for s in planner.solids.spaces if abs(s.floor_z_cad - floor_z) < 0.5 and s.name]
    assert (route.goal.space_name is not None) == bool(names), "a named space wherever the storey has one"


@pytest.mark.data
@pytest.mark.parametrize("building", SHARED or [SHARED_DATA / "bim" / "absent.ifc"], ids=lambda p: p.stem)
def test_every_shared_building_gets_a_take_off_and_a_goal(building: Path) -> None:
    from tests.conftest import shared_data

    shared_data(str(building.relative_to(SHARED_DATA)))
    for seed in (0, 1, 2):
        _check_route(building, seed)


@pytest.mark.parametrize("building", BUNDLED, ids=lambda p: p.stem)
def test_every_bundled_building_gets_a_take_off_and_a_goal(building: Path) -> None:
    _check_route(building, 0)


def test_office_a_keeps_the_route_it_flew_before_issue_59(office_path: Path) -> None:
    """Office_A, the building the demo was made in, takes off where it did before the route was generalised
    (seed 0: the demo's figures in docs/measurements.md)."""
    from macroloc.sim.demo_route import choose_route

    route = choose_route(planner_for(office_path), 0)  # type: ignore[arg-type]
    assert (route.storey, route.start, route.goal.space_name) == \
        ("Level 1", "in front of door 2N3oFtM8X6lO2dN1$77x0R", "107")
    assert route.start_xyz == pytest.approx([30.966, -13.218, 1.4], abs=1e-3)


def test_a_building_without_ifcspace_gets_a_door_window_or_free_cell_goal(fzk_path: Path) -> None:
    """Many IFC exports have no IfcSpace: the goal is then a door, a window or a free cell of another room."""
    from dataclasses import replace

    from macroloc.graph.planning import Planner
    from macroloc.sim.agent import ray_free
    from macroloc.sim.demo_route import choose_route

    full: Planner = planner_for(fzk_path)  # type: ignore[assignment]
    bare = Planner(full.model, replace(full.solids, spaces=[]), full.cell_m, full.vehicle_radius_m,
                   full.flight_height_m)
    for seed in (0, 1, 2):
        route = choose_route(bare, seed)
        assert route.goal.space_name is None and (route.goal.feature_id or route.goal.position_cad)
        bare.plan(route.start_xyz, route.goal.spec())
        grid, free = bare.free_cells(route.start_xyz[2])
        goal_xy = bare.resolve(route.goal.spec(), route.start_xyz)[0][:2]
        assert not ray_free(free, grid.cell_of(route.start_xyz), grid.cell_of(goal_xy))


def test_the_take_off_view_asked_for_is_what_a_storey_offers(fzk_path: Path) -> None:
    """A house's rooms show fewer doors and windows than the registration would like: its best view is asked
    for instead; with a registration that needs more than any point shows, the route still takes off."""
    from macroloc.sim.demo_route import choose_route, wanted_view

    planner = planner_for(fzk_path)
    greedy = choose_route(planner, 0, registration_min_landmarks=40)  # type: ignore[arg-type]
    assert greedy.wanted_view < wanted_view(40) and greedy.view >= greedy.wanted_view
    assert choose_route(planner, 0).wanted_view == wanted_view()  # type: ignore[arg-type]


def test_every_storey_with_something_to_see_is_tried_and_the_refusal_says_what_each_offered(fzk_path: Path) -> None:
    """No goal fits anywhere (a goal at most 0.1 m away is never in another room): both of the house's storeys
    were tried, and the one line gives each one's figures."""
    from macroloc.sim.demo_route import choose_route

    with pytest.raises(UserInputError) as refused:
        choose_route(planner_for(fzk_path), 0, min_goal_distance_m=0.0, max_goal_distance_m=0.1)  # type: ignore[arg-type]
    line = str(refused.value)
    assert "\n" not in line
    assert line.index("Erdgeschoss: 14 doors/windows") < line.index("Dachgeschoss: 2 doors/windows")
    assert "best view" in line and "goals tried" in line


def test_the_users_storey_and_goal_are_taken(office_path: Path) -> None:
    from macroloc.sim.demo_route import choose_route, parse_goal

    planner = planner_for(office_path)
    assert choose_route(planner, 0, storey="Level 2").storey == "Level 2"  # type: ignore[arg-type]
    upstairs = next(s for s in planner.solids.spaces if s.floor_z_cad > 4.0 and s.name)  # type: ignore[attr-defined]
    route = choose_route(planner, 1, goal=upstairs.name)  # type: ignore[arg-type]
    assert route.storey == "Level 2" and route.goal.space_name == upstairs.name  # the goal's storey
    door = next(f for f in planner.model.features if f.storey == "Level 1")  # type: ignore[attr-defined]
    assert parse_goal(planner, door.id).feature_id == door.id  # type: ignore[arg-type]
    point = parse_goal(planner, "20.5, -10, 1.4")  # type: ignore[arg-type]
    assert point.position_cad == (20.5, -10.0, 1.4)
    assert choose_route(planner, 0, goal="20.5,-10,1.4").storey == "Level 1"  # type: ignore[arg-type]
    with pytest.raises(UserInputError, match="no space name"):
        parse_goal(planner, "Narnia")  # type: ignore[arg-type]
    with pytest.raises(UserInputError, match="Level 9"):
        choose_route(planner, 0, storey="Level 9")  # type: ignore[arg-type]


class _Plan:
    """A planner stand-in: a model, a flight height and free cells (none, or all)."""

    def __init__(self, model, free: bool) -> None:  # noqa: ANN001 - BuildingModel
        from macroloc.graph.planning_grid import OccupancyGrid

        self.model, self.flight_height_m = model, 1.4
        self._grid = OccupancyGrid(np.zeros((10, 10), bool), np.zeros(2), 0.2, 1.4)
        self._free = np.full((10, 10), free)

    def free_cells(self, z_cad: float):  # noqa: ANN201
        return self._grid, self._free


def test_a_building_that_cannot_be_flown_says_why_with_the_figure(office_model) -> None:  # noqa: ANN001
    from dataclasses import replace

    from macroloc.sim.demo_route import ranked_storeys

    bare = replace(office_model, features=[])
    with pytest.raises(UserInputError, match="no doors or windows on any of its 3 storeys"):
        ranked_storeys(_Plan(bare, free=True))  # type: ignore[arg-type]
    with pytest.raises(UserInputError, match=r"no free space 1.4 m above the floor.*Level 1 0 m² \(91 doors"):
        ranked_storeys(_Plan(office_model, free=False))  # type: ignore[arg-type]
    assert [r[0] for r in ranked_storeys(_Plan(office_model, free=True))] == ["Level 1", "Level 2"]  # type: ignore[arg-type]


def test_an_unreadable_building_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "mine.ifc"
    bad.write_text("ISO-10303-21;\nHEADER;\n")
    done = subprocess.run([sys.executable, "-m", "macroloc.cli.main", "demo", "--building", str(bad),
                           "--observations", "truth"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "mine.ifc" in done.stderr and "Traceback" not in done.stderr


def test_a_mesh_building_is_refused_in_one_line(tmp_path: Path) -> None:
    """A mesh model (features and localize read it) has no IFC walls and rooms for the demo to plan on."""
    from macroloc.cli.demo import DemoParams, demo_route

    mesh = tmp_path / "walls.obj"
    mesh.write_text("v 0 0 0\nv 4 0 0\nv 4 0 3\nv 0 0 3\nf 1 2 3\nf 1 3 4\n")
    with pytest.raises(UserInputError, match=r"cannot fly in walls.obj: the demo plans on an IFC model's"):
        demo_route(mesh, DemoParams(observations="truth"))


def test_an_ambiguous_flight_names_its_rival_poses() -> None:
    """The demo's outcome: 'ambiguous' with where each rival pose puts the vehicle, from the localizer's rivals."""
    from types import SimpleNamespace

    from macroloc.cli.demo import DemoResult, _outcome, outcome_line
    from macroloc.graph.anchoring import rival_poses
    from macroloc.graph.relocalize import Alignment

    turn = np.diag([-1.0, -1.0, 1.0, 1.0])  # 180° about z
    shift = np.eye(4)
    shift[:3, 3] = [2.0, 0.0, 0.0]
    rivals = rival_poses(Alignment("ambiguous", shift, candidates=[(shift, 5), (turn, 5), (np.eye(4), 3)]))
    assert len(rivals) == 2  # the two that explain as many landmarks as the best
    T_map_body = np.eye(4)
    T_map_body[:3, 3] = [1.0, 1.0, 0.0]
    graph = SimpleNamespace(n_keyframes=3, T_map_body=lambda i: T_map_body)
    front_end = SimpleNamespace(localizer=SimpleNamespace(status="ambiguous", rivals=rivals, graph=graph))
    result = DemoResult(0, False, False, float("nan"), float("nan"), 0.0, float("nan"), "", "", "", 0.0)
    outcome, rivals_xy = _outcome(result, front_end, 0.5)
    assert outcome == "ambiguous" and rivals_xy == [[3.0, 1.0], [-1.0, -1.0]]
    result.outcome, result.rivals_xy = outcome, rivals_xy
    assert "2 poses" in outcome_line(result)
    front_end.localizer.status = "exploring"
    assert _outcome(result, front_end, 0.5) == ("not localized", [])
    result.localized, result.pose_error_m = True, 2.7  # the duplex's mirror image, taken (seen with perception)
    assert _outcome(result, front_end, 0.5)[0] == "localized wrongly"
    result.pose_error_m = 0.02
    assert _outcome(result, front_end, 0.5)[0] == "not reached"


@pytest.mark.slow
@pytest.mark.data
@pytest.mark.parametrize("building", SHARED or [SHARED_DATA / "bim" / "absent.ifc"], ids=lambda p: p.stem)
def test_the_demo_flies_each_shared_building_in_lockstep(building: Path) -> None:
    """Ground-truth sightings (no camera), lock-step, seed 0: an asymmetric building is localized and its goal
    reached within the project's 0.10 m target; the duplex, exactly symmetric, may end 'ambiguous' (said, with
    its rival poses) but is never wrongly reached."""
    from macroloc.cli.demo import DemoParams, run_demo
    from tests.conftest import shared_data

    shared_data(str(building.relative_to(SHARED_DATA)))
    result = run_demo(building, DemoParams(seed=0, lockstep=True, observations="truth"))
    if any(name in building.stem.casefold() for name in SYMMETRIC) and result.outcome == "ambiguous":
        assert len(result.rivals_xy) >= 2
        return
    assert result.outcome == "reached" and result.localized
    assert result.goal_error_m <= 0.10
