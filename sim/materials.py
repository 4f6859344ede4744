"""Dressing a building for one flight: per-triangle textures, colours, door/window styles (seeded), and the
renderer's vertex array.

Every door and window that is a macro-feature of the model gets an instance id (its index in the feature
list + 1; duplicates exported twice share it) and, per vertex, its position (u, v) in [0, 1] across its opening
rectangle, from which the shader draws frames, panels, handles and muntins.
"""

from __future__ import annotations

import zlib

import numpy as np

from macroloc.graph.features import MacroFeature
from macroloc.sim import textures as tx
from macroloc.sim.render import (
    FLAG_CLOSED,
    FLAG_DETAIL,
    FLAGS_COLUMN,
    KIND_DOOR,
    KIND_GLASS,
    KIND_PLAIN,
    KIND_WINDOW_FRAME,
    VERTEX_FLOATS,
)
from macroloc.sim.scene import COVERING, DOOR, FURNITURE, OTHER, SLAB, STAIR, WALL, WINDOW, SceneGeometry

WALL_TINTS = ((0.95, 0.94, 0.9), (0.9, 0.92, 0.95), (0.96, 0.9, 0.8), (0.85, 0.9, 0.85), (0.8, 0.8, 0.82),
              (0.95, 0.85, 0.85), (0.75, 0.8, 0.9))
DOOR_TINTS = ((0.9, 0.75, 0.55), (0.6, 0.4, 0.25), (0.95, 0.95, 0.93), (0.55, 0.57, 0.6), (0.55, 0.2, 0.15),
              (0.2, 0.3, 0.5), (0.3, 0.45, 0.3), (0.4, 0.28, 0.18))
FRAME_TINTS = ((0.95, 0.95, 0.95), (0.25, 0.27, 0.3), (0.45, 0.3, 0.2), (0.7, 0.7, 0.72))
GROUND_HALF_SIZE_M = 150.0
PHOTO_SHARE = 0.5  # doors/windows textured with a real photo, when photos are given
PHOTO_STYLE = 16.0


N_DOOR_PATTERNS = 5  # raised panels x2, x4, vision panel, kick plate, vision slits (scene.frag.glsl)
DOUBLE_DOOR_STYLE = 10.0  # styles 10 + pattern: two leaves; below: one leaf, pattern + 5 x (handle on the left)
DOUBLE_DOOR_WIDTH_M = 1.2  # openings at least this wide are double doors, DOUBLE_SHARE_WIDE of the time
NARROW_DOUBLE_WIDTH_M = 0.95  # from this width up to DOUBLE_DOOR_WIDTH_M, DOUBLE_SHARE_NARROW of the time
DOUBLE_SHARE_WIDE, DOUBLE_SHARE_NARROW = 0.85, 0.2


def door_style(width_m: float | None, rng: np.random.Generator) -> float:
    """A door's style for the shader: a wide opening is mostly a double door; a standard one has one leaf, and
    one in five standard-width (0.95-1.2 m) openings is a pair of narrow leaves."""
    pattern = int(rng.integers(N_DOOR_PATTERNS))
    if width_m is not None and width_m >= NARROW_DOUBLE_WIDTH_M:
        share = DOUBLE_SHARE_WIDE if width_m >= DOUBLE_DOOR_WIDTH_M else DOUBLE_SHARE_NARROW
        if rng.random() < share:
            return DOUBLE_DOOR_STYLE + pattern
    return float(pattern + N_DOOR_PATTERNS * int(rng.integers(2)))


def _door_width_m(gid: str, instances: dict[str, int], features: list[MacroFeature]) -> float | None:
    k = instances.get(gid, 0)
    return features[k - 1].width_m if k else None


def _element_rng(seed: int, key: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(key.encode())])


def feature_instance_map(features: list[MacroFeature]) -> dict[str, int]:
    """{element id: instance id} (feature index + 1), duplicates included."""
    out: dict[str, int] = {}
    for k, f in enumerate(features):
        for gid in (f.id, *f.duplicates):
            out.setdefault(gid, k + 1)
    return out


def dress_scene(scene: SceneGeometry, features: list[MacroFeature], seed: int,
                ground_z_m: float | None = None, open_doors: set[int] | frozenset[int] = frozenset(),
                floor_levels_m: tuple[float, ...] = (), photo_door_layers: tuple[int, ...] = (),
                photo_window_layers: tuple[int, ...] = (),
                storey_z_m: tuple[float, float] | None = None) -> np.ndarray:
    """(3T' + 6, VERTEX_FLOATS) float32 vertex array of the scene plus a ground plane (at `ground_z_m`,
    default the lowest geometry) for the renderer, CAD frame, metres. Doors whose feature index is in
    `open_doors` are drawn without their leaf (frame only): open, so the flight can pass. The bottoms of the
    IfcSpace volumes within 0.3 m of a level in `floor_levels_m` are drawn as floors, 4 mm up (many models have
    no floor slab under their rooms). Doors and windows get, one in two, a photo texture from the given
    texture layers (`photo_*_layers`; style 16 + k tells the shader to stretch it across the opening).
    `storey_z_m` (floor, ceiling): when the model has no ceiling over that floor (meshes of walls and floors),
    its floor is copied up as a ceiling, so the drone flies indoors rather than under the sky."""
    T = len(scene.triangles_cad)
    normals = scene.normals_cad().astype(np.float32)
    layer = np.full(T, tx.PLASTER, np.float32)
    tint = np.clip(0.5 * scene.tri_colour + 0.5, 0, 1).astype(np.float32)
    inst = np.zeros(T, np.float32)
    fuv = np.full((T, 3, 2), -1.0, np.float32)
    kind = np.full(T, KIND_PLAIN, np.float32)
    style = np.zeros(T, np.float32)
    rng = np.random.default_rng(seed)
    frame_tint = np.array(FRAME_TINTS[rng.integers(len(FRAME_TINTS))], np.float32)
    floor_layer = tx.FLOOR_LAYERS[rng.integers(len(tx.FLOOR_LAYERS))]
    instances = feature_instance_map(features)
    scene_mid_z = float(scene.bounds_cad[:, 2].mean())
    photo_windows = np.full(T, -1, np.int64)
    by_element = np.argsort(scene.tri_element, kind="stable")
    bounds = np.searchsorted(scene.tri_element[by_element], np.arange(len(scene.element_ids) + 1))
    for e, gid in enumerate(scene.element_ids):
        idx = by_element[bounds[e]:bounds[e + 1]]
        if len(idx) == 0:
            continue
        cls = int(scene.tri_class[idx[0]])
        er = _element_rng(seed, gid)
        if cls == WALL:
            layer[idx] = tx.WALL_LAYERS[er.integers(len(tx.WALL_LAYERS))]
            tint[idx] = WALL_TINTS[er.integers(len(WALL_TINTS))]
        elif cls in (SLAB, COVERING):
            up = _faces_up(scene.triangles_cad[idx], normals[idx], floor_levels_m, scene_mid_z)
            flat = np.abs(normals[idx, 2]) > 0.7
            layer[idx] = np.where(flat & up, floor_layer, np.where(flat, tx.CEILING, tx.PLASTER))
            tint[idx] = 0.9 + 0.1 * er.random(3)
        elif cls == DOOR:
            layer[idx] = tx.DOOR_LAYERS[er.integers(len(tx.DOOR_LAYERS))]
            tint[idx] = DOOR_TINTS[er.integers(len(DOOR_TINTS))]
            kind[idx] = KIND_DOOR
            style[idx] = door_style(_door_width_m(gid, instances, features), er)
            if photo_door_layers and er.random() < PHOTO_SHARE:
                layer[idx] = photo_door_layers[er.integers(len(photo_door_layers))]
                tint[idx] = 0.9 + 0.2 * er.random()
                style[idx] = PHOTO_STYLE
        elif cls == WINDOW:
            layer[idx] = tx.PAINTED
            tint[idx] = frame_tint
            kind[idx] = KIND_WINDOW_FRAME
            style[idx] = er.integers(3)
            if photo_window_layers and er.random() < PHOTO_SHARE:
                glass_idx = idx[scene.tri_glass[idx]]
                if len(glass_idx):  # the photo goes on the panes; the model's frame stays
                    photo_windows[glass_idx] = photo_window_layers[er.integers(len(photo_window_layers))]
        elif cls == STAIR:
            layer[idx] = tx.METAL if er.random() < 0.5 else tx.WOOD_GRAIN
        elif cls == FURNITURE:
            layer[idx] = (tx.WOOD_GRAIN, tx.PAINTED, tx.CARPET)[er.integers(3)]
            tint[idx] = 0.4 + 0.6 * er.random(3)
        k = instances.get(gid, 0)
        if k and cls in (DOOR, WINDOW):
            inst[idx] = k
            fuv[idx] = _opening_uv(scene.triangles_cad[idx], features[k - 1])
        elif cls in (DOOR, WINDOW):  # a mesh group of many doors/windows: each triangle to the feature around it
            owner = _owners(scene.triangles_cad[idx], features, "door" if cls == DOOR else "window")
            for j in np.unique(owner[owner >= 0]):
                sel = idx[owner == j]
                inst[sel] = j + 1
                fuv[sel] = _opening_uv(scene.triangles_cad[sel], features[j])
    glass = scene.tri_glass
    kind[glass] = KIND_GLASS
    tint[glass] = (0.55, 0.65, 0.65)
    photo_glass = glass & (photo_windows >= 0)
    layer[photo_glass] = photo_windows[photo_glass]
    tint[photo_glass] = 1.0
    style[photo_glass] = PHOTO_STYLE
    verts = np.zeros((T, 3, VERTEX_FLOATS), np.float32)
    verts[:, :, 0:3] = scene.triangles_cad
    verts[:, :, 3:6] = normals[:, None, :]
    verts[:, :, 6:9] = tint[:, None, :]
    verts[:, :, 9] = layer[:, None]
    verts[:, :, 10] = inst[:, None]
    verts[:, :, 11:13] = fuv
    verts[:, :, 13] = kind[:, None]
    verts[:, :, 14] = style[:, None]
    detail = np.isin(scene.tri_class, (FURNITURE, OTHER)) | ((scene.tri_class == STAIR) & (inst == 0))
    # closed solids may be culled from behind (about half the fragments of a building); doors and windows stay
    # double-sided: an opened door loses its leaf and the rest of it is no longer closed
    closed = (scene.tri_closed if scene.tri_closed is not None else np.zeros(T, bool)) & ~np.isin(
        scene.tri_class, (DOOR, WINDOW))
    verts[:, :, FLAGS_COLUMN] = (FLAG_DETAIL * detail + FLAG_CLOSED * closed)[:, None]
    keep = ~_leaf_of(inst, fuv, kind, open_doors)
    z0 = float(scene.bounds_cad[0, 2]) if ground_z_m is None else ground_z_m
    floors = _space_floors(scene, floor_levels_m, floor_layer, rng)
    ceiling = _missing_ceiling(scene, normals, storey_z_m, rng) if storey_z_m is not None else floors[:0]
    return np.concatenate([verts[keep].reshape(-1, VERTEX_FLOATS), floors, ceiling,
                           _ground(scene, z0 - 0.01, rng)])


def _missing_ceiling(scene: SceneGeometry, normals: np.ndarray, storey_z_m: tuple[float, float],
                     rng: np.random.Generator) -> np.ndarray:
    """Vertices of a ceiling copied from the storey's floor when horizontal faces above cover under half of it."""
    floor_z, ceiling_z = storey_z_m
    tri = scene.triangles_cad
    flat = np.abs(normals[:, 2]) > 0.9
    zc = tri[:, :, 2].mean(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    floor = flat & (np.abs(zc - floor_z) < 0.3)
    above = flat & (zc > floor_z + 2.2) & (zc < ceiling_z + 0.6)
    if area[floor].sum() == 0 or area[above].sum() >= 0.5 * area[floor].sum():
        return np.zeros((0, VERTEX_FLOATS), np.float32)
    top = tri[floor].astype(np.float32).copy()
    top[:, :, 2] = ceiling_z - 0.01
    out = np.zeros((len(top), 3, VERTEX_FLOATS), np.float32)
    out[:, :, 0:3] = top
    out[:, :, 3:6] = (0, 0, -1)
    out[:, :, 6:9] = 0.9 + 0.1 * rng.random(3)
    out[:, :, 9] = tx.CEILING
    out[:, :, 11:13] = -1.0
    return out.reshape(-1, VERTEX_FLOATS)


def _space_floors(scene: SceneGeometry, levels_m: tuple[float, ...], layer: int,
                  rng: np.random.Generator) -> np.ndarray:
    spaces = scene.space_triangles_cad
    if len(spaces) == 0 or not levels_m:
        return np.zeros((0, VERTEX_FLOATS), np.float32)
    zmin, zmax = spaces[:, :, 2].min(axis=1), spaces[:, :, 2].max(axis=1)
    near_level = np.abs(zmin[:, None] - np.asarray(levels_m)[None, :]).min(axis=1) < 0.3
    tri = spaces[(zmax - zmin < 0.02) & near_level].astype(np.float32).copy()
    tri[:, :, 2] += 0.004
    out = np.zeros((len(tri), 3, VERTEX_FLOATS), np.float32)
    out[:, :, 0:3] = tri
    out[:, :, 3:6] = (0, 0, 1)
    out[:, :, 6:9] = 0.85 + 0.15 * rng.random(3)
    out[:, :, 9] = layer
    out[:, :, 11:13] = -1.0
    return out.reshape(-1, VERTEX_FLOATS)


def _leaf_of(inst: np.ndarray, fuv: np.ndarray, kind: np.ndarray, open_doors: set[int] | frozenset[int]) -> np.ndarray:
    """(T,) triangles of the leaves of the open doors: inside the opening, clear of the frame band."""
    if not open_doors:
        return np.zeros(len(inst), bool)
    is_open = np.isin(inst, np.array(sorted(open_doors)) + 1) & (kind == KIND_DOOR)
    u, v = fuv[:, :, 0].mean(axis=1), fuv[:, :, 1].mean(axis=1)  # triangle centroids across the opening
    inner = (u > 0.08) & (u < 0.92) & (v < 0.94)
    return is_open & inner


def _owners(tri: np.ndarray, features: list[MacroFeature], kind: str, margin_m: float = 0.05) -> np.ndarray:
    """(n,) index of the `kind` feature whose box (opening rectangle +- 0.3 m along its normal, + margin) holds
    each triangle's centroid, -1 for none."""
    owner = np.full(len(tri), -1)
    centre = tri.mean(axis=1).astype(np.float64)
    for j, f in enumerate(features):
        if f.type != kind:
            continue
        c0 = f.corners_cad[0]
        ax_u, ax_v = f.corners_cad[1] - c0, f.corners_cad[3] - c0
        lu, lv = float(np.linalg.norm(ax_u)), float(np.linalg.norm(ax_v))
        if lu < 1e-6 or lv < 1e-6:
            continue
        rel = centre - c0
        u, v, n = rel @ ax_u / lu, rel @ ax_v / lv, rel @ f.normal_cad
        inside = (u > -margin_m) & (u < lu + margin_m) & (v > -margin_m) & (v < lv + margin_m) & (np.abs(n) < 0.3)
        owner[inside & (owner < 0)] = j
    return owner


def _faces_up(tri: np.ndarray, normals: np.ndarray, levels_m: tuple[float, ...], mid_z: float) -> np.ndarray:
    """(n,) whether each horizontal face of one element is walked on (a floor) rather than looked up at.

    The winding of IFC faces is not reliable, so: the top faces of a thick element are floors; a face of a
    thin one (a single sheet) is a floor when it lies near a storey level (or, with no levels, low in the scene).
    """
    z = tri[:, :, 2].mean(axis=1)
    lo, hi = float(tri[:, :, 2].min()), float(tri[:, :, 2].max())
    if hi - lo > 0.01:
        return z > 0.5 * (lo + hi)
    if levels_m:
        return np.abs(z[:, None] - np.asarray(levels_m)[None, :]).min(axis=1) < 0.3
    return z < mid_z


def _opening_uv(triangles: np.ndarray, f: MacroFeature) -> np.ndarray:
    """(n, 3, 2) position of each vertex across the feature's opening rectangle: u along corner 0->1, v 0->3."""
    c0 = f.corners_cad[0]
    ax_u, ax_v = f.corners_cad[1] - c0, f.corners_cad[3] - c0
    rel = triangles.astype(np.float64) - c0
    u = rel @ ax_u / max(float(ax_u @ ax_u), 1e-9)
    v = rel @ ax_v / max(float(ax_v @ ax_v), 1e-9)
    return np.stack([u, v], axis=-1).astype(np.float32)


def _ground(scene: SceneGeometry, z: float, rng: np.random.Generator) -> np.ndarray:
    """Two triangles of grass or asphalt around the building, so windows show an outside."""
    cx, cy = scene.bounds_cad.mean(axis=0)[:2]
    h = GROUND_HALF_SIZE_M
    quad = np.array([[cx - h, cy - h, z], [cx + h, cy - h, z], [cx + h, cy + h, z], [cx - h, cy + h, z]])
    out = np.zeros((6, VERTEX_FLOATS), np.float32)
    out[:, 0:3] = quad[[0, 1, 2, 0, 2, 3]]
    out[:, 3:6] = (0, 0, 1)
    out[:, 6:9] = 1.0
    out[:, 9] = tx.GRASS if rng.random() < 0.6 else tx.ASPHALT
    out[:, 11:13] = -1.0
    return out
