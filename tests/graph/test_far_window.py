"""The far sightings' window (graph.far_window): kept in the body frames, used in the map frame, checking and
resecting poses in any map frame."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.far_window import FarSightings
from macroloc.graph.features import BuildingModel, CentroidsByType, MacroFeature
from macroloc.graph.params import DepthWindowParams, FarParams, LandmarkParams
from macroloc.graph.rigid import apply, make_T, rot_z, rotation_angle_deg

DOORS_CAD = np.array([[0.0, 0.0, 1.05], [12.0, 1.0, 1.05], [3.0, 14.0, 1.05], [14.0, 11.0, 1.05],
                      [-9.0, 6.0, 1.05], [20.0, -4.0, 1.05]])
VIEWER_BODY = np.array([0.1, 0.0, 0.0])  # the camera 0.1 m ahead of the body's origin


def model() -> BuildingModel:
    features = []
    for k, c in enumerate(DOORS_CAD):
        corners = c + np.array([[-0.5, 0, -1.05], [0.5, 0, -1.05], [0.5, 0, 1.05], [-0.5, 0, 1.05]])
        features.append(MacroFeature(id=f"D{k}", type="door", storey="L1", corners_cad=corners, centroid_cad=c,
                                     normal_cad=np.array([0.0, 1.0, 0.0]), width_m=1.0, height_m=2.1))
    return BuildingModel("synthetic", "0" * 64, features)


def window(T_cad_map: np.ndarray, T_map_bodies: list[np.ndarray], seen: list[list[int]],
           params: FarParams | None = None) -> FarSightings:
    """A window whose keyframe k (at T_map_bodies[k]) saw the doors `seen[k]`, exactly."""
    far = FarSightings(params or FarParams(far_min_sightings=3), DepthWindowParams().surface_window_keyframes,
                       LandmarkParams().position_sigma_m, VIEWER_BODY, CentroidsByType(model().features),
                       lambda i: T_map_bodies[i])
    for i, (T_map_body, doors) in enumerate(zip(T_map_bodies, seen, strict=True)):
        T_body_cad = np.linalg.inv(T_cad_map @ T_map_body)
        far.add(i, ["door"] * len(doors), apply(T_body_cad, DOORS_CAD[doors]))
    return far


def flight(yaw: float, tx: float, ty: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """T_cad_map, and three keyframes' T_map_body 0.5 m apart near (4, 3) in the CAD frame, level."""
    T_cad_map = make_T(rot_z(yaw), np.array([tx, ty, -0.3]))
    bodies_cad = [make_T(rot_z(0.4 + 0.1 * k), np.array([4.0 + 0.5 * k, 3.0, 1.4])) for k in range(3)]
    return T_cad_map, [np.linalg.inv(T_cad_map) @ T for T in bodies_cad]


def test_the_window_holds_its_sightings_in_the_map_frame_and_counts_them() -> None:
    T_cad_map, T_map_bodies = flight(0.7, 3.0, -2.0)
    far = window(T_cad_map, T_map_bodies, [[1, 3], [1], [3, 5]])
    assert len(far) == 5
    far_map = far.in_map()
    assert far_map is not None
    kinds, cameras, centroids = far_map
    assert list(kinds) == ["door"] * 5
    assert np.allclose(apply(T_cad_map, centroids), DOORS_CAD[[1, 3, 1, 3, 5]])
    assert np.allclose(cameras[0], apply(T_map_bodies[0], VIEWER_BODY[None])[0])
    assert window(T_cad_map, T_map_bodies, [[1], [], [3]]).in_map() is None  # fewer than far_min_sightings


def test_a_pair_counts_only_where_its_bearings_are_far_enough_apart() -> None:
    T_cad_map, T_map_bodies = flight(0.0, 0.0, 0.0)
    far = window(T_cad_map, T_map_bodies, [[1, 3], [1], [0, 4]])
    pairs = far.pairs()
    assert [kinds for _, kinds, _ in pairs] == [("door", "door")] * 2  # keyframes 0 and 2; 1 saw one door
    apart = window(T_cad_map, T_map_bodies, [[1, 3], [], []], FarParams(far_pair_min_deg=60.0)).pairs()
    assert apart == []  # doors 1 and 3 are 53 deg apart from (4, 3)


def test_where_no_keyframe_saw_a_pair_one_pairs_across_keyframes() -> None:
    """Each keyframe saw one far door: keyframe 1's door pairs with another keyframe's (two need not be in view
    at once); where a keyframe saw a pair itself, only such pairs are taken (no odometry drift between them)."""
    T_cad_map, T_map_bodies = flight(0.0, 0.0, 0.0)
    pairs = window(T_cad_map, T_map_bodies, [[1], [3], [0]]).pairs()
    assert len(pairs) == 3
    door_3_map = apply(np.linalg.inv(T_cad_map), DOORS_CAD[3][None])[0]
    assert np.any(np.linalg.norm(pairs[1][2] - door_3_map, axis=1) < 1e-9)
    assert not np.allclose(pairs[1][2][0], pairs[1][2][1])
    own = window(T_cad_map, T_map_bodies, [[1, 3], [3], [0]]).pairs()
    assert len(own) == 1  # keyframe 0 saw doors 1 and 3 itself, 53 deg apart


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20))
def test_the_true_pose_explains_every_far_sighting_and_a_turned_one_fewer(yaw: float, tx: float, ty: float) -> None:
    T_cad_map, T_map_bodies = flight(yaw, tx, ty)
    far = window(T_cad_map, T_map_bodies, [[1, 3], [1, 2], [3, 5]])
    far_map = far.in_map()
    assert far_map is not None
    assert far.explained(T_cad_map, far_map, T_map_bodies[-1]) == 1.0
    camera_cad = apply(T_cad_map @ T_map_bodies[-1], VIEWER_BODY[None])[0]
    R = rot_z(np.radians(10.0))  # beyond the 3 deg bearing tolerance and the 2 deg turn
    assert far.explained(make_T(R, camera_cad - R @ camera_cad) @ T_cad_map, far_map, T_map_bodies[-1]) < 1.0


@settings(max_examples=15, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20))
def test_two_far_doors_seen_from_one_keyframe_resect_the_pose(yaw: float, tx: float, ty: float) -> None:
    """Exact sightings of doors 1 and 3 from each keyframe: the true pose is among the resection's places."""
    T_cad_map, T_map_bodies = flight(yaw, tx, ty)
    far = window(T_cad_map, T_map_bodies, [[1, 3], [1, 3], [1, 3]])
    result = far.resected(far.in_map())
    assert result.status == "ambiguous" and result.T_cad_map is None  # the walls choose, not the resection
    off = [(np.linalg.norm(T[:3, 3] - T_cad_map[:3, 3]), rotation_angle_deg(T[:3, :3] @ T_cad_map[:3, :3].T))
           for T, _ in result.candidates]
    assert min(m + d for m, d in off) < 0.05


@settings(max_examples=15, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20))
def test_two_far_doors_seen_from_different_keyframes_resect_the_pose(yaw: float, tx: float, ty: float) -> None:
    """Door 1 seen by keyframes 0 and 1, door 3 by keyframe 2 only (never both in one view): the true pose is
    among the resection's places."""
    T_cad_map, T_map_bodies = flight(yaw, tx, ty)
    far = window(T_cad_map, T_map_bodies, [[1], [1], [3]])
    result = far.resected(far.in_map())
    assert result.status == "ambiguous" and result.candidates
    off = [(np.linalg.norm(T[:3, 3] - T_cad_map[:3, 3]), rotation_angle_deg(T[:3, :3] @ T_cad_map[:3, :3].T))
           for T, _ in result.candidates]
    assert min(m + d for m, d in off) < 0.05


def test_a_pair_that_leaves_the_camera_metres_to_move_resects_nothing() -> None:
    """Doors 2 m apart 10 m away, seen exactly: the one pose per pair of CAD doors that their ranges would give
    is a sample of a metres-long arc, so none is offered for the walls to choose among."""
    doors = np.array([[14.0, 2.0, 1.05], [14.0, 4.0, 1.05], [-6.0, -9.0, 1.05]])
    features = [MacroFeature(f"N{k}", "door", "L1", c + np.array([[-0.5, 0, -1.05], [0.5, 0, -1.05], [0.5, 0, 1.05],
                                                                  [-0.5, 0, 1.05]]), c, np.array([1.0, 0.0, 0.0]),
                             1.0, 2.1) for k, c in enumerate(doors)]
    T_map_body = make_T(np.eye(3), np.array([4.0, 3.0, 1.4]))  # map = CAD
    far = FarSightings(FarParams(far_min_sightings=3), 3, LandmarkParams().position_sigma_m, VIEWER_BODY,
                       CentroidsByType(features), lambda i: T_map_body)
    for i in range(3):
        far.add(i, ["door", "door"], apply(np.linalg.inv(T_map_body), doors[:2]))
    assert far.pairs()  # the bearings are 11 deg apart: a pair ...
    assert far.resected(far.in_map()).status == "not_localized"  # ... that resects nothing
