"""graph.anchoring: registration attempts while exploring, the held rule (`StatusParams.held_sigma_m`) and the
status's decay (localized, degraded, lost) while no CAD-linked landmark is seen, on the synthetic corridor."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.graph.anchoring import Anchoring
from macroloc.graph.cad_links import CadLinks
from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.far_window import FarSightings
from macroloc.graph.features import BuildingModel, CentroidsByType
from macroloc.graph.judge import NullJudge
from macroloc.graph.landmark_map import LandmarkMap
from macroloc.graph.params import LocalizerParams, StatusParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import Registrar, SavedMapRegistrar
from macroloc.graph.rigid import apply
from macroloc.graph.sightings import Sighting
from macroloc.graph.surface_fit import NullFitter
from tests.graph.corridor_flight import UP, model_registrar
from tests.graph.scenes import make_T, sightings_from, straight_flight

STATUS = StatusParams(degraded_after_s=10.0, lost_after_s=30.0, held_sigma_m=0.17)
STEP_NS = 100_000_000  # a keyframe every 0.1 s


def _anchoring(model: BuildingModel, status: StatusParams = STATUS, registrar: Registrar | None = None) -> Anchoring:
    """The anchoring of a flight through `model` with its real components, no model surfaces (null judge and
    fitter), registering by rectangle alignment to the model's features from three landmarks (or `registrar`)."""
    p = LocalizerParams()
    graph = PoseGraph()
    viewer = np.zeros(3)
    depth = DepthWindow(p.depth.surface_window_keyframes, viewer, graph.T_map_body)
    far = FarSightings(p.far, p.depth.surface_window_keyframes, p.landmarks.position_sigma_m, viewer,
                       CentroidsByType(model.features), graph.T_map_body)
    landmarks = LandmarkMap(p.landmarks, graph, viewer)
    links = CadLinks(p.anchor, graph, {f.id: f for f in model.features})
    return Anchoring(p.registration, p.anchor, p.far, status, graph, registrar or model_registrar(model), NullJudge(),
                     depth, far, landmarks, links, NullFitter())


def _keyframe(a: Anchoring, T_map_body: np.ndarray, sightings: list, odometry_sigma_m: float = 0.01) -> int:
    """One keyframe at T_map_body (the odometry exact, with `odometry_sigma_m` per step) and its sightings; a
    registration where `should_register` says so. Returns its stamp (ns)."""
    graph = a.graph
    i = graph.n_keyframes
    if i == 0:
        graph.add_first_keyframe(T_map_body)
    else:
        T_prev = graph.T_map_body(i - 1)
        graph.add_keyframe(np.linalg.inv(T_prev) @ T_map_body, np.r_[np.full(3, 0.01), np.full(3, odometry_sigma_m)],
                           T_map_body)
    graph.add_gravity(i, T_map_body)
    _, reobserved = a.landmarks.add_frames(i, T_map_body, [sightings], UP)
    graph.update()
    stamp_ns = i * STEP_NS
    a.links.seen(reobserved, stamp_ns)
    if a.should_register(stamp_ns):
        a.register(stamp_ns)
    return stamp_ns


def _localized(model: BuildingModel, status: StatusParams = STATUS) -> tuple[Anchoring, int]:
    """An anchoring localized along the corridor; the stamp of its last keyframe."""
    a = _anchoring(model, status)
    for T in straight_flight(15):
        stamp_ns = _keyframe(a, T, sightings_from(model, T))
    assert a.status == "localized" and a.links.links
    return a, stamp_ns


def _dead_reckoned(a: Anchoring, n: int = 10) -> int:
    """`n` keyframes onwards seeing nothing, the odometry loose (1 m a step); the last one's stamp."""
    T = a.graph.T_map_body(a.graph.n_keyframes - 1)
    for _ in range(n):
        T = T @ make_T(np.eye(3), np.array([0.3, 0.0, 0.0]))
        stamp_ns = _keyframe(a, T, [], odometry_sigma_m=1.0)
    return stamp_ns


def test_registration_waits_for_min_landmarks_and_a_new_one(corridor: BuildingModel) -> None:
    """Without the surface check a registration is tried once the registrar's `min_landmarks` landmarks are
    confirmed, and, failing, again only when one more is confirmed."""
    a = _anchoring(corridor, registrar=SavedMapRegistrar([], min_landmarks=3))  # an empty stored map: never localized
    n_confirmed = []
    for T in straight_flight(30):
        _keyframe(a, T, sightings_from(corridor, T))
        n_confirmed.append(len(a.confirmed()))
    grew = [i for i, n in enumerate(n_confirmed) if n >= 3 and (i == 0 or n > n_confirmed[i - 1])]
    assert len(grew) >= 2 and len(grew) < len(n_confirmed) - grew[0]  # keyframes without a new one in between
    assert a.registrations == [(i * STEP_NS, "exploring") for i in grew] and not a.graph.has_anchor


def test_a_registration_anchors_the_graph_and_links_every_landmark_near_a_feature(corridor: BuildingModel) -> None:
    """A registration's pose anchors the graph and localizes; its matches are linked, and so is a landmark seen
    once (no part of the registration) that lies by a CAD feature."""
    a = _anchoring(corridor)
    poses = straight_flight(14)
    for T in poses[:-1]:
        _keyframe(a, T, sightings_from(corridor, T))
    assert a.status == "exploring"
    beside = next(f for f in corridor.features if f.id == "F00")  # beside the start, never in view
    once = Sighting(beside.type, apply(np.linalg.inv(poses[-1]), beside.corners_cad))
    stamp_ns = _keyframe(a, poses[-1], [*sightings_from(corridor, poses[-1]), once])
    assert a.registrations == [(stamp_ns, "localized")] and a.status == "localized" and a.graph.has_anchor
    once_key = next(j for j, lm in a.landmarks.landmarks.items() if lm.n_sightings == 1)
    assert once_key not in a.confirmed() and a.links.links[once_key] == "F00"
    truth = {f.id for f in corridor.features}
    assert set(a.links.links) == set(a.landmarks.landmarks) and set(a.links.links.values()) <= truth
    assert a.links.last_link_ns == stamp_ns


def test_held_while_the_horizontal_sigma_is_within_held_sigma_m(corridor: BuildingModel) -> None:
    """The pose is held only once anchored and while the newest keyframe's horizontal sigma is within
    `held_sigma_m`: localized by the doors it is; dead-reckoned onwards it is not, unless the limit is wider."""
    a = _anchoring(corridor)
    _keyframe(a, straight_flight(1)[0], [])
    assert not a.held()  # not anchored
    a, _ = _localized(corridor)
    assert a.held()
    _dead_reckoned(a)
    sigma_m = a.graph.horizontal_sigma_m(a.graph.n_keyframes - 1)
    assert sigma_m > STATUS.held_sigma_m and not a.held()
    a.status_params = StatusParams(held_sigma_m=1.01 * sigma_m)
    assert a.held()
    a.status_params = StatusParams(held_sigma_m=0.99 * sigma_m)
    assert not a.held()


@pytest.mark.parametrize(("silent_s", "status"), [(9.9, "localized"), (10.1, "degraded"), (29.9, "degraded"),
                                                  (30.1, "lost")])
def test_status_decays_by_the_time_no_linked_landmark_was_seen(corridor: BuildingModel, silent_s: float,
                                                               status: str) -> None:
    """Held, the status is localized until `degraded_after_s` without a CAD-linked sighting, degraded until
    `lost_after_s`, lost after; a linked landmark seen again makes it localized."""
    a, stamp_ns = _localized(corridor)
    last_ns = a.links.last_link_ns
    assert last_ns is not None
    a.update_status(last_ns + int(silent_s * 1e9))
    assert a.status == status
    linked = set(a.links.links)
    a.links.seen(linked, stamp_ns + int(silent_s * 1e9))
    a.update_status(stamp_ns + int(silent_s * 1e9))
    assert a.status == "localized"


def test_degraded_while_not_held(corridor: BuildingModel) -> None:
    """A pose not held is degraded at least, even right after a CAD-linked sighting; lost still by the time."""
    a, _ = _localized(corridor)
    stamp_ns = _dead_reckoned(a)
    a.links.seen(set(a.links.links), stamp_ns)  # a linked landmark seen at this keyframe
    a.update_status(stamp_ns)
    assert a.status == "degraded"
    a.update_status(stamp_ns + int(30.1e9))
    assert a.status == "lost"


def test_the_status_decays_only_once_localized(corridor: BuildingModel) -> None:
    """While exploring (never localized) the status stays as it is, however long nothing was linked."""
    a = _anchoring(corridor)
    stamp_ns = _keyframe(a, straight_flight(1)[0], [])
    a.links.last_link_ns = stamp_ns  # as if a landmark had been linked
    a.update_status(stamp_ns + int(60e9))
    assert a.status == "exploring"
