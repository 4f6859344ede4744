"""The building labels its own doors: where a replayed flight's pose is held, the model's doors and windows are
projected into the frame's left image and written as YOLO labels (0 door, 1 window) for `perception.train --sim`,
so that a detector can be fine-tuned on the user's own camera in the user's own building (`macroloc
adapt-detector --recording`).

`SelfLabeller` is a replay's `FrameRecorder` (service.offline.replay): the poses are those the service itself gives
on its one per-frame path. Its decisions, each counted in the report:

Per frame:
- `not_localized`: the estimate is not `localized` (the service's own rule: anchored and held to the model,
  graph.anchoring.held), or it has no covariance, and no held pose came within `before_fix_s` after it;
- `labelled_before_fix`: a frame before the pose was held (the first fix, or a pose found again), labelled when it
  is, from its keyframe as the pose graph then holds it: anchored and re-optimized with the doors linked at the
  fix, which many of the keyframes before it saw (T_cad_map times the keyframe's T_map_body, its marginal
  covariance), carried to the frame by the odometry (the service's own carry between keyframes; the covariance
  carried by the adjoint, plus the drift the pose graph assumes over that path, `[graph.odometry]`). Keyframes
  that left the graph's window (marginalised) have no covariance left: their frames are not labelled. The frames
  before a fix are most of a flight that localizes late (Office_A seed 4101: 22 s of 60 s, docs/measurements.md,
  "Issue 55 item 5: labels before the first fix");
- `too_soon`: less than `every_s` after the last labelled frame (frames at 30 Hz are near copies);
- `labelled`: the frame is written, with whatever boxes it has (a frame of a held pose with no door in view is a
  true negative, which a detector needs as much).

Per door or window of the model, in a labelled frame:
- `behind`: no part of its opening in front of the camera's near plane;
- `outside`: its opening, clipped to the near plane, projects outside the image;
- `hidden`: fewer than `min_visible_fraction` of the samples of its opening lie inside the image and in view. A
  sample is out of view when the segment from the camera to it meets a surface of the model (walls, slabs,
  stairs, the model's furniture, its doors' leaves as modelled, its windows) nearer than the sample by more than
  `occlusion_tol_m` (the model's own depth, ray-cast: `ModelDepth`; an opening's own leaf or glass lies within
  that tolerance of it). The fraction is the one the simulator's truth
  labels use (sim.export), so the two label sets mean the same;
- `too_small`: its box is under `min_box_px` on a side;
- `uncertain`: at one of the pose's `sigmas`-sigma points (the pose moved by `sigmas` standard deviations along
  each principal axis of its 6x6 covariance, both ways: 12 poses) the box overlaps the labelled one at IoU under
  0.5, the score by which a detection is matched: where the pose is that uncertain, the label may not be the
  door;
- `labelled`, flagged `cut` where the image border cut its box.

A door or window that is there but not labelled (too small, uncertain, or partly in view under the fraction) is
greyed out in the written frame: its box (an uncertain one's: the boxes of all its sigma points) filled with the
frame's mean colour, the labelled boxes spared. A detector trained on the frame is then never taught that a real
door is background, which an unlabelled door in a labelled frame would teach it.

The box is the opening's rectangle projected (clipped to the near plane, then to the image), the convention of
the simulator's truth labels. Occlusion the model does not know (people, furniture added after the model, a door
leaf closed) is not seen by this test.
"""

from __future__ import annotations

import json
import logging
from collections import Counter, deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import gtsam
import numpy as np

from macroloc.common.parameters import Parameters, param
from macroloc.graph.features import MacroFeature
from macroloc.graph.localizer import Estimate, Localizer
from macroloc.graph.params import OdometryFactorParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.rigid import invert
from macroloc.perception.draw import contact_sheet
from macroloc.perception.trainset import YOLO_CLASSES, yolo_folder, yolo_line
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame
from macroloc.service.assets import prepare_building
from macroloc.service.config import MacrolocConfig
from macroloc.service.offline.replay import FrameSeen
from macroloc.service.offline.ros_bag import open_flight
from macroloc.service.offline.run import ReplayOptions, replay_flight

log = logging.getLogger(__name__)

SHEET_TILES = 12  # frames on a recording's contact sheet
SHEET_BGR = {"door": (40, 200, 40), "window": (30, 140, 230)}


@dataclass(frozen=True)
class SelfLabelParams(Parameters):
    """What the self-labeller labels (module doc)."""

    every_s: float = param(0.2, "at most one labelled frame per this many seconds of flight (consecutive frames "
                           "at 30 Hz are near copies)", ge=0)
    min_visible_fraction: float = param(0.25, "a door or window is labelled when at least this share of its opening "
                                        "is inside the image and in view (the simulator's truth labels use the "
                                        "same)", gt=0, le=1)
    min_box_px: float = param(12.0, "a box smaller than this on a side is not labelled (too few pixels for the "
                              "detector's stride-16 grid to learn from)", ge=1)
    samples: int = param(6, "samples per side of an opening for the occlusion test (samples x samples rays)", ge=2)
    occlusion_tol_m: float = param(0.25, "a model surface nearer than an opening's sample by more than this hides "
                                   "it: an opening's frame and reveal stand proud of its rectangle (the "
                                   "simulator's truth uses the same tolerance)", gt=0)
    sigmas: float = param(3.0, "the pose error, in standard deviations of its covariance along each principal "
                          "axis, that must leave a box within IoU 0.5 of itself for it to be labelled", gt=0)
    near_m: float = param(0.1, "the camera's near plane, m", gt=0)
    before_fix_s: float = param(
        60.0, "frames up to this long before the pose is held (the first fix, or found again) are labelled once it "
        "is, from their keyframes in the anchored pose graph (0: none; a keyframe that left the graph's window "
        "has no covariance left, and its frames are not labelled)", ge=0)
    jpeg_quality: int = param(92, "JPEG quality of the written frames", ge=50, le=100)


class ModelDepth:
    """The model's own depth along rays: segments tested against its triangles (Moller-Trumbore, vectorized),
    each segment only against the triangles whose bounding box meets the segment set's."""

    def __init__(self, triangles_cad: np.ndarray) -> None:
        """`triangles_cad`: (T, 3, 3) occluding triangles, CAD frame, metres."""
        tri = np.asarray(triangles_cad, np.float64).reshape(-1, 3, 3)
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]
        self.lo = tri.min(axis=1)
        self.hi = tri.max(axis=1)

    def hidden(self, origin_cad: np.ndarray, points_cad: np.ndarray, tol_m: float) -> np.ndarray:
        """(N,) whether a surface lies on the segment from `origin_cad` to each point, nearer than the point by more
        than `tol_m`."""
        points = np.asarray(points_cad, np.float64).reshape(-1, 3)
        out = np.zeros(len(points), bool)
        if len(points) == 0 or len(self.v0) == 0:
            return out
        lo = np.minimum(points.min(axis=0), origin_cad)
        hi = np.maximum(points.max(axis=0), origin_cad)
        near = np.flatnonzero(np.all(self.hi >= lo, axis=1) & np.all(self.lo <= hi, axis=1))
        if len(near) == 0:
            return out
        v0, e1, e2 = self.v0[near], self.e1[near], self.e2[near]
        d = points - origin_cad  # (N, 3) segment directions, length = the point's distance
        s = origin_cad - v0  # (T, 3): of the rays' common origin, the same for every chunk
        q = np.cross(s, e1)  # (T, 3)
        q_e2 = np.einsum("tk,tk->t", e2, q)[None, :]
        for start in range(0, len(points), 64):  # bounded memory: 64 rays x the triangles near them
            dd = d[start:start + 64]
            p = np.cross(dd[:, None, :], e2[None, :, :])  # (n, T, 3)
            det = np.einsum("tk,ntk->nt", e1, p)
            ok = np.abs(det) > 1e-12
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            u = np.einsum("tk,ntk->nt", s, p) * inv
            v = np.einsum("nk,tk->nt", dd, q) * inv
            t = q_e2 * inv  # along the segment, 1 = at the point
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
            length = np.linalg.norm(dd, axis=1)
            cut = 1.0 - tol_m / np.maximum(length, 1e-9)  # nearer than the point by more than tol_m
            out[start:start + 64] = np.any(hit & (t < cut[:, None]), axis=1)
        return out


@dataclass(frozen=True)
class _Waiting:
    """A frame kept while the pose was not held: its left image encoded (as recorded where JPEG or PNG, else as
    PNG), its keyframe and pose from it, the camera's pose on the body and its intrinsics."""

    stamp_ns: int
    encoded: bytes
    keyframe: int  # the newest keyframe at the frame
    T_kf_body: np.ndarray  # the frame's pose from it (the odometry's)
    path_m: float  # the odometry's path from it
    T_body_cam: np.ndarray
    info: object


@dataclass(frozen=True)
class Box:
    """One label: a door or window of the model in one frame (pixels, pixel centres at integers)."""

    frame: str
    feature_id: str
    type: str
    box_xyxy: tuple[float, float, float, float]
    visible_fraction: float
    cut: bool


@dataclass
class SelfLabelReport:
    """Counts of each decision (module doc) and the boxes written."""

    frames: Counter[str] = field(default_factory=Counter)
    boxes: Counter[str] = field(default_factory=Counter)
    labels: list[Box] = field(default_factory=list)
    greyed: int = 0  # regions greyed out in the written frames

    def to_json(self) -> dict:
        kinds = Counter(b.type for b in self.labels)
        return {"frames": dict(self.frames), "boxes": dict(self.boxes), "doors": kinds["door"],
                "windows": kinds["window"], "cut": sum(b.cut for b in self.labels), "greyed": self.greyed}


def clip_near(corners_cam: np.ndarray, near_m: float) -> np.ndarray:
    """The polygon of `corners_cam` (in order) clipped to z >= near_m (Sutherland-Hodgman, one plane)."""
    out = []
    n = len(corners_cam)
    for i in range(n):
        a, b = corners_cam[i], corners_cam[(i + 1) % n]
        a_in, b_in = a[2] >= near_m, b[2] >= near_m
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (near_m - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def sigma_poses(T_cad_body: np.ndarray, covariance: np.ndarray, sigmas: float) -> list[np.ndarray]:
    """The pose moved by `sigmas` standard deviations along each principal axis of its covariance (6x6, [rot;
    trans] in the body's tangent, GTSAM's convention), both ways: 12 poses T_cad_body."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, float))
    out = []
    for value, vector in zip(values, vectors.T, strict=True):
        step = sigmas * np.sqrt(max(float(value), 0.0)) * vector
        out += [T_cad_body @ gtsam.Pose3.Expmap(sign * step).matrix() for sign in (1.0, -1.0)]
    return out


def _box(corners_cad: np.ndarray, T_cam_cad: np.ndarray, camera: tuple[float, float, float, float], near_m: float,
         ) -> tuple[float, float, float, float] | None:
    """The projected box of an opening (unclipped to the image), or None where it lies behind the near plane."""
    fx, fy, cx, cy = camera
    clipped = clip_near(corners_cad @ T_cam_cad[:3, :3].T + T_cam_cad[:3, 3], near_m)
    if len(clipped) < 3:
        return None
    u, v = fx * clipped[:, 0] / clipped[:, 2] + cx, fy * clipped[:, 1] / clipped[:, 2] + cy
    return float(u.min()), float(v.min()), float(u.max()), float(v.max())


def _clip(box: tuple[float, float, float, float], width: int, height: int) -> tuple[float, float, float, float]:
    return max(box[0], -0.5), max(box[1], -0.5), min(box[2], width - 0.5), min(box[3], height - 0.5)


def iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    """Intersection over union of two boxes (x0, y0, x1, y1)."""
    ix, iy = min(a[2], b[2]) - max(a[0], b[0]), min(a[3], b[3]) - max(a[1], b[1])
    inter = max(ix, 0.0) * max(iy, 0.0)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def _pixels(lo: float, hi: float, touching: bool) -> slice:
    """The pixels (centres at integers) that [lo, hi] touches, or that lie wholly inside it."""
    if touching:
        return slice(max(int(np.floor(lo + 0.5)), 0), max(int(np.ceil(hi - 0.5)) + 1, 0))
    return slice(max(int(np.ceil(lo + 0.5)), 0), max(int(np.floor(hi - 0.5)) + 1, 0))


def grey_out(image: np.ndarray, regions: list[tuple[float, float, float, float]],
             spared: list[tuple[float, float, float, float]]) -> np.ndarray:
    """A copy of `image` with each region (pixels, xyxy) filled with the image's mean colour, except inside the
    `spared` boxes."""
    if not regions:
        return image
    h, w = image.shape[:2]
    fill = np.zeros((h, w), bool)
    for x0, y0, x1, y1 in regions:  # every pixel the region touches (pixel i spans [i - 0.5, i + 0.5])
        fill[_pixels(y0, y1, touching=True), _pixels(x0, x1, touching=True)] = True
    for x0, y0, x1, y1 in spared:  # but those wholly inside a labelled box
        fill[_pixels(y0, y1, touching=False), _pixels(x0, x1, touching=False)] = False
    out = image.copy()
    out[fill] = image.reshape(h * w, -1).mean(axis=0).astype(image.dtype).squeeze()
    return out


class SelfLabeller:
    """Writes a replay's held frames with the model's doors and windows as YOLO labels (module doc) under
    `out_dir` (images/, labels/, data.yaml: the layout `perception.train --sim` reads; PREFIX.boxes.jsonl: each
    box with its door's id, visible fraction and whether the border cut it), the files named PREFIX_STAMP."""

    def __init__(self, features: list[MacroFeature], depth: ModelDepth, out_dir: Path, prefix: str,
                 params: SelfLabelParams | None = None, odometry: OdometryFactorParams | None = None) -> None:
        """`odometry`: the drift the pose graph assumes, which grows a frame's covariance before a fix."""
        self.features = [f for f in features if f.type in YOLO_CLASSES]
        self.depth = depth
        self.out_dir, self.prefix = out_dir, prefix
        self.params = params or SelfLabelParams()
        self.odometry = odometry or OdometryFactorParams()
        self.report = SelfLabelReport()
        self._last_ns: int | None = None
        self._waiting: deque[_Waiting] = deque()  # frames since the pose was last held, every `every_s`
        self._path_m = 0.0  # the odometry's path length so far (map frame)
        self._last_xyz: np.ndarray | None = None
        self._keyframes: dict[int, tuple[np.ndarray, float]] = {}  # keyframe -> its T_map_body then, path at it
        self.greyed: list[tuple[float, float, float, float]] = []  # the last frame's unlabelled openings, pixels
        yolo_folder(out_dir)
        for old in [*(out_dir / "images").glob(f"{prefix}_*"), *(out_dir / "labels").glob(f"{prefix}_*")]:
            old.unlink()  # this recording's frames of an earlier run (another recording's stay)
        self._boxes = (out_dir / f"{prefix}.boxes.jsonl").open("w")

    def frame(self, frame: FlightFrame, inputs: FrameSeen, estimate: Estimate) -> None:
        p = self.params
        xyz = estimate.T_map_body[:3, 3]
        if self._last_xyz is not None:
            self._path_m += float(np.linalg.norm(xyz - self._last_xyz))
        self._last_xyz = xyz.copy()
        if estimate.keyframe >= 0 and estimate.keyframe not in self._keyframes:  # the keyframe's own frame
            self._keyframes[estimate.keyframe] = (estimate.T_map_body.copy(), self._path_m)
        held = estimate.status == "localized" and estimate.T_cad_body is not None and estimate.covariance is not None
        if held and self._waiting:
            self._label_waiting(inputs.graph)
        soon = self._last_ns is not None and (frame.stamp_ns - self._last_ns) * 1e-9 < p.every_s
        if not held or not frame.stereo.left.data:
            if p.before_fix_s > 0 and frame.stereo.left.data and not soon and estimate.keyframe in self._keyframes:
                self._wait(frame, inputs, estimate)
            else:
                self.report.frames["not_localized"] += 1
            return
        if soon:
            self.report.frames["too_soon"] += 1
            return
        self._last_ns = frame.stamp_ns
        self.report.frames["labelled"] += 1
        self._write(frame.stamp_ns, frame.images()[0], estimate, inputs.T_body_cam, frame.stereo.info)

    def _wait(self, frame: FlightFrame, inputs: FrameSeen, estimate: Estimate) -> None:
        """Keep a frame while the pose is not held, for the next held pose to label (`_label_waiting`): its image,
        its keyframe and its pose from that keyframe (the odometry's, as the service carries a keyframe's estimate
        to the frames after it); frames more than `before_fix_s` older than the newest are let go."""
        self._last_ns = frame.stamp_ns
        left = frame.stereo.left
        encoded = left.data if left.encoding in (pb.Image.JPEG, pb.Image.PNG) else \
            cv2.imencode(".png", frame.images()[0])[1].tobytes()  # raw pixels kept losslessly, compressed
        T_map_kf, path_at_kf_m = self._keyframes[estimate.keyframe]
        self._waiting.append(_Waiting(frame.stamp_ns, bytes(encoded), estimate.keyframe,
                                      invert(T_map_kf) @ estimate.T_map_body, self._path_m - path_at_kf_m,
                                      inputs.T_body_cam, frame.stereo.info))
        while (frame.stamp_ns - self._waiting[0].stamp_ns) * 1e-9 > self.params.before_fix_s:
            self._waiting.popleft()
            self.report.frames["not_localized"] += 1

    def _label_waiting(self, graph: PoseGraph | None) -> None:
        """Label the frames kept since the pose was last held (module doc): each from its keyframe as the pose
        graph now holds it, anchored (T_cad_map times the keyframe's re-optimized T_map_body, with its marginal
        covariance), carried to the frame by the odometry; a frame whose keyframe has left the graph's window
        (marginalised, no covariance left) is not labelled."""
        T_cad_map = None if graph is None else graph.T_cad_map()
        o = self.odometry
        while self._waiting:
            w = self._waiting.popleft()
            if graph is None or T_cad_map is None or w.keyframe < graph.live_from or w.keyframe >= graph.n_keyframes:
                self.report.frames["not_localized"] += 1
                continue
            T_map_kf = graph.T_map_body(w.keyframe)
            adjoint = gtsam.Pose3(invert(w.T_kf_body)).AdjointMap()  # a keyframe-body perturbation, in the frame's
            drift = np.r_[np.full(3, o.odometry_rot_sigma_per_m * w.path_m),
                          np.full(3, o.odometry_sigma_per_m * w.path_m)]
            covariance = adjoint @ graph.covariance_cad_body(w.keyframe) @ adjoint.T + np.diag(drift**2)
            T_map_body = T_map_kf @ w.T_kf_body
            estimate = Estimate(w.stamp_ns, "localized", T_map_body, T_cad_map @ T_map_body, T_cad_map, covariance)
            image = cv2.imdecode(np.frombuffer(w.encoded, np.uint8), cv2.IMREAD_UNCHANGED)
            if image is None:
                self.report.frames["not_localized"] += 1
                continue
            self.report.frames["labelled_before_fix"] += 1
            self._write(w.stamp_ns, image, estimate, w.T_body_cam, w.info)

    def _write(self, stamp_ns: int, image: np.ndarray, estimate: Estimate, T_body_cam: np.ndarray,
               info: object) -> None:
        """Write one labelled frame (its left image, its boxes from `estimate`'s pose)."""
        p = self.params
        name = f"{self.prefix}_{stamp_ns}"
        h, w = image.shape[:2]
        fx, fy, cx, cy = (float(getattr(info, k)) for k in ("fx", "fy", "cx", "cy"))
        boxes = self.boxes(estimate, T_body_cam, fx, fy, cx, cy, w, h, name)
        left = grey_out(image, self.greyed, [b.box_xyxy for b in boxes])
        self.report.greyed += len(self.greyed)
        cv2.imwrite(str(self.out_dir / "images" / f"{name}.jpg"), left, [cv2.IMWRITE_JPEG_QUALITY, p.jpeg_quality])
        for b in boxes:
            self._boxes.write(json.dumps(asdict(b)) + "\n")
        (self.out_dir / "labels" / f"{name}.txt").write_text("".join(yolo_line(b.type, b.box_xyxy, w, h) + "\n"
                                                                     for b in boxes))
        self.report.labels += boxes

    def boxes(self, estimate: Estimate, T_body_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float,
              width: int, height: int, frame_name: str = "") -> list[Box]:
        """The labels of one frame seen from `estimate`'s pose (module doc); each decision counted, and the regions
        of the doors and windows there but not labelled in `greyed`."""
        p = self.params
        self.greyed = []
        assert estimate.T_cad_body is not None and estimate.covariance is not None
        T_cad_cam = estimate.T_cad_body @ T_body_cam
        T_cam_cad = invert(T_cad_cam)
        camera = (fx, fy, cx, cy)
        at_sigmas = [invert(T @ T_body_cam) for T in sigma_poses(estimate.T_cad_body, estimate.covariance, p.sigmas)]
        origin = T_cad_cam[:3, 3]
        out: list[Box] = []
        grid = (np.arange(p.samples) + 0.5) / p.samples
        uu, vv = (a.ravel() for a in np.meshgrid(grid, grid))
        for f in self.features:
            c = f.corners_cad
            whole = _box(c, T_cam_cad, camera, p.near_m)
            if whole is None:
                self.report.boxes["behind"] += 1
                continue
            box = _clip(whole, width, height)
            if box[2] <= box[0] or box[3] <= box[1]:
                self.report.boxes["outside"] += 1
                continue
            samples = c[0] + uu[:, None] * (c[1] - c[0]) + vv[:, None] * (c[3] - c[0])
            s_cam = samples @ T_cam_cad[:3, :3].T + T_cam_cad[:3, 3]
            z = np.maximum(s_cam[:, 2], 1e-9)
            su, sv = fx * s_cam[:, 0] / z + cx, fy * s_cam[:, 1] / z + cy
            seen = (s_cam[:, 2] >= p.near_m) & (su >= -0.5) & (su <= width - 0.5) & (sv >= -0.5) & \
                (sv <= height - 0.5)
            if seen.any():
                seen[seen] = ~self.depth.hidden(origin, samples[seen], p.occlusion_tol_m)
            fraction = float(seen.mean())
            if fraction < p.min_visible_fraction:
                self.report.boxes["hidden"] += 1
                if fraction > 0:
                    self.greyed.append(box)
                continue
            if min(box[2] - box[0], box[3] - box[1]) < p.min_box_px:
                self.report.boxes["too_small"] += 1
                self.greyed.append(box)
                continue
            moved = [_box(c, T, camera, p.near_m) for T in at_sigmas]
            if any(b is None or iou(_clip(b, width, height), box) < 0.5 for b in moved):
                self.report.boxes["uncertain"] += 1
                reach = [box, *(_clip(b, width, height) for b in moved if b is not None)]
                self.greyed.append((min(b[0] for b in reach), min(b[1] for b in reach), max(b[2] for b in reach),
                                    max(b[3] for b in reach)))
                continue
            cut = bool(whole[0] < -0.5 or whole[1] < -0.5 or whole[2] > width - 0.5 or whole[3] > height - 0.5)
            self.report.boxes["labelled"] += 1
            out.append(Box(frame_name, f.id, str(f.type), box, round(fraction, 3), cut))
        return out

    def finish(self, localizer: Localizer) -> None:
        """Count the frames still kept (no held pose came after them), close the box list and draw
        `PREFIX.labels.png`: up to `SHEET_TILES` labelled frames with boxes, spread over the flight, each box drawn
        (doors green, windows orange; a box cut by the border dashed-thin)."""
        self.report.frames["not_localized"] += len(self._waiting)
        self._waiting.clear()
        self._boxes.close()
        by_frame: dict[str, list[Box]] = {}
        for b in self.report.labels:
            by_frame.setdefault(b.frame, []).append(b)
        names = sorted(by_frame)
        if not names:
            return
        picked = [names[i] for i in np.linspace(0, len(names) - 1, min(SHEET_TILES, len(names))).round().astype(int)]
        tiles = []
        for name in dict.fromkeys(picked):
            image = cv2.imread(str(self.out_dir / "images" / f"{name}.jpg"), cv2.IMREAD_COLOR)
            if image is None:
                continue
            for b in by_frame[name]:
                x0, y0, x1, y1 = (int(round(v)) for v in b.box_xyxy)
                cv2.rectangle(image, (x0, y0), (x1, y1), SHEET_BGR[b.type], 1 if b.cut else 2)
            tiles.append(image)
        if tiles:
            cv2.imwrite(str(self.out_dir / f"{self.prefix}.labels.png"), contact_sheet(tiles))


def label_recording(recording: Path, building: Path, cfg: MacrolocConfig, occluders_cad: np.ndarray, out_dir: Path,
                    params: SelfLabelParams | None = None, topics: dict[str, str] | None = None) -> dict:
    """Replay `recording` (a macroloc MCAP or a ROS 2 bag with its `topics`: service.offline.ros_bag.open_flight)
    in `building` as the service runs it with `cfg` (perception on: the frames' own camera and the config's
    detector; service.offline.run.replay_flight) and label its held frames into `out_dir` (`SelfLabeller`, files
    named after the recording; `occluders_cad`: (T, 3, 3) the model's triangles). The report's counts, with the
    replay's `localized_at_s`, `wrong_localizations` (where the recording has ground truth) and
    `frames_in_flight`."""
    model = prepare_building(building, cfg.graph, cfg.planning).model
    labeller = SelfLabeller(model.features, ModelDepth(occluders_cad), out_dir, recording.stem, params,
                            cfg.graph.odometry)
    log.info("labelling %s: replaying it with perception; frames where the pose is held are labelled by %s",
             recording.name, building.name)
    frames = open_flight(recording, topics, cfg.camera)
    replayed = replay_flight(frames, building, cfg, ReplayOptions(observations="perception"), recorder=labeller)
    result = replayed.result.to_json()
    return {**labeller.report.to_json(), "localized_at_s": result.get("time_to_localize_s"),
            "wrong_localizations": result.get("wrong_localizations"), "frames_in_flight": result.get("frames")}
