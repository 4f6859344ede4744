"""The 2D occupancy grid of paper §3.3: the building model's cross-section at flight height, plus what was seen.

Grid convention: cell (row, col) covers x in [x0 + col·cell, x0 + (col+1)·cell), y in [y0 + row·cell, ...)
of the CAD frame (metres, z up); its centre is `cell_centre_cad`. Everything here is in the CAD frame.

The static layer comes from the building's solids (walls, slabs, stairs, railings, furniture, …) cut by the
horizontal plane z = storey elevation + flight height. Doors, windows, openings and spaces are left out, and
ifcopenshell subtracts the openings from the walls, so doorways are gaps in the section: a drone passes.
The dynamic layer counts depth points (CAD frame) inside a height band around the flight height: a 2D
projection of a voxel grid, which is all a 2D planner consumes: 0.9 ms per frame of 18,500 depth points
against 11 ms for an OctoMap with ray casting (pyoctomap, 13x; `python -m bench.bench_obstacles`). It does not
clear cells seen free again, as OctoMap would: an obstacle that leaves stays until the layer is reset.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from macroloc.graph.bim import cache_dir, file_sha256

if TYPE_CHECKING:
    from macroloc.graph.surfaces import SurfaceIndex, WallVoxels

log = logging.getLogger(__name__)

NOT_OBSTACLES = ("IfcDoor", "IfcWindow", "IfcOpeningElement", "IfcSpace", "IfcAnnotation", "IfcVirtualElement")
NOT_SEEN = ("IfcOpeningElement", "IfcSpace", "IfcAnnotation", "IfcVirtualElement")  # no surface a camera sees
# what no camera sees through (for line-of-sight checks): not furniture (between its legs), railings, curtain walls
# and their plates (glass), doors or windows
OPAQUE = ("IfcWall", "IfcWallStandardCase", "IfcWallElementedCase", "IfcColumn")
MESH_CACHE_VERSION = 2  # 2: triangles in the elements' id order (1: the iterator's threads' order)


@dataclass(frozen=True)
class Space:
    """An IfcSpace: its Name (often the room number), LongName, and footprint centroid (CAD, metres)."""

    name: str
    long_name: str
    centroid_xy_cad: tuple[float, float]
    floor_z_cad: float


@dataclass
class BuildingSolids:
    """Triangles of every obstacle element (CAD frame, metres) and the building's spaces."""

    vertices_cad: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    spaces: list[Space] = field(default_factory=list)


def load_solids(ifc_path: Path, with_doors_and_windows: bool = False) -> BuildingSolids:
    """Obstacle triangles and spaces of an IFC file, cached by its SHA-256 (the geometry takes seconds).
    `with_doors_and_windows`: every surface a camera sees (the doors' leaves and the windows' frames too), for
    checking what a camera measured against the model (graph.surfaces), not for planning."""
    sha = file_sha256(ifc_path)
    kind = "seen" if with_doors_and_windows else "solids"
    cached = cache_dir() / f"{kind}-v{MESH_CACHE_VERSION}-{sha[:32]}.npz"
    if cached.exists():
        with np.load(cached) as npz:
            spaces = [Space(**s) for s in json.loads(str(npz["spaces_json"]))]
            return BuildingSolids(npz["vertices"], npz["faces"], spaces)
    solids = _read_solids(ifc_path, NOT_SEEN if with_doors_and_windows else NOT_OBSTACLES)
    tmp = cached.with_name(f"{cached.stem}.tmp{os.getpid()}.npz")
    np.savez_compressed(tmp, vertices=solids.vertices_cad, faces=solids.faces,
                        spaces_json=json.dumps([s.__dict__ for s in solids.spaces]))
    os.replace(tmp, cached)
    return solids


def _iterate_shapes(ifc_file, **filters):  # noqa: ANN001, ANN202 - ifcopenshell types
    """(element, vertices (V, 3), faces (F, 3)) of each shape, in the elements' id order: the iterator's two
    threads hand them over in whichever order they finish, and the cached meshes' triangle order decides which
    points the surface index samples, and so a replay's answer (docs/measurements.md, "Mesh order and the surface
    index")."""
    import ifcopenshell.geom

    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)  # vertices in the CAD (model) frame
    it = ifcopenshell.geom.iterator(settings, ifc_file, max(1, min(2, os.cpu_count() or 1)), **filters)
    if not it.initialize():
        return
    shapes = []
    while True:
        shape = it.get()
        geometry = shape.geometry
        shapes.append((shape.id, np.array(geometry.verts).reshape(-1, 3), np.array(geometry.faces).reshape(-1, 3)))
        if not it.next():
            break
    for element_id, verts, faces in sorted(shapes, key=lambda s: s[0]):
        yield ifc_file.by_id(element_id), verts, faces


def _read_solids(ifc_path: Path, exclude: tuple[str, ...] = NOT_OBSTACLES,
                 include: tuple[str, ...] | None = None) -> BuildingSolids:
    """The triangles of every element but `exclude`d ones (or of the `include`d ones only), and the spaces."""
    import ifcopenshell

    ifc_file = ifcopenshell.open(str(ifc_path))
    vertices, faces, offset = [], [], 0
    filters = {"include": list(include)} if include else {"exclude": list(exclude)}
    for _, verts, tris in _iterate_shapes(ifc_file, **filters):
        vertices.append(verts)
        faces.append(tris + offset)
        offset += len(verts)
    spaces = []
    if ifc_file.by_type("IfcSpace"):
        for element, verts, _ in _iterate_shapes(ifc_file, include=["IfcSpace"]):
            if len(verts):
                centre = verts[:, :2].mean(axis=0)
                spaces.append(Space(str(element.Name or ""), str(element.LongName or ""),
                                    (float(centre[0]), float(centre[1])), float(verts[:, 2].min())))
    log.info("%s: %d obstacle triangles, %d spaces", ifc_path.name, offset and sum(len(f) for f in faces),
             len(spaces))
    if not vertices:
        return BuildingSolids(np.zeros((0, 3)), np.zeros((0, 3), np.int64), spaces)
    return BuildingSolids(np.vstack(vertices), np.vstack(faces).astype(np.int64), spaces)


def surfaces_for(building: Path, line_of_sight: bool = True) -> SurfaceIndex | None:
    """The model's surfaces for checking registrations against depth (graph.surfaces): every surface a camera
    sees in an IFC model, and (`line_of_sight`) its walls as voxels; None (logged) for other formats, whose
    registrations then go unchecked. Cached by the file's SHA-256 and the surface parameters."""
    import hashlib

    from macroloc.graph.bim import is_ifc
    from macroloc.graph.surfaces import SurfaceIndex, SurfaceParams

    if not is_ifc(building):
        log.info("%s: no surface check of registrations (IFC models only)", Path(building).name)
        return None
    walls = wall_voxels(Path(building)) if line_of_sight else None
    params = SurfaceParams()
    # the samples are seeded, so a cached index is the one built: ~2 s of sampling and hidden-face tests saved
    settings = hashlib.sha256(f"{params!r} walls={line_of_sight}".encode()).hexdigest()[:12]
    cached = cache_dir() / f"surfaces-v{MESH_CACHE_VERSION}-{file_sha256(Path(building))[:32]}-{settings}.npz"
    if cached.exists():
        with np.load(cached) as a:
            index = SurfaceIndex(a["samples"], params, a["normals"], a["horizontal"], a["horizontal_normals"])
        index.walls = walls
    else:
        seen = load_solids(Path(building), with_doors_and_windows=True)
        index = SurfaceIndex.from_mesh(seen.vertices_cad, seen.faces, params, walls=walls)
        h_samples, h_normals = (index.horizontal[1], index.horizontal[2]) if index.horizontal is not None \
            else (np.zeros((0, 3)), np.zeros((0, 3)))
        assert index.normals_cad is not None  # from_mesh gives every sample its normal
        tmp = cached.with_name(f"{cached.stem}.tmp{os.getpid()}.npz")
        np.savez(tmp, samples=index.samples_cad, normals=index.normals_cad, horizontal=h_samples,
                 horizontal_normals=h_normals)
        os.replace(tmp, cached)
    log.info("%s: %d surface samples and %d wall voxels for checking registrations", Path(building).name, len(index),
             len(index.walls) if index.walls is not None else 0)
    return index


def wall_voxels(ifc_path: Path) -> WallVoxels:
    """The walls and columns of an IFC model (`OPAQUE`; their openings subtracted: a camera sees through doorways
    and windows) as voxels for line-of-sight checks (graph.surfaces.WallVoxels); cached by the file's SHA-256
    (reading the geometry takes seconds)."""
    from macroloc.graph.surfaces import WallVoxels

    cached = cache_dir() / f"opaque-voxels-v{MESH_CACHE_VERSION}-{file_sha256(ifc_path)[:32]}.npy"
    if cached.exists():
        return WallVoxels(np.load(cached))
    walls_only = _read_solids(ifc_path, include=OPAQUE)
    walls = WallVoxels.from_mesh(walls_only.vertices_cad, walls_only.faces)
    tmp = cached.with_name(f"{cached.stem}.tmp{os.getpid()}.npy")
    np.save(tmp, walls.keys)
    os.replace(tmp, cached)
    return walls


@dataclass
class OccupancyGrid:
    """A horizontal occupancy grid at height z_cad. occupied: (H, W) bool, True = an obstacle in that cell."""

    occupied: np.ndarray
    origin_xy_cad: np.ndarray  # (2,) x, y of the corner of cell (0, 0), metres
    cell_m: float
    z_cad: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupied.shape  # type: ignore[return-value]

    def cell_of(self, xy_cad: np.ndarray) -> tuple[int, int]:
        """The (row, col) holding the CAD point (x, y), clipped into the grid."""
        col, row = np.floor((np.asarray(xy_cad, float)[:2] - self.origin_xy_cad) / self.cell_m).astype(int)
        h, w = self.shape
        return int(np.clip(row, 0, h - 1)), int(np.clip(col, 0, w - 1))

    def contains(self, xy_cad: np.ndarray) -> bool:
        """True when the CAD point (x, y) is finite and on the grid (not clipped into it)."""
        xy = np.asarray(xy_cad, float)[:2]
        if not np.isfinite(xy).all():
            return False
        h, w = self.shape
        extent_xy = np.array([w, h], float) * self.cell_m
        return bool(((xy >= self.origin_xy_cad) & (xy < self.origin_xy_cad + extent_xy)).all())

    def centre_cad(self, cells_rc: np.ndarray) -> np.ndarray:
        """(N, 2) rows/cols -> (N, 3) CAD points at cell centres, z = z_cad."""
        rc = np.asarray(cells_rc, float).reshape(-1, 2)
        xy = self.origin_xy_cad + (rc[:, ::-1] + 0.5) * self.cell_m
        return np.column_stack([xy, np.full(len(xy), self.z_cad)])


def section_grid(solids: BuildingSolids, z_cad: float, cell_m: float, margin_m: float = 1.0) -> OccupancyGrid:
    """The cross-section of the solids by the plane z = z_cad, rasterised into cells of cell_m metres."""
    import cv2
    import trimesh.intersections

    v = solids.vertices_cad
    lo = v[:, :2].min(axis=0) - margin_m
    hi = v[:, :2].max(axis=0) + margin_m
    w, h = (np.ceil((hi - lo) / cell_m).astype(int) + 1).tolist()
    occupied = np.zeros((h, w), np.uint8)
    tri_z = v[solids.faces][:, :, 2]
    crossing = solids.faces[(tri_z.min(axis=1) <= z_cad) & (tri_z.max(axis=1) >= z_cad)]
    if len(crossing):
        segments = trimesh.intersections.mesh_plane(
            trimesh.Trimesh(v, crossing, process=False), plane_normal=[0, 0, 1], plane_origin=[0, 0, z_cad])
        # pixel coordinates with 4 fractional bits: x -> col, y -> row
        pts = np.round((segments[:, :, :2] - lo) / cell_m * 16 - 8).astype(np.int32)
        for a, b in pts:
            cv2.line(occupied, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, 1, cv2.LINE_8, 4)
    return OccupancyGrid(occupied.astype(bool), lo, cell_m, z_cad)


class ObstacleLayer:
    """Obstacles seen in depth that the model lacks: hits per cell of points within a band around z_cad."""

    def __init__(self, shape: tuple[int, int], min_hits: int = 3, band_m: float = 0.5) -> None:
        self.hits = np.zeros(shape, np.int32)
        self.min_hits = min_hits
        self.band_m = band_m

    def add_points(self, grid: OccupancyGrid, points_cad: np.ndarray) -> int:
        """Count (N, 3) CAD points within ±band_m of the grid's height; returns how many were counted."""
        p = np.asarray(points_cad, float).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1) & (np.abs(p[:, 2] - grid.z_cad) <= self.band_m)]
        rc = np.floor((p[:, :2] - grid.origin_xy_cad) / grid.cell_m).astype(int)[:, ::-1]
        inside = (rc >= 0).all(axis=1) & (rc[:, 0] < self.hits.shape[0]) & (rc[:, 1] < self.hits.shape[1])
        np.add.at(self.hits, (rc[inside, 0], rc[inside, 1]), 1)
        return int(inside.sum())

    def occupied(self) -> np.ndarray:
        return self.hits >= self.min_hits


def inflate(occupied: np.ndarray, radius_m: float, cell_m: float) -> np.ndarray:
    """Free cells (True) whose centre is farther than radius_m from every occupied cell's centre."""
    from scipy.ndimage import distance_transform_edt

    if not occupied.any():
        return np.ones_like(occupied, bool)
    return distance_transform_edt(~occupied) * cell_m > radius_m
