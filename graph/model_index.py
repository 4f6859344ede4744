"""Everything registration needs from a building, computed once per building (and storey hint).

Holds the CAD centroids and rectangles as arrays, a k-d tree per feature type, and the paper's look-up
tables and descriptors. Frames: CAD, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from graph.descriptor import DescriptorTables, build_tables, describe
from graph.features import FEATURE_TYPES, BuildingModel, MacroFeature


@dataclass
class ModelIndex:
    features: list[MacroFeature]
    centroids: np.ndarray  # (N, 3) CAD
    corners: np.ndarray  # (N, 4, 3) CAD
    types: np.ndarray  # (N,) str
    storeys: np.ndarray  # (N,) str
    edge_u: np.ndarray  # (N, 3) unit: corner1 - corner0 direction
    edge_v: np.ndarray  # (N, 3) unit: corner3 - corner0 direction
    len_u: np.ndarray  # (N,) metres
    len_v: np.ndarray  # (N,)
    trees: dict[str, cKDTree]  # per type, over the indices in type_indices
    type_indices: dict[str, np.ndarray]
    tables: DescriptorTables
    codes: np.ndarray  # (N,) uint64 paper descriptors
    _by_storey: dict[str, ModelIndex] = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, features: list[MacroFeature], tables: DescriptorTables | None = None) -> ModelIndex:
        centroids = np.array([f.centroid_cad for f in features], dtype=float).reshape(-1, 3)
        corners = np.array([f.corners_cad for f in features], dtype=float).reshape(-1, 4, 3)
        types = np.array([f.type for f in features])
        eu = corners[:, 1] - corners[:, 0]
        ev = corners[:, 3] - corners[:, 0]
        lu, lv = np.linalg.norm(eu, axis=1), np.linalg.norm(ev, axis=1)
        type_indices = {t: np.flatnonzero(types == t) for t in FEATURE_TYPES}
        trees = {t: cKDTree(centroids[idx]) for t, idx in type_indices.items() if len(idx)}
        tables = build_tables(centroids) if tables is None else tables
        return cls(features=features, centroids=centroids, corners=corners, types=types,
                   storeys=np.array([str(f.storey) for f in features]),
                   edge_u=eu / np.maximum(lu, 1e-9)[:, None], edge_v=ev / np.maximum(lv, 1e-9)[:, None],
                   len_u=lu, len_v=lv, trees=trees, type_indices=type_indices, tables=tables,
                   codes=describe(centroids, list(types), tables))

    def for_storey(self, storey: str | None) -> ModelIndex:
        """The index restricted to one storey (memoised); the whole building for None."""
        if storey is None:
            return self
        if storey not in self._by_storey:
            self._by_storey[storey] = ModelIndex.build([f for f in self.features if str(f.storey) == storey])
        return self._by_storey[storey]


_CACHE: dict[str, ModelIndex] = {}


def index_for(model: BuildingModel) -> ModelIndex:
    """The ModelIndex of a building: memoised per process, its look-up tables cached on disk per building.

    The KDE tables are the costly part of pre-processing (tens of ms); trees and codes rebuild in ~1 ms.
    """
    if model.sha256 in _CACHE:
        return _CACHE[model.sha256]
    from graph.bim import cache_dir, cache_key

    key = cache_key(model.sha256, {"kind": "descriptor-tables", "n": len(model.features)})
    path = cache_dir() / f"tables-{key}.npz"
    tables = None
    if path.exists():
        try:
            with np.load(path) as z:
                tables = DescriptorTables(z["dist_samples_m"], z["angle_samples_rad"], z["dist_edges_m"],
                                          z["angle_edges_rad"])
        except (OSError, KeyError, ValueError):
            tables = None
    index = ModelIndex.build(model.features, tables)
    if tables is None:
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, dist_samples_m=index.tables.dist_samples_m, angle_samples_rad=index.tables.angle_samples_rad,
                 dist_edges_m=index.tables.dist_edges_m, angle_edges_rad=index.tables.angle_edges_rad)
        tmp.replace(path)
    _CACHE[model.sha256] = index
    return index
