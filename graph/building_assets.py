"""A building's prepared assets, read from its IFC file once and cached on disk by the file's SHA-256
(graph.bim.cache_dir), each written atomically as soon as it is built (a temporary name, then a rename): its
solids (the obstacle triangles and the IfcSpaces, for planning), every surface a camera sees (`surfaces_for`, for
checking registrations against depth: graph.surfaces) and the walls as voxels (`wall_voxels`, for line-of-sight
checks). `macroloc prepare BUILDING` builds them ahead (service/assets.py); anything that needs one builds it
lazily. CAD frame, metres.
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
