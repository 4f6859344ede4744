"""Observed macro-features in the map frame, and the OBS.json document of `macroloc localize`.

OBS.json: {"frame": "map", "gravity": [gx, gy, gz] (optional), "hints": {"storey": NAME} (optional),
           "features": [{"type": "door", "corners": [[x,y,z] x 4]} | {"type": "window", "centroid": [x,y,z]}]}
Corners may come in any order. Units: metres; gravity is a direction (normalised here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.features import FEATURE_TYPES

MAX_COORD_M = 1e5  # 100 km: no building's map frame reaches it; beyond it the arithmetic loses the centimetres
MAX_FEATURES = 10_000  # more than the doors and windows of any one view of a building: refused, not searched


@dataclass(frozen=True)
class Observation:
    """One observed door/window in the map frame: 4 corners (any order) or only a centroid."""

    type: str
    centroid_map: np.ndarray  # (3,)
    corners_map: np.ndarray | None = None  # (4, 3) or None


@dataclass(frozen=True)
class ObservationSet:
    observations: list[Observation]
    gravity_map: np.ndarray | None  # unit vector, map frame, or None when unknown
    storey_hint: str | None = None


def _vector(value, where: str, n: int = 3) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise UserInputError(f"{where}: expected {n} numbers") from None
    if arr.shape != (n,):
        raise UserInputError(f"{where}: expected {n} numbers, got shape {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise UserInputError(f"{where}: NaN or infinite value")
    if np.abs(arr).max() > MAX_COORD_M:
        raise UserInputError(f"{where}: coordinate beyond {MAX_COORD_M:g} m")
    return arr


def parse_observations(doc: object) -> ObservationSet:
    """Validate an OBS.json document; raises UserInputError with a one-line reason."""
    if not isinstance(doc, dict):
        raise UserInputError("observations: the document must be a JSON object")
    frame = doc.get("frame", "map")
    if frame != "map":
        raise UserInputError(f"observations: frame must be 'map', got {frame!r}")
    feats = doc.get("features")
    if not isinstance(feats, list):
        raise UserInputError("observations: 'features' must be a list")
    if len(feats) > MAX_FEATURES:
        raise UserInputError(f"observations: {len(feats)} features, more than the {MAX_FEATURES} accepted")
    gravity = None
    if doc.get("gravity") is not None:
        gravity = _vector(doc["gravity"], "observations.gravity")
        norm = float(np.linalg.norm(gravity))
        if norm < 1e-6:
            raise UserInputError("observations.gravity: zero vector")
        gravity = gravity / norm
    hints = doc.get("hints") or {}
    if not isinstance(hints, dict):
        raise UserInputError("observations.hints: must be an object")
    storey = hints.get("storey")
    if storey is not None and not isinstance(storey, str):
        raise UserInputError("observations.hints.storey: must be a string")
    out = []
    for i, f in enumerate(feats):
        where = f"observations.features[{i}]"
        if not isinstance(f, dict):
            raise UserInputError(f"{where}: must be an object")
        kind = f.get("type")
        if kind not in FEATURE_TYPES:
            raise UserInputError(f"{where}.type: unknown type {kind!r} (expected one of {', '.join(FEATURE_TYPES)})")
        if f.get("corners") is not None:
            try:
                corners = np.asarray(f["corners"], dtype=float)
            except (TypeError, ValueError):
                raise UserInputError(f"{where}.corners: expected 4 points of 3 numbers") from None
            if corners.shape != (4, 3):
                raise UserInputError(f"{where}.corners: expected 4 points of 3 numbers, got shape "
                                     f"{list(corners.shape)}")
            if not np.all(np.isfinite(corners)):
                raise UserInputError(f"{where}.corners: NaN or infinite value")
            if np.abs(corners).max() > MAX_COORD_M:
                raise UserInputError(f"{where}.corners: coordinate beyond {MAX_COORD_M:g} m")
            out.append(Observation(kind, corners.mean(axis=0), corners))
        elif f.get("centroid") is not None:
            out.append(Observation(kind, _vector(f["centroid"], f"{where}.centroid")))
        else:
            raise UserInputError(f"{where}: needs 'corners' (4 x 3) or 'centroid' (3)")
    return ObservationSet(out, gravity, storey)
