"""graph.landmark_map: sightings into landmarks (association by distance and facing, the type by majority; range;
one sighting of a landmark per frame; one factor per landmark per keyframe), the sighting factors' sigmas, and the
landmarks as the registrar takes them."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from macroloc.graph.landmark_map import LandmarkMap
from macroloc.graph.params import LandmarkParams
from macroloc.graph.posegraph import L, PoseGraph
from macroloc.graph.sightings import Sighting
from tests.graph.scenes import door, make_T, rot_z

UP = np.array([0.0, 0.0, 1.0])
VIEWER_BODY = np.array([0.5, 0.0, 0.0])  # the camera half a metre ahead of the body origin
PARAMS = LandmarkParams()  # associate_m 0.6, max_range_m 7, far_range_m 20


def _sighting(x: float, y: float = 0.0, normal_xy: tuple[float, float] = (-1.0, 0.0), kind: str = "door",
              truncated: tuple[bool, bool] = (False, False)) -> Sighting:
    """A 0.9 x 2.1 m opening centred at (x, y) on the floor of the body frame (the body at the map's origin)."""
    return Sighting(kind, door("D", (x, y), normal_xy, kind=kind).corners_cad, truncated=truncated)


def _map() -> tuple[LandmarkMap, PoseGraph]:
    graph = PoseGraph(record_batch=True)
    graph.add_first_keyframe(np.eye(4))
    return LandmarkMap(PARAMS, graph, VIEWER_BODY), graph


def _sighting_factors(graph: PoseGraph, j: int) -> list[gtsam.BetweenFactorPose3]:
    factors, _ = graph.batch_graph()
    return [f for f in (factors.at(k) for k in range(factors.size())) if L(j) in tuple(f.keys())]  # gtsam keys


@pytest.mark.parametrize(("shift_m", "same"), [(0.4, True), (0.55, True), (0.65, False), (1.0, False)])
def test_a_sighting_within_associate_m_re_observes_the_landmark(shift_m: float, same: bool) -> None:
    """A second sighting of the same type within `associate_m` of a landmark re-observes it; farther, it starts a
    new landmark."""
    lmap, _ = _map()
    _, reobserved = lmap.add_frames(0, np.eye(4), [[_sighting(3.0)], [_sighting(3.0, shift_m)]], UP)
    assert len(lmap.landmarks) == (1 if same else 2)
    assert lmap.landmarks[0].n_sightings == (2 if same else 1)
    assert reobserved == ({0} if same else set())


def test_a_sighting_re_observes_the_nearest_landmark() -> None:
    """Of two same-type landmarks within `associate_m`, the sighting re-observes the nearer."""
    for y_m, nearer in ((0.25, 0), (0.45, 1)):
        lmap, _ = _map()
        lmap.add_frames(0, np.eye(4), [[_sighting(3.0, 0.0), _sighting(3.0, 0.7)]], UP)
        _, reobserved = lmap.add_frames(0, np.eye(4), [[_sighting(3.0, y_m)]], UP)
        assert reobserved == {nearer} and lmap.landmarks[nearer].n_sightings == 2


def test_a_sighting_called_another_type_at_the_same_place_is_the_same_opening() -> None:
    """Association ignores the type the detector called: a window where a door landmark stands re-observes it (a
    detector calls one opening a door in some frames, a window in others), and the landmark's type is the one most
    of its sightings were called (the first on a tie)."""
    lmap, _ = _map()
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0)], [_sighting(3.0, kind="window")]], UP)
    assert [(lm.type, lm.n_sightings) for lm in lmap.landmarks.values()] == [("door", 2)]
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0, kind="window")]], UP)
    assert [lm.type for lm in lmap.landmarks.values()] == ["window"]


def test_association_needs_the_same_facing_either_side() -> None:
    """A sighting at a landmark re-observes it where their normals are alike up to sign: a door seen from its other
    side is the same landmark, its factor turned to the landmark's frame; turned a quarter-turn, it is another."""
    lmap, graph = _map()
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0)]], UP)
    T_map_behind = make_T(rot_z(np.pi), np.array([6.0 + VIEWER_BODY[0], 0.0, 0.0]))  # the door's other side
    graph.add_keyframe(T_map_behind, np.full(6, 0.01), T_map_behind)
    _, reobserved = lmap.add_frames(1, T_map_behind, [[_sighting(3.0 + VIEWER_BODY[0])]], UP)
    assert reobserved == {0} and len(lmap.landmarks) == 1
    measured = [f.measured().matrix() for f in _sighting_factors(graph, 0)]
    assert np.allclose(measured[1], np.linalg.inv(T_map_behind) @ graph.T_map_rect(0), atol=1e-9)
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0, normal_xy=(0.0, 1.0))]], UP)
    assert len(lmap.landmarks) == 2


@pytest.mark.parametrize(("camera_range_m", "landmark", "far"), [(6.9, True, False), (7.1, False, True),
                                                                 (19.9, False, True), (20.1, False, False)])
def test_range_from_the_camera_decides_landmark_far_or_nothing(camera_range_m: float, landmark: bool,
                                                               far: bool) -> None:
    """Within `max_range_m` of the camera a sighting is a landmark; beyond it, up to `far_range_m`, it is handed
    back as a far sighting; farther still it is dropped."""
    lmap, _ = _map()
    s = _sighting(VIEWER_BODY[0] + camera_range_m)
    far_sightings, _ = lmap.add_frames(0, np.eye(4), [[s]], UP)
    assert (len(lmap.landmarks) == 1) == landmark
    assert far_sightings == ([s] if far else [])


def test_a_frame_sees_a_landmark_once() -> None:
    """A second detection of a landmark in the same frame is dropped (counted in `duplicates`); in the next frame
    carried into the same keyframe it is a sighting."""
    lmap, graph = _map()
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0), _sighting(3.0, 0.1)]], UP)
    assert lmap.landmarks[0].n_sightings == 1 and lmap.duplicates == 1 and len(_sighting_factors(graph, 0)) == 1
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0, 0.1)]], UP)
    assert lmap.landmarks[0].n_sightings == 2 and lmap.duplicates == 1 and len(_sighting_factors(graph, 0)) == 2


def test_a_rectangle_not_upright_is_no_sighting() -> None:
    """Only upright rectangles (wall openings) are taken: one lying flat makes neither a landmark nor a far
    sighting."""
    lmap, _ = _map()
    flat = _sighting(3.0).corners_body[:, [2, 1, 0]]  # the opening turned level, 3 m up: a skylight
    far, _ = lmap.add_frames(0, np.eye(4), [[Sighting("door", flat)]], UP)
    assert lmap.landmarks == {} and far == []


def test_a_cut_side_loosens_the_sighting_along_it() -> None:
    """A sighting cut by the image border sideways is held along the wall by `truncated_sigma_m` only; one cut
    vertically, in height; the other axes keep the range's sigma."""
    lmap, graph = _map()
    lmap.add_frames(0, np.eye(4), [[_sighting(3.0, truncated=(True, False)),
                                    _sighting(3.0, 3.0, truncated=(False, True))]], UP)
    range_m = float(np.linalg.norm([3.0 - VIEWER_BODY[0], 0.0, 1.05]))
    sigma_m = PARAMS.position_sigma_m(range_m)
    assert np.allclose(_sighting_factors(graph, 0)[0].noiseModel().sigmas()[3:],
                       [PARAMS.truncated_sigma_m, sigma_m, sigma_m])
    sigmas = _sighting_factors(graph, 1)[0].noiseModel().sigmas()[3:]
    assert sigmas[0] < PARAMS.truncated_sigma_m and sigmas[2] == PARAMS.truncated_sigma_m


def test_observed_gives_the_landmarks_frames_and_corners_in_the_map() -> None:
    """`observed` returns each landmark's key, type and current frame, and its rectangle (4, 3) of its measured size
    about that frame, in the map frame; `confirmed` the keys seen from enough keyframes (two frames carried into
    one keyframe are one)."""
    lmap, graph = _map()
    T_map_body = np.eye(4)
    T_map_body[:3, 3] = [1.0, 2.0, 0.0]
    lmap.add_frames(0, T_map_body, [[_sighting(3.0), _sighting(2.0, 3.0, kind="window")], [_sighting(3.0)]], UP)
    assert lmap.confirmed(2) == [] and lmap.confirmed(1) == [0, 1] and lmap.landmarks[0].n_sightings == 2
    graph.add_keyframe(np.eye(4), np.full(6, 0.01), T_map_body)
    lmap.add_frames(1, T_map_body, [[_sighting(3.0)]], UP)
    assert lmap.confirmed(2) == [0] and lmap.confirmed(1) == [0, 1]
    observed, corners = lmap.observed([1, 0])
    assert [(o.key, o.type) for o in observed] == [(1, "window"), (0, "door")]
    assert all(np.array_equal(o.T_map_rect, graph.T_map_rect(o.key)) for o in observed)
    truth = door("D", (4.0, 2.0), (-1.0, 0.0)).corners_cad
    assert sorted(map(tuple, np.round(corners[1], 6))) == sorted(map(tuple, np.round(truth, 6)))


def test_the_frames_of_one_keyframe_add_one_factor_per_landmark_at_their_mean() -> None:
    """Three frames carried into one keyframe see a door 4 cm apart: one factor, at the mean of the three, with
    one sighting's sigmas (their errors are shared: module doc); each frame still counts as a sighting of it (its
    size). With `one_factor_per_keyframe` off, a factor per frame."""
    frames = [[_sighting(3.0, y)] for y in (-0.04, 0.0, 0.04)]
    lmap, graph = _map()
    lmap.add_frames(0, np.eye(4), frames, UP)
    (factor,) = _sighting_factors(graph, 0)
    assert lmap.landmarks[0].n_sightings == 3
    one, _ = _map()
    one.add_frames(0, np.eye(4), frames[1:2], UP)
    (middle,) = _sighting_factors(one.graph, 0)
    assert np.allclose(factor.measured().matrix(), middle.measured().matrix(), atol=1e-9)
    assert np.allclose(factor.noiseModel().sigmas(), middle.noiseModel().sigmas(), rtol=1e-3)  # ranges alike
    each = LandmarkMap(replace(PARAMS, one_factor_per_keyframe=False), graph := PoseGraph(record_batch=True),
                       VIEWER_BODY)
    graph.add_first_keyframe(np.eye(4))
    each.add_frames(0, np.eye(4), frames, UP)
    assert len(_sighting_factors(graph, 0)) == 3
