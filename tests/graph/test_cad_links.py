"""graph.cad_links: landmarks linked to the model's features once the map is anchored (by type and distance, one
landmark per feature), by their orientation too only within `cad_link_max_turn_deg`, and the links' sightings."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from macroloc.graph.cad_links import CadLinks
from macroloc.graph.features import MacroFeature
from macroloc.graph.landmarks import FLIP_ABOUT_UP, feature_frame_cad
from macroloc.graph.params import AnchorParams
from macroloc.graph.posegraph import ANCHOR, CAD_LINK_POSITION_SIGMAS, CAD_LINK_SIGMAS, L, PoseGraph
from macroloc.graph.sightings import Landmark
from tests.graph.scenes import door, make_T, rot_z

PARAMS = AnchorParams()  # cad_link_m 0.5, cad_link_max_turn_deg 8
NEAR_D1 = [door("D1", (3.0, 1.5), (0.0, -1.0)), door("D3", (3.5, 1.5), (0.0, -1.0))]  # two doors 0.5 m apart
FEATURES = [door("D1", (3.0, 1.5), (0.0, -1.0)), door("D2", (6.0, 1.5), (0.0, -1.0)),
            door("W1", (3.0, -1.5), (0.0, 1.0), kind="window", bottom=0.9, height=1.2)]
STAMP_NS = 5_000_000_000


def _frame(fid: str, shift: tuple[float, float, float] = (0.0, 0.0, 0.0), turn_deg: float = 0.0) -> np.ndarray:
    """Feature `fid`'s frame moved by `shift` (m) and turned by `turn_deg` about its vertical axis."""
    T = feature_frame_cad(next(f for f in FEATURES if f.id == fid))
    T = T @ make_T(rot_z(np.radians(turn_deg)), np.zeros(3))
    T[:3, 3] += shift
    return T


def _anchored(frames: list[tuple[str, np.ndarray]], features: list[MacroFeature] = FEATURES
              ) -> tuple[CadLinks, PoseGraph, dict[int, Landmark]]:
    """A graph anchored with the map on the model (T_cad_map = I), one keyframe seeing the landmarks (type,
    T_map_rect), and their links (none yet)."""
    graph = PoseGraph(record_batch=True)
    graph.add_first_keyframe(np.eye(4))
    landmarks = {}
    for j, (kind, T_map_rect) in enumerate(frames):
        graph.add_landmark(j, T_map_rect)
        graph.add_sighting(0, j, T_map_rect)
        corners = door("x", (0.0, 0.0), (0.0, 1.0)).corners_cad
        landmarks[j] = Landmark.first_seen(j, kind, corners, (False, False))
    graph.add_anchor(np.eye(4))
    graph.update()
    return CadLinks(PARAMS, graph, {f.id: f for f in features}), graph, landmarks


def _link_factor(graph: PoseGraph, j: int) -> gtsam.BetweenFactorPose3:
    factors, _ = graph.batch_graph()
    links = [f for f in (factors.at(k) for k in range(factors.size())) if list(f.keys()) == [ANCHOR, L(j)]]
    assert len(links) == 1
    return links[0]


@pytest.mark.parametrize(("shift_m", "linked"), [(0.45, True), (0.55, False)])
def test_a_landmark_within_cad_link_m_of_a_same_type_feature_is_linked(shift_m: float, linked: bool) -> None:
    """A landmark within `cad_link_m` of a same-type feature is linked to it (and the model counts as seen then);
    farther away, it is not."""
    links, _, landmarks = _anchored([("door", _frame("D1", (shift_m, 0.0, 0.0)))])
    links.link_new(landmarks, STAMP_NS)
    assert links.links == ({0: "D1"} if linked else {})
    assert links.last_link_ns == (STAMP_NS if linked else None)


def test_a_landmark_at_a_feature_of_another_type_is_not_linked() -> None:
    """Only a feature of the landmark's type is linked: a door landmark at a window stays unlinked."""
    links, _, landmarks = _anchored([("door", _frame("W1"))])
    links.link_new(landmarks, STAMP_NS)
    assert links.links == {}


def test_the_nearest_feature_within_reach_is_linked() -> None:
    """Of two same-type features within `cad_link_m`, the landmark is linked to the nearer."""
    for shift_m, fid in ((0.2, "D1"), (0.4, "D3")):
        links, _, landmarks = _anchored([("door", _frame("D1", (shift_m, 0.0, 0.0)))], NEAR_D1)
        links.link_new(landmarks, STAMP_NS)
        assert links.links == {0: fid}


def test_a_feature_is_linked_to_one_landmark_only() -> None:
    """A feature another landmark is linked to is not linked again: of two landmarks at one feature the first (by
    key) takes it and the second stays unlinked, even where the second is the nearer; a feature linked before
    (by a registration's match) is taken too."""
    links, _, landmarks = _anchored([("door", _frame("D1", (0.3, 0.0, 0.0))), ("door", _frame("D1"))])
    links.link_new(landmarks, STAMP_NS)
    assert links.links == {0: "D1"}
    links, _, landmarks = _anchored([("door", _frame("D1")), ("door", _frame("D1", (0.1, 0.0, 0.0)))])
    links.link(0, "D1", np.eye(4))
    links.link_new(landmarks, STAMP_NS)
    assert links.links == {0: "D1"} and links.last_link_ns is None


@pytest.mark.parametrize(("turn_deg", "oriented"), [(5.0, True), (7.5, True), (12.0, False), (30.0, False),
                                                    (185.0, True), (200.0, False)])
def test_orientation_is_linked_only_within_cad_link_max_turn_deg(turn_deg: float, oriented: bool) -> None:
    """A linked landmark is held at its feature's frame (the side closer to its own), by its orientation too only
    where its own lies within `cad_link_max_turn_deg` of it; turned farther, by its position only."""
    links, graph, landmarks = _anchored([("door", _frame("D1", turn_deg=turn_deg))])
    links.link_new(landmarks, STAMP_NS)
    assert links.links == {0: "D1"}
    factor = _link_factor(graph, 0)
    sigmas = factor.noiseModel().noise().sigmas()
    assert np.allclose(sigmas, CAD_LINK_SIGMAS if oriented else CAD_LINK_POSITION_SIGMAS)
    side = FLIP_ABOUT_UP if abs(turn_deg) > 90.0 else np.eye(4)
    assert np.allclose(factor.measured().matrix(), _frame("D1") @ side, atol=1e-9)


def test_a_landmark_is_linked_once() -> None:
    """A landmark already linked keeps its link when new landmarks are linked: not linked again (no second link
    factor), not even to another feature within reach."""
    links, graph, landmarks = _anchored([("door", _frame("D1", (0.2, 0.0, 0.0)))], NEAR_D1)
    links.link_new(landmarks, STAMP_NS)
    links.link_new(landmarks, STAMP_NS + 1)
    _link_factor(graph, 0)  # exactly one
    assert links.links == {0: "D1"} and links.last_link_ns == STAMP_NS


def test_only_a_vertical_feature_of_the_model_is_linked() -> None:
    """`link` ignores an id that is no feature of the model and a feature that is not vertical (a skylight)."""
    skylight = MacroFeature("S1", "window", "L1", FEATURES[0].corners_cad, FEATURES[0].centroid_cad,
                            np.array([0.0, 0.0, 1.0]), 0.9, 2.1, orientation="horizontal")
    links, _, landmarks = _anchored([("window", _frame("D1"))], [*FEATURES, skylight])
    links.link(0, "nowhere", np.eye(4))
    links.link(0, "S1", np.eye(4))
    links.link_new(landmarks, STAMP_NS)
    assert links.links == {}


def test_seeing_a_linked_landmark_is_seeing_the_model() -> None:
    """`seen` moves `last_link_ns` only where one of the re-observed landmarks is linked."""
    links, _, landmarks = _anchored([("door", _frame("D1")), ("door", _frame("D2", (0.0, -2.0, 0.0)))])
    links.link_new(landmarks, STAMP_NS)
    assert links.links == {0: "D1"}
    links.seen({1}, STAMP_NS + 1)
    assert links.last_link_ns == STAMP_NS
    links.seen({0, 1}, STAMP_NS + 2)
    assert links.last_link_ns == STAMP_NS + 2
