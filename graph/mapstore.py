"""A flight's map, saved and loaded: keyframes, landmarks (with their CAD links) and T_cad_map.

JSON, one document: {"version", "building_sha256", "T_cad_map": 4x4, "keyframes": [{"stamp_ns", "T_map_body",
"view"?}], "landmarks": [{"key", "type", "T_map_rect", "corners_map", "feature"}], "carried_views"?: [{"T_map_body",
"view"}]}. Frames as in graph.localizer.

Place recognition has two things to go on here. The landmarks: a new flight's first sightings aligned to the
stored CAD-linked rectangles (graph.relocalize). And, where the flight that made the map kept them, its
keyframes' views (`KeyframeView`: image features with their 3D points, perception.place): a new flight's
first keyframe matched to them is placed in the stored map before it sees any door. A view is stored as
base64 of its little-endian arrays ("points_body": float32 (N, 3), "descriptors": uint8 (N, 32)); "carried_views"
[{"T_map_body", "view"}] are an earlier map's, where this flight made none near (`carried_views`).
Version 1 maps (no views) load as they are.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from macroloc.common.views import KeyframeView
from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.relocalize import KnownRect

MAP_VERSION = 2
VIEW_SPACING_M, VIEW_SPACING_DEG = 0.5, 15.0  # one view of a place will do within this of another


PlacedView = tuple[np.ndarray, KeyframeView]  # (T_map_body, view)



@dataclass
class StoredLandmark:
    key: int
    type: str
    T_map_rect: np.ndarray  # 4x4
    corners_map: np.ndarray  # (4, 3)
    feature: str | None  # CAD feature id when linked


@dataclass
class StoredMap:
    building_sha256: str
    T_cad_map: np.ndarray | None
    keyframes: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (stamp_ns, T_map_body)
    landmarks: list[StoredLandmark] = field(default_factory=list)
    views: dict[int, KeyframeView] = field(default_factory=dict)  # keyframe index -> its view, where kept
    carried: list[PlacedView] = field(default_factory=list)  # an earlier map's views, this map's frame

    def placed_views(self) -> list[PlacedView]:
        """(T_map_body, view) of every keyframe with a view, then the carried views: what place recognition
        matches a new flight to."""
        own = [(self.keyframes[i][1], v) for i, v in sorted(self.views.items()) if i < len(self.keyframes)]
        return own + self.carried

    def known_rects(self, model: BuildingModel) -> list[KnownRect]:
        """The model's frames of every feature this map linked: what a new flight re-localizes against."""
        by_id = {f.id: f for f in model.features}
        ids = sorted({lm.feature for lm in self.landmarks if lm.feature in by_id})
        return [KnownRect(i, by_id[i].type, feature_frame_cad(by_id[i])) for i in ids]

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        doc = {"version": MAP_VERSION, "building_sha256": self.building_sha256,
               "T_cad_map": None if self.T_cad_map is None else self.T_cad_map.tolist(),
               "keyframes": [{"stamp_ns": s, "T_map_body": T.tolist(),
                              **({"view": self.views[i].to_json()} if i in self.views else {})}
                             for i, (s, T) in enumerate(self.keyframes)],
               "landmarks": [{"key": lm.key, "type": lm.type, "T_map_rect": lm.T_map_rect.tolist(),
                              "corners_map": lm.corners_map.tolist(), "feature": lm.feature}
                             for lm in self.landmarks],
               "carried_views": [{"T_map_body": T.tolist(), "view": v.to_json()} for T, v in self.carried]}
        path.write_text(json.dumps(doc))
        return path

    @classmethod
    def load(cls, path: str | Path, model: BuildingModel | None = None) -> StoredMap:
        """Read a map; with `model`, refuse a map made in another building (UserInputError)."""
        path = Path(path)
        if not path.is_file():
            raise UserInputError(f"stored map not found: {path}")
        try:
            doc = json.loads(path.read_text())
            out = cls(doc["building_sha256"], None if doc["T_cad_map"] is None else np.array(doc["T_cad_map"]),
                      [(int(k["stamp_ns"]), np.array(k["T_map_body"])) for k in doc["keyframes"]],
                      [StoredLandmark(int(d["key"]), d["type"], np.array(d["T_map_rect"]), np.array(d["corners_map"]),
                                      d["feature"]) for d in doc["landmarks"]],
                      {i: KeyframeView.from_json(k["view"]) for i, k in enumerate(doc["keyframes"]) if "view" in k},
                      [(np.array(d["T_map_body"]), KeyframeView.from_json(d["view"]))
                       for d in doc.get("carried_views", [])])
        except (ValueError, KeyError, TypeError) as exc:  # a bad base64 view is a ValueError too
            raise UserInputError(f"stored map {path} is not a macroloc map: {exc}") from None
        if model is not None and out.building_sha256 != model.sha256:
            raise UserInputError(f"stored map {path} was made in another building")
        return out


def carried_views(own: list[PlacedView], T_cad_map: np.ndarray, earlier: StoredMap,
                  apart_m: float = VIEW_SPACING_M, apart_deg: float = VIEW_SPACING_DEG) -> list[PlacedView]:
    """The `earlier` map's views (`placed_views`) moved into the frame of a map with `T_cad_map`, less those within
    `apart_m` and `apart_deg` of one of its `own` (T_map_body, view): the places it has no view of, for a later
    flight to be placed by, without piling up views of the same places flight after flight. None where the
    earlier map was not localized."""
    if earlier.T_cad_map is None:
        return []
    T_map_earlier = np.linalg.inv(T_cad_map) @ earlier.T_cad_map
    moved = [(T_map_earlier @ T, v) for T, v in earlier.placed_views()]
    if not moved or not own:
        return moved
    A, B = np.array([T for T, _ in moved]), np.array([T for T, _ in own])
    near = cKDTree(B[:, :3, 3]).query_ball_point(A[:, :3, 3], r=apart_m)  # own views within apart_m of each
    cos_apart = np.cos(np.radians(apart_deg))
    # trace(Ra^T Rb) = 1 + 2 cos(angle between them)
    covered = [bool(nb) and bool(((np.einsum("ij,bij->b", A[a, :3, :3], B[nb, :3, :3]) - 1.0) / 2.0 > cos_apart).any())
               for a, nb in enumerate(near)]
    return [m for m, c in zip(moved, covered, strict=True) if not c]
