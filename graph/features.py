"""Macro-features of a building: the typed record every other module speaks.

Frames: everything here is in the CAD frame (the model's world frame, z up), metres.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from macroloc.graph.errors import UserInputError

FeatureType = Literal["door", "window"]
FEATURE_TYPES: tuple[FeatureType, ...] = ("door", "window")
Orientation = Literal["vertical", "horizontal"]


@dataclass(frozen=True)
class MacroFeature:
    """One door or window of the model.

    corners_cad: (4, 3) opening rectangle, ordered (-u,-z) (+u,-z) (+u,+z) (-u,+z) with u = z x normal
    (for a horizontal skylight the rectangle spans u and the horizontal normal direction instead of z).
    normal_cad: unit horizontal wall normal (+z for a skylight); its sign points away from the building's
    horizontal centre of features.
    """

    id: str
    type: FeatureType
    storey: str | None
    corners_cad: np.ndarray
    centroid_cad: np.ndarray
    normal_cad: np.ndarray
    width_m: float
    height_m: float
    orientation: Orientation = "vertical"
    name: str | None = None
    duplicates: tuple[str, ...] = ()

    def to_json(self) -> dict:
        return {
            "id": self.id,
            "type": self.type,
            "storey": self.storey,
            "centroid": [round(float(v), 5) for v in self.centroid_cad],
            "corners": [[round(float(v), 5) for v in c] for c in self.corners_cad],
            "normal": [round(float(v), 5) for v in self.normal_cad],
            "width": round(self.width_m, 4),
            "height": round(self.height_m, 4),
            "orientation": self.orientation,
        }


@dataclass
class BuildingModel:
    """A building's macro-features plus what was learnt while reading it."""

    source: str
    sha256: str
    features: list[MacroFeature]
    storeys: list[str] = field(default_factory=list)
    storey_elevations_m: dict[str, float] = field(default_factory=dict)
    report: dict = field(default_factory=dict)  # counts: elements, no_geometry, duplicates_merged, ...

    def centroids_cad(self) -> np.ndarray:
        """(N, 3) feature centroids in the CAD frame, metres."""
        return np.array([f.centroid_cad for f in self.features], dtype=float).reshape(-1, 3)

    def checked_storey(self, name: str | None) -> str | None:
        """`name` when some door or window of the model is on that storey (None passes); else UserInputError."""
        known = sorted({f.storey for f in self.features if f.storey})
        if name is not None and name not in known:
            raise UserInputError(f"storey {name!r} has no doors or windows in {self.source} "
                                 f"(storeys: {', '.join(known) or 'none'})")
        return name

    def by_storey(self) -> dict[str | None, list[MacroFeature]]:
        out: dict[str | None, list[MacroFeature]] = {}
        for f in self.features:
            out.setdefault(f.storey, []).append(f)
        return out


class CentroidsByType:
    """The centroids of each type of some features (a model's, one per id), (N, 3) CAD frame, metres: computed
    once per type."""

    def __init__(self, features: Iterable[MacroFeature]) -> None:
        self._features = list(features)
        self._by_type: dict[str, np.ndarray] = {}

    def __call__(self, kind: str) -> np.ndarray:
        if kind not in self._by_type:
            self._by_type[kind] = np.array([f.centroid_cad for f in self._features
                                            if f.type == kind]).reshape(-1, 3)
        return self._by_type[kind]
