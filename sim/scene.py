"""The building's geometry for the simulator: triangles per element class, CAD frame, metres.

IFC files go through ifcopenshell's geometry iterator with world coordinates (already metres); meshes (OBJ,
GLB, DAE, ...) through trimesh, with their unit scale. The result is cached per file hash in the macroloc cache.

A `SceneGeometry` is a triangle soup: `triangles_cad` (T, 3, 3) with per-triangle class, element index, IFC
style colour and a glass flag. IfcSpace volumes are kept apart (`space_triangles_cad`): they are not rendered
but tell the flight planner where the inside of the building is.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

import ifcopenshell.geom
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from macroloc.graph.bim import IFC_SUFFIXES, MESH_SUFFIXES, cache_dir, cache_key, file_sha256
from macroloc.graph.bim_ifc import geometry_settings, open_ifc
from macroloc.graph.bim_mesh import model_mesh_file, read_nodes, world_includes
from macroloc.graph.errors import BuildingError

log = logging.getLogger(__name__)

SCENE_VERSION = 2  # 2: closed solids wound outward, tri_closed
# element classes (values stored per triangle)
WALL, SLAB, DOOR, WINDOW, STAIR, FURNITURE, COVERING, OTHER = range(8)
CLASS_NAMES = ("wall", "slab", "door", "window", "stair", "furniture", "covering", "other")
_IFC_CLASS = {
    "IfcWall": WALL, "IfcWallStandardCase": WALL, "IfcCurtainWall": WALL, "IfcColumn": WALL, "IfcPlate": WALL,
    "IfcSlab": SLAB, "IfcRoof": SLAB, "IfcFooting": SLAB, "IfcBeam": WALL,
    "IfcDoor": DOOR, "IfcDoorStandardCase": DOOR, "IfcWindow": WINDOW, "IfcWindowStandardCase": WINDOW,
    "IfcStair": STAIR, "IfcStairFlight": STAIR, "IfcRailing": STAIR, "IfcRamp": STAIR, "IfcRampFlight": STAIR,
    "IfcMember": STAIR,
    "IfcFurnishingElement": FURNITURE, "IfcFurniture": FURNITURE,
    "IfcCovering": COVERING,
}
_SKIPPED = ("IfcSpace", "IfcOpeningElement", "IfcSite", "IfcAnnotation", "IfcGrid", "IfcVirtualElement")
GLASS_TRANSPARENCY = 0.5  # an IFC style at least this transparent is glass


@dataclass
class SceneGeometry:
    """Triangles of a building, CAD frame (z up), metres.

    triangles_cad: (T, 3, 3) float32; tri_class: (T,) int8 (WALL, SLAB, ...); tri_element: (T,) int32 index
    into element_ids; tri_colour: (T, 3) float32 linear RGB in [0, 1] (the model's own style colour);
    tri_glass: (T,) bool; element_ids: GlobalIds (or mesh node names); space_triangles_cad: (S, 3, 3);
    tri_closed: (T,) bool, the triangle bounds a closed solid and is wound outward (counter-clockwise seen from
    outside), so the renderer may cull it from behind; None: not known (all drawn double-sided).
    """

    source: str
    sha256: str
    triangles_cad: np.ndarray
    tri_class: np.ndarray
    tri_element: np.ndarray
    tri_colour: np.ndarray
    tri_glass: np.ndarray
    element_ids: list[str]
    space_triangles_cad: np.ndarray
    tri_closed: np.ndarray | None = None

    @property
    def bounds_cad(self) -> np.ndarray:
        """(2, 3) min and max corner of the rendered triangles, metres."""
        pts = self.triangles_cad.reshape(-1, 3)
        return np.stack([pts.min(axis=0), pts.max(axis=0)])

    def normals_cad(self) -> np.ndarray:
        """(T, 3) unit face normals (sign as the model's winding gives it)."""
        t = self.triangles_cad.astype(np.float64)
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def load_scene(path: str | Path, use_cache: bool = True) -> SceneGeometry:
    """Geometry of the building at `path` (IFC or mesh), cached by the file's SHA-256."""
    path = Path(path)
    if not path.is_file():
        raise BuildingError(f"building model not found: {path}")
    suffix = path.suffix.lower()
    if suffix not in IFC_SUFFIXES | MESH_SUFFIXES:
        raise BuildingError(f"unsupported building model type {suffix!r} (IFC, or a mesh: OBJ, GLB, DAE, ...)")
    sha = file_sha256(path)
    cached = cache_dir() / f"scene-{cache_key(sha, {'scene': SCENE_VERSION})}.npz"
    if use_cache and cached.exists():
        try:
            return _from_npz(cached, str(path))
        except (OSError, KeyError, ValueError):
            log.warning("ignoring unreadable scene cache %s", cached)
    scene = _read_ifc(path, sha) if suffix in IFC_SUFFIXES else _read_mesh(path, sha)
    if len(scene.triangles_cad) == 0:
        raise BuildingError(f"{path.name}: no renderable geometry")
    scene.triangles_cad, scene.tri_closed = orient_closed_solids(scene.triangles_cad, scene.tri_element)
    tmp = cached.with_name(f"{cached.stem}.tmp{os.getpid()}.npz")
    np.savez(tmp, triangles=scene.triangles_cad, tri_class=scene.tri_class, tri_element=scene.tri_element,
             tri_colour=scene.tri_colour, tri_glass=scene.tri_glass, element_ids=np.array(scene.element_ids),
             spaces=scene.space_triangles_cad, sha=np.array(sha), closed=scene.tri_closed)
    os.replace(tmp, cached)
    return scene


def _from_npz(path: Path, source: str) -> SceneGeometry:
    with np.load(path) as z:
        return SceneGeometry(source, str(z["sha"]), z["triangles"], z["tri_class"], z["tri_element"], z["tri_colour"],
                             z["tri_glass"], [str(s) for s in z["element_ids"]], z["spaces"], z["closed"])


def orient_closed_solids(triangles: np.ndarray, tri_element: np.ndarray,
                         tol_m: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """(triangles with every closed solid wound outward, (T,) bool closed flag).

    A solid is a connected set of one element's triangles (vertices equal within `tol_m`) in which every edge is
    shared by exactly two triangles that run it in opposite directions (watertight and consistently wound); a
    solid with negative signed volume is inside out and gets flipped. Everything else (single-sided panes, open
    shells, degenerate triangles) stays as it was and is reported not closed: it must be drawn from both sides.
    """
    T = len(triangles)
    if T == 0:
        return triangles, np.zeros(0, bool)
    q = np.rint(triangles.reshape(-1, 3).astype(np.float64) / tol_m).astype(np.int64)
    keyed = np.column_stack([np.repeat(tri_element.astype(np.int64), 3), q])
    _, vid = np.unique(keyed, axis=0, return_inverse=True)
    vid = vid.reshape(T, 3)
    a, b = vid.reshape(-1), vid[:, [1, 2, 0]].reshape(-1)  # directed edges, 3 per triangle
    face = np.repeat(np.arange(T), 3)
    _, und, und_count = np.unique(np.column_stack([np.minimum(a, b), np.maximum(a, b)]), axis=0,
                                  return_inverse=True, return_counts=True)
    _, dir_inv, dir_count = np.unique(np.column_stack([a, b]), axis=0, return_inverse=True, return_counts=True)
    und, dir_inv = und.reshape(-1), dir_inv.reshape(-1)
    bad_edge = (a == b) | (und_count[und] != 2) | (dir_count[dir_inv] != 1)
    bad_face = np.zeros(T, bool)
    np.logical_or.at(bad_face, face, bad_edge)
    # faces joined through shared edges; a component is closed when none of its faces has a bad edge
    order = np.argsort(und, kind="stable")
    first = order[:-1][und[order[:-1]] == und[order[1:]]]
    second = order[1:][und[order[:-1]] == und[order[1:]]]
    adj = coo_matrix((np.ones(len(first)), (face[first], face[second])), shape=(T, T))
    n_comp, comp = connected_components(adj, directed=False)
    comp_bad = np.zeros(n_comp, bool)
    np.logical_or.at(comp_bad, comp, bad_face)
    t = triangles.astype(np.float64)
    volume = np.bincount(comp, np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0, n_comp)
    closed_comp = ~comp_bad & (np.abs(volume) > 1e-9)
    closed = closed_comp[comp]
    flip = closed & (volume[comp] < 0)
    out = triangles.copy()
    out[flip] = triangles[flip][:, [0, 2, 1]]
    return out, closed


def _read_ifc(path: Path, sha: str) -> SceneGeometry:
    ifc = open_ifc(path)
    iterator = ifcopenshell.geom.iterator(geometry_settings(), ifc, max(1, min(2, os.cpu_count() or 1)))
    if not iterator.initialize():
        raise BuildingError(f"{path.name}: ifcopenshell found no geometry")
    tris, classes, elements, colours, glass, spaces = [], [], [], [], [], []
    element_ids: list[str] = []
    while True:
        shape = iterator.get()
        entity = ifc.by_id(shape.id)
        kind = entity.is_a()
        g = shape.geometry
        verts = np.asarray(g.verts, dtype=np.float32).reshape(-1, 3)
        faces = np.asarray(g.faces, dtype=np.int64).reshape(-1, 3)
        if len(faces):
            if kind == "IfcSpace":
                spaces.append(verts[faces])
            elif kind not in _SKIPPED:
                cls = _IFC_CLASS.get(kind, OTHER)
                mat_rgb, mat_glass = _materials(g.materials)
                mat_ids = np.asarray(g.material_ids, dtype=np.int64).reshape(-1)
                if len(mat_ids) != len(faces) or len(mat_rgb) == 0:
                    mat_ids = np.zeros(len(faces), np.int64)
                    mat_rgb, mat_glass = np.full((1, 3), 0.7, np.float32), np.zeros(1, bool)
                mat_ids = np.clip(mat_ids, 0, len(mat_rgb) - 1)
                tris.append(verts[faces])
                classes.append(np.full(len(faces), cls, np.int8))
                elements.append(np.full(len(faces), len(element_ids), np.int32))
                colours.append(mat_rgb[mat_ids])
                glass.append(mat_glass[mat_ids] & (cls in (WINDOW, DOOR, WALL, OTHER)))
                element_ids.append(entity.GlobalId)
        if not iterator.next():
            break
    return SceneGeometry(str(path), sha, _cat(tris, (0, 3, 3), np.float32), _cat(classes, (0,), np.int8),
                         _cat(elements, (0,), np.int32), _cat(colours, (0, 3), np.float32),
                         _cat(glass, (0,), bool), element_ids, _cat(spaces, (0, 3, 3), np.float32))


def _materials(materials) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001 - ifcopenshell's style objects
    rgb, glass = [], []
    for m in materials:
        try:
            d = m.diffuse
            rgb.append((float(d.r()), float(d.g()), float(d.b())))
        except (AttributeError, TypeError, RuntimeError):
            rgb.append((0.7, 0.7, 0.7))
        t = float(getattr(m, "transparency", 0.0) or 0.0)
        glass.append(bool(np.isfinite(t) and t >= GLASS_TRANSPARENCY))
    return np.clip(np.array(rgb, np.float32).reshape(-1, 3), 0, 1), np.array(glass, bool)


def _cat(parts: list, empty_shape: tuple, dtype) -> np.ndarray:  # noqa: ANN001
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(empty_shape, dtype)


MESH_NAME_CLASSES = (("sign", OTHER), ("door", DOOR), ("window", WINDOW), ("glass", WINDOW), ("wall", WALL),
                     ("floor", SLAB),
                     ("ceiling", COVERING), ("stair", STAIR), ("rail", STAIR), ("elevator", WALL),
                     ("curtain", FURNITURE), ("bed", FURNITURE), ("chair", FURNITURE), ("table", FURNITURE))


def _read_mesh(path: Path, sha: str) -> SceneGeometry:
    """A mesh file (through graph.bim_mesh's reader: names, node transforms, declared unit) or a Gazebo
    `.world` (its models placed at their poses): one element per node, class from the node's names."""
    parts: list[tuple[str, list[str], np.ndarray, np.ndarray]] = []
    if path.suffix.lower() == ".world":
        for name, uri, T_cad_model in world_includes(path):
            mesh_file = model_mesh_file(path.parent, uri)
            if mesh_file is None:
                continue
            for nm, names, verts, faces in _mesh_nodes(mesh_file):
                parts.append((f"{name}/{nm}", names, verts @ T_cad_model[:3, :3].T + T_cad_model[:3, 3], faces))
    else:
        parts = _mesh_nodes(path)
    tris, classes, elements, colours = [], [], [], []
    element_ids: list[str] = []
    for name, names, verts, faces in parts:
        lname = re.sub(r"floor[_ -]?\d+", "", " ".join(names).lower())  # "hospital_floor_01_stairs": a storey
        cls = next((c for key, c in MESH_NAME_CLASSES if key in lname), OTHER)
        tris.append(verts.astype(np.float32)[faces])
        classes.append(np.full(len(faces), cls, np.int8))
        elements.append(np.full(len(faces), len(element_ids), np.int32))
        colours.append(np.full((len(faces), 3), 0.75, np.float32))
        element_ids.append(name)
    triangles = _cat(tris, (0, 3, 3), np.float32)
    tri_class = _cat(classes, (0,), np.int8)
    return SceneGeometry(str(path), sha, triangles, tri_class, _cat(elements, (0,), np.int32),
                         _cat(colours, (0, 3), np.float32), np.zeros(len(triangles), bool), element_ids,
                         np.zeros((0, 3, 3), np.float32))


def _mesh_nodes(path: Path) -> list[tuple[str, list[str], np.ndarray, np.ndarray]]:
    """[(node name, its names, (N, 3) vertices in metres, (M, 3) faces)] of one mesh file."""
    nodes, unit_m, _ = read_nodes(path)
    scale = unit_m if unit_m else 1.0  # metres per file unit (the hospital's DAE files: centimetres)
    return [(n.name, n.names, n.vertices * scale, n.faces) for n in nodes]


def occluding_triangles(path: str | Path) -> np.ndarray:
    """(T, 3, 3) the building's triangles that hide what lies behind them, CAD frame, metres
    (service.offline.self_label): all of them, its doors' leaves as the model has them (closed, mostly) and its
    windows' glass included. A door's own leaf lies within its opening's frame and does not hide it (the
    labeller's occlusion tolerance); a door seen through another's opening is hidden, as it is behind a closed
    door."""
    return load_scene(path).triangles_cad
