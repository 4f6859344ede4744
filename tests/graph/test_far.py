"""Candidate poses from far sightings (graph.far): the two-bearing resection and the fit to many bearings."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.far import refined_by_bearings, resection_candidates
from macroloc.graph.rigid import apply, make_T, rot_z, rotation_angle_deg


def sigma_m(range_m):  # noqa: ANN001, ANN201 (the localizer's default: 0.03 + 0.004 r^2)
    return 0.03 + 0.004 * np.asarray(range_m) ** 2


FEATURES = np.array([[0.0, 0.0, 1.1], [12.0, 1.0, 1.1], [3.0, 9.0, 1.1], [14.0, 11.0, 1.6], [7.0, -4.0, 1.1],
                     [-6.0, 5.0, 1.1], [20.0, 4.0, 1.1], [9.0, 16.0, 1.1]])
CAMERA_CAD = np.array([4.0, 3.0, 1.4])


@settings(max_examples=30, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20), tz=st.floats(-3, 3),
       range_error=st.floats(-1.0, 1.0))
def test_the_true_pose_is_among_the_candidates_in_any_map_frame(yaw: float, tx: float, ty: float, tz: float,
                                                                range_error: float) -> None:
    """Two features seen from one camera, their ranges off by up to one sigma: one candidate is the true pose,
    to the bearings' precision where the ranges are exact and within the range error where they are not."""
    T_cad_map = make_T(rot_z(yaw), np.array([tx, ty, tz]))
    T_map_cad = np.linalg.inv(T_cad_map)
    a, b = FEATURES[1], FEATURES[3]  # 8.1 and 13.0 m away, 41 deg apart in bearing
    seen = []
    for f in (a, b):
        ray = f - CAMERA_CAD
        r = np.linalg.norm(ray[:2])
        seen.append(CAMERA_CAD + ray * (1 + range_error * sigma_m(r) / r))
    camera_map = apply(T_map_cad, CAMERA_CAD[None])[0]
    candidates = resection_candidates(camera_map, apply(T_map_cad, np.array(seen)), FEATURES, FEATURES, sigma_m,
                                      same_features=True)
    placed = np.einsum("hij,j->hi", candidates[:, :3, :3], camera_map) + candidates[:, :3, 3]  # the camera
    off_m = np.linalg.norm(placed - CAMERA_CAD, axis=1)
    k = int(np.argmin(off_m))
    assert off_m[k] <= (0.01 if range_error == 0 else 1.2 * abs(range_error) * float(sigma_m(13.0)) + 0.01)
    assert rotation_angle_deg(candidates[k][:3, :3] @ T_cad_map[:3, :3].T) < 3.0
    assert np.allclose(candidates[:, 2, :3], [0, 0, 1])  # levelled: a heading and a translation


def test_features_too_far_apart_for_the_measured_ranges_give_no_candidate() -> None:
    """Two sightings 8 and 13 m away, 41 deg apart, are ~8.6 m apart: a pair of features 30 m apart is none."""
    seen = np.array([FEATURES[1], FEATURES[3]])
    far_apart = np.array([[0.0, 0.0, 1.1], [30.0, 0.0, 1.1]])
    assert len(resection_candidates(CAMERA_CAD, seen, far_apart, far_apart, sigma_m, same_features=True)) == 0
    assert len(resection_candidates(CAMERA_CAD, seen, FEATURES, FEATURES, sigma_m, same_features=True)) > 0


def test_a_pair_at_another_height_difference_gives_no_candidate() -> None:
    """Seen 0.5 m apart in height (1.1 and 1.6 m), a pair of features on one level is not them."""
    seen = np.array([FEATURES[1], FEATURES[3]])
    level = FEATURES.copy()
    level[:, 2] = 1.1
    assert len(resection_candidates(CAMERA_CAD, seen, level, level, sigma_m, same_features=True,
                                    height_tolerance_m=0.2)) == 0


@settings(max_examples=20, deadline=None)
@given(dx=st.floats(-0.25, 0.25), dy=st.floats(-0.25, 0.25), dyaw_deg=st.floats(-1.0, 1.0), seed=st.integers(0, 99))
def test_the_bearings_of_several_keyframes_fit_a_coarse_pose(dx: float, dy: float, dyaw_deg: float,
                                                            seed: int) -> None:
    """Six keyframes along 3 m see four features 7-17 m away, bearings exact, ranges off by a sigma (normal): from
    a pose up to 0.35 m and 1 deg off (the resection's error; its sightings are taken within 3 deg), the fit to
    the bearings comes back within 3 of its own sigmas, which are under 0.1 m and 0.3 deg."""
    rng = np.random.default_rng(seed)
    T_cad_map = make_T(rot_z(0.3), np.array([1.0, -2.0, 0.2]))
    cameras_cad = np.array([[4.0 + 0.5 * k, 3.0, 1.4] for k in range(6)])
    cams, cents, kinds = [], [], []
    for c in cameras_cad:
        for f in FEATURES[[1, 2, 3, 6]]:
            ray = f - c
            r = np.linalg.norm(ray[:2])
            cams.append(c)
            cents.append(c + ray * (1 + rng.normal(0, float(sigma_m(r))) / r))
            kinds.append("door")
    T_map_cad = np.linalg.inv(T_cad_map)
    start = make_T(rot_z(np.radians(dyaw_deg)), np.array([dx, dy, 0.0])) @ T_cad_map
    T, sigmas = refined_by_bearings(start, apply(T_map_cad, np.array(cams)), apply(T_map_cad, np.array(cents)),
                                    np.array(kinds), {"door": FEATURES}, np.radians(0.5), sigma_m, np.radians(3.0))
    assert sigmas is not None and sigmas[0] < 0.1 and sigmas[1] < np.radians(0.3)
    placed = apply(T, apply(T_map_cad, cameras_cad))
    assert np.linalg.norm(placed[:, :2] - cameras_cad[:, :2], axis=1).max() < 3 * sigmas[0]
    assert rotation_angle_deg(T[:3, :3] @ T_cad_map[:3, :3].T) < np.degrees(3 * sigmas[1])


def test_too_few_bearings_leave_the_pose_as_it_is() -> None:
    T = make_T(rot_z(0.3), np.array([1.0, -2.0, 0.2]))
    out, sigmas = refined_by_bearings(T, CAMERA_CAD[None], FEATURES[1][None], np.array(["door"]),
                                      {"door": FEATURES}, np.radians(0.5), sigma_m, np.radians(3.0))
    assert sigmas is None and np.array_equal(out, T)


@settings(max_examples=30, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20),
       range_error=st.floats(-1.0, 1.0))
def test_two_far_doors_27_degrees_apart_resect_the_true_pose(yaw: float, tx: float, ty: float,
                                                             range_error: float) -> None:
    """Two doors 7.5 m and 13.1 m away and 27 deg apart in bearing (issue 38's flight), their ranges off by up
    to one sigma: the true pose is among the candidates."""
    bearing = np.radians([0.0, 27.0])
    ranges = np.array([7.5, 13.1])
    pair = CAMERA_CAD + np.column_stack([ranges * np.cos(bearing), ranges * np.sin(bearing), [-0.3, -0.3]])
    features = np.vstack([FEATURES, pair])
    T_cad_map = make_T(rot_z(yaw), np.array([tx, ty, 0.5]))
    T_map_cad = np.linalg.inv(T_cad_map)
    seen = [CAMERA_CAD + (f - CAMERA_CAD) * (1 + range_error * sigma_m(r) / r) for f, r in zip(pair, ranges,
                                                                                                  strict=True)]
    camera_map = apply(T_map_cad, CAMERA_CAD[None])[0]
    candidates = resection_candidates(camera_map, apply(T_map_cad, np.array(seen)), features, features, sigma_m,
                                      same_features=True)
    assert len(candidates)
    placed = np.einsum("hij,j->hi", candidates[:, :3, :3], camera_map) + candidates[:, :3, 3]
    off_m = np.linalg.norm(placed - CAMERA_CAD, axis=1)
    k = int(np.argmin(off_m))
    assert off_m[k] <= 1.2 * abs(range_error) * float(sigma_m(13.1)) + 0.02
    assert rotation_angle_deg(candidates[k][:3, :3] @ T_cad_map[:3, :3].T) < 3.0


def test_two_doors_close_together_far_away_leave_the_camera_metres_to_move() -> None:
    """Two doors 2 m apart 10 m away (11 deg apart) pin the camera to a circle, their ranges (0.4 m sigma) to
    metres of it; two doors 14 m apart, 61 deg apart in bearing, to a place."""
    from macroloc.graph.far import resection_spread_m
    from macroloc.graph.params import LandmarkParams

    sigma = LandmarkParams().position_sigma_m
    camera = np.array([0.0, 0.0, 1.4])
    narrow = np.array([[10.0, -1.0, 1.05], [10.0, 1.0, 1.05]])
    wide = np.array([[7.7 * np.cos(0.3), 7.7 * np.sin(0.3), 1.05],
                     [15.8 * np.cos(0.3 - 1.066), 15.8 * np.sin(0.3 - 1.066), 1.05]])
    assert resection_spread_m(camera, narrow, sigma) > 2.0
    assert resection_spread_m(camera, wide, sigma) < 1.0
