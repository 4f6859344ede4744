"""Everything registration needs from a building, computed once per building (and storey hint).

Holds the CAD centroids and rectangles as arrays, a k-d tree per feature type, and the paper's look-up
tables and descriptors. Frames: CAD, metres.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from macroloc.graph.descriptor import DescriptorTables, build_tables, describe
from macroloc.graph.features import FEATURE_TYPES, BuildingModel, MacroFeature
from macroloc.graph.layout import Layout, LayoutParams, build_layout
from macroloc.graph.self_maps import SELF_MAPS_VERSION, SelfMaps, building_self_maps

TYPE_SEPARATION_M = 1.0e4  # the type axis of the lifted k-d tree: farther than any real distance
PAIRS_VERSION = 2  # bump when pairs_within or its row look-up changes: the disk cache is keyed by it
LAYOUT_CACHE_VERSION = 1  # ... and when graph.layout.build_layout changes


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
    cache_key: str | None = field(default=None, repr=False)  # its assets' names on disk (index_for); None: none
    _assets: dict[str, dict[str, np.ndarray]] = field(default_factory=dict, repr=False)

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
            self._set_pairs(max_m, i, j)
        return self._pairs[max_m]

    def prepare_pairs(self, max_m: float) -> None:
        """Build `pairs_within(max_m)` and its row look-up (`pairs_of`) now, from the disk cache where this index
        has a `cache_key` (written there when absent): per-building work (0.35 s at 10k features and 2.1 million
        pairs within 30 m), which a registration must not do inside its timed block (a one-shot command runs one
        registration a process)."""
        if max_m in self._pairs and max_m in self._pair_rows:
            return
        path = None if self.cache_key is None else _cache_path(f"pairs-v{PAIRS_VERSION}-{self.cache_key}-{max_m!r}")
        if path is not None:
            try:
                with np.load(path) as z:  # the vectors too: reading them is ~4x faster than computing them
                    self._pairs[max_m] = FeaturePairs(z["i"].astype(np.int64), z["j"].astype(np.int64), z["v"],
                                                      z["d_xy"], z["dz"])
                    self._pair_rows[max_m] = (z["order"].astype(np.int64), z["starts"].astype(np.int64))
                    return
            except (OSError, KeyError, ValueError):
                pass
        self.pairs_of(max_m, np.zeros(0, dtype=np.int64))
        if path is not None:
            pairs, (order, starts) = self._pairs[max_m], self._pair_rows[max_m]
            small = np.int32 if max(len(self.features), len(order)) < np.iinfo(np.int32).max else np.int64
            _save(path, i=pairs.i.astype(small), j=pairs.j.astype(small), v=pairs.v, d_xy=pairs.d_xy, dz=pairs.dz,
                  order=order.astype(small), starts=starts)

    def _set_pairs(self, max_m: float, i: np.ndarray, j: np.ndarray) -> None:
        v = self.centroids[j] - self.centroids[i]
        self._pairs[max_m] = FeaturePairs(i, j, v, np.linalg.norm(v[:, :2], axis=1), v[:, 2])

    def asset(self, name: str, build: Callable[[ModelIndex], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """Arrays that another module derives from this building alone (`build`; `name`: what and its version,
        e.g. "posterior-v1"): memoised, and cached on disk where the index has a `cache_key`, so that a one-shot
        command reads them instead of computing them in every process. Call it before a registration's timed
        block (graph.robust.prepare)."""
        if name not in self._assets:
            path = None if self.cache_key is None else _cache_path(f"{name}-{self.cache_key}")
            arrays = None
            if path is not None:
                try:
                    with np.load(path) as z:
                        arrays = {k: z[k] for k in z.files}
                except (OSError, KeyError, ValueError):
                    arrays = None
            if arrays is None:
                arrays = build(self)
                if path is not None:
                    _save(path, **arrays)
            self._assets[name] = arrays
        return self._assets[name]

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
            features = [f for f in self.features if str(f.storey) == storey]
            if self.cache_key is None or not features:  # none: nothing to cache (no self-maps, layout of none)
                self._by_storey[storey] = ModelIndex.build(features)
            else:  # its own assets, cached on disk as the whole building's are
                tag = hashlib.sha256(storey.encode()).hexdigest()[:12]
                self._by_storey[storey] = _build_cached(features, f"{self.cache_key}-storey-{tag}")
        return self._by_storey[storey]


_CACHE: dict[str, ModelIndex] = {}


def index_for(model: BuildingModel) -> ModelIndex:
    """The ModelIndex of a building: memoised per process, its per-building assets cached on disk by the building's
    SHA-256 (graph.bim.cache_key) and built here, before any registration: the descriptor tables (KDE, the costly
    part of the tables), the self-maps, the layout histograms and the pair table of the default pair baseline
    (`RobustParams.pair_max_baseline_m`; a registration with another prepares its own, `prepare_pairs`).
    A one-shot command reads them from disk instead of building them again in every process; trees and descriptor
    codes are rebuilt (a few ms per thousand features).
    """
    if model.sha256 in _CACHE:
        return _CACHE[model.sha256]
    from macroloc.graph.bim import cache_key

    index = _build_cached(model.features, cache_key(model.sha256, {"kind": "descriptor-tables",
                                                                  "n": len(model.features)}))
    _CACHE[model.sha256] = index
    return index


def _build_cached(features: list[MacroFeature], key: str) -> ModelIndex:
    """A ModelIndex of `features` with its assets read from the disk cache under `key` (built and written there
    when absent): descriptor tables, self-maps, layout, the default pair table."""
    from macroloc.graph.params import RobustParams

    path = _cache_path(f"tables-{key}")
    tables = None
    if path.exists():
        try:
            with np.load(path) as z:
                tables = DescriptorTables(z["dist_samples_m"], z["angle_samples_rad"], z["dist_edges_m"],
                                          z["angle_edges_rad"])
        except (OSError, KeyError, ValueError):
            tables = None
    index = ModelIndex.build(features, tables)
    index.cache_key = key
    if tables is None:
        _save(path, dist_samples_m=index.tables.dist_samples_m, angle_samples_rad=index.tables.angle_samples_rad,
              dist_edges_m=index.tables.dist_edges_m, angle_edges_rad=index.tables.angle_edges_rad)
    _load_self_maps(index, _cache_path(f"selfmaps-v{SELF_MAPS_VERSION}-{key}"))
    _load_layout(index, _cache_path(f"layout-v{LAYOUT_CACHE_VERSION}-{key}-{_digest(LayoutParams())}"))
    index.prepare_pairs(RobustParams().pair_max_baseline_m)
    return index


def _cache_path(stem: str) -> Path:
    from macroloc.graph.bim import cache_dir

    return cache_dir() / f"{stem}.npz"


def _digest(params: object) -> str:
    return hashlib.sha256(repr(params).encode()).hexdigest()[:12]


def _save(path: Path, **arrays: np.ndarray) -> None:
    """Write arrays to `path` atomically (a temporary name per process, then a rename: two may build at once)."""
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npz")
    np.savez(tmp, **arrays)  # type: ignore[arg-type]
    tmp.replace(path)


def _load_self_maps(index: ModelIndex, path: Path) -> None:
    """The building's self-maps from the disk cache at `path`, computed and written there when absent."""
    try:
        with np.load(path) as z:
            index._self_maps = SelfMaps(z["yaw_rad"], z["shift_m"], z["votes"], z["lands"])
            return
    except (OSError, KeyError, ValueError):
        pass
    maps = index.self_maps()
    _save(path, yaw_rad=maps.yaw_rad, shift_m=maps.shift_m, votes=maps.votes, lands=maps.lands)


def _load_layout(index: ModelIndex, path: Path) -> None:
    """The features' layout histograms (`graph.layout`, default parameters) from the disk cache at `path`,
    computed and written there when absent (~2 s at 10k features)."""
    try:
        with np.load(path) as z:
            index._layout = Layout(z["dilated"], z["weight"], z["dz_edges"], z["d_edges"], z["w_edges"],
                                   LayoutParams())
            return
    except (OSError, KeyError, ValueError):
        pass
    lay = index.layout()
    _save(path, dilated=lay.dilated, weight=lay.weight, dz_edges=lay.dz_edges, d_edges=lay.d_edges,
          w_edges=lay.w_edges)
