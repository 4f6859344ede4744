"""Stereo frames to sightings inside the service: the perception chain behind the `FramePipeline` seam.

`PerceptionPipeline` runs `perception.pipeline.Perception` (detector -> LSD -> SGBM -> 3D corners) on a wire
`StereoFrame`'s decoded pair and returns the doors/windows with corners in the body frame, using the frame's own
CameraInfo (intrinsics, baseline, T_body_cam). `StereoDepth` measures the depth points of the localizer's surface
check (graph.surfaces) for the front end (service.front_end). `configured_pipeline` picks the chain when the
detector's weights load, and the null pipeline otherwise (logged).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.graph.localizer import Sighting
from macroloc.graph.rigid import apply
from macroloc.perception.calib import StereoRig
from macroloc.perception.params import DepthPointsParams, PerceptionParams
from macroloc.perception.pipeline import Perception, StereoPair
from macroloc.perception.stereo import (
    FrameDisparity,
    SgbmMatcher,
    SgbmParams,
    back_project,
    depth_from_disparity,
    depth_grid,
)
from macroloc.perception.threads import SERVICE_THREADS, set_threads
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import decode_image, matrix_from_pose

if TYPE_CHECKING:
    from macroloc.perception.stereo import FrameDisparity

log = logging.getLogger(__name__)


class FramePipeline(Protocol):
    """Stereo frame (its decoded images, and gravity's up at it, body frame, when known) -> sightings (doors/windows,
    corners in the body frame). Perception plugs in here. `disparity`: the frame's one SGBM
    (perception.stereo.FrameDisparity) that the front end's depth points and visual odometry share, where the
    pipeline has one."""

    @property
    def disparity(self) -> FrameDisparity | None: ...

    def __call__(self, frame: pb.StereoFrame, up_body: np.ndarray | None = None,
                 images: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None) -> list[Sighting]: ...


def gravity_cam(up_body: np.ndarray | None, T_body_cam: np.ndarray) -> np.ndarray | None:
    """Gravity's direction (down) in the camera frame, for the perception chain (perception.pipeline.StereoPair),
    from up in the body frame; None where up is unknown."""
    return None if up_body is None else -(T_body_cam[:3, :3].T @ up_body)


class NullPipeline:
    """Sees nothing in the frames (perception off or unavailable): a frame still gets its pose from odometry,
    and sightings come on the observations key (e.g. from the vehicle's own detector)."""

    disparity: FrameDisparity | None = None

    def __call__(self, frame: pb.StereoFrame, up_body: np.ndarray | None = None,
                 images: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None) -> list[Sighting]:
        return []


class StereoDepth:
    """Depth points for the surface check and fit (graph.surfaces): SGBM over the whole rectified pair, every
    `stride_px`-th pixel at 0.3-8 m, back-projected (eq. 2) into the body frame. The service's pipeline and the
    replay's sources measure depth alike through it, on one of two schedules: `at_keyframes` (the default of
    [perception.depth]), only on the frames that become keyframes, when the session asks (`deferred`: a keyframe
    takes the newest depth points before it and no other frame's are ever used, so measuring every third frame
    threw away two SGBMs of three: docs/measurements.md, "Depth points measured for keyframes only"); else every
    `every`-th frame (`__call__`).

    Its SGBM searches `num_disparities` (128: down to fx * baseline / 128, 0.45 m with the simulated rig), not the
    perception chain's 64 (0.9 m): a wall nearer than the search reaches is matched at a wrong disparity and lands
    behind itself. With 64 disparities most points at 0.6-0.9 m lie more than 0.1 m off, with 128 few; a drone
    turning in front of a door (the demo's take-off) sees such walls in much of its view, and with 64 the true pose
    then puts fewer of the window's points on the model's walls than a pose must (docs/measurements.md, "Change by
    change")."""

    def __init__(self, every: int = 3, stride_px: int = 16, num_disparities: int = 128,
                 disparity=None, range_m: tuple[float, float] = (0.3, 8.0),  # noqa: ANN001 - FrameDisparity
                 at_keyframes: bool = False) -> None:
        """`disparity`: the frame's shared SGBM (perception.stereo.FrameDisparity) where the perception chain or
        the odometry match the same frames; None: its own, with `num_disparities`. `range_m`: the points kept.
        `every` 0: no depth points on either schedule."""
        self.matcher = disparity or SgbmMatcher(SgbmParams(num_disparities=num_disparities))
        self.every = every
        self.stride_px = stride_px
        self.range_m = range_m
        self.at_keyframes = at_keyframes
        self._n = 0

    @classmethod
    def configured(cls, params: DepthPointsParams, disparity=None) -> StereoDepth:  # noqa: ANN001 - FrameDisparity
        """As [perception.depth] says, on the frame's shared SGBM (`disparity`) where given."""
        return cls(params.every, params.stride_px, disparity=disparity,
                   range_m=(params.min_range_m, params.max_range_m), at_keyframes=params.at_keyframes)

    def __call__(self, left: np.ndarray, right: np.ndarray, rig, T_body_cam: np.ndarray) -> np.ndarray | None:  # noqa: ANN001 - StereoRig
        """Every `every`-th frame's points (None on the others, and on every frame `at_keyframes`)."""
        n, self._n = self._n, self._n + 1
        if self.at_keyframes or not self.every or n % self.every:
            return None
        return self.measure(left, right, rig, T_body_cam)

    def deferred(self, left: np.ndarray, right: np.ndarray, rig,  # noqa: ANN001 - StereoRig
                 T_body_cam: np.ndarray) -> Callable[[], np.ndarray] | None:
        """`at_keyframes`: this frame's points, measured when called (service.localizer_loop calls it for a keyframe);
        else None. The images must not change until then."""
        if not self.at_keyframes or not self.every:
            return None
        return lambda: self.measure(left, right, rig, T_body_cam)

    def measure(self, left: np.ndarray, right: np.ndarray, rig, T_body_cam: np.ndarray) -> np.ndarray:  # noqa: ANN001 - StereoRig
        """The pair's depth points (N, 3), body frame, metres."""
        depth_m = depth_from_disparity(self.matcher.disparity_px(left, right), rig)
        return apply(T_body_cam, back_project(*depth_grid(depth_m, self.stride_px, *self.range_m), rig))


class PerceptionPipeline:
    """StereoFrame -> sightings (corners in the body frame, metres) through the perception chain."""

    def __init__(self, perception) -> None:  # noqa: ANN001 - perception.Perception
        """`disparity`: the chain's matcher where it is a shared FrameDisparity (one SGBM a frame for the chain,
        the depth points and the visual odometry), else None."""
        self.perception = perception
        self.disparity = perception.matcher if isinstance(perception.matcher, FrameDisparity) else None

    def __call__(self, frame: pb.StereoFrame, up_body: np.ndarray | None = None,
                 images: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None) -> list[Sighting]:
        """Frames come checked (service.inputs: sizes from the headers, equal left and right and camera info);
        a frame without camera info cannot be perceived and gives no sightings. `up_body`: gravity's up (the
        session's), which tells the chain which way is down; `images()`: the frame's decoded pair (decoded here
        without)."""
        if not calibrated(frame):
            return []
        left, right = images() if images is not None else (decode_image(frame.left), decode_image(frame.right))
        rig, T_body_cam = stereo_rig(frame), stereo_T_body_cam(frame)
        result = self.perception.process(StereoPair(left, right, rig, gravity_cam(up_body, T_body_cam),
                                                    frame.header.stamp_ns))
        return [Sighting(f.type, apply(T_body_cam, f.corners_cam), truncated=f.truncated)
                for f in result.features]


def calibrated(frame: pb.StereoFrame) -> bool:
    """Whether a frame can be perceived and measured: its CameraInfo with a positive focal length and baseline, and
    both images (a ground-truth-only flight's frames carry neither)."""
    info = frame.info
    return frame.HasField("info") and info.fx > 0 and info.baseline_m > 0 and bool(frame.left.data) and \
        bool(frame.right.data)


def stereo_rig(frame: pb.StereoFrame) -> StereoRig:
    """The stereo rig a frame's CameraInfo describes (the images' size from the frame: service.inputs checked that
    they agree with the info's)."""
    info = frame.info
    return StereoRig(info.fx, info.fy, info.cx, info.cy, info.baseline_m, frame.left.width, frame.left.height)


def stereo_T_body_cam(frame: pb.StereoFrame) -> np.ndarray:
    """The left camera in the body frame (4x4): the frame's CameraInfo's, else the forward-looking stereo pair's
    (common.geometry: the simulator's)."""
    info = frame.info
    return matrix_from_pose(info.T_body_cam) if info.HasField("T_body_cam") else forward_stereo_T_body_cam()


def make_perception_pipeline(threads: int | None = None, detector_model: Path | None = None,
                             params: PerceptionParams | None = None) -> PerceptionPipeline | None:
    """The perception chain with the given detector (default: the shipped one), or None when it cannot load
    (logged). The libraries' threads follow perception.threads.SERVICE_THREADS (OpenCV's set here, process-wide);
    `threads`: the detector's, instead of the plan's; `params`: the chain's ([perception.*]: the frame's SGBM,
    the sides, the plausibility limits, the wall plane)."""
    try:
        plan = set_threads(SERVICE_THREADS)
        log.info("threads: %s", plan.describe())
        p = params or PerceptionParams()
        chain = Perception.create(detector_model, threads=threads or plan.onnxruntime,
                                  disparity=FrameDisparity(SgbmMatcher(p.stereo)), params=p)
        return PerceptionPipeline(chain)
    except Exception as exc:  # missing weights or runtime: the service still runs, without perception
        log.warning("perception chain unavailable (%s): stereo frames are not perceived", exc)
        return None


def depth_points_body(frame: pb.StereoFrame, stride_px: int = 8, max_range_m: float = 6.0) -> np.ndarray:
    """(N, 3) body-frame points from the frame's optional depth image (every stride_px-th pixel, 0 < z <= max)."""
    if not frame.HasField("depth") or frame.depth.encoding != pb.Image.RAW_DEPTH_F32:
        return np.zeros((0, 3))
    info = frame.info
    depth_m = decode_image(frame.depth)[::stride_px, ::stride_px]
    v, u = np.mgrid[0:frame.depth.height:stride_px, 0:frame.depth.width:stride_px]
    ok = np.isfinite(depth_m) & (depth_m > 0) & (depth_m <= max_range_m)
    z = depth_m[ok]
    points_cam = np.column_stack([(u[ok] - info.cx) / info.fx * z, (v[ok] - info.cy) / info.fy * z, z])  # pinhole
    T_body_cam = stereo_T_body_cam(frame)
    return points_cam @ T_body_cam[:3, :3].T + T_body_cam[:3, 3]


def configured_pipeline(cfg) -> FramePipeline:  # noqa: ANN001 - service.config.MacrolocConfig
    """The stereo-frame pipeline the config asks for: the perception chain when [service] perception is on and it
    loads, else none (frames still give a pose from the odometry; sightings then come on the observations key)."""
    if cfg.service.perception:
        pipeline = make_perception_pipeline(detector_model=cfg.perception.detector_model,
                                            params=cfg.perception.to_params())
        if pipeline is not None:
            return pipeline
    return NullPipeline()
