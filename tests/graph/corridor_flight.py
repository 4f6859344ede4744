"""A drone flying a synthetic corridor of doors through the Localizer (the pose-graph and localizer tests)."""

from __future__ import annotations

import numpy as np

from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.localizer import Localizer, LocalizerParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import SavedMapRegistrar
from macroloc.graph.relocalize import KnownRect
from tests.graph.scenes import (
    sightings_from,
)

UP = np.array([0.0, 0.0, 1.0])


def model_registrar(model, min_landmarks: int = 3) -> SavedMapRegistrar:
    """Registration by rectangle alignment against every feature of the model (no ground truth used)."""
    return SavedMapRegistrar([KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features], min_landmarks)


def fly(model, poses, odometry, registrar=None, seed: int = 0, sigma_m: float = 0.0,
        graph: PoseGraph | None = None, params: LocalizerParams | None = None) -> Localizer:
    rng = np.random.default_rng(seed)
    loc = Localizer(model, graph or PoseGraph(), registrar or model_registrar(model), params)
    for k, (T_true, T_odom) in enumerate(zip(poses, odometry, strict=True)):
        loc.add_keyframe(k * 100_000_000, T_odom, sightings_from(model, T_true, rng=rng, sigma_m=sigma_m), UP)
    return loc


def position_error(loc: Localizer, poses: list[np.ndarray], i: int) -> float:
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None
    return float(np.linalg.norm((T_cad_map @ loc.graph.T_map_body(i))[:3, 3] - poses[i][:3, 3]))


def tilt_deg(R: np.ndarray) -> float:
    """Angle between R's z axis and z (deg): the tilt of a rotation between two z-up frames."""
    return float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))
