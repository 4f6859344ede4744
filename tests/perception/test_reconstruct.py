import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.perception.lines import Sides
from macroloc.perception.reconstruct import (
    Reconstruction,
    check_plausible,
    closest_point_to_ray,
    corners_on_plane,
    fit_line_robust,
    measure,
    reconstruct_sides,
    wall_plane,
)
from macroloc.perception.stereo import back_project
from tests.perception.helpers import RIG

unit = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 0.2)


@settings(max_examples=80, deadline=None)
@given(st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(1, 8)), unit, st.integers(0, 2**31 - 1))
def test_line_fit_recovers_a_line_through_noise_and_outliers(point, direction, seed):
    rng = np.random.default_rng(seed)
    d = np.asarray(direction) / np.linalg.norm(direction)
    t = rng.uniform(-1.0, 1.0, 40)
    pts = np.asarray(point) + t[:, None] * d + rng.normal(0, 0.005, (40, 3))
    bad = rng.choice(40, 8, replace=False)  # 20 % gross outliers, 0.3-1 m off the line
    off = rng.normal(size=(8, 3))
    off -= np.outer(off @ d, d)
    pts[bad] += off / np.linalg.norm(off, axis=1, keepdims=True) * rng.uniform(0.3, 1.0, (8, 1))
    line = fit_line_robust(pts)
    assert line is not None
    assert abs(line.direction @ d) > np.cos(np.radians(1.5))
    assert not line.inliers[bad].any()
    assert line.distances_m(np.asarray(point)[None])[0] < 0.02


@pytest.mark.xfail(strict=True, reason="known defect (2026-12-07): gross outliers at both ends of a short side pull "
                   "the paper's first TLS fit 20 deg off, and the MAD cut then admits them; found by hypothesis, rare "
                   "(0 of 20,000 random draws), left because changing the line fit moves every perception figure")
def test_line_fit_outliers_at_both_ends_of_a_vertical_side() -> None:
    """The counterexample hypothesis found for the property above (point (0, 0, 1), direction z, seed 128969252):
    3 of the 8 outliers sit at the segment's ends (t = -1.0, 0.94, 0.96 of [-1, 1]), 0.80-0.96 m off the line."""
    test_line_fit_recovers_a_line_through_noise_and_outliers.hypothesis.inner_test((0.0, 0.0, 1.0), (0.0, 0.0, 1.0),
                                                                                   128969252)


def test_closest_point_to_ray():
    from macroloc.perception.reconstruct import Line3D

    line = Line3D(np.array([1.0, 0.0, 5.0]), np.array([0.0, 1.0, 0.0]), np.ones(1, bool))
    ray = np.array([1.0, -1.0, 5.0]) / np.linalg.norm([1.0, -1.0, 5.0])
    assert np.allclose(closest_point_to_ray(line, ray), [1.0, -1.0, 5.0])


def _depth_of_plane(n_cam: np.ndarray, offset_m: float) -> np.ndarray:
    """Depth image (m) of the plane n . X = offset seen by the rig."""
    v, u = np.mgrid[0:RIG.height_px, 0:RIG.width_px].astype(np.float64)
    rays = np.stack([(u - RIG.cx_px) / RIG.fx_px, (v - RIG.cy_px) / RIG.fy_px, np.ones_like(u)], -1)
    return (offset_m / (rays @ n_cam)).astype(np.float32)


@pytest.mark.parametrize("yaw_deg", [0.0, 35.0])
def test_corners_of_a_door_on_a_wall(yaw_deg):
    yaw = np.radians(yaw_deg)
    normal = np.array([np.sin(yaw), 0.0, -np.cos(yaw)])  # wall facing the camera, turned about the vertical
    centre = np.array([0.2, 0.1, 4.0])
    depth = _depth_of_plane(normal, normal @ centre)
    along = np.array([np.cos(yaw), 0.0, np.sin(yaw)])
    up = np.array([0.0, -1.0, 0.0])
    corners = np.stack([centre - 0.45 * along + 1.0 * up, centre + 0.45 * along + 1.0 * up,
                        centre + 0.45 * along - 1.0 * up, centre - 0.45 * along - 1.0 * up])  # TL TR BR BL
    px = corners[:, :2] / corners[:, 2:] * RIG.fx_px + [RIG.cx_px, RIG.cy_px]
    depth[RIG.height_px // 2, :] = np.nan  # a row without stereo
    sides = Sides(np.stack([px[0], px[3]]), np.stack([px[1], px[2]]), (True, True))
    result = reconstruct_sides(sides, depth, RIG)
    assert not isinstance(result, str), result
    corners_cam, _ = result
    # depth is read 4-12 px inside each side: on an oblique wall that costs ~z tan(yaw) / f * 8 px (5 cm here)
    tol = 0.02 + 4.0 * np.tan(yaw) / RIG.fx_px * 8
    assert np.abs(corners_cam - corners).max() < tol
    rec = measure(corners_cam, None)
    assert rec.width_m == pytest.approx(0.9, abs=tol) and rec.height_m == pytest.approx(2.0, abs=tol)
    assert rec.tilt_deg < 1.0


def _rec(width, height, tilt_deg=0.0, z=4.0):
    t = np.radians(tilt_deg)
    down = np.array([np.sin(t), np.cos(t), 0.0]) * height
    tl, tr = np.array([0, 0, z]), np.array([width, 0, z])
    return measure(np.stack([tl, tr, tr + down, tl + down]).astype(float), None)


def test_plausibility_checks():
    assert check_plausible("door", _rec(0.9, 2.1), (np.array([0, 1, 0]),) * 2, False) is None
    assert "width" in check_plausible("door", _rec(3.5, 2.1), (np.array([0, 1, 0]),) * 2, False)
    assert "height" in check_plausible("door", _rec(0.9, 0.6), (np.array([0, 1, 0]),) * 2, False)
    assert "depth" in check_plausible("door", _rec(0.9, 2.1, z=20.0), (np.array([0, 1, 0]),) * 2, False)
    assert "vertical" in check_plausible("window", _rec(1.0, 1.0, tilt_deg=40), (np.array([0, 1, 0]),) * 2, False)
    rec: Reconstruction = _rec(0.9, 2.1, tilt_deg=20)
    assert check_plausible("door", rec, (np.array([0, 1, 0]),) * 2, gravity_known=False) is None
    assert "vertical" in check_plausible("door", rec, (np.array([0, 1, 0]),) * 2, gravity_known=True)
    skew = (np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.5]))
    assert "parallel" in check_plausible("door", _rec(0.9, 2.1), skew, False)


def test_missing_depth_is_reported_not_guessed():
    depth = np.full((RIG.height_px, RIG.width_px), np.nan, np.float32)
    sides = Sides(np.array([[100.0, 100], [100, 300]]), np.array([[200.0, 100], [200, 300]]), (True, True))
    assert "too few points" in reconstruct_sides(sides, depth, RIG)


def test_back_projected_side_points_lie_on_the_fitted_line():
    pts = back_project(np.array([[100.0, 50 + 5 * i] for i in range(20)]), np.full(20, 3.0), RIG)
    line = fit_line_robust(pts)
    assert line is not None and np.allclose(line.distances_m(pts), 0, atol=1e-9)


def _doorway_on_a_wall(yaw_deg: float, centre: np.ndarray, behind_m: float, noise_m: float, seed: int
                       ) -> tuple[np.ndarray, Sides, np.ndarray, np.ndarray]:
    """A wall turned `yaw_deg` about the vertical with a 0.9 x 2.0 m open doorway centred at `centre` (camera
    frame), through which the camera sees a room `behind_m` deeper: the depth image (with stereo-like noise
    growing with depth squared, and 5 % of the pixels without depth), the doorway's sides, its corners (TL TR
    BR BL) and the wall's unit normal."""
    rng = np.random.default_rng(seed)
    yaw = np.radians(yaw_deg)
    normal = np.array([np.sin(yaw), 0.0, -np.cos(yaw)])
    depth = _depth_of_plane(normal, normal @ centre).astype(np.float64)
    along, up = np.array([np.cos(yaw), 0.0, np.sin(yaw)]), np.array([0.0, -1.0, 0.0])
    corners = np.stack([centre - 0.45 * along + 1.0 * up, centre + 0.45 * along + 1.0 * up,
                        centre + 0.45 * along - 1.0 * up, centre - 0.45 * along - 1.0 * up])  # TL TR BR BL
    px = corners[:, :2] / corners[:, 2:] * RIG.fx_px + [RIG.cx_px, RIG.cy_px]
    inside = np.zeros(depth.shape, np.uint8)  # the doorway's outline in the image (a trapezoid seen obliquely)
    cv2.fillConvexPoly(inside, np.rint(px).astype(np.int32), 1)
    depth[inside.astype(bool)] += behind_m  # through the doorway
    depth += rng.normal(0.0, noise_m, depth.shape) * depth**2
    depth[rng.random(depth.shape) < 0.05] = np.nan
    sides = Sides(np.stack([px[0], px[3]]), np.stack([px[1], px[2]]), (True, True))
    return depth.astype(np.float32), sides, corners, normal


@settings(max_examples=40, deadline=None)
@given(st.floats(-50, 50), st.floats(-0.6, 0.6), st.floats(2.5, 6.5), st.floats(0.0, 0.004), st.integers(0, 2**31 - 1))
def test_a_doorway_s_corners_lie_on_its_wall_not_in_the_room_behind(yaw_deg, x_m, z_m, noise_m, seed):
    """Seen through an open doorway, the room behind is metres deeper than the door; the wall beside it holds the
    door's plane, and the corners on that plane are where the doorway is, at any angle and range."""
    depth, sides, corners, normal = _doorway_on_a_wall(yaw_deg, np.array([x_m, 0.1, z_m]), 3.0, noise_m, seed)
    plane = wall_plane(sides, depth, RIG, gravity_cam=np.array([0.0, 1.0, 0.0]))
    assert plane is not None
    n, d = plane
    assert abs(n @ normal) > np.cos(np.radians(2.0 + 400 * noise_m * z_m))  # a few degrees at 6 m with noise
    found = corners_on_plane(sides, plane, RIG)
    assert found is not None
    assert np.abs(found - corners).max() < 0.03 + 3.0 * noise_m * z_m**2


def test_the_sides_own_depth_would_put_that_doorway_in_the_room_behind():
    """Why the wall: the sides' depth, read inside the opening, is the room's (the doorway 1.3 m too deep)."""
    depth, sides, corners, _ = _doorway_on_a_wall(25.0, np.array([0.2, 0.1, 4.0]), 3.0, 0.0, 0)
    fitted = reconstruct_sides(sides, depth, RIG)
    assert not isinstance(fitted, str)
    assert np.abs(fitted[0] - corners).max() > 1.0
    plane = wall_plane(sides, depth, RIG)
    assert plane is not None
    found = corners_on_plane(sides, plane, RIG)
    assert found is not None and np.abs(found - corners).max() < 0.02


def test_no_wall_beside_an_opening_gives_no_plane():
    """With depth only inside the opening (nothing beside it: a glass front, the image's border), there is no
    wall to read; so is a strip that is not a wall (a tilted plane, with gravity known)."""
    depth, sides, _, _ = _doorway_on_a_wall(0.0, np.array([0.0, 0.1, 4.0]), 3.0, 0.0, 0)
    (tl, bl), (tr, _) = sides.left_px, sides.right_px
    inside = np.full_like(depth, np.nan)
    u0, u1, v0, v1 = int(tl[0]) + 2, int(tr[0]) - 2, int(tl[1]) + 2, int(bl[1]) - 2
    inside[v0:v1, u0:u1] = depth[v0:v1, u0:u1]
    assert wall_plane(sides, inside, RIG) is None
    tilted = _depth_of_plane(np.array([0.0, -np.sin(0.5), -np.cos(0.5)]), -4.0)  # a floor-like slope, 29 deg
    assert wall_plane(sides, tilted, RIG, gravity_cam=np.array([0.0, 1.0, 0.0])) is None
    assert wall_plane(sides, tilted, RIG) is not None


def test_a_ray_grazing_the_plane_gives_no_corners():
    sides = Sides(np.array([[100.0, 100], [100, 300]]), np.array([[200.0, 100], [200, 300]]), (True, True))
    assert corners_on_plane(sides, (np.array([0.0, 0.0, -1.0]), -4.0), RIG) is not None
    ahead = Sides(np.array([[310.0, 100], [310, 300]]), np.array([[330.0, 100], [330, 300]]), (True, True))
    assert corners_on_plane(ahead, (np.array([1.0, 0.0, 0.0]), -4.0), RIG) is None  # a wall along the view
    assert corners_on_plane(sides, (np.array([0.0, 0.0, 1.0]), -4.0), RIG) is None  # behind the camera
