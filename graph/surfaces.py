"""The building's surfaces as a check on registration: do the points the camera saw lie on the model's walls?

A registration from two or three doors is often not unique in an office: other doors of the building sit at
the same distances (a wrong pose often lines up three of them within 0.6 m: docs/measurements.md, "The walls as a
check: chance fits and look-alike rooms"). The
walls, furniture and door frames around the doors are far more specific. `SurfaceIndex` samples the model's
non-horizontal surfaces (walls, door and window frames, furniture sides; floors and ceilings say nothing about
where on a storey one is) and answers, for a pose hypothesis, which fraction of the observed points lies within
`tolerance_m` of a surface (`support`; a point seen from a known camera also within `range_sigmas` of its stereo
depth noise, which grows with range squared: a wall 8 m away is measured to +-0.3 m). The localizer uses it to
choose among the registrar's candidate poses and to refuse a pose the walls contradict (graph.localizer).

Support alone is a weak test in a building of look-alike rooms: a pose turned 90 deg in the next room puts 80 % of
the points near some wall. What a camera measured also says where the walls are *not*: the line of
sight from the camera to each point is free. `WallVoxels` holds the model's walls (without doors, windows and
openings: a camera sees through doorways and glass) as occupied voxels, and `SurfaceIndex.check` counts the points
whose line of sight crosses a wall well before the point (further than its depth noise): under a wrong pose most
points are seen through a wall, under the right one almost none (`SurfaceCheck.score`).

Once localized, `align_to_surfaces` fits a keyframe's points to the surfaces (point-to-plane) for a measured
pose. The floors, sampled apart, take part there: a stereo camera sees the floor ahead, and its height is the
one thing the walls cannot give and the doors' corners give worst (their bottoms hide behind the image's edge
or furniture, their tops include the frame).

Points: CAD frame, metres. The observed points for the check should come from a band around the camera's
height (see `band_points`), where the floor and ceiling do not appear; `floor_points` picks those below it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

MAX_SAMPLES = 3_000_000  # memory bound of the index (~100 MB with the tree)
COVERED_M = 0.5  # a horizontal surface with another this little above it is a slab's underside: not a floor


@dataclass(frozen=True)
class SurfaceParams:
    spacing_m: float = 0.1  # distance between surface samples
    max_normal_z: float = 0.7  # triangles whose normal's |z| exceeds this (floors, ceilings, slabs) are left out
    tolerance_m: float = 0.2  # a point this close to a sample lies on the surface ...
    range_sigmas: float = 2.0  # ... or, seen from a known camera, this many sigmas of its depth noise (below)
    horizontal_spacing_m: float = 0.2  # the floors' samples (open above), for fitting heights (0: none)
    depth_sigma_per_m2: float = 0.005  # the points' depth noise (stereo, ~ range^2), for the line-of-sight check ...
    sight_margin_m: float = 0.2  # ... which lets a ray cross a wall this + 3 sigmas before its point
    hidden_gap_m: float = 0.45  # with the walls' voxels, faces of slots narrower than this are not sampled (0: all)


class WallVoxels:
    """The model's walls as occupied voxels (`voxel_m` cubes), for line-of-sight checks: sorted int64 keys of the
    voxels a wall triangle passes through. Each triangle is sampled on a lattice at most half a voxel apart along
    its edges, so a wall leaves no hole a line of sight slips through, however thin it is modelled. CAD frame,
    metres."""

    OFFSET = 1 << 20  # voxel indices are shifted positive: +-100 km at 0.1 m
    SPAN = 1 << 21
    CHUNK = 4_000_000  # lattice points per pass (memory)

    def __init__(self, keys: np.ndarray, voxel_m: float = 0.1) -> None:
        keys = np.asarray(keys, np.int64)
        # sorted and unique as they come from the cache: np.unique again would cost a large model's start a second
        self.keys = keys if bool(np.all(keys[1:] > keys[:-1])) else np.unique(keys)
        self.voxel_m = voxel_m

    @classmethod
    def from_mesh(cls, vertices_cad: np.ndarray, faces: np.ndarray, voxel_m: float = 0.1,
                  max_normal_z: float = 0.7) -> WallVoxels:
        """The non-horizontal triangles (V, 3) / (F, 3) (walls, columns; not floors, ceilings or slabs, which
        lines of sight at the camera's height do not cross) as voxels."""
        tri, _, area, nz = _triangles(vertices_cad, faces)
        tri = tri[(area > 1e-9) & (nz <= max_normal_z)]
        if len(tri) == 0:
            return cls(np.zeros(0, np.int64), voxel_m)
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        n1 = np.ceil(np.linalg.norm(e1, axis=1) / (0.5 * voxel_m)).astype(np.int64)
        n2 = np.ceil(np.linalg.norm(e2, axis=1) / (0.5 * voxel_m)).astype(np.int64)
        count = (n1 + 1) * (n2 + 1)  # the parallelogram's lattice; the half beyond the triangle is dropped
        keys, first = [], 0
        ends = np.searchsorted(np.cumsum(count), np.arange(cls.CHUNK, count.sum() + cls.CHUNK, cls.CHUNK))
        for last in np.unique(np.minimum(np.maximum(ends, 1), len(tri))):
            k = np.arange(first, last)
            first = last
            t = np.repeat(k, count[k])
            local = np.arange(len(t)) - np.repeat(np.cumsum(count[k]) - count[k], count[k])
            u = (local // (n2[t] + 1)) / n1[t]
            v = (local % (n2[t] + 1)) / n2[t]
            inside = u + v <= 1.0 + 1e-9
            t, u, v = t[inside], u[inside], v[inside]
            points = tri[t, 0] + u[:, None] * e1[t] + v[:, None] * e2[t]
            keys.append(np.unique(cls._key(points, voxel_m)))
        return cls(np.concatenate(keys), voxel_m)

    @classmethod
    def _key(cls, points: np.ndarray, voxel_m: float) -> np.ndarray:
        q = np.floor(points / voxel_m).astype(np.int64) + cls.OFFSET
        return (q[:, 0] * cls.SPAN + q[:, 1]) * cls.SPAN + q[:, 2]

    def __len__(self) -> int:
        return len(self.keys)

    def occupied(self, points_cad: np.ndarray) -> np.ndarray:
        """(N,) bool: the points' voxels hold a wall."""
        if len(self.keys) == 0 or len(points_cad) == 0:
            return np.zeros(len(points_cad), bool)
        k = self._key(np.asarray(points_cad, float).reshape(-1, 3), self.voxel_m)
        i = np.minimum(np.searchsorted(self.keys, k), len(self.keys) - 1)
        return self.keys[i] == k

    def enclosed(self, points_cad: np.ndarray, normals_cad: np.ndarray, gap_m: float,
                 chunk: int = 500_000) -> np.ndarray:
        """(N,) bool: a wall voxel lies within `gap_m` of each point (N, 3) along its surface's normal (N, 3) on
        both sides (probed every voxel from 1.5 voxels out, past the point's own surface): a face of a slot
        narrower than `gap_m` (a wall's face behind a panel standing in front of it, the inner faces of a double
        wall), which no camera sees. The normals' sign does not matter (the solids' winding is not reliable)."""
        pts = np.asarray(points_cad, float).reshape(-1, 3)
        nrm = np.asarray(normals_cad, float).reshape(-1, 3)
        offsets = np.arange(1.5 * self.voxel_m, gap_m + 1e-9, self.voxel_m)
        def closed(p: np.ndarray, n: np.ndarray) -> np.ndarray:
            probes = p[:, None, :] + offsets[None, :, None] * n[:, None, :]  # (n, K, 3)
            return np.asarray(self.occupied(probes.reshape(-1, 3)).reshape(len(p), -1).any(axis=1))

        out = np.zeros(len(pts), bool)
        for lo in range(0, len(pts), chunk):
            p, n = pts[lo:lo + chunk], nrm[lo:lo + chunk]
            one = np.flatnonzero(closed(p, n))  # most faces are open on one side: the other side only for the rest
            out[lo + one[closed(p[one], -n[one])]] = True
        return out

    def seen_through(self, origins_cad: np.ndarray, points_cad: np.ndarray, depth_sigma_per_m2: float = 0.005,
                     margin_m: float = 0.2, start_m: float = 0.2) -> np.ndarray:
        """(N,) bool: the line of sight from each origin (N, 3) to its point (N, 3) crosses a wall (passes into a
        wall voxel and out again) more than `margin_m` + 3 depth sigmas (`depth_sigma_per_m2` x range^2) before
        the point: the point cannot have been seen from there. A line of sight that runs into a wall and stays in
        it to the end is one grazing the wall it ends on. Sampled every half voxel from `start_m` (the camera's
        own clearance). A line that passes a wall's edge within a voxel counts as crossing it."""
        o = np.asarray(origins_cad, float).reshape(-1, 3)
        d = np.asarray(points_cad, float).reshape(-1, 3) - o
        rng = np.linalg.norm(d, axis=1)
        free_to = rng - margin_m - 3.0 * depth_sigma_per_m2 * rng**2  # along the line, m
        step = 0.5 * self.voxel_m
        n = np.maximum(0, np.floor((free_to - start_m) / step).astype(np.int64) + 1)
        ray = np.repeat(np.arange(len(o)), n)
        if len(ray) == 0:
            return np.zeros(len(o), bool)
        k = np.arange(len(ray)) - np.repeat(np.cumsum(n) - n, n)  # the sample's index along its line
        u = d[ray] / rng[ray, None]
        hit = self.occupied(o[ray] + u * (start_m + step * k)[:, None])
        first_hit = np.full(len(o), np.iinfo(np.int64).max)
        np.minimum.at(first_hit, ray[hit], k[hit])
        last_free = np.full(len(o), -1)
        np.maximum.at(last_free, ray[~hit], k[~hit])
        return first_hit < last_free


@dataclass(frozen=True)
class SurfaceCheck:
    """A pose hypothesis against the model: `support`, the fraction of the points on a surface; `seen_through`,
    the fraction whose line of sight crosses a wall (0 without walls or origins); `score`, the fraction on a
    surface and in sight."""

    support: float
    seen_through: float
    score: float


class SurfaceIndex:
    """Samples of the model's non-horizontal surfaces in a k-d tree (see module doc), and optionally of its
    horizontal ones (floors, tables, stairs' treads) in a second tree: they say nothing about where on a storey
    one is, so `support` leaves them out, but they fix the height in `align_to_surfaces`."""

    def __init__(self, samples_cad: np.ndarray, params: SurfaceParams | None = None,
                 normals_cad: np.ndarray | None = None, horizontal_cad: np.ndarray | None = None,
                 horizontal_normals_cad: np.ndarray | None = None) -> None:
        """samples_cad (N, 3) metres; normals_cad (N, 3) unit normals of their surfaces (for `align`); the same
        for the horizontal surfaces (M, 3), when given."""
        self.params = params or SurfaceParams()
        self.samples_cad = np.asarray(samples_cad, float).reshape(-1, 3)
        self.normals_cad = None if normals_cad is None else np.asarray(normals_cad, float).reshape(-1, 3)
        self.tree = cKDTree(self.samples_cad)
        self.walls: WallVoxels | None = None  # for line-of-sight checks (`check`), when set
        self.horizontal: tuple[cKDTree, np.ndarray, np.ndarray] | None = None  # (tree, samples, normals)
        if horizontal_cad is not None and horizontal_normals_cad is not None and len(horizontal_cad):
            h = np.asarray(horizontal_cad, float).reshape(-1, 3)
            self.horizontal = (cKDTree(h), h, np.asarray(horizontal_normals_cad, float).reshape(-1, 3))

    @classmethod
    def from_mesh(cls, vertices_cad: np.ndarray, faces: np.ndarray, params: SurfaceParams | None = None,
                  seed: int = 0, walls: WallVoxels | None = None) -> SurfaceIndex:
        """Samples on the triangles (V, 3) / (F, 3) at about `spacing_m` (the horizontal ones at
        `horizontal_spacing_m`), area-weighted, seeded. With `walls` (set as the index's `walls`), the samples
        of faces no camera sees, in slots narrower than `hidden_gap_m` (`WallVoxels.enclosed`), are left out: a
        pose that puts the points on such a face would otherwise fit them as well as the true one."""
        p = params or SurfaceParams()
        tri, cross, area, nz = _triangles(vertices_cad, faces)
        if len(tri) == 0:
            return cls(np.zeros((0, 3)), p)
        rng = np.random.default_rng(seed)
        samples, normals = _sample(tri, cross, area, (area > 1e-9) & (nz <= p.max_normal_z), p.spacing_m, rng)
        if walls is not None and p.hidden_gap_m > 0:
            seen = ~walls.enclosed(samples, normals, p.hidden_gap_m)
            samples, normals = samples[seen], normals[seen]
        horizontal = (None, None)
        if p.horizontal_spacing_m > 0:
            h, h_normals = _sample(tri, cross, area, (area > 1e-9) & (nz > p.max_normal_z), p.horizontal_spacing_m,
                                   rng)
            open_above = _open_above(h, p.horizontal_spacing_m)
            horizontal = (h[open_above], h_normals[open_above])
        index = cls(samples, p, normals, *horizontal)
        index.walls = walls
        return index

    def __len__(self) -> int:
        return len(self.samples_cad)

    def support(self, points_cad: np.ndarray) -> float:
        """Fraction of the points within `tolerance_m` of a surface (0 for no points)."""
        return self.check(points_cad).support

    def supports(self, points_cad: np.ndarray) -> np.ndarray:
        """`support` of each of H point sets (H, N, 3) at once, (H,): one k-d tree query for all."""
        pts = np.asarray(points_cad, float)
        if pts.size == 0 or len(self.samples_cad) == 0:
            return np.zeros(len(pts))
        d = self.tree.query(pts.reshape(-1, 3), distance_upper_bound=self.params.tolerance_m)[0]
        return np.isfinite(d).reshape(pts.shape[:2]).mean(axis=1)

    def check(self, points_cad: np.ndarray, origins_cad: np.ndarray | None = None) -> SurfaceCheck:
        """`support` of the points (N, 3) and, with `walls` and the cameras they were seen from (N, 3), the
        fraction seen through a wall (see module doc). With the cameras, `support` allows for each point's depth
        noise (is the pose consistent with what was measured?) and `score` does not: it compares poses, as
        sharply as the near points allow (a looser tolerance lifts the rivals' scores more than the true one's)."""
        pts = np.asarray(points_cad, float).reshape(-1, 3)
        if len(pts) == 0 or len(self.samples_cad) == 0:
            return SurfaceCheck(0.0, 0.0, 0.0)
        p = self.params
        if origins_cad is None:
            on = np.isfinite(self.tree.query(pts, distance_upper_bound=p.tolerance_m)[0])
            return SurfaceCheck(float(on.mean()), 0.0, float(on.mean()))
        range_m = np.linalg.norm(pts - np.asarray(origins_cad, float).reshape(-1, 3), axis=1)
        tolerance_m = np.hypot(p.tolerance_m, p.range_sigmas * p.depth_sigma_per_m2 * range_m**2)
        d = self.tree.query(pts, distance_upper_bound=float(tolerance_m.max()))[0]
        within_noise, near = d <= tolerance_m, d <= p.tolerance_m
        through = np.zeros(len(pts), bool) if self.walls is None else \
            self.walls.seen_through(origins_cad, pts, p.depth_sigma_per_m2, p.sight_margin_m)
        return SurfaceCheck(float(within_noise.mean()), float(through.mean()), float((near & ~through).mean()))


def _triangles(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The triangles (T, 3, 3) of a mesh (V, 3) / (F, 3), their edges' cross products (T, 3), areas (T,) and
    |normal z| (T,) (NaN for a degenerate triangle)."""
    tri = np.asarray(vertices, float)[np.asarray(faces, np.int64)].reshape(-1, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        nz = np.abs(cross[:, 2]) / (2.0 * area)
    return tri, cross, area, nz


def _open_above(samples: np.ndarray, spacing_m: float) -> np.ndarray:
    """(N,) bool: the horizontal samples with no other within COVERED_M above them (and a spacing aside). A
    point measured on a floor lies on a surface open above; a slab's underside lies its thickness below its top,
    often nearer to such a point than the top's next sample, and would pull a fit down (the IFC solids' winding
    is not reliable enough to tell top from underside: Office_A's slabs face either way)."""
    if len(samples) == 0:
        return np.zeros(0, bool)
    half_height, aside = 0.5 * COVERED_M, 2.0 * spacing_m
    scale = np.array([1.0 / aside, 1.0 / aside, 1.0 / half_height])  # an ellipsoid becomes the unit ball
    tree = cKDTree(samples * scale)
    lifted = (samples + [0.0, 0.0, half_height + 0.02]) * scale  # from 2 cm to COVERED_M + 2 cm above
    return np.asarray(tree.query_ball_point(lifted, r=1.0, return_length=True)) == 0


def _sample(tri: np.ndarray, cross: np.ndarray, area: np.ndarray, keep: np.ndarray, spacing_m: float,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(samples (N, 3), unit normals (N, 3)) on the kept triangles, area-weighted, about `spacing_m` apart."""
    tri, cross, area = tri[keep], cross[keep], area[keep]
    if len(tri) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    n_total = int(min(MAX_SAMPLES, max(1, area.sum() / spacing_m**2)))
    # every triangle gets floor(expected) samples, plus one more with the fractional part's probability
    expected = area / area.sum() * n_total
    counts = np.floor(expected).astype(np.int64) + (rng.random(len(area)) < expected % 1.0)
    idx = np.repeat(np.arange(len(tri)), counts)
    r1, r2 = rng.random(len(idx)), rng.random(len(idx))
    s = np.sqrt(r1)
    a, b, c = tri[idx, 0], tri[idx, 1], tri[idx, 2]
    samples = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    return samples, cross[idx] / (2.0 * area[idx])[:, None]


@dataclass(frozen=True)
class SurfaceFit:
    """A pose from depth points against the model's surfaces: T_cad_body and its information matrix (6 x 6,
    GTSAM's tangent order [rot; trans], body frame); directions the surfaces do not fix carry ~no information."""

    T_cad_body: np.ndarray
    information: np.ndarray
    inliers: int
    rms_m: float


def align_to_surfaces(index: SurfaceIndex, points_body: np.ndarray, T_cad_body: np.ndarray,
                      floor_body: np.ndarray | None = None, iterations: int = 6, max_distance_m: float = 0.3,
                      sigma_m: float = 0.05, depth_sigma_per_m2: float = 0.005, independent_points: int = 30,
                      min_inliers: int = 50, tilt_sigma_rad: float = 0.01,
                      hold_height: bool = False) -> SurfaceFit | None:
    """Point-to-plane ICP of the points (body frame) on the index's walls, and of `floor_body` (points below the
    camera, `floor_points`) on its horizontal surfaces when it has them, from the initial T_cad_body.
    Gauss-Newton with Huber weights, in the CAD frame about the points' centroid; roll and pitch
    are held near the initial pose's (gravity's) with `tilt_sigma_rad`, since points at camera height on
    vertical walls hardly see them, while the floor does; with `hold_height`, the height stays the initial
    pose's (without the floor the walls hardly see it either: a few sloped or bounded faces would set it
    alone). The information of the result is the points' alone (not that hold), for all 6 directions, in
    GTSAM's right perturbation T exp(xi). None when fewer than `min_inliers` of the wall points (or half of
    them) find a wall within `max_distance_m`: the floor alone says only the height.

    A point's distance to its surface has sigma `sigma_m` (the model against reality) + `depth_sigma_per_m2`
    times its range squared (stereo depth); residuals beyond 1.5 sigma are down-weighted (Huber).

    The points of one keyframe share errors (the depth's calibration, the model against reality), so the
    information is that of `independent_points` points, however many there are: the walls' and the floor's
    points each, since they measure different directions (position and yaw; height)."""
    if index.normals_cad is None or len(index) == 0:
        return None
    walls = np.asarray(points_body, float).reshape(-1, 3)
    if len(walls) < min_inliers:
        return None
    floor = np.zeros((0, 3)) if floor_body is None or index.horizontal is None else \
        np.asarray(floor_body, float).reshape(-1, 3)
    p = np.vstack([walls, floor])
    in_band = np.arange(len(p)) < len(walls)  # the first points are the band's, the rest from below
    surfaces = [(index.tree, index.samples_cad, index.normals_cad)]
    if len(floor):
        assert index.horizontal is not None
        surfaces.append(index.horizontal)
    T = np.asarray(T_cad_body, float).copy()
    R0, z0 = T[:3, :3].copy(), float(T[2, 3])
    height_prior = 1e12 if hold_height else 1e-6
    sigma = sigma_m + depth_sigma_per_m2 * np.einsum("ij,ij->i", p, p)  # per point, m
    tilt_prior = 1.0 / tilt_sigma_rad**2  # roll and pitch stay near the initial pose's unless the points say
    for it in range(iterations + 1):
        q = p @ T[:3, :3].T + T[:3, 3]
        # every point on its nearest surface; the band's points count where that is a wall, the points below
        # where it is a floor (the walls' feet and what stands on the floor, furniture the model may lack, are
        # left to the band)
        best = np.full(len(p), np.inf)
        on, n, on_floor = np.zeros((len(p), 3)), np.zeros((len(p), 3)), np.zeros(len(p), bool)
        for s_i, (tree, samples, normals) in enumerate(surfaces):
            d, k = tree.query(q, distance_upper_bound=max_distance_m)
            nearer = d < best
            best[nearer], on[nearer], n[nearer] = d[nearer], samples[k[nearer]], normals[k[nearer]]
            on_floor[nearer] = s_i == 1
        on_walls = in_band & ~on_floor
        ok = np.isfinite(best) & (on_walls | (on_floor & ~in_band))
        if on_walls[ok].sum() < max(min_inliers, 0.5 * len(walls)):
            return None
        on, n = on[ok], n[ok]
        r = np.einsum("ij,ij->i", n, q[ok] - on)  # signed point-to-plane distance
        s_ok = sigma[ok]
        w = np.minimum(1.0, 1.5 * s_ok / np.maximum(np.abs(r), 1e-12)) / s_ok**2  # Huber x inverse variance
        if it == iterations:
            break
        c = q[ok].mean(axis=0)
        J6 = np.hstack([np.cross(q[ok] - c, n), n])  # d r / d [rotation about c; translation], CAD frame
        P = np.diag([tilt_prior, tilt_prior, 1e-6, 1e-6, 1e-6, height_prior])
        tilt = np.zeros(6)  # how far roll and pitch have moved from the initial pose's (CAD frame, rad)
        tilt[:2] = Rotation.from_matrix(T[:3, :3] @ R0.T).as_rotvec()[:2]
        step = -np.linalg.solve((J6 * w[:, None]).T @ J6 + P, (J6 * w[:, None]).T @ r + P @ tilt)
        delta = np.eye(4)
        delta[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
        delta[:3, 3] = c - delta[:3, :3] @ c + step[3:]
        T = delta @ T
        if hold_height:  # the body's height, which a tilt about the points' centroid would move too
            T[2, 3] = z0
        if np.abs(step).max() < 1e-5:
            break
    m = n @ T[:3, :3]  # the normals in the body frame
    J = np.hstack([np.cross(p[ok], m), m])  # d r / d [rot; trans], right perturbation
    H = np.zeros((6, 6))
    for group in (on_walls[ok], ~on_walls[ok]):
        Jg = J[group]
        H += (Jg * w[group, None]).T @ Jg * min(1.0, independent_points / max(1, int(group.sum())))
    rms = float(np.sqrt(np.mean(r * r)))
    return SurfaceFit(T, H + 1e-6 * np.eye(6), int(ok.sum()), rms)


def floor_points(points_body: np.ndarray, up_body: np.ndarray, below_m: float = 0.5, max_range_m: float = 4.0,
                 max_points: int = 100, seed: int = 0) -> np.ndarray:
    """The points (N, 3), body frame, more than `below_m` below the camera's height and within `max_range_m`:
    mostly the floor, which fixes the height when fitted (`align_to_surfaces` with a horizontal index). At most
    `max_points`, drawn evenly (seeded)."""
    p = np.asarray(points_body, float).reshape(-1, 3)
    up = np.asarray(up_body, float) / np.linalg.norm(up_body)
    return _at_most(p[(p @ up < -below_m) & (np.linalg.norm(p, axis=1) <= max_range_m)], max_points, seed)


def band_points(points_body: np.ndarray, up_body: np.ndarray, half_height_m: float = 0.5,
                max_range_m: float = 8.0, max_points: int = 300, seed: int = 0) -> np.ndarray:
    """The points (N, 3), body frame, within `half_height_m` of the camera's height (along `up_body`) and
    `max_range_m` of it: walls, doors and furniture, not the floor or the ceiling (which every pose on a storey
    explains). At most `max_points`, drawn evenly (seeded)."""
    p = np.asarray(points_body, float).reshape(-1, 3)
    up = np.asarray(up_body, float) / np.linalg.norm(up_body)
    keep = (np.abs(p @ up) <= half_height_m) & (np.linalg.norm(p, axis=1) <= max_range_m)
    return _at_most(p[keep], max_points, seed)


def _at_most(points: np.ndarray, max_points: int, seed: int) -> np.ndarray:
    """`points`, or `max_points` of them drawn at random (seeded), in their order."""
    if len(points) <= max_points:
        return points
    return points[np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))]
