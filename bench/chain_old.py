"""The perception chain's code as it was before issue 37, kept only for bench.bench_chain to time and compare
against: the pure-Python segment joiner (perception.lines before vectorising), the wall plane's RANSAC one
hypothesis at a time and the depth samples' np.nanmedian (perception.reconstruct, perception.stereo), and the
odometry's settings."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np

import macroloc.perception.pipeline as pipeline
import macroloc.perception.reconstruct as reconstruct
from macroloc.perception.calib import StereoRig
from macroloc.perception.lines import LineParams, Sides, _merge, _orient
from macroloc.perception.odometry import VisualOdometryParams
from macroloc.perception.reconstruct import WallPlaneParams
from macroloc.perception.stereo import back_project


def _angle_deg(seg: np.ndarray) -> float:
    d = seg[1] - seg[0]
    return float(np.degrees(np.arctan2(d[1], d[0])) % 180.0)


def _angle_diff_deg(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def _joinable(a: np.ndarray, b: np.ndarray, cfg: LineParams) -> bool:
    if _angle_diff_deg(_angle_deg(a), _angle_deg(b)) > cfg.join_angle_deg:
        return False
    gap = min(np.linalg.norm(p - q) for p in a for q in b)
    if gap > cfg.join_gap_px:
        return False
    d = (a[1] - a[0]) / max(np.linalg.norm(a[1] - a[0]), 1e-9)
    normal = np.array([-d[1], d[0]])
    return bool(np.max(np.abs((b - a[0]) @ normal)) <= cfg.join_offset_px)


def join_segments_python(segments: list[np.ndarray], cfg: LineParams | None = None) -> list[np.ndarray]:
    """perception.lines.join_segments before issue 37: pair by pair in Python, restarting after each merge."""
    cfg = cfg or LineParams()
    segs = [_orient(np.asarray(s, np.float64).reshape(2, 2)) for s in segments]
    merged = True
    while merged:
        merged = False
        for i in range(len(segs)):
            for j in range(i + 1, len(segs)):
                if _joinable(segs[i], segs[j], cfg):
                    segs[i] = _merge(segs[i], segs[j])
                    del segs[j]
                    merged = True
                    break
            if merged:
                break
    return segs


# The odometry's settings before issue 37 (perception.odometry.VisualOdometryParams's defaults then).
OLD_ODOMETRY = VisualOdometryParams(n_features=2000, tracker="orb")  # ORB matched every frame


def sample_depth_nanmedian(depth_m: np.ndarray, uv_px: np.ndarray, half_width_px: int = 2) -> np.ndarray:
    """Depth at pixels (N,2): median of the valid depths in a (2h+1)-wide horizontal window (NaN if none)."""
    h, w = depth_m.shape
    uv = np.rint(np.asarray(uv_px, np.float64).reshape(-1, 2)).astype(np.int64)
    cols = uv[:, :1] + np.arange(-half_width_px, half_width_px + 1)[None]  # (N, 2h+1)
    rows = np.broadcast_to(uv[:, 1:2], cols.shape)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    values = np.full(cols.shape, np.nan)
    values[inside] = depth_m[rows[inside], cols[inside]]
    out = np.full(len(uv), np.nan)
    has = np.isfinite(values).any(axis=1)
    out[has] = np.nanmedian(values[has], axis=1)
    return out


def _strip_points_old(edge_px: np.ndarray, offset_px: np.ndarray, depth_m: np.ndarray, rig: StereoRig,
                  cfg: WallPlaneParams) -> np.ndarray:
    """Back-projected points (M, 3) of a strip beside an edge (2, 2): `n_samples` along it at each offset
    from `near_px` to `far_px` in the unit direction `offset_px`; those without depth left out."""
    t = np.linspace(0.05, 0.95, cfg.n_samples)[:, None]
    along = edge_px[0] * (1 - t) + edge_px[1] * t
    steps = np.arange(cfg.near_px, cfg.far_px + 1e-9, 3.0)
    uv = (along[None] + steps[:, None, None] * offset_px).reshape(-1, 2)
    pts = back_project(uv, sample_depth_nanmedian(depth_m, uv, half_width_px=1), rig)
    return pts[np.all(np.isfinite(pts), axis=1)]


def wall_plane_loop(sides: Sides, depth_m: np.ndarray, rig: StereoRig, gravity_cam: np.ndarray | None = None,
               cfg: WallPlaneParams | None = None) -> tuple[np.ndarray, float] | None:
    """perception.reconstruct.wall_plane before issue 37: one RANSAC hypothesis at a time."""
    cfg = cfg or WallPlaneParams()
    (tl, bl), (tr, br) = sides.left_px, sides.right_px
    across = (tr + br - tl - bl) / 2
    across = across / max(float(np.linalg.norm(across)), 1e-9)
    up = np.array([across[1], -across[0]])  # 90 deg from left-to-right, towards the image's top
    strips = [_strip_points_old(sides.left_px, -across, depth_m, rig, cfg),
              _strip_points_old(sides.right_px, across, depth_m, rig, cfg),
              _strip_points_old(np.stack([tl, tr]), up, depth_m, rig, cfg)]
    strips = [s for s in strips if len(s) >= cfg.min_points]
    if len(strips) < cfg.min_strips:
        return None
    pts = np.vstack(strips)
    group = np.repeat(np.arange(len(strips)), [len(s) for s in strips])
    tol = cfg.threshold_m[0] + cfg.threshold_m[1] * pts[:, 2] ** 2
    rng = np.random.default_rng(0)
    best, best_n = None, 0
    for _ in range(cfg.iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        inliers = np.abs(pts @ n - n @ a) <= tol
        if inliers.sum() > best_n:
            best, best_n = inliers, int(inliers.sum())
    if best is None:
        return None
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


@contextlib.contextmanager
def old_reconstruction() -> Iterator[None]:
    """Within: the perception chain reconstructs with the code above (for the benchmark only)."""
    saved = pipeline.wall_plane, reconstruct.sample_depth_m
    pipeline.wall_plane = wall_plane_loop  # type: ignore[assignment]
    reconstruct.sample_depth_m = sample_depth_nanmedian
    try:
        yield
    finally:
        pipeline.wall_plane, reconstruct.sample_depth_m = saved


def band_depth_m(chain: pipeline.Perception, pair: pipeline.StereoPair,
                 detections: list) -> np.ndarray:  # type: ignore[type-arg]
    """Perception._depth_m before issue 37: the matcher on the band of rows the boxes span, every column."""
    from macroloc.perception.stereo import depth_from_disparity

    h = pair.left.shape[0]
    depth_m = np.full(pair.left.shape[:2], np.nan, np.float32)
    if not detections:
        return depth_m
    margin = chain.band_margin_px
    v0 = max(0, int(np.floor(min(d.box_xyxy[1] for d in detections))) - margin)
    v1 = min(h, int(np.ceil(max(d.box_xyxy[3] for d in detections))) + margin)
    band = chain.matcher.disparity_px(pair.left[v0:v1], pair.right[v0:v1])
    depth_m[v0:v1] = depth_from_disparity(band, pair.rig)
    return depth_m
