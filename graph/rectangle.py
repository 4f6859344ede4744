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
