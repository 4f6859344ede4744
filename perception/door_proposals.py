"""Door candidates from geometry where the detector is blind (issue 32: close-up doors the CNN misses).

A door is proposed where two long near-vertical LSD lines stand as far apart, in metres by stereo depth, as one of
the model's doors is wide; their span fits one of its heights (or runs off the image's top or bottom); their tops
are joined by a horizontal edge (or cut by the top border); and what lies between them is not nearer than the wall
beside them (a doorway, a leaf recessed in its frame, or a flush leaf: never an object standing in front).
All pair tests are numpy over the (N, N) pairs of lines; the lines come from LSD on the image at half resolution.

Pixels: (u right, v down) of the full left image; depth in metres; points in the left camera's optical frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from macroloc.perception.calib import StereoRig
from macroloc.perception.evaluate import iou_xyxy
from macroloc.perception.lines import Sides, detect_segments
from macroloc.perception.params import ProposalParams
from macroloc.perception.reconstruct import WallPlaneParams, wall_plane
from macroloc.perception.size_check import OpeningSizes, SizeTolerance, fitting
from macroloc.perception.stereo import back_project, to_gray


@dataclass(frozen=True)
class DoorProposal:
    """A door candidate: its box (image pixels), measured width/height (m), depth (m), whether cut at the top or
    bottom, the model size it fits, `fit` in (0, 1]: 1 - the worst misfit over the tolerance, and the step in
    depth from the wall beside it to what lies between its sides (a doorway: the room behind; a leaf: ~0)."""

    box_xyxy: tuple[float, float, float, float]
    width_m: float
    height_m: float
    depth_m: float
    cut_vertically: bool
    model_wh_m: tuple[float, float]
    fit: float
    depth_step_m: float = float("nan")  # the depth between the sides minus the wall's beside them (NaN: unknown)


@dataclass(frozen=True)
class _Lines:
    """Near-vertical lines, each top (u, v) and bottom (u, v), full-resolution pixels: (N, 2) each."""

    top: np.ndarray
    bottom: np.ndarray

    def u_at(self, v: np.ndarray) -> np.ndarray:
        """u of each line (N,) at rows v (N, ...) broadcast: the line through its ends."""
        du = (self.bottom[:, 0] - self.top[:, 0]) / np.maximum(self.bottom[:, 1] - self.top[:, 1], 1e-9)
        shape = (-1,) + (1,) * (np.ndim(v) - 1)
        return self.top[:, 0].reshape(shape) + du.reshape(shape) * (v - self.top[:, 1].reshape(shape))


def segments(gray: np.ndarray, cfg: ProposalParams) -> tuple[np.ndarray, np.ndarray]:
    """LSD's segments (S, 2, 2) of the image at `cfg.scale`, in full-resolution pixels: (near-vertical,
    near-horizontal), each within max_tilt_deg."""
    small = cv2.resize(gray, None, fx=cfg.scale, fy=cfg.scale, interpolation=cv2.INTER_AREA)
    segs = np.array(detect_segments(small), float).reshape(-1, 2, 2) / cfg.scale
    d = np.abs(segs[:, 1] - segs[:, 0])
    tan = np.tan(np.radians(cfg.max_tilt_deg))
    return segs[d[:, 0] <= d[:, 1] * tan], segs[d[:, 1] <= d[:, 0] * tan]


def vertical_lines(segs: np.ndarray, cfg: ProposalParams) -> _Lines:
    """Near-vertical segments (S, 2, 2) oriented top first, collinear pieces joined, those >= min_side_px kept."""
    segs = segs.copy()
    flip = segs[:, 0, 1] > segs[:, 1, 1]
    segs[flip] = segs[flip, ::-1]
    top, bottom = _join(segs[:, 0], segs[:, 1], cfg)
    keep = bottom[:, 1] - top[:, 1] >= cfg.min_side_px
    return _Lines(top[keep], bottom[keep])


def _contrast(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """I(u + 2, v) - I(u - 2, v) at the nearest pixels (any shape; 0 outside the image)."""
    h, w = img.shape
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = (ui >= 2) & (ui < w - 2) & (vi >= 0) & (vi < h)
    ui, vi = np.clip(ui, 2, w - 3), np.clip(vi, 0, h - 1)
    return np.where(inside, img[vi, ui + 2] - img[vi, ui - 2], 0.0)


def extend_lines(lines: _Lines, gray: np.ndarray, cfg: ProposalParams) -> _Lines:
    """Each line grown along itself, up and down, by at most its own length, through rows whose horizontal
    contrast has the line's sign and at least half its median, across gaps up to the joining distance: LSD stops
    short of a side's ends where it fades into the corner's shading (perception.lines does the same in a box)."""
    if not len(lines.top):
        return lines
    img = gray.astype(np.float32)
    gap = int(round(cfg.join_gap_px / cfg.scale))
    v_on = lines.top[:, 1:2] + (lines.bottom[:, 1:2] - lines.top[:, 1:2]) * np.linspace(0.0, 1.0, 24)
    signed = np.median(_contrast(img, lines.u_at(v_on), v_on), axis=1)
    steps = np.arange(1, img.shape[0])
    length = lines.bottom[:, 1] - lines.top[:, 1]
    ends = []
    for sign, end in ((-1.0, lines.top), (1.0, lines.bottom)):
        v = end[:, 1:2] + sign * steps
        along = _contrast(img, lines.u_at(v), v) * np.sign(signed)[:, None]
        strong = (along >= np.maximum(0.5 * np.abs(signed), 1.0)[:, None]) & (steps <= length[:, None])
        weak = np.cumsum(np.pad(~strong, ((0, 0), (1, 0))), axis=1)
        run = (weak[:, gap:] - weak[:, :-gap]) == gap  # a run of `gap` weak rows starts at this step
        stop = np.where(run.any(axis=1), run.argmax(axis=1), len(steps))
        grown = np.where(strong & (np.arange(len(steps)) < stop[:, None]), steps, 0).max(axis=1)
        v_end = end[:, 1] + sign * grown
        ends.append(np.column_stack([lines.u_at(v_end[:, None])[:, 0], v_end]))
    return _Lines(ends[0], ends[1])


def _join(top: np.ndarray, bottom: np.ndarray, cfg: ProposalParams) -> tuple[np.ndarray, np.ndarray]:
    """Chain pieces, in order of their top, onto a line above whose extension passes within join_offset_px of the
    piece's top and whose bottom lies within join_gap_px of it (or past it): LSD breaks a side into a handful.
    Both distances are the paper's in the image LSD ran on: / cfg.scale in full-resolution pixels."""
    order = np.argsort(top[:, 1])
    out_t, out_b = top[order].copy(), bottom[order].copy()
    alive = np.ones(len(order), bool)
    for k in range(len(order)):
        prev = np.flatnonzero(alive[:k])
        if not len(prev):
            continue
        t = out_t[k]
        bt, bb = out_t[prev], out_b[prev]
        slope = (bb[:, 0] - bt[:, 0]) / np.maximum(bb[:, 1] - bt[:, 1], 1e-9)
        ok = (np.abs(bt[:, 0] + slope * (t[1] - bt[:, 1]) - t[0]) <= cfg.join_offset_px / cfg.scale) \
            & (t[1] - bb[:, 1] <= cfg.join_gap_px / cfg.scale)
        if ok.any():
            i = prev[np.flatnonzero(ok)[0]]
            if out_b[k, 1] > out_b[i, 1]:
                out_b[i] = out_b[k]
            alive[k] = False
    return out_t[alive], out_b[alive]


def _wall_depth_m(lines: _Lines, depth_m: np.ndarray, side: float, cfg: ProposalParams) -> np.ndarray:
    """Median depth (N,) of the strip `strip_px` outside each line, on its left (side -1) or right (+1): the wall
    an opening stands in, where the line is the opening's side (NaN where the strip has none)."""
    t = np.linspace(0.1, 0.9, 12)
    v = lines.top[:, 1:2] * (1 - t) + lines.bottom[:, 1:2] * t  # (N, 12)
    offsets = np.arange(cfg.strip_px[0], cfg.strip_px[1] + 1e-9, 6.0)
    u = lines.u_at(v)[:, :, None] + side * offsets  # (N, 12, K)
    z = _lookup(depth_m, u, np.broadcast_to(v[:, :, None], u.shape)).reshape(len(u), -1)
    return _row_median(z, min_valid=4)


def _top_edge_support(horizontal: np.ndarray, u_i: np.ndarray, u_j: np.ndarray, v_top: np.ndarray,
                      gap_px: float) -> np.ndarray:
    """(M,) fraction of 16 columns from u_i to u_j (M,) covered (within gap_px) by near-horizontal segments
    (S, 2, 2) lying within gap_px of the pair's top row v_top (M,): the lintel meets the sides' tops."""
    if not len(horizontal) or not len(u_i):
        return np.zeros(len(u_i))
    seg_v = horizontal[:, :, 1].mean(axis=1)
    seg_u0, seg_u1 = horizontal[:, :, 0].min(axis=1) - gap_px, horizontal[:, :, 0].max(axis=1) + gap_px
    in_rows = np.abs(seg_v - v_top[:, None]) <= gap_px  # (M, S)
    grid = np.linspace(0.05, 0.95, 16)
    u = u_i[:, None] * (1 - grid) + u_j[:, None] * grid  # (M, 16)
    covered = in_rows[:, None, :] & (u[..., None] >= seg_u0) & (u[..., None] <= seg_u1)  # (M, 16, S)
    return np.asarray(covered.any(axis=-1).mean(axis=-1))


def propose_doors(image: np.ndarray, depth_m: np.ndarray, rig: StereoRig, sizes: OpeningSizes,
                  tol: SizeTolerance | None = None, cfg: ProposalParams | None = None,
                  gravity_cam: np.ndarray | None = None, wall: WallPlaneParams | None = None) -> list[DoorProposal]:
    """Door candidates (best fit first, at most cfg.max_proposals, overlapping ones suppressed) in the left image
    from its LSD lines, its depth (m, NaN unknown) and the model's door sizes. A door stands on the floor the
    vehicle flies above: where its bottom is in view it lies below the camera (along `gravity_cam`, a unit vector
    in the camera frame, where known; else the camera's y axis: a level camera). The sides must stand in one wall
    by `wall` (the chain's; None: its defaults) unless `cfg.check_wall` is off."""
    cfg, tol, wall = cfg or ProposalParams(), tol or SizeTolerance(), wall or WallPlaneParams()
    doors = sizes.wh_m("door")
    gray = to_gray(image)
    vertical, horizontal = segments(gray, cfg)
    lines = extend_lines(vertical_lines(vertical, cfg), gray, cfg)
    n = len(lines.top)
    if n < 2 or not len(doors):
        return []
    z_left, z_right = _wall_depth_m(lines, depth_m, -1.0, cfg), _wall_depth_m(lines, depth_m, 1.0, cfg)
    i, j = np.nonzero(np.ones((n, n), bool))
    v_top = np.maximum(lines.top[i, 1], lines.top[j, 1])
    v_bot = np.minimum(lines.bottom[i, 1], lines.bottom[j, 1])
    short = np.minimum(lines.bottom[i, 1] - lines.top[i, 1], lines.bottom[j, 1] - lines.top[j, 1])
    v_mid = (v_top + v_bot) / 2
    u_i, u_j = _u(lines, i, v_mid), _u(lines, j, v_mid)
    zi, zj = z_left[i], z_right[j]
    ok = (u_j > u_i) & (v_bot - v_top >= 0.5 * short) & np.isfinite(zi) & np.isfinite(zj)
    i, j, v_mid, u_i, u_j, zi, zj = i[ok], j[ok], v_mid[ok], u_i[ok], u_j[ok], zi[ok], zj[ok]
    if not len(i):
        return []
    p_i = back_project(np.column_stack([u_i, v_mid]), zi, rig)
    p_j = back_project(np.column_stack([u_j, v_mid]), zj, rig)
    width = np.linalg.norm(p_j - p_i, axis=1)
    z = (zi + zj) / 2
    h_img = gray.shape[0]
    top_v = np.minimum(lines.top[i, 1], lines.top[j, 1])
    bot_v = np.maximum(lines.bottom[i, 1], lines.bottom[j, 1])
    height = (bot_v - top_v) * z / rig.fy_px  # the two sides' LSD pieces together, at the wall's depth (eq. 2)
    margin = cfg.border_fraction * h_img
    cut_top, cut = top_v < margin, (top_v < margin) | (bot_v > h_img - margin)
    tol_m = tol.floor_m + tol.per_m * z
    fits = fitting(doors, width, height, tol_m, np.column_stack([np.zeros_like(cut), cut]))  # (M, doors)
    down = np.array([0.0, 1.0, 0.0]) if gravity_cam is None else np.asarray(gravity_cam, float)
    bottom_px = np.column_stack([(u_i + u_j) / 2, bot_v])
    below = back_project(bottom_px, z, rig) @ (down / np.linalg.norm(down)) > 0  # the bottom under the camera
    keep: np.ndarray = np.asarray(fits.any(axis=1) & (below | (bot_v > h_img - margin)))
    edge = _top_edge_support(horizontal, u_i[keep], u_j[keep], top_v[keep], cfg.join_gap_px / cfg.scale)
    keep[keep] = cut_top[keep] | (edge >= 0.5)
    inside = np.full(len(i), np.nan)
    inside[keep] = _inside_depth_m(lines, i[keep], j[keep], depth_m)
    keep &= ~(inside < z - (cfg.depth_tol_m[0] + cfg.depth_tol_m[1] * z ** 2))  # nearer than the wall: in front
    on_wall = _OnWall(depth_m, rig, gravity_cam, wall if cfg.check_wall else None)
    return _best(lines, i, j, width, height, z, cut, fits, tol_m, doors, keep, inside - z, on_wall, cfg)


def _u(lines: _Lines, k: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u of lines k (M,) at rows v (M,)."""
    t, b = lines.top[k], lines.bottom[k]
    return t[:, 0] + (b[:, 0] - t[:, 0]) / np.maximum(b[:, 1] - t[:, 1], 1e-9) * (v - t[:, 1])


def _length_m(lines: _Lines, k: np.ndarray, z: np.ndarray, rig: StereoRig) -> np.ndarray:
    """Length (M,) of lines k, m, both ends back-projected at the wall's depth z beside them."""
    return np.linalg.norm(back_project(lines.top[k], z, rig) - back_project(lines.bottom[k], z, rig), axis=1)


def _inside_depth_m(lines: _Lines, i: np.ndarray, j: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Median depth (M,) on a 5 x 5 grid over the middle half between lines i and j (NaN where none)."""
    t = np.linspace(0.25, 0.75, 5)
    v_top = np.maximum(lines.top[i, 1], lines.top[j, 1])
    v_bot = np.minimum(lines.bottom[i, 1], lines.bottom[j, 1])
    v = v_top[:, None] * (1 - t) + v_bot[:, None] * t  # (M, 5)
    ui, uj = _u(lines, np.repeat(i, 5), v.ravel()).reshape(-1, 5), _u(lines, np.repeat(j, 5), v.ravel()).reshape(-1, 5)
    u = ui[:, :, None] * (1 - t) + uj[:, :, None] * t  # (M, 5 rows, 5 columns)
    z = _lookup(depth_m, u, np.broadcast_to(v[:, :, None], u.shape)).reshape(len(i), 25)
    return _row_median(z, min_valid=1)


def _lookup(depth_m: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Depth at the nearest pixels (any shape; NaN outside the image)."""
    h, w = depth_m.shape
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    out = np.full(ui.shape, np.nan)
    out[inside] = depth_m[vi[inside], ui[inside]]
    return out


def _row_median(z: np.ndarray, min_valid: int) -> np.ndarray:
    """The (lower) median of each row's finite values (R,), NaN where fewer than `min_valid` (np.nanmedian is 10x
    slower on short rows)."""
    n = np.isfinite(z).sum(axis=1)
    ordered = np.sort(np.where(np.isfinite(z), z, np.inf), axis=1)
    med = np.take_along_axis(ordered, np.maximum((n - 1) // 2, 0)[:, None], axis=1)[:, 0]
    return np.where(n >= min_valid, med, np.nan)


def _best(lines: _Lines, i: np.ndarray, j: np.ndarray, width: np.ndarray, height: np.ndarray, z: np.ndarray,
          cut: np.ndarray, fits: np.ndarray, tol_m: np.ndarray, doors: np.ndarray, keep: np.ndarray,
          step: np.ndarray, on_wall: _OnWall, cfg: ProposalParams) -> list[DoorProposal]:
    """The kept pairs as proposals, best fit first, a box overlapping a better one by IoU >= 0.3 dropped, and one
    whose sides do not stand in one wall dropped (checked here, on the few that get this far: ~1 ms each)."""
    out: list[DoorProposal] = []
    boxes: list[np.ndarray] = []
    misfit = np.where(fits, np.maximum(np.abs(width[:, None] - doors[:, 0]),
                                       np.where(cut[:, None], 0.0, np.abs(height[:, None] - doors[:, 1]))), np.inf)
    fit = 1.0 - misfit.min(axis=1) / tol_m
    for k in np.flatnonzero(keep)[np.argsort(-fit[keep])]:
        if len(out) >= cfg.max_proposals:
            break
        pts = np.vstack([lines.top[[i[k], j[k]]], lines.bottom[[i[k], j[k]]]])
        box = np.array([pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()])
        if boxes and iou_xyxy(box[None], np.array(boxes))[0].max() >= 0.3:
            continue
        if not on_wall(lines, int(i[k]), int(j[k])):
            continue
        boxes.append(box)
        w, h = doors[int(np.argmin(misfit[k]))]
        out.append(DoorProposal((float(box[0]), float(box[1]), float(box[2]), float(box[3])), float(width[k]),
                                float(height[k]), float(z[k]), bool(cut[k]), (float(w), float(h)), float(fit[k]),
                                float(step[k])))
    return out


@dataclass(frozen=True)
class _OnWall:
    """Whether a pair of lines stands in one wall: `perception.reconstruct.wall_plane` on the depth beside the
    sides and above the top (the chain's own test of the wall an opening sits in). A pair across a corner, or
    between things at different depths, has its strips on different surfaces."""

    depth_m: np.ndarray
    rig: StereoRig
    gravity_cam: np.ndarray | None
    cfg: WallPlaneParams | None

    def __call__(self, lines: _Lines, i: int, j: int) -> bool:
        if self.cfg is None:
            return True
        sides = Sides(np.stack([lines.top[i], lines.bottom[i]]), np.stack([lines.top[j], lines.bottom[j]]),
                      (True, True))
        return wall_plane(sides, self.depth_m, self.rig, self.gravity_cam, self.cfg) is not None

