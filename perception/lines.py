"""Line refinement of a detection box (paper §2.2.2): LSD inside the box, broken segments joined,
the longest lines nearest the box's two vertical sides taken as the feature's sides.

Pixels: (u right, v down) of the full image. A segment is `(2, 2)` float: [[u0, v0], [u1, v1]], top end first.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from macroloc.perception.params import LineParams
from macroloc.perception.stereo import to_gray

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class Sides:
    """The feature's two vertical sides in image pixels, each (2,2) top end first; `from_lines[i]` says whether
    side i came from LSD (else from the strongest edge column, spanning the box's rows)."""

    left_px: np.ndarray
    right_px: np.ndarray
    from_lines: tuple[bool, bool]


def _orient(seg: np.ndarray) -> np.ndarray:
    return seg if seg[0, 1] <= seg[1, 1] else seg[::-1]


def _angles_deg(segs: np.ndarray) -> np.ndarray:
    """Undirected angles (N,) in [0, 180) degrees of segments (N, 2, 2)."""
    d = segs[:, 1] - segs[:, 0]
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0


def _angle_diff_deg(a: np.ndarray, b: np.ndarray | float) -> np.ndarray:
    """Differences of undirected angles (degrees, broadcast), in [0, 90]."""
    d = np.abs(a - b) % 180.0
    return np.minimum(d, 180.0 - d)


def _joinable(a: np.ndarray, b: np.ndarray, cfg: LineParams) -> np.ndarray:
    """Whether each segment of `a` (N, 2, 2) joins the one of `b` (M, 2, 2): (N, M) bool. Not symmetric: the
    collinearity is measured from the line of `a`'s segment (as the paper's pairwise test, first against later).
    Angles within `join_angle_deg`, nearest endpoints within `join_gap_px`, `b`'s ends within `join_offset_px`
    of `a`'s line."""
    ok = _angle_diff_deg(_angles_deg(a)[:, None], _angles_deg(b)[None]) <= cfg.join_angle_deg
    ends = a[:, None, :, None, :] - b[None, :, None, :, :]  # (N, M, 2 ends of a, 2 ends of b, uv)
    gap = np.sqrt(np.min(np.sum(ends * ends, axis=-1), axis=(2, 3)))
    ok &= gap <= cfg.join_gap_px
    d = a[:, 1] - a[:, 0]
    d = d / np.maximum(np.sqrt(np.sum(d * d, axis=1)), 1e-9)[:, None]
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1)  # (N, 2)
    offset = np.einsum("nmku,nu->nmk", b[None] - a[:, None, None, 0], normal)  # b's ends from a's line
    return ok & (np.max(np.abs(offset), axis=2) <= cfg.join_offset_px)


def _merge(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The segment between the two farthest-apart endpoints of a and b."""
    pts = np.vstack([a, b])
    dists = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    i, j = np.unravel_index(int(np.argmax(dists)), dists.shape)
    return _orient(np.stack([pts[i], pts[j]]))


def join_segments(segments: list[np.ndarray], cfg: LineParams | None = None) -> list[np.ndarray]:
    """Join broken segments (angle <= 2 deg, endpoint gap <= 10 px, collinear) until none can be joined.

    The first joinable pair (i < j, in index order) is merged into i and j dropped, and the search starts over:
    the pairwise test runs once over all pairs as numpy (an (N, N) table), and after each merge only the merged
    segment's row and column are tested again."""
    cfg = cfg or LineParams()
    segs = np.array([_orient(np.asarray(s, np.float64).reshape(2, 2)) for s in segments]).reshape(-1, 2, 2)
    table = np.triu(_joinable(segs, segs, cfg), k=1)
    while (first := np.flatnonzero(table)).size:
        i, j = divmod(int(first[0]), len(segs))
        segs[i] = _merge(segs[i], segs[j])
        segs, table = np.delete(segs, j, axis=0), np.delete(np.delete(table, j, axis=0), j, axis=1)
        table[i, i + 1:] = _joinable(segs[i:i + 1], segs[i + 1:], cfg)[0]
        table[:i, i] = _joinable(segs[:i], segs[i:i + 1], cfg)[:, 0]
    return list(segs)


def detect_segments(gray: np.ndarray) -> list[np.ndarray]:
    """LSD segments of a grey image, each (2,2) in its pixels."""
    lsd = cv2.createLineSegmentDetector()
    lines = lsd.detect(gray)[0]
    if lines is None:
        return []
    return [line.reshape(2, 2).astype(np.float64) for line in lines]


def _extend_to_rows(seg: np.ndarray, v_top: float, v_bottom: float) -> np.ndarray:
    (u0, v0), (u1, v1) = seg
    slope = (u1 - u0) / (v1 - v0) if abs(v1 - v0) > 1e-9 else 0.0  # du/dv of a near-vertical line
    return np.array([[u0 + slope * (v_top - v0), v_top], [u0 + slope * (v_bottom - v0), v_bottom]])


def _edge_extent(gray: np.ndarray, seg: np.ndarray, v_top: float, v_bottom: float,
                 gap_px: float) -> tuple[float, float]:
    """Rows over which the side's edge is really there: walking along the side's line within the box's rows, the
    run of rows with a horizontal contrast of at least half the one under the LSD segment, through gaps of at most
    `gap_px` (the paper's joining distance). LSD breaks a long edge; this recovers the edge's true ends, which in
    an oblique view differ from the box's rows (the far side of a door is shorter)."""
    h, w = gray.shape
    full = _extend_to_rows(seg, v_top, v_bottom)
    rows = np.arange(int(np.ceil(max(0.0, v_top))), int(np.floor(min(h - 1.0, v_bottom))) + 1)
    if rows.size < 3:
        return float(seg[0, 1]), float(seg[1, 1])
    u = np.rint(full[0, 0] + (full[1, 0] - full[0, 0]) * (rows - v_top) / max(v_bottom - v_top, 1e-9)).astype(int)
    img = gray.astype(np.float32)
    contrast = np.zeros(rows.size)
    for du in (-1, 0, 1):  # best of three columns: the edge may sit a pixel off the fitted line
        lo, hi = np.clip(u + du - 2, 0, w - 1), np.clip(u + du + 2, 0, w - 1)
        contrast = np.maximum(contrast, np.abs(img[rows, hi] - img[rows, lo]))
    on_seg = (rows >= seg[0, 1]) & (rows <= seg[1, 1])
    strong = contrast >= 0.5 * (np.median(contrast[on_seg]) if on_seg.any() else contrast.max())
    top_i, bottom_i = int(np.searchsorted(rows, seg[0, 1])), int(np.searchsorted(rows, seg[1, 1])) - 1
    top_i, bottom_i = min(max(top_i, 0), rows.size - 1), min(max(bottom_i, 0), rows.size - 1)
    gap = 0
    for i in range(top_i - 1, -1, -1):  # grow upwards through short gaps
        gap = 0 if strong[i] else gap + 1
        if gap > gap_px:
            break
        if strong[i]:
            top_i = i
    gap = 0
    for i in range(bottom_i + 1, rows.size):  # and downwards
        gap = 0 if strong[i] else gap + 1
        if gap > gap_px:
            break
        if strong[i]:
            bottom_i = i
    return float(min(rows[top_i], seg[0, 1])), float(max(rows[bottom_i], seg[1, 1]))


def _side_ends(gray: np.ndarray, seg: np.ndarray, v_top: float, v_bottom: float, cfg: LineParams) -> np.ndarray:
    """The side's segment, extended along its line to the edge's true ends; an end within `snap` x box height of
    the box's top or bottom row goes onto that row (edges fade into a corner's shading)."""
    top, bottom = _edge_extent(gray, seg, v_top, v_bottom, cfg.join_gap_px)
    tol = cfg.snap * (v_bottom - v_top)
    top = v_top if abs(top - v_top) <= tol else top
    bottom = v_bottom if abs(bottom - v_bottom) <= tol else bottom
    return _extend_to_rows(seg, top, bottom)


def _pick_side(cands: list[np.ndarray], edge_u: float, cfg: LineParams) -> np.ndarray | None:
    if not cands:
        return None
    lengths = np.array([np.linalg.norm(s[1] - s[0]) for s in cands])
    dist = np.array([abs(s[:, 0].mean() - edge_u) for s in cands])
    ok = lengths >= cfg.near_length * lengths.max()
    best = int(np.argmin(np.where(ok, dist, np.inf)))
    return cands[best]


Joiner = Callable[[list[np.ndarray], LineParams], list[np.ndarray]]


def refine_box(image: np.ndarray, box_xyxy: tuple[float, float, float, float], cfg: LineParams | None = None,
               join: Joiner = join_segments) -> Sides:
    """The two vertical sides of the feature inside a detection box (image pixels; `image` grey or BGR: a frame
    with several boxes is best given grey, converted once). `join`: the segment joiner (bench.bench_chain passes
    the pure-Python one this replaced, to compare)."""
    cfg = cfg or LineParams()
    gray = to_gray(image)
    h_img, w_img = gray.shape
    x0, y0, x1, y1 = box_xyxy
    bw, bh = x1 - x0, y1 - y0
    cx0, cy0 = int(max(0, np.floor(x0 - cfg.margin * bw))), int(max(0, np.floor(y0 - cfg.margin * bh)))
    cx1, cy1 = int(min(w_img, np.ceil(x1 + cfg.margin * bw))), int(min(h_img, np.ceil(y1 + cfg.margin * bh)))
    segs = [s + np.array([cx0, cy0]) for s in detect_segments(np.ascontiguousarray(gray[cy0:cy1, cx0:cx1]))]
    if segs:
        tilt_deg = _angle_diff_deg(_angles_deg(np.array(segs)), 90.0)
        segs = [s for s, t in zip(segs, tilt_deg, strict=True) if t <= cfg.max_tilt_deg]
    joined = [_orient(s) for s in join(segs, cfg)]
    long_enough = [s for s in joined if s[1, 1] - s[0, 1] >= cfg.min_length * bh]
    left = _pick_side([s for s in long_enough if -cfg.side_band_out * bw <= s[:, 0].mean() - x0 <= cfg.side_band * bw],
                      x0, cfg)
    right = _pick_side([s for s in long_enough if -cfg.side_band_out * bw <= x1 - s[:, 0].mean() <= cfg.side_band * bw],
                       x1, cfg)
    if left is not None and right is not None and right[:, 0].mean() - left[:, 0].mean() < 0.3 * bw:
        left, right = None, None  # both picked the same edge region: not a usable pair
    return Sides(
        _side_ends(gray, left, y0, y1, cfg) if left is not None else _edge_column(gray, box_xyxy, x0, cfg),
        _side_ends(gray, right, y0, y1, cfg) if right is not None else _edge_column(gray, box_xyxy, x1, cfg),
        (left is not None, right is not None),
    )


def _edge_column(gray: np.ndarray, box_xyxy: tuple[float, float, float, float], edge_u: float,
                 cfg: LineParams) -> np.ndarray:
    """Fallback when LSD finds no side: the image column of strongest horizontal gradient within the side band
    (summed over the box's rows), as a vertical segment over the box's rows; the box edge if nothing stands out."""
    x0, y0, x1, y1 = box_xyxy
    inside, outside = cfg.side_band * (x1 - x0), cfg.side_band_out * (x1 - x0)
    lo, hi = (edge_u - outside, edge_u + inside) if edge_u <= (x0 + x1) / 2 else (edge_u - inside, edge_u + outside)
    u_lo, u_hi = int(max(1, lo)), int(min(gray.shape[1] - 1, hi))
    v_lo, v_hi = int(max(0, y0)), int(min(gray.shape[0], y1))
    if u_hi - u_lo < 3 or v_hi - v_lo < 3:
        return np.array([[edge_u, y0], [edge_u, y1]])
    strip = gray[v_lo:v_hi, u_lo - 1:u_hi + 1].astype(np.float32)
    profile = np.abs(strip[:, 2:] - strip[:, :-2]).sum(axis=0)  # central difference d/du, summed over rows
    profile = np.convolve(profile, np.ones(3) / 3, mode="same")
    if profile.max() <= 2.0 * np.median(profile) + 1e-6:
        return np.array([[edge_u, y0], [edge_u, y1]])
    u = float(u_lo + int(np.argmax(profile)))
    return np.array([[u, y0], [u, y1]])
