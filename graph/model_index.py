"""Everything registration needs from a building, computed once per building (and storey hint).

Holds the CAD centroids and rectangles as arrays, a k-d tree per feature type, and the paper's look-up
tables and descriptors. Frames: CAD, metres.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from macroloc.graph.descriptor import DescriptorTables, build_tables, describe
from macroloc.graph.features import FEATURE_TYPES, BuildingModel, MacroFeature
from macroloc.graph.layout import Layout, build_layout
from macroloc.graph.self_maps import SELF_MAPS_VERSION, SelfMaps, building_self_maps

TYPE_SEPARATION_M = 1.0e4  # the type axis of the lifted k-d tree: farther than any real distance


@dataclass(frozen=True)
class FeaturePairs:
    """Ordered CAD feature pairs: indices, vector j - i (CAD, metres), its horizontal length and height change."""

    i: np.ndarray
    j: np.ndarray
    v: np.ndarray
    d_xy: np.ndarray
    dz: np.ndarray


@dataclass
class ModelIndex:
    features: list[MacroFeature]
    centroids: np.ndarray  # (N, 3) CAD
    corners: np.ndarray  # (N, 4, 3) CAD
    types: np.ndarray  # (N,) str
    type_codes: np.ndarray  # (N,) int8 index into FEATURE_TYPES
    storeys: np.ndarray  # (N,) str
    edge_u: np.ndarray  # (N, 3) unit: corner1 - corner0 direction
    edge_v: np.ndarray  # (N, 3) unit: corner3 - corner0 direction
    len_u: np.ndarray  # (N,) metres
    len_v: np.ndarray  # (N,)
    normals: np.ndarray  # (N, 3) unit wall normal, CAD (its sign is a convention)
    tree_all: cKDTree  # all features, x y z
    tree_typed: cKDTree  # all features in (x, y, z, type code x 1e4 m): a same-type nearest neighbour in one query
    type_indices: dict[str, np.ndarray]
    tables: DescriptorTables
    codes: np.ndarray  # (N,) uint64 paper descriptors
    _by_storey: dict[str, ModelIndex] = field(default_factory=dict, repr=False)
    _pairs: dict[float, FeaturePairs] = field(default_factory=dict, repr=False)
    _self_maps: SelfMaps | None = field(default=None, repr=False)
    _layout: Layout | None = field(default=None, repr=False)
    _pair_rows: dict[float, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, features: list[MacroFeature], tables: DescriptorTables | None = None) -> ModelIndex:
        centroids = np.array([f.centroid_cad for f in features], dtype=float).reshape(-1, 3)
        corners = np.array([f.corners_cad for f in features], dtype=float).reshape(-1, 4, 3)
        types = np.array([f.type for f in features])
        eu = corners[:, 1] - corners[:, 0]
        ev = corners[:, 3] - corners[:, 0]
        lu, lv = np.linalg.norm(eu, axis=1), np.linalg.norm(ev, axis=1)
        type_indices: dict[str, np.ndarray] = {t: np.flatnonzero(types == t) for t in FEATURE_TYPES}
        tables = build_tables(centroids) if tables is None else tables
        lifted = TYPE_SEPARATION_M * np.array([FEATURE_TYPES.index(t) for t in types], dtype=float).reshape(-1, 1)
        return cls(features=features, centroids=centroids, corners=corners, types=types,
                   type_codes=np.array([FEATURE_TYPES.index(t) for t in types], dtype=np.int8),
                   storeys=np.array([str(f.storey) for f in features]),
                   edge_u=eu / np.maximum(lu, 1e-9)[:, None], edge_v=ev / np.maximum(lv, 1e-9)[:, None],
                   len_u=lu, len_v=lv,
                   normals=np.array([f.normal_cad for f in features], dtype=float).reshape(-1, 3),
                   tree_all=cKDTree(centroids),
                   tree_typed=cKDTree(np.concatenate([centroids, lifted], axis=1)),
                   type_indices=type_indices, tables=tables, codes=describe(centroids, list(types), tables))

    def has_type(self, kind: str) -> bool:
        """Whether the building has any feature of this type."""
        return len(self.type_indices.get(kind, ())) > 0

    def pairs_within(self, max_m: float) -> FeaturePairs:
        """Ordered pairs (i, j), i != j, with horizontal distance <= max_m (memoised per distance)."""
        if max_m not in self._pairs:
            pairs = self.tree_all.query_pairs(max_m, output_type="ndarray")
            i = np.concatenate([pairs[:, 0], pairs[:, 1]]) if len(pairs) else np.zeros(0, dtype=np.int64)
            j = np.concatenate([pairs[:, 1], pairs[:, 0]]) if len(pairs) else np.zeros(0, dtype=np.int64)
            v = self.centroids[j] - self.centroids[i]
            self._pairs[max_m] = FeaturePairs(i, j, v, np.linalg.norm(v[:, :2], axis=1), v[:, 2])
        return self._pairs[max_m]

    def pairs_of(self, max_m: float, rows: np.ndarray) -> np.ndarray:
        """Indices into `pairs_within(max_m)` of the pairs whose first feature is one of `rows` (by a CSR look-up:
        the cost grows with the answer, not with the building)."""
        pairs = self.pairs_within(max_m)
        if max_m not in self._pair_rows:
            order = np.argsort(pairs.i, kind="stable")
            starts = np.searchsorted(pairs.i[order], np.arange(len(self.features) + 1))
            self._pair_rows[max_m] = (order, starts)
        order, starts = self._pair_rows[max_m]
        rows = np.asarray(rows, dtype=np.int64)
        if not len(rows):
            return np.zeros(0, dtype=np.int64)
        return np.concatenate([order[starts[r]:starts[r + 1]] for r in rows])

    def layout(self) -> Layout:
        """The features' layout descriptors (`graph.layout`), computed once per index."""
        if self._layout is None:
            self._layout = build_layout(self.centroids, self.normals, self.type_codes, tree=self.tree_all)
        return self._layout

    def self_maps(self) -> SelfMaps:
        """The building's near-self-maps (`graph.self_maps`), computed once per index."""
        if self._self_maps is None:
            self._self_maps = building_self_maps(self.centroids, self.normals, self.type_codes)
        return self._self_maps

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
    from macroloc.graph.bim import cache_dir, cache_key

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
        tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npz")  # one per process: two may build at once
        np.savez(tmp, dist_samples_m=index.tables.dist_samples_m, angle_samples_rad=index.tables.angle_samples_rad,
                 dist_edges_m=index.tables.dist_edges_m, angle_edges_rad=index.tables.angle_edges_rad)
        tmp.replace(path)
    _load_self_maps(index, cache_dir() / f"selfmaps-v{SELF_MAPS_VERSION}-{key}.npz")
    index.layout()  # pre-processing too: the registration ranks its candidates by it
    _CACHE[model.sha256] = index
    return index


def _load_self_maps(index: ModelIndex, path: Path) -> None:
    """The building's self-maps from the disk cache at `path`, computed and written there when absent."""
    try:
        with np.load(path) as z:
            index._self_maps = SelfMaps(z["yaw_rad"], z["shift_m"], z["votes"], z["lands"])
            return
    except (OSError, KeyError, ValueError):
        pass
    maps = index.self_maps()
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, yaw_rad=maps.yaw_rad, shift_m=maps.shift_m, votes=maps.votes, lands=maps.lands)
    tmp.replace(path)
