"""Waypoint yaws (service.planning.waypoint_yaws): the direction of travel, and facing the goal's door."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.graph.planning import GoalSpec, Planner, waypoint_yaws


def test_yaw_is_the_direction_of_travel() -> None:
    points = np.array([[0, 0, 1], [2, 0, 1], [2, 2, 1], [2, 2, 1], [0, 4, 1]], float)
    yaws = waypoint_yaws(points)
    assert np.allclose(yaws, [0.0, np.pi / 2, np.pi / 2, 3 * np.pi / 4, 3 * np.pi / 4])
    assert np.allclose(waypoint_yaws(points, facing_cad=np.array([0.0, -1.0, 0.0]))[-1], -np.pi / 2)
    assert np.allclose(waypoint_yaws(points[:1]), [0.0])


@pytest.fixture(scope="module")
def office_planner(office_path) -> Planner:
    return Planner.for_building(office_path, cell_m=0.2, vehicle_radius_m=0.35, flight_height_m=1.4)


def test_a_plan_to_a_door_ends_facing_it(office_planner, office_model) -> None:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    start = door.centroid_cad + np.r_[door.normal_cad[:2] * 3.0, 0.0]
    start[2] = door.centroid_cad[2] + 0.3
    plan = office_planner.plan(start, GoalSpec(feature_id=door.id))
    assert len(plan.yaw_rad) == len(plan.points_cad) >= 2
    legs = np.diff(plan.points_cad[:, :2], axis=0)
    for yaw, leg in zip(plan.yaw_rad[:-1], legs, strict=True):
        if np.hypot(*leg) > 1e-3:
            assert np.isclose(yaw, np.arctan2(leg[1], leg[0]))
    heading = np.array([np.cos(plan.yaw_rad[-1]), np.sin(plan.yaw_rad[-1])])
    assert abs(abs(heading @ door.normal_cad[:2]) - 1.0) < 1e-6  # square to the door's plane
    assert heading @ (door.centroid_cad[:2] - plan.points_cad[-2, :2]) > 0  # looking at it, not away
