"""The opening rectangle of a door or window from its geometry's vertices.

The data README's lessons, applied: the wall normal is the horizontal direction of *least extent* of the
vertices (the exact minimum width of the convex hull of their horizontal footprint, by rotating calipers;
PCA is biased by vertex density), the centre comes from the geometry (never the placement), and an element
flatter than it is wide (a skylight) gets a horizontal rectangle with normal +z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Rectangle:
    centroid: np.ndarray  # (3,) metres
    corners: np.ndarray  # (4, 3) ordered (-u,-v) (+u,-v) (+u,+v) (-u,+v)
    normal: np.ndarray  # (3,) unit
    width_m: float
    height_m: float
    depth_m: float
    orientation: str  # "vertical" | "horizontal"


def least_width_direction(points_xy: np.ndarray) -> np.ndarray:
    """Unit 2D direction along which the points' convex hull is thinnest (rotating calipers).

    The minimum width of a convex polygon is attained perpendicular to one of its edges, so checking the
    normal of every hull edge is exact.
    """
    pts = np.asarray(points_xy, dtype=float)
    try:
        hull = pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        hull = pts
    edges = np.roll(hull, -1, axis=0) - hull
    lengths = np.linalg.norm(edges, axis=1)
    edges, lengths = edges[lengths > 1e-9], lengths[lengths > 1e-9]
    if len(edges) == 0:
        return np.array([1.0, 0.0])
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1) / lengths[:, None]
    widths = np.ptp(hull @ normals.T, axis=0)
    return normals[int(np.argmin(widths))]


def opening_rectangle(vertices: np.ndarray, normal_xy: np.ndarray | None = None) -> Rectangle:
    """Rectangle of a vertex cloud (N, 3) in metres; `normal_xy` overrides the least-width direction."""
    verts = np.asarray(vertices, dtype=float).reshape(-1, 3)
    n2 = least_width_direction(verts[:, :2]) if normal_xy is None else np.asarray(normal_xy, dtype=float)
    n = np.array([n2[0], n2[1], 0.0]) / max(float(np.linalg.norm(n2)), 1e-12)
    u = np.cross(Z_UP, n)
    axes = np.stack([u, n, Z_UP])  # rows: u (along the wall), n (through it), z (up)
    proj = verts @ axes.T
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    w, d, h = (hi - lo).tolist()
    centre = ((lo + hi) / 2) @ axes
    signs = ((-1, -1), (1, -1), (1, 1), (-1, 1))
    if h < min(w, d):  # skylight / roof window: horizontal rectangle spanning u and n
        corners = np.array([centre + a * w / 2 * u + b * d / 2 * n for a, b in signs])
        return Rectangle(centre, corners, Z_UP.copy(), w, d, h, "horizontal")
    corners = np.array([centre + a * w / 2 * u + b * h / 2 * Z_UP for a, b in signs])
    return Rectangle(centre, corners, n, w, h, d, "vertical")


def flip_normal(rect: Rectangle) -> Rectangle:
    """The same rectangle seen from the other side: normal negated, corner order kept as (-u,..) for u = z x n."""
    return Rectangle(rect.centroid, rect.corners[[1, 0, 3, 2]], -rect.normal, rect.width_m, rect.height_m,
                     rect.depth_m, rect.orientation)


def unordered_edges(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edge frames of R rectangles (R, 4, 3) whose corners come in any order: (a (R, 3), b (R, 3) unit and
    orthogonal, their lengths la, lb (R,), closure (R, 3)).

    Corner 0's diagonal partner is the corner k whose pairing closes best: |p0 + pk - pi - pj| is the sum of four
    corners' noise for the true diagonal and twice a side's length for a wrong one (the farthest corner is not
    safe: with noise, a 0.9 x 1.4 m window's long side and its diagonal, 1.4 and 1.66 m, can swap). The sides
    are the averages of opposite edges; the unit pair is the nearest orthonormal one (polar decomposition)."""
    p = np.asarray(corners, dtype=float).reshape(-1, 4, 3)
    rows = np.arange(len(p))
    pairings = np.array([[1, 2, 3], [2, 1, 3], [3, 1, 2]])  # (diagonal partner, the two beside it)
    closures = np.stack([p[:, 0] + p[:, k] - p[:, i] - p[:, j] for k, i, j in pairings], axis=1)  # (R, 3, 3)
    opp, i, j = pairings[np.argmin(np.linalg.norm(closures, axis=2), axis=1)].T
    p0, pi, pj, po = p[:, 0], p[rows, i], p[rows, j], p[rows, opp]
    e1, e2 = ((pi - p0) + (po - pj)) / 2.0, ((pj - p0) + (po - pi)) / 2.0
    l1, l2 = np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1)
    M = np.stack([e1 / np.maximum(l1, 1e-9)[:, None], e2 / np.maximum(l2, 1e-9)[:, None]], axis=2)
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    Q = U @ Vt
    return Q[:, :, 0], Q[:, :, 1], l1, l2, p0 + po - pi - pj
