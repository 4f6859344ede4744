"""A small synthetic building for simulator tests: one box room with a door and a window, as SceneGeometry."""

from __future__ import annotations

import numpy as np

from macroloc.graph.features import MacroFeature
from macroloc.sim.scene import DOOR, SLAB, WALL, WINDOW, SceneGeometry

ROOM_X_M, ROOM_Y_M, ROOM_Z_M = 8.0, 6.0, 3.0


def quad(a, b, c, d) -> np.ndarray:  # noqa: ANN001
    """Two triangles (2, 3, 3) of the quad a-b-c-d."""
    return np.array([[a, b, c], [a, c, d]], dtype=np.float32)


def box(lo, hi) -> np.ndarray:  # noqa: ANN001
    """12 triangles of an axis-aligned box."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    p = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0), (x0, y0, z1), (x1, y0, z1), (x1, y1, z1),
         (x0, y1, z1)]
    faces = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (3, 0, 4, 7)]
    return np.concatenate([quad(*(p[i] for i in f)) for f in faces])


def room_scene() -> tuple[SceneGeometry, list[MacroFeature]]:
    """Room [0, 8] x [0, 6] x [0, 3] m; a door in the wall y = 6 (x 3..4, z 0..2.1, 5 cm thick, standing 2 cm
    proud of the wall), a window in the wall x = 8 (y 2..3.5, z 1..2.2, with a glass pane)."""
    X, Y, Z = ROOM_X_M, ROOM_Y_M, ROOM_Z_M
    parts = [
        (quad((0, 0, 0), (X, 0, 0), (X, Y, 0), (0, Y, 0)), SLAB, "floor", False),
        (quad((0, 0, Z), (X, 0, Z), (X, Y, Z), (0, Y, Z)), SLAB, "ceiling", False),
        (quad((0, 0, 0), (X, 0, 0), (X, 0, Z), (0, 0, Z)), WALL, "wall_s", False),
        (quad((0, Y, 0), (X, Y, 0), (X, Y, Z), (0, Y, Z)), WALL, "wall_n", False),
        (quad((0, 0, 0), (0, Y, 0), (0, Y, Z), (0, 0, Z)), WALL, "wall_w", False),
        # the east wall, with the window's opening (y 2..3.5, z 1..2.2) left open
        (quad((X, 0, 0), (X, 2.0, 0), (X, 2.0, Z), (X, 0, Z)), WALL, "wall_e", False),
        (quad((X, 3.5, 0), (X, Y, 0), (X, Y, Z), (X, 3.5, Z)), WALL, "wall_e", False),
        (quad((X, 2.0, 0), (X, 3.5, 0), (X, 3.5, 1.0), (X, 2.0, 1.0)), WALL, "wall_e", False),
        (quad((X, 2.0, 2.2), (X, 3.5, 2.2), (X, 3.5, Z), (X, 2.0, Z)), WALL, "wall_e", False),
        (box((3.0, Y - 0.05, 0.0), (4.0, Y - 0.0, 2.1)), DOOR, "door1", False),
        (box((X - 0.08, 2.0, 1.0), (X, 3.5, 1.08)), WINDOW, "window1", False),
        (box((X - 0.08, 2.0, 2.12), (X, 3.5, 2.2)), WINDOW, "window1", False),
        (quad((X - 0.04, 2.0, 1.08), (X - 0.04, 3.5, 1.08), (X - 0.04, 3.5, 2.12), (X - 0.04, 2.0, 2.12)),
         WINDOW, "window1", True),
    ]
    ids = list(dict.fromkeys(name for _, _, name, _ in parts))
    tris = np.concatenate([p[0] for p in parts])
    cls = np.concatenate([np.full(len(p[0]), p[1], np.int8) for p in parts])
    elem = np.concatenate([np.full(len(p[0]), ids.index(p[2]), np.int32) for p in parts])
    glass = np.concatenate([np.full(len(p[0]), p[3], bool) for p in parts])
    scene = SceneGeometry("room", "0" * 64, tris, cls, elem, np.full((len(tris), 3), 0.8, np.float32), glass, ids,
                          np.zeros((0, 3, 3), np.float32))
    door = MacroFeature("door1", "door", "Level 1",
                        np.array([[4.0, Y - 0.025, 0.0], [3.0, Y - 0.025, 0.0], [3.0, Y - 0.025, 2.1],
                                  [4.0, Y - 0.025, 2.1]]),
                        np.array([3.5, Y - 0.025, 1.05]), np.array([0.0, 1.0, 0.0]), 1.0, 2.1)
    window = MacroFeature("window1", "window", "Level 1",
                          np.array([[X - 0.04, 2.0, 1.0], [X - 0.04, 3.5, 1.0], [X - 0.04, 3.5, 2.2],
                                    [X - 0.04, 2.0, 2.2]]),
                          np.array([X - 0.04, 2.75, 1.6]), np.array([1.0, 0.0, 0.0]), 1.5, 1.2)
    return scene, [door, window]


def look_at(eye, target) -> np.ndarray:  # noqa: ANN001
    """T_cad_cam of an optical camera (x right, y down, z forward) at `eye` looking at `target`, level."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def ray_cast_depth(triangles: np.ndarray, T_cad_cam: np.ndarray, K: np.ndarray, pixels_uv: np.ndarray) -> np.ndarray:
    """z depth (m, optical axis) of the nearest triangle hit by the ray through each pixel (inf for none);
    Moeller-Trumbore, brute force over all triangles."""
    d_cam = np.linalg.solve(K, np.column_stack([pixels_uv, np.ones(len(pixels_uv))]).T).T  # z = 1
    d = d_cam @ T_cad_cam[:3, :3].T
    o = T_cad_cam[:3, 3]
    v0, v1, v2 = (triangles[:, i].astype(np.float64) for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d[:, None, :], e2[None])
    det = np.einsum("tk,ntk->nt", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - v0
    u = np.einsum("tk,ntk->nt", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("nk,tk->nt", d, q) * inv
    t = np.einsum("tk,tk->t", e2, q)[None, :] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    return np.where(hit, t, np.inf).min(axis=1)  # t along d with d_cam.z = 1: t is the z depth
