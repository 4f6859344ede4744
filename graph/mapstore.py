"""A flight's map, saved and loaded: keyframes, landmarks (with their CAD links) and T_cad_map.

JSON, one document: {"version", "building_sha256", "T_cad_map": 4x4, "keyframes": [{"stamp_ns", "T_map_body"}],
"landmarks": [{"key", "type", "T_map_rect", "corners_map", "feature"}]}. Frames as in graph.localizer.
What place recognition needs here is the landmarks themselves: a new flight re-localizes by aligning its
first sightings to the stored CAD-linked rectangles (graph.relocalize).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from graph.errors import UserInputError
from graph.features import BuildingModel
from graph.landmarks import feature_frame_cad
from graph.relocalize import KnownRect

MAP_VERSION = 1


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
               "keyframes": [{"stamp_ns": s, "T_map_body": T.tolist()} for s, T in self.keyframes],
               "landmarks": [{"key": lm.key, "type": lm.type, "T_map_rect": lm.T_map_rect.tolist(),
                              "corners_map": lm.corners_map.tolist(), "feature": lm.feature}
                             for lm in self.landmarks]}
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
                                      d["feature"]) for d in doc["landmarks"]])
        except (ValueError, KeyError, TypeError) as exc:
            raise UserInputError(f"stored map {path} is not a macroloc map: {exc}") from None
        if model is not None and out.building_sha256 != model.sha256:
            raise UserInputError(f"stored map {path} was made in another building")
        return out
