"""3D sides and corners of a macro-feature (paper §2.2.3), and the plausibility checks.

Points sampled along each 2D side are back-projected with their stereo depth (eq. 2); a 3D line is fitted by
orthogonal regression (total least squares), points farther than a threshold removed, the line refitted.
The side's ends are the points of the fitted line nearest the viewing rays through the 2D side's ends
(the paper projects the 3D endpoints onto the line; the rays need no depth at the very ends, where
stereo is least reliable). Where the depth beside the opening shows the wall it sits in (`wall_plane`), the corners
are instead where those rays meet that wall (`corners_on_plane`): inside an open doorway the sides' depth is the
room behind it.
Frames: camera optical frame (x right, y down, z forward), metres. Corners are ordered
top-left, top-right, bottom-right, bottom-left as seen in the image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from macroloc.perception.calib import StereoRig
from macroloc.perception.lines import Sides
from macroloc.perception.params import PlausibilityParams, WallPlaneParams
from macroloc.perception.stereo import back_project, ray_cam, sample_depth_m

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Line3D:
    """A 3D line: a point on it and a unit direction (camera frame, m); `inliers` used in the final fit."""

    point_m: np.ndarray
    direction: np.ndarray
    inliers: np.ndarray

    def distances_m(self, points_m: np.ndarray) -> np.ndarray:
        rel = points_m - self.point_m
        return np.linalg.norm(rel - np.outer(rel @ self.direction, self.direction), axis=1)


def fit_line_tls(points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthogonal-regression line through points (N,3): (centroid, unit direction of largest spread)."""
    centroid = points_m.mean(axis=0)
    _, _, vt = np.linalg.svd(points_m - centroid, full_matrices=False)
    return centroid, vt[0]


def fit_line_robust(points_m: np.ndarray, threshold_m: float = 0.08, mad_k: float = 3.0,
                    min_points: int = 4, max_rounds: int = 5) -> Line3D | None:
    """Fit, drop points farther than the cut, refit (paper §2.2.3), repeated until the inliers settle.

    The paper does one removal and one refit. With gross outliers the first fit is pulled off the line
    and a fixed threshold can reject every point, so the cut starts adaptive,
    max(threshold_m, median + mad_k * 1.4826 * MAD of the inliers' distances), and the rounds repeat.
    """
    pts = points_m[np.all(np.isfinite(points_m), axis=1)]
    if len(pts) < min_points:
        return None
    inliers = np.ones(len(pts), bool)
    for _ in range(max_rounds):
        centroid, direction = fit_line_tls(pts[inliers])
        d = Line3D(centroid, direction, inliers).distances_m(pts)
        d_in = d[inliers]
        cut = max(threshold_m, float(np.median(d_in) + mad_k * 1.4826 * np.median(np.abs(d_in - np.median(d_in)))))
        new = d <= cut
        if new.sum() < min_points:
            return None
        if np.array_equal(new, inliers):
            break
        inliers = new
    centroid, direction = fit_line_tls(pts[inliers])
    return Line3D(centroid, direction, inliers)


def closest_point_to_ray(line: Line3D, ray: np.ndarray) -> np.ndarray | None:
    """Point of `line` nearest the ray from the camera centre along unit `ray` (None if they are parallel)."""
    d, r = line.direction, ray
    # Minimise |p + s d - t r|: solve the 2x2 normal equations for (s, t).
    A = np.array([[d @ d, -(d @ r)], [d @ r, -(r @ r)]])
    b = -np.array([line.point_m @ d, line.point_m @ r])
    if abs(np.linalg.det(A)) < 1e-9:
        return None
    s, _ = np.linalg.solve(A, b)
    return line.point_m + s * d


@dataclass(frozen=True)
class Reconstruction:
    """4 corners (4,3) in the camera frame (m), width/height (m), tilt of the sides from vertical (deg)."""

    corners_cam: np.ndarray
    width_m: float
    height_m: float
    tilt_deg: float
    depth_m: float


def _side_points(side_px: np.ndarray, depth_m: np.ndarray, rig: StereoRig, n: int, inward_px: float) -> np.ndarray:
    """Back-projected points along a side. Depth is the median over columns |inward_px|/2 to 3|inward_px|/2
    inside the feature (the sign of `inward_px` gives the direction in u): at the side itself stereo mixes the
    feature with what is beside it (an open doorway, the far side of a window), metres away. The price: on a wall
    seen obliquely the depth is that of a point ~|inward_px| px inside (about 5 cm at 4 m and 35 deg).
    (Extrapolating inverse depth from two strips back to the side removes that bias on clean data but amplified
    the noise of real 7-px disparities into metres: not used.)"""
    t = np.linspace(0.05, 0.95, n)[:, None]
    uv = side_px[0] * (1 - t) + side_px[1] * t
    depth = sample_depth_m(depth_m, uv + np.array([inward_px, 0.0]), half_width_px=int(abs(inward_px) // 2))
    return back_project(uv, depth, rig)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b), 0, 1))))


def reconstruct_sides(sides: Sides, depth_m: np.ndarray, rig: StereoRig, n_samples: int = 40,
                      threshold_m: float = 0.08, min_inlier_fraction: float = 0.5, inward_px: float = 8.0,
                      ) -> tuple[np.ndarray, list[Line3D]] | str:
    """Corners (4,3) from the two 2D sides and the depth image, or the reason it failed."""
    lines, ends = [], []
    for name, side, sign in (("left", sides.left_px, 1.0), ("right", sides.right_px, -1.0)):
        pts = _side_points(side, depth_m, rig, n_samples, sign * inward_px)
        valid = int(np.all(np.isfinite(pts), axis=1).sum())
        line = fit_line_robust(pts, threshold_m)
        if line is None or line.inliers.sum() < min_inlier_fraction * n_samples:
            return f"{name} side: too few points with depth ({valid}/{n_samples})"
        top, bottom = (closest_point_to_ray(line, r) for r in ray_cam(side, rig))
        if top is None or bottom is None:
            return f"{name} side: line along the viewing ray"
        lines.append(line)
        ends.append((top, bottom))
    (tl, bl), (tr, br) = ends
    return np.stack([tl, tr, br, bl]), lines





def _strip_points(edge_px: np.ndarray, offset_px: np.ndarray, depth_m: np.ndarray, rig: StereoRig,
                  cfg: WallPlaneParams) -> np.ndarray:
    """Back-projected points (M, 3) of a strip beside an edge (2, 2): `n_samples` along it at each offset
    from `near_px` to `far_px` in the unit direction `offset_px`; those without depth left out."""
    t = np.linspace(0.05, 0.95, cfg.n_samples)[:, None]
    along = edge_px[0] * (1 - t) + edge_px[1] * t
    steps = np.arange(cfg.near_px, cfg.far_px + 1e-9, 3.0)
    uv = (along[None] + steps[:, None, None] * offset_px).reshape(-1, 2)
    pts = back_project(uv, sample_depth_m(depth_m, uv, half_width_px=1), rig)
    return pts[np.all(np.isfinite(pts), axis=1)]


def wall_plane(sides: Sides, depth_m: np.ndarray, rig: StereoRig, gravity_cam: np.ndarray | None = None,
               cfg: WallPlaneParams | None = None) -> tuple[np.ndarray, float] | None:
    """The plane n . X = d (unit n towards the camera, d < 0; camera frame, m) of the wall an opening sits in,
    or None where the depth beside it does not show one.

    Points are taken in three strips outside the opening: left of its left side, right of its right side and
    above its top, where the wall stands in the opening's own plane, and a plane is fitted to them by RANSAC
    (tolerance growing with depth squared, as stereo's noise does) and refitted to its inliers. It must hold
    `min_strips` of the strips and `min_inlier_fraction` of their points, and stand vertical where gravity is
    known. Inside the opening a camera sees the leaf, or through an open doorway the room behind, metres away;
    beside a side, within a few pixels, the jamb's reveal: a side's depth from there puts a door up to a metre off
    along the line of sight and its plane degrees off at range.

    Against the sides' depth, the wall's plane lowers the corners' median error at every range, with the true
    boxes and the detector's, and lets more of the detector's openings pass the plausibility checks
    (`bench.eval_perception_sim`: docs/measurements.md, "Door corners from the wall beside the opening").
    Where the box itself is wrong (wider than the door, or a doorway's box around a door seen through it) the
    wall beside it is some other wall: the tail grows a little."""
    cfg = cfg or WallPlaneParams()
    (tl, bl), (tr, br) = sides.left_px, sides.right_px
    across = (tr + br - tl - bl) / 2
    across = across / max(float(np.linalg.norm(across)), 1e-9)
    up = np.array([across[1], -across[0]])  # 90 deg from left-to-right, towards the image's top
    strips = [_strip_points(sides.left_px, -across, depth_m, rig, cfg),
              _strip_points(sides.right_px, across, depth_m, rig, cfg),
              _strip_points(np.stack([tl, tr]), up, depth_m, rig, cfg)]
    strips = [s for s in strips if len(s) >= cfg.min_points]
    if len(strips) < cfg.min_strips:
        return None
    pts = np.vstack(strips)
    group = np.repeat(np.arange(len(strips)), [len(s) for s in strips])
    tol = cfg.threshold_m[0] + cfg.threshold_m[1] * pts[:, 2] ** 2
    rng = np.random.default_rng(0)
    abc = pts[np.array([rng.choice(len(pts), 3, replace=False) for _ in range(cfg.iterations)])]  # (I, 3, 3)
    normals = np.cross(abc[:, 1] - abc[:, 0], abc[:, 2] - abc[:, 0])  # all hypotheses at once
    norms = np.linalg.norm(normals, axis=1)
    ok = norms >= 1e-9
    normals = normals[ok] / norms[ok, None]
    inliers = np.abs(pts @ normals.T - np.einsum("ij,ij->i", normals, abc[ok, 0])) <= tol[:, None]  # (N, I)
    counts = inliers.sum(axis=0)
    if not counts.size or counts.max() == 0:
        return None
    best = inliers[:, int(np.argmax(counts))]  # the first hypothesis with the most inliers
    for _ in range(2):  # refit to the inliers, then take the inliers of the refit
        centroid = pts[best].mean(axis=0)
        n = np.linalg.svd(pts[best] - centroid, full_matrices=False)[2][2]
        best = np.abs((pts - centroid) @ n) <= tol
        if best.sum() < 3:
            return None
    if best.mean() < cfg.min_inlier_fraction or \
            sum(int(best[group == g].sum()) >= cfg.min_points for g in range(len(strips))) < cfg.min_strips:
        return None
    if gravity_cam is not None:
        g = np.asarray(gravity_cam, float) / np.linalg.norm(gravity_cam)
        if abs(float(n @ g)) > np.sin(np.radians(cfg.max_tilt_deg)):
            return None
    d = float(n @ pts[best].mean(axis=0))
    return (n, d) if d < 0 else (-n, -d)


def corners_on_plane(sides: Sides, plane: tuple[np.ndarray, float], rig: StereoRig,
                     min_incidence_deg: float = 10.0) -> np.ndarray | None:
    """The corners (4, 3) TL, TR, BR, BL where the viewing rays through the sides' ends meet the plane, or None
    where a ray grazes it (less than `min_incidence_deg`) or meets it behind the camera."""
    n, d = plane
    (tl, bl), (tr, br) = sides.left_px, sides.right_px
    rays = ray_cam(np.stack([tl, tr, br, bl]), rig)
    along = rays @ n
    if np.any(np.abs(along) < np.sin(np.radians(min_incidence_deg))):
        return None
    s = d / along
    return None if np.any(s <= 0) else rays * s[:, None]


def measure(corners_cam: np.ndarray, gravity_cam: np.ndarray | None) -> Reconstruction:
    """Width (mean of top and bottom edges), height (mean of the sides), tilt of the sides from vertical."""
    tl, tr, br, bl = corners_cam
    width = 0.5 * (np.linalg.norm(tr - tl) + np.linalg.norm(br - bl))
    height = 0.5 * (np.linalg.norm(bl - tl) + np.linalg.norm(br - tr))
    up = np.array([0.0, 1.0, 0.0]) if gravity_cam is None else np.asarray(gravity_cam, np.float64)
    tilt = max(_angle_deg(bl - tl, up), _angle_deg(br - tr, up))
    return Reconstruction(corners_cam, float(width), float(height), tilt, float(corners_cam[:, 2].mean()))


def check_plausible(kind: str, rec: Reconstruction, side_dirs: tuple[np.ndarray, np.ndarray],
                    gravity_known: bool, cfg: PlausibilityParams | None = None) -> str | None:
    """None if the reconstruction is a plausible door/window, else the reason to reject it."""
    cfg = cfg or PlausibilityParams()
    z = rec.corners_cam[:, 2]
    if z.min() < cfg.depth_range_m[0] or z.max() > cfg.depth_range_m[1]:
        return f"depth {z.min():.2f}-{z.max():.2f} m outside {cfg.depth_range_m}"
    w_lim, h_lim = (cfg.door_width_m, cfg.door_height_m) if kind == "door" else (cfg.window_width_m,
                                                                                  cfg.window_height_m)
    if not w_lim[0] <= rec.width_m <= w_lim[1]:
        return f"width {rec.width_m:.2f} m outside {w_lim}"
    if not h_lim[0] <= rec.height_m <= h_lim[1]:
        return f"height {rec.height_m:.2f} m outside {h_lim}"
    max_tilt = cfg.max_tilt_deg if gravity_known else cfg.max_tilt_no_gravity_deg
    if rec.tilt_deg > max_tilt:
        return f"sides {rec.tilt_deg:.1f} deg from vertical (> {max_tilt})"
    if _angle_deg(*side_dirs) > cfg.max_side_angle_deg:
        return f"sides {_angle_deg(*side_dirs):.1f} deg apart (not parallel)"
    return None
