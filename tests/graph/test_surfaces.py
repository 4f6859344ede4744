"""graph.surfaces: the model's surfaces as samples, support of a pose by depth points, lines of sight through
voxelized walls (the test room: tests/graph/rooms.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.rigid import apply
from macroloc.graph.surfaces import (
    SurfaceIndex,
    WallVoxels,
    band_points,
)
from tests.graph.rooms import (
    UP,
    seen_points,
    wall_points,
)
from tests.graph.scenes import make_T, rot_z


def test_samples_cover_the_walls_only(room: SurfaceIndex) -> None:
    wall_area = 2 * (12 + 7) * 3.0 + 4 * 3.0  # each wall is one quad
    assert len(room) == pytest.approx(wall_area / 0.05**2, rel=0.02)
    assert np.abs(room.samples_cad[:, 2] - 1.5).max() <= 1.5 + 1e-9
    on_wall = ((np.abs(room.samples_cad[:, 0]) < 1e-9) | (np.abs(room.samples_cad[:, 0] - 12) < 1e-9)
               | (np.abs(room.samples_cad[:, 1]) < 1e-9) | (np.abs(room.samples_cad[:, 1] - 7) < 1e-9)
               | ((np.abs(room.samples_cad[:, 0] - 5) < 1e-9) & (room.samples_cad[:, 1] <= 4 + 1e-9)))
    assert on_wall.all()  # floor and ceiling (horizontal) are not among the walls' samples ...
    assert room.horizontal is not None  # ... but apart, every 0.2 m, for fitting heights
    _, floors, normals = room.horizontal
    assert len(floors) == pytest.approx(2 * 12 * 7 / 0.2**2, rel=0.05)
    assert np.allclose(np.minimum(np.abs(floors[:, 2]), np.abs(floors[:, 2] - 3.0)), 0.0)
    assert np.allclose(np.abs(normals[:, 2]), 1.0)


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20), seed=st.integers(0, 1000))
def test_support_is_full_at_the_true_pose_in_any_map_frame(room: SurfaceIndex, yaw: float, tx: float, ty: float,
                                                          seed: int) -> None:
    """Points measured in an arbitrary map frame, moved back by the true T_cad_map, all lie on the walls."""
    points_cad = wall_points(np.random.default_rng(seed))
    T_map_cad = make_T(rot_z(yaw), np.array([tx, ty, 0.3]))
    points_map = apply(T_map_cad, points_cad)
    assert room.support(apply(np.linalg.inv(T_map_cad), points_map)) == 1.0


def test_supports_of_many_poses_at_once_are_each_poses_support(room: SurfaceIndex) -> None:
    rng = np.random.default_rng(4)
    points = wall_points(rng, 300)
    poses = [make_T(rot_z(a), np.array([dx, 0.0, 0.0])) for a, dx in ((0.0, 0.0), (0.2, 0.5), (1.0, 2.0))]
    sets = np.stack([apply(T, points) for T in poses])
    assert room.supports(sets) == pytest.approx([room.support(s) for s in sets])
    assert room.supports(sets)[0] == 1.0 and room.supports(sets)[2] < 0.9
    assert room.supports(np.zeros((0, 5, 3))).shape == (0,)


def test_support_falls_when_the_pose_is_off(room: SurfaceIndex) -> None:
    points = wall_points(np.random.default_rng(1))
    assert room.support(points) == 1.0
    for T in (make_T(np.eye(3), np.array([1.0, 0.0, 0.0])), make_T(np.eye(3), np.array([0.0, 1.0, 0.0])),
              make_T(rot_z(np.radians(10)), np.zeros(3))):
        assert room.support(apply(T, points)) < 0.7
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))  # the outer walls onto themselves
    assert 0.7 < room.support(apply(half_turn, points)) < 0.95  # only the partition's points tell
    assert room.support(np.zeros((0, 3))) == 0.0


def test_a_point_behind_a_wall_is_seen_through_it(room_with_walls: SurfaceIndex) -> None:
    """Points on the far wall (x = 12 m) behind the partition (x = 5 m, y < 4 m): on a surface, but a camera in
    the partition's pocket cannot see them; from the other side of the partition it can."""
    walls = room_with_walls.walls
    assert walls is not None
    far = np.column_stack([np.full(50, 12.0), np.linspace(0.5, 3.5, 50), np.full(50, 1.4)])
    pocket, open_side = np.array([2.0, 2.0, 1.4]), np.array([8.0, 2.0, 1.4])
    assert walls.seen_through(np.tile(pocket, (50, 1)), far).all()
    assert not walls.seen_through(np.tile(open_side, (50, 1)), far).any()
    on_far = room_with_walls.check(far, np.tile(pocket, (50, 1)))
    assert on_far.support == 1.0 and on_far.seen_through == 1.0 and on_far.score == 0.0
    assert room_with_walls.check(far).score == 1.0  # without the cameras: support alone
    # past the partition's end (y > 4 m) the line of sight is free
    past = np.column_stack([np.linspace(8.0, 11.0, 20), np.full(20, 7.0), np.full(20, 1.4)])
    assert not walls.seen_through(np.tile([2.0, 3.5, 1.4], (20, 1)), past).any()
    # a point measured a little behind its wall (depth noise) is not seen through it; a metre behind, it is
    camera = np.array([[10.0, 3.0, 1.4]])
    assert not walls.seen_through(camera, np.array([[12.1, 3.0, 1.4]])).any()
    assert walls.seen_through(camera, np.array([[13.0, 3.0, 1.4]])).all()


def test_support_allows_for_the_depth_noise_of_far_points_and_the_score_does_not(room_with_walls: SurfaceIndex) -> None:
    """A far wall measured 1.5 sigmas of stereo depth noise short (11 m away: sigma 0.6 m) is still on the model's
    surface by `support` (the check's absolute test: is this pose consistent with what was measured?), not by
    `score` (its comparison of poses, as sharp as the near points allow). A near point as far off its wall is off
    by both."""
    p = room_with_walls.params
    camera = np.array([1.0, 5.5, 1.4])
    wall_points = np.column_stack([np.full(30, 12.0), np.linspace(4.6, 6.4, 30), np.full(30, 1.4)])
    ray = wall_points - camera
    r = np.linalg.norm(ray, axis=1, keepdims=True)
    short = wall_points - ray / r * 1.5 * p.depth_sigma_per_m2 * r**2
    origins = np.tile(camera, (len(short), 1))
    far = room_with_walls.check(short, origins)
    assert far.support == 1.0 and far.seen_through == 0.0 and far.score == 0.0
    assert room_with_walls.check(wall_points, origins).score == 1.0
    assert room_with_walls.check(short).support == 0.0  # without the cameras no range is known: the fixed tolerance
    near_camera = np.array([10.0, 5.5, 1.4])
    off = np.column_stack([np.full(30, 11.4), np.linspace(4.6, 6.4, 30), np.full(30, 1.4)])  # 0.6 m short of x = 12
    near = room_with_walls.check(off, np.tile(near_camera, (len(off), 1)))
    assert near.support == 0.0 and near.score == 0.0


@settings(max_examples=20, deadline=None)
@given(x=st.floats(5.5, 11.5), y=st.floats(0.5, 6.5), noise=st.floats(0.0, 1.0), seed=st.integers(0, 1000))
def test_what_a_camera_sees_is_never_seen_through_a_wall(room_with_walls: SurfaceIndex, x: float, y: float,
                                                         noise: float, seed: int) -> None:
    """Anywhere in the room, the points a camera measures (with up to one sigma of depth noise along the line of
    sight) lie on surfaces and in sight, and a pose a metre off is seen through walls for some of them. (A line of
    sight that passes the partition's end within a voxel's diagonal may be taken for one through it, and only
    such a line: a few in a hundred, more the nearer the camera is to that end.)"""
    rng = np.random.default_rng(seed)
    points = seen_points(rng, np.array([x, y]), 300)
    origins = np.tile([x, y, 1.4], (len(points), 1))
    check = room_with_walls.check(points, origins)
    grazing = _passes_near(origins[:, :2], points[:, :2], np.array([5.0, 4.0]), 0.15)
    assert not np.any(seen_through(room_with_walls, points, origins) & ~grazing) and check.support > 0.95
    off = make_T(rot_z(0.5), np.array([1.0, 0.5, 0.0]))
    assert room_with_walls.check(apply(off, points), apply(off, origins)).score < check.score - 0.2
    ray = points - origins
    r = np.linalg.norm(ray, axis=1, keepdims=True)
    sign = rng.choice([-1.0, 1.0], (len(points), 1))
    noisy = points + ray / r * noise * room_with_walls.params.depth_sigma_per_m2 * r**2 * sign
    assert not np.any(seen_through(room_with_walls, noisy, origins) & ~grazing)  # (support falls beyond 0.2 m of noise)


def seen_through(index: SurfaceIndex, points: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """(N,) bool: which points the index's check counts as seen through a wall."""
    assert index.walls is not None
    return index.walls.seen_through(origins, points, index.params.depth_sigma_per_m2, index.params.sight_margin_m)


def _passes_near(a: np.ndarray, b: np.ndarray, c: np.ndarray, within: float) -> np.ndarray:
    """(N,) bool: the segments a -> b (N, 2) pass within `within` of the point c (2,)."""
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", c - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return np.asarray(np.linalg.norm(a + t[:, None] * d - c, axis=1) < within)


def test_voxels_of_an_empty_model_block_nothing() -> None:
    walls = WallVoxels.from_mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert len(walls) == 0 and not walls.seen_through(np.zeros((3, 3)), np.ones((3, 3))).any()


def test_band_points_keep_the_camera_height_and_range() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(-10, 10, (20000, 3))
    kept = band_points(points, np.array([0.0, 0.0, 2.0]), half_height_m=0.5, max_range_m=8.0, max_points=10_000)
    assert len(kept) and np.abs(kept[:, 2]).max() <= 0.5 and np.linalg.norm(kept, axis=1).max() <= 8.0
    expected = (np.abs(points[:, 2]) <= 0.5) & (np.linalg.norm(points, axis=1) <= 8.0)
    assert len(kept) == expected.sum()
    assert len(band_points(points, UP, max_points=50)) == 50
