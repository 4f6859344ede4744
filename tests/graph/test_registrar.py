"""graph.registrar: the model registrar (answers, candidates, storey hint, one rectangle), the stored-map registrar
and the first-of chain with its fallback, on a small asymmetric building and its copy one storey up."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.registrar import FirstOfRegistrar, ModelRegistrar, SavedMapRegistrar
from macroloc.graph.relocalize import KnownRect, ObservedRect
from macroloc.graph.rigid import apply
from tests.graph.helpers import random_building
from tests.graph.scenes import make_T, rot_z

LOWER = random_building(np.random.default_rng(3), n=20, size_m=20.0)  # 9 doors (0.9 m), 11 windows of 3 sizes
STOREY_M = 3.0
UPPER = [replace(f, id=f.id + "u", storey="L2", corners_cad=f.corners_cad + [0.0, 0.0, STOREY_M],
                 centroid_cad=f.centroid_cad + [0.0, 0.0, STOREY_M]) for f in LOWER]
ONE_STOREY = BuildingModel(source="test", sha256="test-registrar-one-storey", features=LOWER, storeys=["L1"])
TWO_STOREYS = BuildingModel(source="test", sha256="test-registrar-two-storeys", features=LOWER + UPPER,
                            storeys=["L1", "L2"])
T_MAP_CAD = make_T(rot_z(0.7), np.array([3.0, -2.0, 0.0]))  # the flight's map frame is anywhere
T_CAD_MAP = np.linalg.inv(T_MAP_CAD)


def _seen(features: list[MacroFeature]) -> tuple[list[ObservedRect], list[np.ndarray]]:
    """The features as landmarks of a flight whose map is T_MAP_CAD: their frames and corners in the map frame."""
    landmarks = [ObservedRect(k, f.type, T_MAP_CAD @ feature_frame_cad(f)) for k, f in enumerate(features)]
    return landmarks, [apply(T_MAP_CAD, f.corners_cad) for f in features]


def _known(features: list[MacroFeature]) -> list[KnownRect]:
    return [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in features]


def _is_truth(T_cad_map: np.ndarray | None, shift_z_m: float = 0.0) -> bool:
    expected = make_T(np.eye(3), np.array([0.0, 0.0, shift_z_m])) @ T_CAD_MAP
    return T_cad_map is not None and np.allclose(T_cad_map, expected, atol=1e-3)


def test_enough_landmarks_are_localized_with_their_matches() -> None:
    """From `min_landmarks` landmarks that the building explains one way only, the answer is 'localized' at the
    true pose, each landmark matched to its feature."""
    landmarks, corners = _seen(LOWER[:5])
    result = ModelRegistrar(ONE_STOREY, min_landmarks=4)(landmarks, corners)
    assert result.status == "localized" and result.inliers == 5
    assert _is_truth(result.T_cad_map)
    assert result.matches == [(k, f.id) for k, f in enumerate(LOWER[:5])]


def test_fewer_inliers_than_min_landmarks_are_candidates_not_an_answer() -> None:
    """A pose explaining fewer landmarks than `min_landmarks` is no answer: with `candidates_from` it is 'ambiguous'
    without matches, the true pose among its candidates; without, nothing is offered ('not_localized')."""
    landmarks, corners = _seen(LOWER[:3])
    result = ModelRegistrar(ONE_STOREY, min_landmarks=4, candidates_from=2)(landmarks, corners)
    assert result.status == "ambiguous" and result.matches == [] and result.inliers == 3
    assert any(_is_truth(T) for T, _ in result.candidates)
    assert ModelRegistrar(ONE_STOREY, min_landmarks=4)(landmarks, corners).status == "not_localized"


def test_candidates_from_is_capped_by_min_landmarks_and_robust_only() -> None:
    """`candidates_from` never exceeds `min_landmarks`, defaults to it, and the paper method ignores it."""
    assert ModelRegistrar(ONE_STOREY, min_landmarks=4, candidates_from=1).candidates_from == 1
    assert ModelRegistrar(ONE_STOREY, min_landmarks=4, candidates_from=6).candidates_from == 4
    assert ModelRegistrar(ONE_STOREY, min_landmarks=4).candidates_from == 4
    assert ModelRegistrar(ONE_STOREY, method="paper", min_landmarks=4, candidates_from=1).candidates_from == 4


@pytest.mark.parametrize(("hint", "shift_z_m", "suffix"), [("L1", 0.0, ""), ("L2", STOREY_M, "u")])
def test_a_storey_hint_registers_among_that_storeys_features_only(hint: str, shift_z_m: float, suffix: str) -> None:
    """Two identical storeys explain the landmarks alike: without a hint the answer is 'ambiguous'; with one, it
    is 'localized' on the hinted storey, matched to its features."""
    landmarks, corners = _seen(LOWER[:5])
    assert ModelRegistrar(TWO_STOREYS, min_landmarks=4)(landmarks, corners).status == "ambiguous"
    result = ModelRegistrar(TWO_STOREYS, min_landmarks=4, storey_hint=hint)(landmarks, corners)
    assert result.status == "localized" and _is_truth(result.T_cad_map, shift_z_m)
    assert {fid for _, fid in result.matches} == {f.id + suffix for f in LOWER[:5]}


def test_one_landmark_offers_every_alike_feature_from_either_side() -> None:
    """One door or window is never an answer: it comes back 'ambiguous' with one candidate pose per feature of its
    type and size, from either side (the truth among them), on the hinted storey only; without corners, nothing."""
    door, window = LOWER[0], next(f for f in LOWER if f.type == "window")
    registrar = ModelRegistrar(ONE_STOREY, min_landmarks=4, candidates_from=1)
    for f in (door, window):
        landmarks, corners = _seen([f])
        result = registrar(landmarks, corners)
        alike = [g for g in LOWER if g.type == f.type and abs(g.width_m - f.width_m) < 0.05]
        assert result.status == "ambiguous" and result.T_cad_map is None and result.matches == []
        assert len(result.candidates) == 2 * len(alike)
        assert any(_is_truth(T) for T, _ in result.candidates)
    assert len(alike) < sum(g.type == "window" for g in LOWER)  # windows of other sizes are no candidates
    landmarks, corners = _seen([door])
    n_doors = sum(f.type == "door" for f in LOWER)
    assert len(ModelRegistrar(TWO_STOREYS, min_landmarks=4, candidates_from=1)(landmarks, corners).candidates) \
        == 4 * n_doors
    hinted = ModelRegistrar(TWO_STOREYS, min_landmarks=4, candidates_from=1, storey_hint="L1")(landmarks, corners)
    assert len(hinted.candidates) == 2 * n_doors
    assert registrar(landmarks, [None]).status == "not_localized"


def test_a_stored_map_localizes_from_its_linked_features_only() -> None:
    """The saved map's features are the only candidates: landmarks it holds are 'localized' from `min_landmarks`
    on; landmarks elsewhere in the building are 'not_localized'."""
    landmarks, corners = _seen(LOWER[:5])
    result = SavedMapRegistrar(_known(LOWER[:5]), min_landmarks=2)(landmarks, corners)
    assert result.status == "localized" and _is_truth(result.T_cad_map)
    assert result.matches == [(k, f.id) for k, f in enumerate(LOWER[:5])]
    assert SavedMapRegistrar(_known(LOWER[10:15]), min_landmarks=2)(landmarks, corners).status == "not_localized"


def test_one_landmark_in_a_stored_map_offers_only_its_stored_features() -> None:
    """With `candidates_from` and the model, one landmark gets a candidate per alike stored feature (either side),
    not per alike door of the building; without `candidates_from` it gets none."""
    landmarks, corners = _seen(LOWER[:1])
    stored = _known(LOWER[:5])
    n_stored_doors = sum(k.type == "door" for k in stored)
    result = SavedMapRegistrar(stored, min_landmarks=2, candidates_from=1, model=ONE_STOREY)(landmarks, corners)
    assert result.status == "ambiguous" and len(result.candidates) == 2 * n_stored_doors
    assert n_stored_doors < sum(f.type == "door" for f in LOWER)
    assert any(_is_truth(T) for T, _ in result.candidates)
    assert SavedMapRegistrar(stored, min_landmarks=2, model=ONE_STOREY)(landmarks, corners).status == "not_localized"


def test_first_of_falls_back_to_the_model_where_the_stored_map_does_not_localize() -> None:
    """The first 'localized' answer wins: a saved map without the landmarks' features gives none, so the whole
    model's answer is returned; the chain answers from the fewest landmarks any of its registrars does."""
    landmarks, corners = _seen(LOWER[:5])
    stored = SavedMapRegistrar(_known(LOWER[10:15]), min_landmarks=2)
    chain = FirstOfRegistrar([stored, ModelRegistrar(ONE_STOREY, min_landmarks=4, candidates_from=1)])
    assert (chain.min_landmarks, chain.candidates_from) == (2, 1)
    result = chain(landmarks, corners)
    assert result.status == "localized" and _is_truth(result.T_cad_map) and result.fallback is None


def test_first_of_returns_the_stored_answer_with_the_models_as_its_fallback() -> None:
    """A saved map's 'localized' answer comes back first, with the later registrars' answer as its `fallback`
    (asked only on demand); the last registrar's answer has no fallback."""
    landmarks, corners = _seen(LOWER[:5])
    model = ModelRegistrar(TWO_STOREYS, min_landmarks=4, storey_hint="L2")
    result = FirstOfRegistrar([SavedMapRegistrar(_known(LOWER[:5]), min_landmarks=2), model])(landmarks, corners)
    assert result.status == "localized" and _is_truth(result.T_cad_map)
    assert result.fallback is not None and not result.fallback_holds_these
    later = result.fallback()
    assert later.status == "localized" and _is_truth(later.T_cad_map, STOREY_M) and later.fallback is None


def test_first_of_passes_over_an_ambiguous_answer_without_candidates() -> None:
    """An 'ambiguous' answer without candidates does not stop the chain: a later 'localized' one wins; where none
    follows, the first 'ambiguous' answer is returned."""
    landmarks, corners = _seen(LOWER[:5])
    two_of_them = SavedMapRegistrar(_known(LOWER[:2]), min_landmarks=2)
    alone = two_of_them(landmarks, corners)
    assert alone.status == "ambiguous" and not alone.candidates
    result = FirstOfRegistrar([two_of_them, ModelRegistrar(ONE_STOREY, min_landmarks=4)])(landmarks, corners)
    assert result.status == "localized" and _is_truth(result.T_cad_map)
    elsewhere = SavedMapRegistrar(_known(LOWER[10:15]), min_landmarks=2)
    result = FirstOfRegistrar([two_of_them, elsewhere])(landmarks, corners)
    assert result.status == "ambiguous" and result.matches == alone.matches


def test_first_of_one_landmark_candidates_are_held_by_the_models() -> None:
    """A saved map's candidates from one landmark each explain every landmark, too few for the model to answer
    by itself: its candidates would hold these (`fallback_holds_these`); the fallback offers the model's."""
    landmarks, corners = _seen(LOWER[:1])
    stored = SavedMapRegistrar(_known(LOWER[:5]), min_landmarks=2, candidates_from=1, model=ONE_STOREY)
    model = ModelRegistrar(ONE_STOREY, min_landmarks=4, candidates_from=1)
    result = FirstOfRegistrar([stored, model])(landmarks, corners)
    assert result.status == "ambiguous" and result.candidates and result.fallback_holds_these
    assert result.fallback is not None
    n_doors = sum(f.type == "door" for f in LOWER)
    assert len(result.fallback().candidates) == 2 * n_doors > len(result.candidates)
