"""Stereo depth: OpenCV SGBM (3-way mode) on a rectified pair, depth from disparity, back-projection (eq. 2).

Frames: pixels (u right, v down) of the rectified left image; points in the left camera's optical frame
(x right, y down, z forward), metres.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict

import cv2
import numpy as np

from macroloc.perception.calib import StereoRig
from macroloc.perception.params import SgbmParams

log = logging.getLogger(__name__)

MAX_PIXELS = 4096 * 4096  # the largest image SGBM is given (its buffers grow with width x disparities)


def to_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.shape[2] == 1:
        return image[:, :, 0]
    return cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2GRAY)



class SgbmMatcher:
    """Dense disparity of the left image (px, float32; NaN where unknown).

    Both images are padded on the left by `num_disparities` columns first, so that SGBM's blind band on
    the left edge falls in the padding: a near-edge pixel whose match lies inside the right image is kept. A
    disparity that puts the match in the padding (greater than the pixel's column) is dropped: the padding
    repeats the right image's first column, and SGBM matches the left image's first columns to it at any
    disparity: far walls measured metres too near, a band down the left edge that stands between the true pose and
    the walls (docs/measurements.md, "SGBM's padding on the left edge").
    """

    def __init__(self, config: SgbmParams | None = None) -> None:
        c = config or SgbmParams()
        self.config = c
        self._disparities = max(16, int(round(c.num_disparities * c.scale / 16)) * 16)  # at the matched size
        self._local = threading.local()  # OpenCV's matcher keeps its buffers: one per thread that matches

    @property
    def _sgbm(self) -> cv2.StereoSGBM:
        sgbm = getattr(self._local, "sgbm", None)
        if sgbm is None:
            c = self.config
            block = c.block_size if c.scale >= 1.0 else max(3, int(round(c.block_size * c.scale)) | 1)
            sgbm = self._local.sgbm = cv2.StereoSGBM.create(
                minDisparity=0, numDisparities=self._disparities, blockSize=block,
                P1=8 * block**2, P2=32 * block**2, disp12MaxDiff=1,
                uniquenessRatio=c.uniqueness_ratio, speckleWindowSize=c.speckle_window, speckleRange=c.speckle_range,
                mode=cv2.StereoSGBM_MODE_SGBM_3WAY if c.three_way else cv2.StereoSGBM_MODE_SGBM,
            )
        return sgbm

    def disparity_px(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Raises ValueError on images of different sizes or larger than MAX_PIXELS: OpenCV's matcher is never
        handed them (a 20000 x 20000 pair crashed the process in it)."""
        _check_pair(left, right)
        return self._match(left, right, self._disparities, 0)

    def _match(self, left: np.ndarray, right: np.ndarray, pad: int, first_col: int) -> np.ndarray:
        """Disparity of `left`, whose first column is the image's `first_col`, both padded by `pad` columns."""
        scale = self.config.scale
        gl, gr = to_gray(left), to_gray(right)
        if scale != 1.0:
            size = (max(1, round(gl.shape[1] * scale)), max(1, round(gl.shape[0] * scale)))
            gl, gr = (cv2.resize(g, size, interpolation=cv2.INTER_AREA) for g in (gl, gr))
        gl = cv2.copyMakeBorder(gl, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
        gr = cv2.copyMakeBorder(gr, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
        raw = self._sgbm.compute(gl, gr)[:, pad:]
        disparity = raw.astype(np.float32) / 16.0  # SGBM returns fixed point with 4 fractional bits
        column = np.arange(first_col, first_col + disparity.shape[1], dtype=np.float32)
        disparity[(raw <= 0) | (disparity > column)] = np.nan  # no match, or the match left of the right image
        if scale != 1.0:  # back to the pair's pixels: disparities in full-size pixels, each on its nearest
            disparity = np.asarray(cv2.resize(disparity / scale, (left.shape[1], left.shape[0]),
                                              interpolation=cv2.INTER_NEAREST), np.float32)
        return disparity

    def window_px(self, left: np.ndarray, right: np.ndarray, v0: int, v1: int, u0: int, u1: int) -> np.ndarray:
        """Disparity of the left image's window [v0:v1, u0:u1] only (what a frame's openings need: less work than
        the whole frame), matched on those rows from `num_disparities` columns left of u0 (where its matches can
        lie) to 16 right of u1 (SGBM's paths along the row then reach the window's last columns from both sides);
        padded as the whole frame is where u0 is nearer the left edge than that."""
        _check_pair(left, right)
        w = left.shape[1]
        if self.config.scale != 1.0:
            return self.disparity_px(left[v0:v1], right[v0:v1])[:, u0:u1]
        a0, b1 = max(0, u0 - self.config.num_disparities), min(w, u1 + 16)
        pad = self.config.num_disparities - (u0 - a0)
        return self._match(left[v0:v1, a0:b1], right[v0:v1, a0:b1], pad, a0)[:, u0 - a0:u1 - a0]


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    if left.shape[:2] != right.shape[:2] or left.shape[0] * left.shape[1] > MAX_PIXELS or not left.size:
        raise ValueError(f"stereo pair of {left.shape[:2]} and {right.shape[:2]} pixels: not the same size, "
                         f"empty or over {MAX_PIXELS}")


class FrameDisparity:
    """One SGBM per stereo frame, shared by whatever needs disparity in it (the perception chain's band, the
    depth points of service.frames.StereoDepth, the visual odometry's keyframes): the first call on a pair
    matches the whole frame, later calls on the same pair (the same array objects) get it back, or the window
    asked for. Before issue 37 a frame could be matched three times (a 64-disparity band, then two full frames
    at 128: ~40 + 2 x 63 ms CPU at 640 x 480). The matcher's disparities serve all: 128 by default (down to
    0.45 m with the simulated rig, see StereoDepth). A window asked for before anything needed the whole frame
    is matched alone (cheaper), so the consumers of the whole frame go first in a frame. Frames must not
    be overwritten in place between calls.

    It keeps the whole-frame disparity of the last `keep` pairs matched: 1 where one thread takes the frames in
    turn (the service's front end); more where a caller runs the odometry some frames ahead of the chain on another
    thread, so that a frame's match is still there when the chain comes to it. Calls from
    different threads are safe (each thread matches with its own OpenCV matcher)."""

    def __init__(self, matcher: SgbmMatcher | None = None, keep: int = 1) -> None:
        self.matcher = matcher or SgbmMatcher(SgbmParams(num_disparities=128))
        self.config = self.matcher.config
        self.keep = max(1, keep)
        self._matched: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()  # id(left)
        self._lock = threading.Lock()
        self.computed = 0  # frames matched so far (for benchmarks and tests)

    def _whole(self, left: np.ndarray, right: np.ndarray) -> np.ndarray | None:
        with self._lock:
            hit = self._matched.get(id(left))
        return hit[2] if hit is not None and hit[0] is left and hit[1] is right else None

    def disparity_px(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """The whole frame's disparity (px, float32, NaN unknown); matched once per pair. Read only."""
        disparity = self._whole(left, right)
        if disparity is None:
            disparity = self.matcher.disparity_px(left, right)
            disparity.flags.writeable = False
            with self._lock:
                self._matched[id(left)] = (left, right, disparity)  # the arrays held: their ids stay theirs
                self._matched.move_to_end(id(left))
                while len(self._matched) > self.keep:
                    self._matched.popitem(last=False)
                self.computed += 1
        return disparity

    def window_px(self, left: np.ndarray, right: np.ndarray, v0: int, v1: int, u0: int, u1: int) -> np.ndarray:
        """The window [v0:v1, u0:u1] of the whole frame's disparity where this pair has been matched, else that
        window alone (SgbmMatcher.window_px)."""
        disparity = self._whole(left, right)
        if disparity is not None:
            return disparity[v0:v1, u0:u1]
        with self._lock:
            self.computed += 1
        return self.matcher.window_px(left, right, v0, v1, u0, u1)


def depth_from_disparity(disparity_px: np.ndarray, rig: StereoRig) -> np.ndarray:
    """depth_m = fx * baseline / disparity (NaN where the disparity is unknown or not positive)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        depth_m = rig.fx_px * rig.baseline_m / disparity_px
    return np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, np.nan).astype(np.float32)


def back_project(uv_px: np.ndarray, depth_m: np.ndarray, rig: StereoRig) -> np.ndarray:
    """Pixels (N,2) with depths (N,) -> points (N,3) in the camera frame.

    eq. (2): P3 = d * [(u - cx)/fx, (v - cy)/fy, 1].
    """
    uv = np.asarray(uv_px, np.float64).reshape(-1, 2)
    d = np.asarray(depth_m, np.float64).reshape(-1)
    return np.stack([d * (uv[:, 0] - rig.cx_px) / rig.fx_px, d * (uv[:, 1] - rig.cy_px) / rig.fy_px, d], axis=1)


def depth_grid(depth_m: np.ndarray, stride_px: int, min_m: float,
               max_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) on a grid (every `stride_px`, from half a stride in) whose depth lies in (min_m, max_m),
    and those depths (N,) in metres, float64: the points to `back_project`."""
    s = stride_px
    v, u = np.mgrid[s // 2:depth_m.shape[0]:s, s // 2:depth_m.shape[1]:s]
    z = depth_m[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > min_m) & (z < max_m)
    return np.column_stack([u[ok], v[ok]]), z[ok]


def ray_cam(uv_px: np.ndarray, rig: StereoRig) -> np.ndarray:
    """Viewing rays (N,3), unit length, through pixels (N,2), in the camera frame (eq. 2 with d = 1, normalised)."""
    rays = back_project(uv_px, np.ones(len(np.asarray(uv_px).reshape(-1, 2))), rig)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def sample_depth_m(depth_m: np.ndarray, uv_px: np.ndarray, half_width_px: int = 2) -> np.ndarray:
    """Depth at pixels (N,2): median of the valid depths in a (2h+1)-wide horizontal window (NaN if none)."""
    h, w = depth_m.shape
    uv = np.rint(np.asarray(uv_px, np.float64).reshape(-1, 2)).astype(np.int64)
    cols = uv[:, :1] + np.arange(-half_width_px, half_width_px + 1)[None]  # (N, 2h+1)
    rows = np.broadcast_to(uv[:, 1:2], cols.shape)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    values = np.full(cols.shape, np.nan)
    values[inside] = depth_m[rows[inside], cols[inside]]
    # the median of each row's valid values (np.nanmedian's, without its per-call cost): sorted, NaN go last
    values.sort(axis=1)
    n = np.isfinite(values).sum(axis=1)
    rows_i = np.arange(len(uv))
    lo, hi = values[rows_i, np.maximum(n - 1, 0) // 2], values[rows_i, n // 2]
    return np.where(n > 0, (lo + hi) / 2, np.nan)


def keypoint_points(disparity_px: np.ndarray, uv_px: np.ndarray, rig: StereoRig, min_disparity_px: float = 1.0,
                    edge_disparity_px: float = 1.0, max_depth_m: float = 15.0) -> np.ndarray:
    """(N, 3) points in the camera frame of keypoints at pixels `uv_px` (N, 2), by eq. 2 from SGBM's sub-pixel
    disparity there; z = 0 where the depth is unreliable: no disparity in the 3 x 3 pixels around it, a disparity
    below `min_disparity_px`, a spread above `edge_disparity_px` in that window (a depth edge), or beyond
    `max_depth_m`."""
    uv = np.asarray(uv_px, np.float64).reshape(-1, 2)
    points = np.zeros((len(uv), 3))
    if not len(uv):
        return points
    h, w = disparity_px.shape
    u = np.clip(np.rint(uv[:, 0]).astype(np.int64), 1, w - 2)
    v = np.clip(np.rint(uv[:, 1]).astype(np.int64), 1, h - 2)
    window = np.stack([disparity_px[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    d = disparity_px[v, u]
    ok = np.isfinite(window).all(axis=1) & (d > min_disparity_px)
    ok[ok] &= np.ptp(window[ok], axis=1) <= edge_disparity_px
    z = np.zeros(len(uv))
    z[ok] = rig.fx_px * rig.baseline_m / d[ok]  # eq. 2
    ok &= z < max_depth_m
    points[ok] = back_project(uv[ok], z[ok], rig)
    return points
