"""Doors and windows of a mesh model (OBJ, GLB, DAE, ... through trimesh; Gazebo `.world` files).

A mesh has no IfcDoor: the type of a node comes from its name through regex rules (`DEFAULT_RULES`,
overridable with `mesh_rules`). A node often holds a whole *group* ("all door frames of floor 1"), so its
geometry is split into connected components, and components whose bounding boxes lie within
`instance_gap_m` of each other are clustered into one instance (a door frame's jambs and head). Each
instance becomes a `MacroFeature` through `graph.rectangle.opening_rectangle`.

Frames and units: the output is in the CAD frame (the model's world frame, z up), metres. trimesh keeps a
COLLADA file's vertices in the file's unit (the hospital's DAE files are in centimetres; trimesh only
records `scene.units == "0.01 * meters"`), so the scale to metres is applied here: `mesh_rules["unit_scale"]`
if given, else the file's declared unit, else a guess from the size of the door/window instances.
Up axis: z unless `mesh_rules["up_axis"] == "y"` (a y-up mesh is rotated by +90 deg about x into z-up).
Node transforms of the file are applied (the hospital's Cinema 4D export turns its y-up groups z-up there).

Gazebo `.world`: every `<model>`/`<include>` whose `model://NAME` has a mesh beside the world file
(`NAME_visual.dae`, `NAME.dae`, or `models/NAME/meshes/*.dae`) is read and placed at its `<pose>`
(x y z roll pitch yaw, metres and radians); models that are absent are listed in the report.
"""

from __future__ import annotations

import logging
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from macroloc.graph.errors import BuildingError
from macroloc.graph.features import FeatureType, MacroFeature
from macroloc.graph.rectangle import opening_rectangle

log = logging.getLogger(__name__)

DEFAULT_RULES: dict[str, Any] = {
    "door": [r"door"],
    "window": [r"window", r"glass", r"glazing"],
    "exclude": [r"sign", r"handle", r"knob"],
    "wall": [r"wall"],
    "unit_scale": None,  # metres per file unit; None: from the file, else guessed
    "up_axis": "z",
    "instance_gap_m": 0.05,  # components closer than this (bbox gap) belong to one door/window
    "min_size_m": 0.3,  # an instance narrower or lower than this is no door/window (trim, a handle)
}
GUESS_DOOR_HEIGHT_M = 2.1  # a typical door, to guess the unit of a file that does not declare it
STOREY_GAP_M = 1.5  # features whose bottoms differ by more than this are on different storeys (height bands)
_FLOOR_NAME = re.compile(r"floor[_ -]?(\d+)", re.IGNORECASE)


@dataclass(frozen=True)
class MeshRules:
    """Resolved name->type rules and parameters (see DEFAULT_RULES)."""

    door: tuple[re.Pattern[str], ...]
    window: tuple[re.Pattern[str], ...]
    exclude: tuple[re.Pattern[str], ...]
    wall: tuple[re.Pattern[str], ...]
    unit_scale: float | None
    up_axis: str
    instance_gap_m: float
    min_size_m: float

    def type_of(self, names: list[str]) -> FeatureType | None:
        """'door', 'window' or None for a node known by these names (node name, geometry name, ...): a rule
        matches when its regex is found in any one of the names (re.search, case-insensitive)."""
        if _matches(self.exclude, names):
            return None
        if _matches(self.door, names):
            return "door"
        if _matches(self.window, names):
            return "window"
        return None

    def is_wall(self, names: list[str]) -> bool:
        return _matches(self.wall, names)


def _matches(patterns: tuple[re.Pattern[str], ...], names: list[str]) -> bool:
    return any(p.search(n) for p in patterns for n in names if n)


def resolve_rules(mesh_rules: dict | None) -> MeshRules:
    """Defaults overridden key by key by `mesh_rules`. Raises BuildingError for a bad regex or value."""
    merged = dict(DEFAULT_RULES, **(mesh_rules or {}))
    unknown = set(merged) - set(DEFAULT_RULES)
    if unknown:
        raise BuildingError(f"unknown mesh rule(s) {sorted(unknown)}; known: {sorted(DEFAULT_RULES)}")

    def patterns(key: str) -> tuple[re.Pattern[str], ...]:
        value = merged[key]
        items = [value] if isinstance(value, str) else list(value or [])
        try:
            return tuple(re.compile(p, re.IGNORECASE) for p in items)
        except re.error as exc:
            raise BuildingError(f"mesh rule {key!r}: bad regex: {exc}") from None

    scale = merged["unit_scale"]
    if scale is not None and not (isinstance(scale, int | float) and np.isfinite(scale) and scale > 0):
        raise BuildingError(f"mesh rule 'unit_scale' must be a positive number (metres per unit), got {scale!r}")
    if merged["up_axis"] not in ("z", "y"):
        raise BuildingError(f"mesh rule 'up_axis' must be 'z' or 'y', got {merged['up_axis']!r}")
    return MeshRules(door=patterns("door"), window=patterns("window"), exclude=patterns("exclude"),
                     wall=patterns("wall"), unit_scale=None if scale is None else float(scale),
                     up_axis=str(merged["up_axis"]), instance_gap_m=float(merged["instance_gap_m"]),
                     min_size_m=float(merged["min_size_m"]))


@dataclass
class NodeMesh:
    """One geometry node of a file, in the file's world frame and unit (not yet metres)."""

    name: str
    names: list[str]  # every name it is known by (node, geometry), for the rules
    vertices: np.ndarray  # (N, 3) file units, file world frame
    faces: np.ndarray  # (M, 3) int


# ---------------------------------------------------------------- reading one mesh file


def _dae_names(path: Path) -> dict[str, list[str]]:
    """{geometry id: [node name, geometry name]} from a COLLADA file (trimesh keeps only the ids)."""
    out: dict[str, list[str]] = {}
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return out
    for el in root.iter():
        tag = el.tag.rsplit("}", 1)[-1]
        if tag == "geometry" and el.get("id"):
            out.setdefault(el.get("id", ""), []).append(el.get("name") or "")
        if tag == "node":
            for child in el:
                if child.tag.rsplit("}", 1)[-1] == "instance_geometry":
                    gid = (child.get("url") or "").lstrip("#")
                    out.setdefault(gid, []).insert(0, el.get("name") or el.get("id") or "")
    return out


def _declared_unit_m(path: Path, scene) -> float | None:
    """Metres per file unit as the file declares it (COLLADA <unit meter=...>, trimesh's scene.units)."""
    if path.suffix.lower() == ".dae":
        with open(path, "rb") as fh:
            head = fh.read(1 << 16).decode("utf-8", "replace")
        m = re.search(r"<unit[^>]*meter=\"([0-9.eE+-]+)\"", head)
        if m:
            return float(m.group(1))
    units = getattr(scene, "units", None)
    if units:
        try:
            import trimesh

            return float(trimesh.units.unit_conversion(units, "meters"))
        except (ValueError, KeyError, AttributeError, TypeError):
            return None
    return None


def read_nodes(path: Path) -> tuple[list[NodeMesh], float | None, list[str]]:
    """(geometry nodes in file units, declared metres per unit or None, names of nodes without geometry)."""
    import trimesh

    kwargs: dict[str, Any] = {"force": "scene"}
    if path.suffix.lower() == ".obj":
        kwargs.update(split_objects=True, group_material=False)  # keep OBJ objects apart
    try:
        scene: Any = trimesh.load(str(path), **kwargs)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types for a malformed file
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BuildingError(f"cannot read mesh file {path}: {first}") from None
    dae_names = _dae_names(path) if path.suffix.lower() == ".dae" else {}
    nodes, empty = [], []
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        names = [*dae_names.get(str(geom_name), []), str(node), str(geom_name)]
        name = _display_name(names)
        verts = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
        faces = np.asarray(getattr(geom, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
        if len(verts) == 0 or len(faces) == 0 or not np.all(np.isfinite(verts)):
            empty.append(name)
            continue
        verts = verts @ np.asarray(transform)[:3, :3].T + np.asarray(transform)[:3, 3]
        nodes.append(NodeMesh(name=name, names=names, vertices=verts, faces=faces))
    # nodes listed in the file without any geometry (e.g. an OBJ object with no faces, empty glTF nodes)
    geometry_nodes = set(scene.graph.nodes_geometry)
    for node in scene.graph.nodes:
        if node not in geometry_nodes and node != scene.graph.base_frame:
            empty.append(str(node))
    return nodes, _declared_unit_m(path, scene), empty


def _display_name(names: list[str]) -> str:
    """The first of a node's names that is not an id-like key (trimesh names DAE nodes by their ids, 'ID61')."""
    named = [n for n in names if n and not re.fullmatch(r"(ID)?\d+|geometry_\d+", n)]
    return named[0] if named else names[0]


# ---------------------------------------------------------------- instances


def component_instances(vertices_m: np.ndarray, faces: np.ndarray, gap_m: float) -> list[np.ndarray]:
    """Split one group's triangles into instances: connected components, then clusters of components whose
    axis-aligned boxes lie within `gap_m` of each other. Returns a list of (K, 3) vertex arrays, metres."""
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    mesh = trimesh.Trimesh(vertices=vertices_m, faces=faces, process=True)  # merges coincident vertices
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    n_comp = int(labels.max()) + 1 if len(labels) else 0
    if n_comp == 0:
        return []
    face_verts = mesh.vertices[mesh.faces]  # (M, 3, 3)
    lo = np.full((n_comp, 3), np.inf)
    hi = np.full((n_comp, 3), -np.inf)
    np.minimum.at(lo, labels, face_verts.min(axis=1))
    np.maximum.at(hi, labels, face_verts.max(axis=1))
    # boxes within gap_m on every axis touch: union them (n_comp is a few hundred at most per group)
    near = np.all((lo[:, None, :] <= hi[None, :, :] + gap_m) & (lo[None, :, :] <= hi[:, None, :] + gap_m), axis=2)
    i, j = np.nonzero(near)
    n_clusters, cluster = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n_comp,) * 2),
                                               directed=False)
    out = []
    for c in range(n_clusters):
        comp_ids = np.nonzero(cluster == c)[0]
        verts = face_verts[np.isin(labels, comp_ids)].reshape(-1, 3)
        out.append(verts)
    # a stable order: by x, then y, then z of the instance centre
    out.sort(key=lambda v: tuple(np.round((v.min(axis=0) + v.max(axis=0)) / 2, 3)))
    return out


def _y_up_to_z_up(points: np.ndarray) -> np.ndarray:
    """Rotate +90 deg about x: a y-up point (x, y, z) becomes z-up (x, -z, y)."""
    return np.stack([points[:, 0], -points[:, 2], points[:, 1]], axis=1)


def _guess_unit_m(groups: list[tuple[NodeMesh, FeatureType]]) -> tuple[float, str]:
    """Metres per unit guessed from the typical vertical extent of door/window groups' components."""
    heights = [float(np.ptp(n.vertices[:, 2])) for n, _ in groups if len(n.vertices)]
    if not heights:
        return 1.0, "assumed metres (nothing to measure)"
    h = float(np.median(heights))
    for scale, unit in ((1.0, "m"), (0.01, "cm"), (0.001, "mm")):
        if h * scale < 6 * GUESS_DOOR_HEIGHT_M:
            return scale, f"guessed {unit} from door/window heights"
    return 0.001, "guessed mm from door/window heights"


# ---------------------------------------------------------------- storeys


def storey_from_name(name: str) -> str | None:
    """'floor_02' from a name holding 'floor_02' / 'floor2' / 'Floor 2'; None without one."""
    m = _FLOOR_NAME.search(name)
    return f"floor_{int(m.group(1)):02d}" if m else None


def height_band_storeys(bottoms_m: np.ndarray) -> tuple[list[str], dict[str, float]]:
    """Storey names 'level_00', 'level_01', ... from features' bottom heights (metres), clustered where they
    differ by more than STOREY_GAP_M; elevations are each band's lowest bottom."""
    if len(bottoms_m) == 0:
        return [], {}
    order = np.argsort(bottoms_m)
    band = np.zeros(len(bottoms_m), dtype=int)
    current, last = 0, bottoms_m[order[0]]
    for idx in order:
        if bottoms_m[idx] - last > STOREY_GAP_M:
            current += 1
        band[idx], last = current, bottoms_m[idx]
    names = [f"level_{b:02d}" for b in band]
    elevations = {f"level_{b:02d}": float(bottoms_m[band == b].min()) for b in range(current + 1)}
    return names, elevations


# ---------------------------------------------------------------- gazebo worlds


def pose_matrix(pose_text: str | None) -> np.ndarray:
    """4x4 transform of an SDF pose 'x y z roll pitch yaw' (metres, radians; R = Rz(yaw) Ry(pitch) Rx(roll))."""
    values = [float(v) for v in (pose_text or "").split()] + [0.0] * 6
    x, y, z, roll, pitch, yaw = values[:6]
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T = np.eye(4)
    T[:3, :3] = rz @ ry @ rx
    T[:3, 3] = (x, y, z)
    return T


def world_includes(path: Path) -> list[tuple[str, str, np.ndarray]]:
    """[(instance name, model name, T_world_model)] of a Gazebo .world file's <include>s (model poses composed)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise BuildingError(f"cannot read Gazebo world {path}: {exc}") from None
    out = []
    for world in root.iter("world"):
        for model in world.findall("model"):
            T_world_outer = pose_matrix(model.findtext("pose"))
            for inc in model.findall("include"):
                uri = (inc.findtext("uri") or "").strip()
                out.append((model.get("name") or uri, uri.removeprefix("model://"),
                            T_world_outer @ pose_matrix(inc.findtext("pose"))))
        for inc in world.findall("include"):
            uri = (inc.findtext("uri") or "").strip()
            out.append((inc.findtext("name") or uri, uri.removeprefix("model://"), pose_matrix(inc.findtext("pose"))))
    return out


def model_mesh_file(world_dir: Path, model_name: str) -> Path | None:
    """The mesh of `model://model_name` beside a world file, or None."""
    for candidate in (world_dir / f"{model_name}_visual.dae", world_dir / f"{model_name}.dae"):
        if candidate.is_file():
            return candidate
    meshes = sorted((world_dir / "models" / model_name / "meshes").glob("*visual*.dae")) + sorted(
        (world_dir / "models" / model_name / "meshes").glob("*.dae"))
    return meshes[0] if meshes else None


# ---------------------------------------------------------------- the reader


@dataclass
class _Placed:
    """A door/window group in metres, CAD frame, with the storey its file or placement gives."""

    node: NodeMesh
    kind: FeatureType
    prefix: str  # id prefix (node name, or world instance / node name)
    storey: str | None


def _file_groups(path: Path, rules: MeshRules, T_cad_file: np.ndarray, prefix: str, report: dict,
                 read_cache: dict[Path, Any] | None = None) -> tuple[list[_Placed], list[NodeMesh], list[NodeMesh]]:
    """(door/window groups, wall nodes, other nodes) of one mesh file, in metres, placed by T_cad_file.

    read_cache: {path: read_nodes(path)} shared by the placements of one world (a file placed 3 times is read once).
    """
    if read_cache is None:
        read_cache = {}
    if path not in read_cache:
        read_cache[path] = read_nodes(path)
    nodes, declared_m, empty = read_cache[path]
    report["no_geometry"].extend(f"{prefix}{n}" for n in empty if rules.type_of([n]) is not None)
    typed = [(n, rules.type_of(n.names)) for n in nodes]
    matched = [(n, k) for n, k in typed if k is not None]
    if rules.unit_scale is not None:
        scale, source = rules.unit_scale, "mesh_rules"
    elif declared_m is not None:
        scale, source = declared_m, "declared by the file"
    else:
        scale, source = _guess_unit_m(matched)
    report["unit_scale"][path.name] = {"metres_per_unit": scale, "source": source}
    groups, walls, others = [], [], []
    file_storey = storey_from_name(path.stem)
    for n, kind in typed:
        verts = n.vertices * scale  # file units -> metres
        if rules.up_axis == "y":
            verts = _y_up_to_z_up(verts)
        verts = verts @ T_cad_file[:3, :3].T + T_cad_file[:3, 3]
        placed = NodeMesh(name=n.name, names=n.names, vertices=verts, faces=n.faces)
        if kind is not None:
            groups.append(_Placed(placed, kind, f"{prefix}{n.name}", file_storey))
        elif rules.is_wall(n.names):
            walls.append(placed)
        else:
            others.append(placed)
            report["ignored_nodes"].append(f"{prefix}{n.name}")
    return groups, walls, others


def _instances_to_features(groups: list[_Placed], rules: MeshRules, report: dict) -> list[MacroFeature]:
    features = []
    for g in groups:
        instances = component_instances(g.node.vertices, g.node.faces, rules.instance_gap_m)
        kept = 0
        for idx, verts in enumerate(instances):
            fid = f"{g.prefix}#{idx}"
            if len(verts) < 3:
                report["no_geometry"].append(fid)
                continue
            rect = opening_rectangle(verts)
            if min(rect.width_m, rect.height_m) < rules.min_size_m:
                report["rejected_small"].append(fid)
                continue
            kept += 1
            features.append(MacroFeature(
                id=fid, type=g.kind, storey=g.storey, corners_cad=rect.corners, centroid_cad=rect.centroid,
                normal_cad=rect.normal, width_m=float(rect.width_m), height_m=float(rect.height_m),
                orientation=rect.orientation,  # type: ignore[arg-type]
                name=g.node.name))
        report["groups"][g.prefix] = {"type": g.kind, "instances": kept, "parts": len(instances)}
    return features


def _assign_storeys(features: list[MacroFeature], report: dict) -> list[MacroFeature]:
    """Storeys from file names where every feature has one, else from height bands of their bottoms."""
    from dataclasses import replace

    if features and all(f.storey is not None for f in features):
        storeys = sorted({str(f.storey) for f in features})
        bottoms = {s: min(float(f.corners_cad[:, 2].min()) for f in features if f.storey == s) for s in storeys}
        report["storeys"], report["storey_elevations_m"] = storeys, bottoms
        return features
    bottoms_m = np.array([float(f.corners_cad[:, 2].min()) for f in features])
    names, elevations = height_band_storeys(bottoms_m)
    report["storeys"], report["storey_elevations_m"] = list(elevations), elevations
    return [replace(f, storey=s) for f, s in zip(features, names, strict=True)]


def _new_report(path: Path) -> dict:
    return {"format": path.suffix.lower().lstrip("."), "elements": 0, "no_geometry": [], "rejected_small": [],
            "ignored_nodes": [], "groups": {}, "unit_scale": {}, "missing_models": [], "storeys": [],
            "storey_elevations_m": {}}


def read_mesh_features(path: Path, mesh_rules: dict | None = None) -> tuple[list[MacroFeature], dict]:
    """(features, report) of a mesh file or Gazebo world; CAD frame (z up), metres.

    report: {"format", "elements" (door/window instances found), "no_geometry": [ids], "rejected_small": [ids],
    "ignored_nodes": [names], "groups": {group id: {"type", "instances", "parts"}}, "unit_scale": {file: ...},
    "missing_models": [model names a .world names but that are not beside it], "storeys", "storey_elevations_m"}.
    Raises BuildingError for an unreadable file or bad rules.
    """
    path = Path(path)
    rules = resolve_rules(mesh_rules)
    report = _new_report(path)
    groups: list[_Placed] = []
    if path.suffix.lower() == ".world":
        groups = _world_groups(path, rules, report)
    else:
        groups, _, _ = _file_groups(path, rules, np.eye(4), "", report)
    features = _instances_to_features(groups, rules, report)
    report["elements"] = len(features) + len(report["rejected_small"])
    features = _assign_storeys(features, report)
    if report["no_geometry"]:
        log.warning("%s: %d nodes/instances without usable geometry", path.name, len(report["no_geometry"]))
    log.info("%s: %d doors, %d windows from %d groups", path.name, sum(f.type == "door" for f in features),
             sum(f.type == "window" for f in features), len(report["groups"]))
    return features, report


def _world_groups(path: Path, rules: MeshRules, report: dict) -> list[_Placed]:
    """Door/window groups of every model a Gazebo world places whose mesh lies beside it; storeys by pose z."""
    from dataclasses import replace

    groups: list[_Placed] = []
    missing: set[str] = set()
    read_cache: dict[Path, Any] = {}
    for instance, model, T_world_model in world_includes(path):
        mesh_file = model_mesh_file(path.parent, model)
        if mesh_file is None:
            if model not in ("sun", "ground_plane"):
                missing.add(model)
            continue
        found, _, _ = _file_groups(mesh_file, rules, T_world_model, f"{instance}/", report, read_cache)
        # storey: the placement's height band (a .world may stack the same floor file several times)
        groups.extend(replace(g, storey=None) for g in found)
    report["missing_models"] = sorted(missing)
    if missing:
        log.warning("%s: %d referenced models are not beside it and were skipped", path.name, len(missing))
    return groups


def read_wall_mesh(path: Path, mesh_rules: dict | None = None):
    """The walls of a mesh file or world as one trimesh.Trimesh (CAD frame, metres), or None without walls.

    Walls are nodes matching the 'wall' rule that are not doors/windows; without any, every non-door/window
    node is taken (a whole-building mesh).
    """
    import trimesh

    path = Path(path)
    rules = resolve_rules(mesh_rules)
    report = _new_report(path)
    placements = ([(inst, model_mesh_file(path.parent, m), T) for inst, m, T in world_includes(path)]
                  if path.suffix.lower() == ".world" else [("", path, np.eye(4))])
    walls: list[NodeMesh] = []
    others: list[NodeMesh] = []
    read_cache: dict[Path, Any] = {}
    for inst, mesh_file, T in placements:
        if mesh_file is None:
            continue
        _, file_walls, file_others = _file_groups(mesh_file, rules, T, f"{inst}/", report, read_cache)
        walls.extend(file_walls)
        others.extend(file_others)
    parts = [trimesh.Trimesh(vertices=w.vertices, faces=w.faces, process=False) for w in (walls or others)]
    if not parts:
        return None
    return trimesh.util.concatenate(parts)
