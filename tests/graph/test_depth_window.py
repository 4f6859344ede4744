"""The recent keyframes' depth points (graph.depth_window): kept in the body frames, used in the map frame."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.rigid import apply, make_T, rot_z

VIEWER_BODY = np.array([0.1, 0.0, 0.05])


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), x=st.floats(-30, 30), y=st.floats(-30, 30), seed=st.integers(0, 99))
def test_points_are_moved_by_their_keyframes_current_estimates(yaw: float, x: float, y: float, seed: int) -> None:
    """Each keyframe's points land where its pose (as the graph estimates it now) puts them, each with the
    camera it was seen from; a later estimate moves them with it."""
    rng = np.random.default_rng(seed)
    poses = {0: make_T(rot_z(yaw), np.array([x, y, 1.4])), 1: make_T(rot_z(yaw + 0.3), np.array([x + 1, y, 1.4]))}
    window = DepthWindow(10, VIEWER_BODY, lambda i: poses[i])
    body = {i: rng.normal(0, 3, (5, 3)) for i in poses}
    for i in poses:
        window.add(i, body[i], np.zeros((0, 3)))
    points, origins = window.points_map()
    assert np.allclose(points, np.vstack([apply(poses[i], body[i]) for i in poses]))
    assert np.allclose(origins[:5], apply(poses[0], VIEWER_BODY[None]))
    poses[1] = make_T(rot_z(yaw - 0.2), np.array([x, y + 2, 1.5]))  # the graph moved keyframe 1
    assert np.allclose(window.points_map()[0][5:], apply(poses[1], body[1]))


def test_the_window_keeps_the_newest_keyframes_and_draws_at_most_as_many_points_as_asked() -> None:
    window = DepthWindow(3, VIEWER_BODY, lambda i: np.eye(4))
    for i in range(5):
        window.add(i, np.full((100, 3), float(i)), np.zeros((0, 3)))
    assert len(window) == 3 and window.newest[0] == 4 and window.n_points == 300
    points, _ = window.points_map(at_most=50)
    assert len(points) <= 50
    assert set(np.unique(points[:, 0])) == {2.0, 3.0, 4.0}  # evenly drawn over the three kept keyframes
