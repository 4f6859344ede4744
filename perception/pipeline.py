"""The perception chain (paper §2.2): stereo pair -> doors and windows with 4 corners in the camera frame.

detect (CNN) -> refine sides (LSD) -> stereo depth (SGBM, eq. 2) -> 3D sides and corners -> plausibility.
Frames: `corners_cam` in the rectified left camera's optical frame (x right, y down, z forward), metres;
`box_xyxy` in the left image's pixels; `gravity_cam` (optional) a unit vector in the camera frame.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from macroloc.perception.calib import StereoRig
from macroloc.perception.detector import DEFAULT_MODEL, Detection, Detector
from macroloc.perception.lines import LineParams, Sides, refine_box
from macroloc.perception.params import PerceptionParams
from macroloc.perception.reconstruct import (
    PlausibilityParams,
    WallPlaneParams,
    check_plausible,
    corners_on_plane,
    measure,
    reconstruct_sides,
    wall_plane,
)
from macroloc.perception.stereo import FrameDisparity, SgbmMatcher, SgbmParams, depth_from_disparity, to_gray

log = logging.getLogger(__name__)

# An opening whose box or corners come this near the image border (fraction of the image's height) is taken to
# run on past it (ObservedFeature.truncation): 40 px at 640 x 480. A margin of a few pixels lets cut openings through
# as whole; from 20 to 60 px the replayed flights' APE is flat (docs/measurements.md, "The border margin").
BORDER_MARGIN_FRACTION = 40 / 480


@dataclass(frozen=True)
class StereoPair:
    """A rectified stereo pair (uint8, grey HxW or BGR HxWx3), its rig, and gravity in the camera frame if known."""

    left: np.ndarray
    right: np.ndarray
    rig: StereoRig
    gravity_cam: np.ndarray | None = None
    stamp_ns: int = 0


@dataclass(frozen=True)
class ObservedFeature:
    """A door or window seen in one frame: corners (4,3) in the camera frame, m (TL, TR, BR, BL in the image)."""

    type: str
    score: float
    box_xyxy: tuple[float, float, float, float]
    corners_cam: np.ndarray
    width_m: float
    height_m: float
    tilt_deg: float
    sides_px: tuple[np.ndarray, np.ndarray]
    sides_from_lines: tuple[bool, bool]
    truncated: tuple[bool, bool] = (False, False)  # (sideways, vertically): the box touches the image border

    @staticmethod
    def truncation(box_xyxy: tuple[float, float, float, float], width_px: int, height_px: int,
                   corners_px: np.ndarray | None = None,
                   margin_fraction: float = BORDER_MARGIN_FRACTION) -> tuple[bool, bool]:
        """Whether the opening runs on past the image border: (at the left or right, at the top or bottom).

        True where its box, or its corners as projected (`corners_px`, (4, 2)), come within `margin_fraction`
        of the image's height of the border. The margin is wide on purpose: where a window runs on below the
        image, the detector's box may still stop tens of pixels short of the border (docs/measurements.md, "The
        border margin"), and the corners then cut the window to two thirds of its height, unflagged."""
        margin = margin_fraction * height_px
        x0, y0, x1, y1 = box_xyxy
        u = [x0, x1] if corners_px is None else [min(x0, *corners_px[:, 0]), max(x1, *corners_px[:, 0])]
        v = [y0, y1] if corners_px is None else [min(y0, *corners_px[:, 1]), max(y1, *corners_px[:, 1])]
        return (u[0] < margin or u[1] > width_px - margin, v[0] < margin or v[1] > height_px - margin)

    @property
    def centroid_cam(self) -> np.ndarray:
        return self.corners_cam.mean(axis=0)

    def to_json(self) -> dict[str, object]:
        return {"type": self.type, "score": round(self.score, 4), "box_xyxy": [round(v, 1) for v in self.box_xyxy],
                "corners_cam": np.round(self.corners_cam, 4).tolist(), "width_m": round(self.width_m, 3),
                "height_m": round(self.height_m, 3), "tilt_deg": round(self.tilt_deg, 2),
                "truncated": {"sideways": bool(self.truncated[0]), "vertically": bool(self.truncated[1])}}


@dataclass(frozen=True)
class Rejected:
    """A detection that did not become a feature, and why."""

    detection: Detection
    reason: str


@dataclass
class PerceptionResult:
    features: list[ObservedFeature]
    rejected: list[Rejected]
    detections: list[Detection]
    timings_ms: dict[str, float] = field(default_factory=dict)


class Perception:
    """The whole chain with its components; `process(pair)` is the paper's §2.2 step by step."""

    def __init__(self, detector: Detector, matcher: SgbmMatcher | FrameDisparity, lines: LineParams | None = None,
                 plausibility: PlausibilityParams | None = None, wall: WallPlaneParams | None = WallPlaneParams()
                 ) -> None:
        self.detector = detector
        self.matcher = matcher  # a FrameDisparity shares the frame's one SGBM with the depth points and odometry
        self.lines = lines or LineParams()
        self.plausibility = plausibility or PlausibilityParams()
        self.wall = wall  # corners on the wall's plane beside the opening, where it shows one (None: the sides')
        self.band_margin_px = 24  # rows of stereo context above and below the boxes

    @staticmethod
    def create(model_path: Path | None = None, sgbm: SgbmParams | None = None, threads: int = 2,
               disparity: FrameDisparity | None = None, params: PerceptionParams | None = None) -> Perception:
        """The chain with the detector at `model_path` (None: the shipped one); stereo from `disparity` (the
        frame's shared SGBM) where given, else its own band SGBM with `sgbm`; the sides, plausibility limits and
        wall plane of `params` (their defaults without)."""
        p = params or PerceptionParams()
        return Perception(Detector(model_path or DEFAULT_MODEL, threads=threads), disparity or SgbmMatcher(sgbm),
                          lines=p.lines, plausibility=p.plausibility, wall=p.wall_plane)

    def process(self, pair: StereoPair) -> PerceptionResult:
        clock = _Clock()
        detections = self.detector.detect(pair.left)
        clock.lap("detect")
        return self.process_boxes(pair, detections, clock)

    def process_boxes(self, pair: StereoPair, detections: list[Detection], clock: _Clock | None = None,
                      depth_m: np.ndarray | None = None) -> PerceptionResult:
        """The chain after the detector, on given boxes (the detector's, or ground truth's for evaluation);
        `depth_m` (HxW, m, NaN unknown) where the caller has the left image's depth already."""
        clock = clock or _Clock()
        gray = to_gray(pair.left) if detections else pair.left  # once for all boxes
        sides = [refine_box(gray, d.box_xyxy, self.lines) for d in detections]
        clock.lap("lines")
        if depth_m is None:
            depth_m = self._depth_m(pair, detections, sides)  # after the sides: the columns depth is read in
        clock.lap("stereo")
        features: list[ObservedFeature] = []
        rejected: list[Rejected] = []
        for det, side in zip(detections, sides, strict=True):
            result = self._reconstruct(det, side, depth_m, pair)
            if isinstance(result, ObservedFeature):
                features.append(result)
            else:
                rejected.append(result)
        clock.lap("reconstruct")
        for r in rejected:
            log.debug("rejected %s %.2f at %s: %s", r.detection.type, r.detection.score, r.detection.box_xyxy, r.reason)
        return PerceptionResult(features, rejected, detections, clock.laps)

    def _depth_m(self, pair: StereoPair, detections: list[Detection], sides: list[Sides]) -> np.ndarray:
        """Depth (m, NaN unknown) of the left image, computed only on the band of rows the boxes span (plus a
        margin) and the columns from left of the leftmost side to right of the rightmost by what reconstruction
        reads beside them (the wall's strips, `far_px`, and the sides' inward samples): depth is read nowhere
        else, and a frame without detections needs no stereo at all."""
        h, w = pair.left.shape[:2]
        depth_m = np.full(pair.left.shape[:2], np.nan, np.float32)
        if not detections:
            return depth_m
        margin = self.band_margin_px
        v0 = max(0, int(np.floor(min(d.box_xyxy[1] for d in detections))) - margin)
        v1 = min(h, int(np.ceil(max(d.box_xyxy[3] for d in detections))) + margin)
        u_sides = np.concatenate([np.r_[s.left_px[:, 0], s.right_px[:, 0]] for s in sides])
        beside = (self.wall.far_px if self.wall is not None else 0.0) + 16.0  # + the samples' windows, rounding
        u0 = int(np.clip(np.floor(u_sides.min() - beside), 0, w - 1))
        u1 = int(np.clip(np.ceil(u_sides.max() + beside) + 1, u0 + 1, w))
        window = self.matcher.window_px(pair.left, pair.right, v0, v1, u0, u1)
        depth_m[v0:v1, u0:u1] = depth_from_disparity(window, pair.rig)
        return depth_m

    def _reconstruct(self, det: Detection, sides: Sides, depth_m: np.ndarray,
                     pair: StereoPair) -> ObservedFeature | Rejected:
        corners_cam = None
        if self.wall is not None and (plane := wall_plane(sides, depth_m, pair.rig, pair.gravity_cam, self.wall)):
            corners_cam = corners_on_plane(sides, plane, pair.rig, self.wall.min_incidence_deg)
        if corners_cam is None:
            fitted = reconstruct_sides(sides, depth_m, pair.rig)
            if isinstance(fitted, str):
                return Rejected(det, fitted)
            corners_cam = fitted[0]
        tl, tr, br, bl = corners_cam
        rec = measure(corners_cam, pair.gravity_cam)
        reason = check_plausible(det.type, rec, (bl - tl, br - tr), pair.gravity_cam is not None, self.plausibility)
        if reason is not None:
            return Rejected(det, reason)
        h, w = pair.left.shape[:2]
        return ObservedFeature(det.type, det.score, det.box_xyxy, corners_cam, rec.width_m, rec.height_m,
                               rec.tilt_deg, (sides.left_px, sides.right_px), sides.from_lines,
                               ObservedFeature.truncation(det.box_xyxy, w, h, pair.rig.project(corners_cam)))


class _Clock:
    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = (now - self._t) * 1e3
        self._t = now
