"""Verification by rectangles (graph/verify.py), building self-maps (graph/self_maps.py) and the rival rule."""

from __future__ import annotations

import numpy as np

from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.model_index import ModelIndex
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.rectangle import opening_rectangle
from macroloc.graph.registration import register
from macroloc.graph.rigid import apply, invert, make_T
from macroloc.graph.verify import Noise, VerifyParams, observed_shapes, one_per_feature, verify, verify_all
from tests.graph.helpers import box_vertices, random_building


def _door(fid: str, centre_xy, normal_xy, storey: str = "L1", z0: float = 0.0) -> MacroFeature:
    r = opening_rectangle(box_vertices(np.array([*centre_xy, z0 + 1.05]), normal_xy, 0.9, 2.1))
    return MacroFeature(fid, "door", storey, r.corners, r.centroid, r.normal, r.width_m, r.height_m)


def _yaw_T(yaw_deg: float, t) -> np.ndarray:
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return make_T(R, np.asarray(t, dtype=float))


def _model(features: list[MacroFeature]) -> BuildingModel:
    return BuildingModel(features=features, sha256=f"test-{len(features)}-{features[0].centroid_cad.sum():.6f}",
                         source="test")


def _observe(features: list[MacroFeature], T_map_cad: np.ndarray, rng: np.random.Generator | None = None,
             sigma_m: float = 0.0) -> list[Observation]:
    out = []
    for f in features:
        corners = apply(T_map_cad, f.corners_cad[[2, 0, 3, 1]])
        if rng is not None:
            corners = corners + rng.normal(0.0, sigma_m, corners.shape)
        out.append(Observation(f.type, corners.mean(axis=0), corners))
    return out


def test_centroid_coincidences_with_wrong_normals_never_beat_aligned_rectangles() -> None:
    """Three doors seen; the building also has three doors exactly where a 56-degree turn puts the seen ones' centroids,
    but in walls whose normals are 40-60 degrees off: those coincidences support nothing."""
    seen = [_door("A", (0.0, 0.0), (1, 0)), _door("B", (6.0, 1.0), (0, 1)), _door("C", (2.0, 7.0), (1, 0))]
    S = _yaw_T(56.0, (3.0, -4.1, 0.0))  # the wrong pose's turn, CAD -> CAD
    decoys = [_door(f"D{i}", apply(S, f.centroid_cad)[:2], n)
              for i, (f, n) in enumerate(zip(seen, [(1, 0), (1, 0), (0, 1)], strict=True))]
    fourth = _door("E", (9.0, 6.0), (0, 1))  # one more seen door: no single observation decides (the rival rule)
    model = _model(seen + decoys + [fourth])
    index = ModelIndex.build(model.features)
    T_map_cad = _yaw_T(33.0, (5.0, 2.0, 0.4))
    obs = _observe(seen, T_map_cad)
    shapes = observed_shapes(obs, np.zeros(len(obs), dtype=np.int8))
    noise, params = Noise.from_rms(0.05, VerifyParams()), VerifyParams()
    truth = verify(invert(T_map_cad), shapes, index, noise, 0.3, 0.5, params)
    wrong = verify(S @ invert(T_map_cad), shapes, index, noise, 0.3, 0.5, params)
    assert truth.n_inliers == 3 and wrong.n_inliers == 0
    assert truth.loglik > wrong.loglik
    r = register(model, ObservationSet(obs + _observe([fourth], T_map_cad), np.array([0.0, 0.0, -1.0])))
    assert r.status == "localized", str(r.diagnostics)
    assert np.linalg.norm(apply(r.T_cad_map, obs[0].centroid_map) - seen[0].centroid_cad) < 0.05


def test_symmetric_storey_pair_with_one_spurious_inlier_stays_ambiguous() -> None:
    """Storey L2 is storey L1 turned 180 degrees (3 m up), plus one door L1 lacks; a false detection sits where that
    extra door lands under the wrong pose, so the wrong pose explains one observation more: still 'ambiguous'."""
    rng = np.random.default_rng(5)
    lower = random_building(rng, n=24, size_m=20.0)
    S = _yaw_T(180.0, (20.0, 20.0, 3.0))  # L1 -> L2
    upper = [MacroFeature(f.id + "'", f.type, "L2", apply(S, f.corners_cad), apply(S, f.centroid_cad),
                          S[:3, :3] @ f.normal_cad, f.width_m, f.height_m) for f in lower]
    extra = _door("X", (12.0, 11.0), (1, 0), storey="L2", z0=3.0)
    model = _model(lower + upper + [extra])
    start = lower[0].centroid_cad[:2]
    seen = sorted(lower, key=lambda f: float(np.linalg.norm(f.centroid_cad[:2] - start)))[:8]
    for trial in range(3):
        T_map_cad = _yaw_T(40.0 + 70.0 * trial, (3.0, -2.0, 1.0))
        obs = _observe(seen, T_map_cad, rng, 0.05)
        fp = _observe([extra], T_map_cad @ invert(S), rng, 0.05)  # at S^-1(X): on nothing under the truth
        r = register(model, ObservationSet(obs + fp, np.array([0.0, 0.0, -1.0])))
        assert r.status == "ambiguous", (trial, r.status, str(r.diagnostics))


def test_a_storey_turned_onto_itself_is_among_the_building_self_maps() -> None:
    """A storey and its copy turned 180 degrees about (10, 10) and 3 m up: that yaw and shift is a self-map whose
    landing table maps every feature of the storey onto an alike one; an asymmetric storey alone has none as good."""
    from macroloc.graph.self_maps import building_self_maps

    lower = random_building(np.random.default_rng(3), n=20, size_m=20.0)
    S = _yaw_T(180.0, (20.0, 20.0, 3.0))
    upper = [MacroFeature(f.id + "'", f.type, "L2", apply(S, f.corners_cad), apply(S, f.centroid_cad),
                          S[:3, :3] @ f.normal_cad, f.width_m, f.height_m) for f in lower]
    both = ModelIndex.build(lower + upper)
    maps = building_self_maps(both.centroids, both.normals, both.type_codes)
    T = maps.transforms()
    k = int(np.argmin([np.abs(T_m - S).max() for T_m in T]))
    assert np.abs(T[k] - S).max() < 0.2
    assert maps.lands[k, : len(lower)].all()
    alone = ModelIndex.build(lower)
    maps_alone = building_self_maps(alone.centroids, alone.normals, alone.type_codes)
    assert maps_alone.lands.sum(axis=1).max() < len(lower) // 2


def test_the_pose_graphs_registrar_answers_the_symmetric_storey_pair_as_the_one_shot_registration() -> None:
    """The registrar of the pose graph (graph.registrar.ModelRegistrar) uses the same verification and rival rule:
    eight landmarks of the storey that its 180-degree copy repeats, plus a false one where the copy's extra door
    lands, are 'ambiguous' there too; without the copy the same landmarks are 'localized'."""
    from macroloc.graph.landmarks import feature_frame_cad
    from macroloc.graph.registrar import ModelRegistrar
    from macroloc.graph.relocalize import ObservedRect

    rng = np.random.default_rng(5)
    lower = random_building(rng, n=24, size_m=20.0)
    S = _yaw_T(180.0, (20.0, 20.0, 3.0))
    upper = [MacroFeature(f.id + "'", f.type, "L2", apply(S, f.corners_cad), apply(S, f.centroid_cad),
                          S[:3, :3] @ f.normal_cad, f.width_m, f.height_m) for f in lower]
    extra = _door("X", (12.0, 11.0), (1, 0), storey="L2", z0=3.0)
    start = lower[0].centroid_cad[:2]
    seen = [f for f in sorted(lower, key=lambda f: float(np.linalg.norm(f.centroid_cad[:2] - start)))
            if f.orientation == "vertical"][:8]
    T_map_cad = _yaw_T(40.0, (3.0, -2.0, 0.0))
    fp = MacroFeature("fp", "door", "L1", apply(invert(S), extra.corners_cad), apply(invert(S), extra.centroid_cad),
                      invert(S)[:3, :3] @ extra.normal_cad, extra.width_m, extra.height_m)
    landmarks = [ObservedRect(k, f.type, T_map_cad @ feature_frame_cad(f)) for k, f in enumerate(seen + [fp])]
    corners = [apply(T_map_cad, f.corners_cad) for f in seen + [fp]]
    both = ModelRegistrar(_model(lower + upper + [extra]), min_landmarks=4)(landmarks, corners)
    alone = ModelRegistrar(_model(lower), min_landmarks=4)(landmarks, corners)
    assert both.status == "ambiguous"
    assert alone.status == "localized"
    assert np.allclose(alone.T_cad_map, invert(T_map_cad), atol=1e-3)


def test_each_cad_feature_keeps_the_observation_it_explains_best_pose_by_pose() -> None:
    """Per pose (row): the greatest worth keeps the feature, the first among equals; -1 matches nothing; two poses
    matching the same feature do not compete."""
    match = np.array([[5, 5, -1, 7, 7], [-1, -1, 7, 7, -1], [5, -1, 7, 7, 5]])
    worth = np.array([[1.0, 3.0, 9.0, 2.0, 2.0], [9.0, 9.0, 1.0, 1.5, 9.0], [2.0, 9.0, 1.0, 1.5, 2.0]])
    np.testing.assert_array_equal(one_per_feature(match, worth), [[False, True, False, True, False],
                                                                  [False, False, False, True, False],
                                                                  [True, False, False, True, False]])


def test_verifying_poses_together_gives_each_its_own_verdict() -> None:
    rng = np.random.default_rng(4)
    features = random_building(rng, n=30, size_m=25.0)
    index = ModelIndex.build(features)
    T_map_cad = _yaw_T(20.0, (1.0, -2.0, 0.3))
    obs = _observe(features[:10], T_map_cad, rng, 0.02) + _observe(features[:2], T_map_cad, rng, 0.05)  # seen twice
    types = np.array([0 if o.type == "door" else 1 for o in obs], dtype=np.int8)
    shapes = observed_shapes(obs, types)
    noise, params = Noise.from_rms(0.05, VerifyParams()), VerifyParams()
    poses = np.stack([invert(T_map_cad), _yaw_T(0.5, (0.05, 0.0, 0.0)) @ invert(T_map_cad), _yaw_T(90.0, (3, 0, 0))])
    together = verify_all(poses, shapes, index, noise, 0.3, 0.5, params)
    assert together[0].n_inliers == 10  # each feature seen twice keeps one observation
    for T, v in zip(poses, together, strict=True):
        alone = verify(T, shapes, index, noise, 0.3, 0.5, params)
        np.testing.assert_array_equal(v.match, alone.match)
        np.testing.assert_allclose(v.term, alone.term, atol=1e-12)
