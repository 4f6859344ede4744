"""The building's surfaces as a check on registration: do the points the camera saw lie on the model's walls?

A registration from two or three doors is often not unique in an office: other doors of the building sit at
the same distances (the chance that a wrong pose lines up three of them within 0.6 m is ~0.3 on Office_A). The
walls, furniture and door frames around the doors are far more specific. `SurfaceIndex` samples the model's
non-horizontal surfaces (walls, door and window frames, furniture sides; floors and ceilings say nothing about
where on a storey one is) and answers, for a pose hypothesis, which fraction of the observed points lies within
`tolerance_m` of a surface (`support`). The localizer uses it to choose among the registrar's candidate poses
and to refuse a pose the walls contradict (graph.localizer).

Points: CAD frame, metres. The observed points should come from a band around the camera's height (see
`band_points`), where the floor and ceiling do not appear.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

MAX_SAMPLES = 3_000_000  # memory bound of the index (~100 MB with the tree)


@dataclass(frozen=True)
class SurfaceParams:
    spacing_m: float = 0.1  # distance between surface samples
    max_normal_z: float = 0.7  # triangles whose normal's |z| exceeds this (floors, ceilings, slabs) are left out
    tolerance_m: float = 0.2  # a point this close to a sample lies on the surface


class SurfaceIndex:
    """Samples of the model's non-horizontal surfaces in a k-d tree (see module doc)."""

    def __init__(self, samples_cad: np.ndarray, params: SurfaceParams | None = None,
                 normals_cad: np.ndarray | None = None) -> None:
        """samples_cad (N, 3) metres; normals_cad (N, 3) unit normals of their surfaces (for `align`)."""
        self.params = params or SurfaceParams()
        self.samples_cad = np.asarray(samples_cad, float).reshape(-1, 3)
        self.normals_cad = None if normals_cad is None else np.asarray(normals_cad, float).reshape(-1, 3)
        self.tree = cKDTree(self.samples_cad)

    @classmethod
    def from_mesh(cls, vertices_cad: np.ndarray, faces: np.ndarray, params: SurfaceParams | None = None,
                  seed: int = 0) -> SurfaceIndex:
        """Samples on the triangles (V, 3) / (F, 3) at about `spacing_m`, area-weighted, seeded."""
        p = params or SurfaceParams()
        tri = np.asarray(vertices_cad, float)[np.asarray(faces, np.int64)]
        if len(tri) == 0:
            return cls(np.zeros((0, 3)), p)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            nz = np.abs(cross[:, 2]) / (2.0 * area)
        keep = (area > 1e-9) & (nz <= p.max_normal_z)
        tri, area = tri[keep], area[keep]
        density = 1.0 / p.spacing_m**2
        n_total = int(min(MAX_SAMPLES, max(1, area.sum() * density)))
        rng = np.random.default_rng(seed)
        # every triangle gets floor(expected) samples, plus one more with the fractional part's probability
        expected = area / area.sum() * n_total
        counts = np.floor(expected).astype(np.int64) + (rng.random(len(area)) < expected % 1.0)
        idx = np.repeat(np.arange(len(tri)), counts)
        r1, r2 = rng.random(len(idx)), rng.random(len(idx))
        s = np.sqrt(r1)
        a, b, c = tri[idx, 0], tri[idx, 1], tri[idx, 2]
        samples = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
        normals = cross[keep][idx] / (2.0 * area[idx])[:, None]
        return cls(samples, p, normals)

    def __len__(self) -> int:
        return len(self.samples_cad)

    def support(self, points_cad: np.ndarray) -> float:
        """Fraction of the points within `tolerance_m` of a surface (0 for no points)."""
        pts = np.asarray(points_cad, float).reshape(-1, 3)
        if len(pts) == 0 or len(self.samples_cad) == 0:
            return 0.0
        d, _ = self.tree.query(pts, distance_upper_bound=self.params.tolerance_m)
        return float(np.isfinite(d).mean())


@dataclass(frozen=True)
class SurfaceFit:
    """A pose from depth points against the model's surfaces: T_cad_body and its information matrix (6 x 6,
    GTSAM's tangent order [rot; trans], body frame); directions the surfaces do not fix carry ~no information."""

    T_cad_body: np.ndarray
    information: np.ndarray
    inliers: int
    rms_m: float


def align_to_surfaces(index: SurfaceIndex, points_body: np.ndarray, T_cad_body: np.ndarray,
                      iterations: int = 6, max_distance_m: float = 0.3, sigma_m: float = 0.05,
                      depth_sigma_per_m2: float = 0.005, independent_points: int = 30,
                      min_inliers: int = 50) -> SurfaceFit | None:
    """Point-to-plane ICP of the points (body frame) on the index's surfaces from the initial T_cad_body. The
    steps move yaw and translation only (Gauss-Newton with Huber weights, in the CAD frame about the points'
    centroid): gravity fixes roll and pitch far better than points at camera height on vertical walls do. The
    information of the result is that of all 6 directions, in GTSAM's right perturbation T exp(xi). None when
    fewer than `min_inliers` points (or half of them) find a surface within `max_distance_m`.

    A point's distance to its surface has sigma `sigma_m` (the model against reality) + `depth_sigma_per_m2`
    times its range squared (stereo depth); residuals beyond 1.5 sigma are down-weighted (Huber).

    The points of one keyframe share errors (the depth's calibration, the model against reality), so the
    information is that of `independent_points` points, however many there are."""
    if index.normals_cad is None or len(index) == 0:
        return None
    p = np.asarray(points_body, float).reshape(-1, 3)
    if len(p) < min_inliers:
        return None
    T = np.asarray(T_cad_body, float).copy()
    sigma = sigma_m + depth_sigma_per_m2 * np.einsum("ij,ij->i", p, p)  # per point, m
    for it in range(iterations + 1):
        q = p @ T[:3, :3].T + T[:3, 3]
        d, k = index.tree.query(q, distance_upper_bound=max_distance_m)
        ok = np.isfinite(d)
        if ok.sum() < max(min_inliers, 0.5 * len(p)):
            return None
        n = index.normals_cad[k[ok]]
        r = np.einsum("ij,ij->i", n, q[ok] - index.samples_cad[k[ok]])  # signed point-to-plane distance
        s_ok = sigma[ok]
        w = np.minimum(1.0, 1.5 * s_ok / np.maximum(np.abs(r), 1e-12)) / s_ok**2  # Huber x inverse variance
        if it == iterations:
            break
        c = q[ok].mean(axis=0)
        arm = q[ok] - c
        J4 = np.column_stack([arm[:, 0] * n[:, 1] - arm[:, 1] * n[:, 0], n])  # d r / d [yaw about c; x, y, z]
        H4 = (J4 * w[:, None]).T @ J4 + 1e-6 * np.eye(4)
        step = -np.linalg.solve(H4, (J4 * w[:, None]).T @ r)
        cy, sy = np.cos(step[0]), np.sin(step[0])
        Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        delta = np.eye(4)
        delta[:3, :3], delta[:3, 3] = Rz, c - Rz @ c + step[1:]
        T = delta @ T
        if np.abs(step).max() < 1e-5:
            break
    m = n @ T[:3, :3]  # the normals in the body frame
    J = np.hstack([np.cross(p[ok], m), m])  # d r / d [rot; trans], right perturbation
    H = (J * w[:, None]).T @ J
    scale = min(1.0, independent_points / max(1, int(ok.sum())))
    rms = float(np.sqrt(np.mean(r * r)))
    return SurfaceFit(T, H * scale + 1e-6 * np.eye(6), int(ok.sum()), rms)


def band_points(points_body: np.ndarray, up_body: np.ndarray, half_height_m: float = 0.5,
                max_range_m: float = 8.0, max_points: int = 300, seed: int = 0) -> np.ndarray:
    """The points (N, 3), body frame, within `half_height_m` of the camera's height (along `up_body`) and
    `max_range_m` of it: walls, doors and furniture, not the floor or the ceiling (which every pose on a storey
    explains). At most `max_points`, drawn evenly (seeded)."""
    p = np.asarray(points_body, float).reshape(-1, 3)
    up = np.asarray(up_body, float) / np.linalg.norm(up_body)
    keep = (np.abs(p @ up) <= half_height_m) & (np.linalg.norm(p, axis=1) <= max_range_m)
    p = p[keep]
    if len(p) > max_points:
        p = p[np.sort(np.random.default_rng(seed).choice(len(p), max_points, replace=False))]
    return p
