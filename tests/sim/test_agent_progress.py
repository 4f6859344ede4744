"""sim.agent.ProgressMonitor: a vehicle circling or oscillating is told apart from one on its way."""

from __future__ import annotations

import numpy as np

from macroloc.sim.agent import ProgressMonitor, ProgressParams, WaypointFollower


def _run(monitor: ProgressMonitor, remaining_m: np.ndarray, dt_s: float = 0.1) -> list[str]:
    return [monitor.update(k * dt_s, float(r)) for k, r in enumerate(remaining_m)]


def test_a_vehicle_on_its_way_is_never_flagged_even_on_a_detour() -> None:
    # 60 s at 1 m/s along a 60 m plan whose straight-line distance first grows: the way left shrinks throughout
    actions = _run(ProgressMonitor(), np.linspace(60.0, 0.0, 600))
    assert set(actions) == {"ok"}


def test_circling_asks_for_new_plans_then_holds() -> None:
    # 10 m from the goal, circling: the way left swings between 8 and 12 m, never a new minimum
    t = np.arange(0, 90, 0.1)
    actions = _run(ProgressMonitor(ProgressParams(window_s=15.0, max_replans=2)), 10.0 + 2.0 * np.sin(t))
    first_replan = actions.index("replan") * 0.1
    assert 15.0 <= first_replan <= 25.0
    assert actions.count("replan") == 2 and actions.count("hold") == 1
    assert actions.index("hold") > len(actions) - actions[::-1].index("replan") - 1  # hold after the replans
    assert actions[-1] == "held"


def test_progress_after_a_replan_clears_the_count() -> None:
    monitor = ProgressMonitor(ProgressParams(window_s=5.0, max_replans=1))
    stuck = _run(monitor, np.full(60, 10.0))
    assert "replan" in stuck
    moving = [monitor.update(6.0 + 0.1 * k, 9.0 - 0.1 * k) for k in range(50)]
    assert set(moving) == {"ok"} and monitor.replans == 0


def test_remaining_length_follows_the_plan() -> None:
    follower = WaypointFollower()
    follower.set_waypoints(np.array([[0.0, 0, 1], [4.0, 0, 1], [4.0, 3.0, 1]]))
    assert np.isclose(follower.remaining_m(np.array([1.0, 0.0, 1.0])), 3.0 + 3.0)
