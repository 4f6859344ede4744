"""Rectangle alignment: recovers a known gravity-aligned transform; a symmetric layout is ambiguous."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.landmarks import FLIP_ABOUT_UP, feature_frame_cad
from macroloc.graph.relocalize import KnownRect, ObservedRect, align_rectangles
from tests.graph.scenes import corridor_model, door, make_T, rot_z


@given(yaw=st.floats(-3.1, 3.1), tx=st.floats(-30, 30), ty=st.floats(-30, 30), seed=st.integers(0, 100))
@settings(max_examples=25, deadline=None)
def test_recovers_a_known_transform_or_says_ambiguous(yaw: float, tx: float, ty: float, seed: int) -> None:
    """A corridor of regularly spaced doors can be genuinely ambiguous: never a wrong `localized`."""
    model = corridor_model(seed=seed % 5)
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features]
    T_cad_map = make_T(rot_z(yaw), np.array([tx, ty, 0.3]))
    rng = np.random.default_rng(seed)
    seen = rng.choice(len(known), 5, replace=False)
    observed = []
    for key, k in enumerate(seen):
        T = np.linalg.inv(T_cad_map) @ known[k].T_cad_rect @ (FLIP_ABOUT_UP if rng.random() < 0.5 else np.eye(4))
        T[:3, 3] += rng.normal(0, 0.03, 3)
        observed.append(ObservedRect(key, known[k].type, T))
    result = align_rectangles(observed, known)
    assert result.status in ("localized", "ambiguous")
    if result.status == "ambiguous":
        return
    assert result.T_cad_map is not None
    assert np.linalg.norm(result.T_cad_map[:3, 3] - T_cad_map[:3, 3]) < 0.2 + 0.01 * np.hypot(tx, ty)
    assert sorted(fid for _, fid in result.matches) == sorted(known[k].id for k in seen)


def test_a_point_symmetric_layout_is_ambiguous() -> None:
    feats = [door("A", (5.0, 0.0), (1.0, 0.0)), door("B", (-5.0, 0.0), (-1.0, 0.0)),
             door("C", (0.0, 3.0), (0.0, 1.0)), door("D", (0.0, -3.0), (0.0, -1.0))]
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in feats]
    observed = [ObservedRect(i, k.type, k.T_cad_rect) for i, k in enumerate(known[:3])]
    assert align_rectangles(observed, known).status == "ambiguous"


def test_too_few_landmarks_are_not_localized() -> None:
    model = corridor_model()
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features]
    assert align_rectangles([ObservedRect(0, known[0].type, known[0].T_cad_rect)], known).status == "not_localized"


def test_one_rectangle_offers_every_known_one_of_its_type_from_either_side() -> None:
    """Below `min_inliers`, from `candidates_from` on: one observed door is each known door, seen from either
    side, and the true pose is among those candidates."""
    model = corridor_model()
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features]
    T_cad_map = make_T(rot_z(0.7), np.array([3.0, -2.0, 0.0]))
    seen = known[4]
    observed = [ObservedRect(0, seen.type, np.linalg.inv(T_cad_map) @ seen.T_cad_rect @ FLIP_ABOUT_UP)]
    assert align_rectangles(observed, known, min_inliers=2).candidates == []  # asked for none
    result = align_rectangles(observed, known, min_inliers=2, candidates_from=1)
    assert result.status == "ambiguous" and result.T_cad_map is None and result.matches == []
    n_doors = sum(k.type == seen.type for k in known)
    assert len(result.candidates) == 2 * n_doors  # the doors stand metres apart: every pose is distinct
    errors = [np.linalg.norm(T[:3, 3] - T_cad_map[:3, 3]) + np.linalg.norm(T[:3, :3] - T_cad_map[:3, :3])
              for T, _ in result.candidates]
    assert min(errors) < 1e-6


def test_a_symmetric_layout_offers_both_poses() -> None:
    feats = [door("A", (5.0, 0.0), (1.0, 0.0)), door("B", (-5.0, 0.0), (-1.0, 0.0)),
             door("C", (0.0, 3.0), (0.0, 1.0)), door("D", (0.0, -3.0), (0.0, -1.0))]
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in feats]
    observed = [ObservedRect(i, k.type, k.T_cad_rect) for i, k in enumerate(known[:3])]
    result = align_rectangles(observed, known, candidates_from=2)
    assert result.status == "ambiguous" and result.inliers == 3
    offsets = sorted(float(np.linalg.norm(T[:3, 3]) + np.linalg.norm(T[:3, :3] - np.eye(3))) for T, _ in
                     result.candidates)
    assert len(offsets) >= 2 and offsets[0] < 1e-6  # the identity (the truth) and its rival(s)
