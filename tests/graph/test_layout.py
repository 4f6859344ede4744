"""Issue 37: the layout descriptor that ranks and prunes the registration's candidates, and the rival images that
keep repeated layouts `ambiguous`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.model_index import ModelIndex
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.registration import register
from macroloc.graph.rigid import apply
from macroloc.graph.robust import RobustParams, _prepare, seed_candidates
from tests.graph.helpers import random_building, random_T


def _observe(features: list[MacroFeature], T_map_cad: np.ndarray) -> ObservationSet:
    obs = [Observation(f.type, apply(T_map_cad, f.centroid_cad), apply(T_map_cad, f.corners_cad[[2, 0, 3, 1]]))
           for f in features]
    return ObservationSet(obs, T_map_cad[:3, :3] @ np.array([0.0, 0.0, -1.0]))


def _tiled(features: list[MacroFeature], units: int, pitch_m: float, jitter_m: float = 0.0,
           seed: int = 0) -> BuildingModel:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(units):
        for f in features:
            shift = np.array([k * pitch_m, 0.0, 0.0])
            if jitter_m:
                u = np.cross([0.0, 0.0, 1.0], f.normal_cad)
                shift = shift + rng.normal(0.0, jitter_m) * u / np.linalg.norm(u)
            out.append(replace(f, id=f"u{k}:{f.id}", corners_cad=f.corners_cad + shift,
                               centroid_cad=f.centroid_cad + shift))
    return BuildingModel("tiled", f"tiled-{units}-{jitter_m}-{seed}", out, ["L1"])


def test_true_candidate_survives_pruning_with_2_of_5_neighbours_missing() -> None:
    rng = np.random.default_rng(37)
    features = random_building(rng, n=400, size_m=100.0)
    index = ModelIndex.build(features)
    params = RobustParams(prune_top=16)  # of ~200 candidates of its type
    tried = 0
    for k in rng.permutation(len(features))[:40]:
        f = features[k]
        d = np.linalg.norm(index.centroids - f.centroid_cad, axis=1)
        near = [int(j) for j in np.argsort(d)[1:6] if d[j] <= index.layout().params.radius_m]
        if len(near) < 5 or len(index.type_indices[f.type]) <= params.prune_top:
            continue
        kept_neighbours = [features[j] for j in rng.permutation(near)[:3]]  # 2 of the 5 missed
        prep = _prepare(_observe([f, *kept_neighbours], random_T(rng, yaw_only=True)))
        assert k in seed_candidates(0, prep, index, params)
        assert len(seed_candidates(0, prep, index, params)) == params.prune_top
        tried += 1
    assert tried >= 20


def test_exact_copies_of_a_unit_are_ambiguous_and_perturbed_ones_never_wrong() -> None:
    rng = np.random.default_rng(3)
    unit = random_building(rng, n=60, size_m=30.0)
    centre = np.array([15.0, 15.0])
    inner = [f for f in unit if np.linalg.norm(f.centroid_cad[:2] - centre) < 10.0]
    for jitter_m, expect in ((0.0, {"ambiguous"}), (0.3, {"localized", "ambiguous"})):
        model = _tiled(unit, 4, pitch_m=35.0, jitter_m=jitter_m)
        index_ids = {f.id: f for f in model.features}
        seen = [index_ids[f"u2:{f.id}"] for f in inner]  # the third unit
        T_map_cad = random_T(rng, yaw_only=True)
        r = register(model, _observe(seen, T_map_cad))
        assert r.status in expect, (jitter_m, r.status, r.diagnostics)
        if r.status == "localized":  # the right unit, never one of its copies
            truth = np.array([f.centroid_cad for f in seen])
            moved = apply(r.T_cad_map, apply(T_map_cad, truth))
            assert np.abs(moved - truth).max() < 0.15
        if jitter_m == 0.0:
            assert len(r.alternatives) >= 1
    # 16 copies: the best pose's 15 images are found by the layout index, not sampled
    big = _tiled(unit, 16, pitch_m=35.0)
    seen = [f for f in big.features if f.id.startswith("u5:") and f.id[3:] in {g.id for g in inner}]
    r = register(big, _observe(seen, random_T(rng, yaw_only=True)))
    assert r.status == "ambiguous"
    assert r.diagnostics["images"] >= 15
