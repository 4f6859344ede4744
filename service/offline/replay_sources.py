"""Where the replay's per-frame inputs come from: odometry and door/window sightings (gravity's up is the session's,
from the frame's IMU samples and the odometry: `gravity_at`).

`TruthSource` (`--observations truth`) turns a simulated flight's ground truth into what a good front end
would deliver, with realistic errors: odometry that drifts (a scale error, a yaw bias, noise growing with
motion), stereo-like corner noise (depth error ~ z^2), missed detections, and gravity with a small tilt
error. `PerceptionSource` (`--observations perception`) runs the perception chain and the visual odometry
on the recorded images (or takes the vehicle's own odometry, where the recording has one). Both return a
`FrameInput` per recorded frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.localizer import Sighting
from macroloc.graph.rigid import apply, rot_z, rotation_angle_rad
from macroloc.proto.recording import FlightFrame, matrix_from_pose
from macroloc.service.visual_odometry import VisualOdometry, _rig, _specific_forces

if TYPE_CHECKING:
    from macroloc.perception.params import PerceptionParams
    from macroloc.perception.stereo import FrameDisparity

log = logging.getLogger(__name__)

AHEAD_FRAMES = 4  # frames the replay's reading thread may run `ahead` of the session (their images held meanwhile)
KEPT_MATCHES = AHEAD_FRAMES + 4  # whole-frame SGBMs a source's FrameDisparity keeps: between the odometry's match
#   of a frame and the chain's use of it, at most one more from each thread per frame in flight (one thread: 1)


@dataclass(frozen=True)
class FrameInput:
    """One frame's inputs to the localizer. T_odom_body: 4x4 odometry pose (odometry frame z up);
    up_body: unit up direction in the body frame (the session's from the IMU, or the simulator's truth), or None."""

    stamp_ns: int
    T_odom_body: np.ndarray
    sightings: list[Sighting]
    up_body: np.ndarray | None
    T_body_cam: np.ndarray
    points_body: np.ndarray | None = None  # (N, 3) stereo depth points, body frame, when this frame measured them
    dead_reckoned_s: float = 0.0  # seconds since the previous frame the odometry only extrapolated (it lost track)
    measure_depth: Callable[[], np.ndarray] | None = None  # this frame's depth points when called (for a keyframe)


class ObservationSource(Protocol):
    """A frame's inputs in two parts. `ahead(frame)`: what depends only on the recording and the frames before it,
    never on the session (the images decoded, the visual odometry: an `OdometryStep`): where `runs_ahead` says so,
    the replay calls it on a thread of its own, a few frames ahead of the session (service.offline.replay).
    `__call__(frame, ahead, up_body)`: the rest, in frame order on the session's thread (`ahead`: what
    `ahead(frame)` gave, None: computed there; `up_body`: gravity's up at the frame, `gravity_at`, for the
    perception chain). `T_body_cam(frame)`: the left camera in the body frame (4x4)."""

    runs_ahead: bool
    uses_images: bool  # the replay's reading thread decodes them (FlightFrame.images) where it does

    def ahead(self, frame: FlightFrame) -> object: ...

    def __call__(self, frame: FlightFrame, ahead: object = None, up_body: np.ndarray | None = None
                 ) -> FrameInput: ...

    def T_body_cam(self, frame: FlightFrame) -> np.ndarray: ...


class ImuInput(Protocol):
    """Where gravity's up comes from: service.session.LocalizationSession, or perception.gravity.ImuGravity."""

    def imu(self, accel_body_mps2: np.ndarray) -> None: ...

    def odometry(self, stamp_ns: int, T_odom_body: np.ndarray) -> np.ndarray | None: ...


def gravity_at(gravity: ImuInput, frame: FlightFrame, ahead: object) -> np.ndarray | None:
    """Gravity's up at the frame: the frame's IMU samples and the odometry's pose (where `ahead` is an
    `OdometryStep`) to `gravity` (the session), in the order the service takes them; None without an odometry."""
    if not isinstance(ahead, OdometryStep):
        return None
    gravity.imu(_specific_forces(frame))
    return gravity.odometry(frame.stamp_ns, ahead.T_odom_body)


@dataclass(frozen=True)
class OdometryStep:
    """What an odometry gives for one frame (VisualOdometry, VehicleOdometry)."""

    T_odom_body: np.ndarray
    points_body: np.ndarray | None
    measure_depth: Callable[[], np.ndarray] | None
    dead_reckoned_s: float

    @staticmethod
    def of(odometry: VisualOdometry | VehicleOdometry, frame: FlightFrame) -> OdometryStep:
        """Run the odometry on the frame's images (decoded here unless they were already)."""
        left, right = frame.images()
        T_odom_body = odometry(frame, left, right)
        return OdometryStep(T_odom_body, odometry.points_body, odometry.measure_depth, odometry.dead_reckoned_s)


@dataclass(frozen=True)
class TruthNoise:
    """Errors added to ground truth. Defaults: a decent stereo VIO and stereo corners at 0.12 m baseline."""

    odom_scale_error: float = 0.01  # odometry measures 1 % too much motion
    odom_yaw_bias_radps: float = 0.001  # ~3.4 deg/min heading drift
    odom_trans_sigma_per_m: float = 0.01
    odom_rot_sigma_per_rad: float = 0.01
    corner_sigma_m: float = 0.01  # lateral, per corner
    depth_sigma_per_m2: float = 0.005  # stereo: sigma_z = 0.3 px * z^2 / (fx * baseline) ~ 0.005 z^2
    gravity_sigma_rad: float = 0.005
    miss_rate: float = 0.1
    min_visible_corners: int = 3  # three corners complete a rectangle
    depth_stride_px: int = 20  # depth points: every this many pixels of the true depth image, with the noise above,
    depth_every: int = 1  # ... on every this many frames (a keyframe takes the newest): a depth camera's rate


class TruthSource:
    """Ground truth with realistic errors (see module doc); deterministic for a seed."""

    runs_ahead = True  # nothing ahead: reading the recording
    uses_images = False

    def __init__(self, noise: TruthNoise | None = None, seed: int = 0) -> None:
        self.noise = noise or TruthNoise()
        self.rng = np.random.default_rng(seed)
        self.depth_rng = np.random.default_rng([seed, 1])  # its own stream: depth leaves the sightings' noise alone
        self._n = 0
        self._T_true_prev: np.ndarray | None = None
        self._T_odom: np.ndarray | None = None
        self._stamp_prev = 0

    def ahead(self, frame: FlightFrame) -> None:
        return None

    def T_body_cam(self, frame: FlightFrame) -> np.ndarray:
        return matrix_from_pose(self._truth(frame).T_body_cam)

    @staticmethod
    def _truth(frame: FlightFrame):  # noqa: ANN205 - pb.GroundTruth
        if frame.ground_truth is None:
            raise UserInputError("--observations truth needs a simulated recording with ground truth")
        return frame.ground_truth

    def __call__(self, frame: FlightFrame, ahead: object = None, up_body: np.ndarray | None = None) -> FrameInput:
        """`up_body` is not used: gravity's up is the truth's, with `TruthNoise.gravity_sigma_rad`."""
        gt = self._truth(frame)
        T_cad_body = matrix_from_pose(gt.T_cad_body)
        T_body_cam = matrix_from_pose(gt.T_body_cam)
        T_odom_body = self._odometry(T_cad_body, frame.stamp_ns)
        up_body = T_cad_body[:3, :3].T @ np.array([0.0, 0.0, 1.0]) + self.rng.normal(0, self.noise.gravity_sigma_rad, 3)
        up_body /= np.linalg.norm(up_body)
        with_depth = self._n % self.noise.depth_every == 0
        self._n += 1
        return FrameInput(frame.stamp_ns, T_odom_body, self._sightings(gt, T_body_cam), up_body, T_body_cam,
                          self._points(gt, frame.stereo.info, T_body_cam) if with_depth else None)

    def _points(self, gt, info, T_body_cam: np.ndarray) -> np.ndarray | None:  # noqa: ANN001 - pb types
        """Points of the true depth image on a grid, with the stereo depth noise, body frame."""
        if not gt.HasField("depth"):
            return None
        from macroloc.perception.stereo import back_project, depth_grid
        from macroloc.proto.recording import decode_image

        uv, z = depth_grid(decode_image(gt.depth), self.noise.depth_stride_px, 0.3)
        z = z + self.depth_rng.normal(0, 1, len(z)) * self.noise.depth_sigma_per_m2 * z * z
        rig = _rig(info)
        points_cam = back_project(uv, z, rig)
        return apply(T_body_cam, points_cam)

    def odometry(self, frame: FlightFrame) -> np.ndarray:
        """The frame's odometry pose alone (4x4, odometry frame), as a vehicle's VIO would publish it: the
        ground truth with the drift of `TruthNoise` (the sightings' noise is not drawn)."""
        gt = frame.ground_truth
        if gt is None:
            raise UserInputError("simulated odometry needs a simulated recording with ground truth")
        return self._odometry(matrix_from_pose(gt.T_cad_body), frame.stamp_ns)

    def _odometry(self, T_cad_body: np.ndarray, stamp_ns: int) -> np.ndarray:
        n = self.noise
        if self._T_true_prev is None or self._T_odom is None:
            yaw0 = np.arctan2(T_cad_body[1, 0], T_cad_body[0, 0])
            self._T_odom = np.eye(4)
            self._T_odom[:3, :3] = rot_z(-yaw0) @ T_cad_body[:3, :3]  # odometry frame: level, starts here
        else:
            dT = np.linalg.inv(self._T_true_prev) @ T_cad_body
            step_m = float(np.linalg.norm(dT[:3, 3]))
            angle = rotation_angle_rad(dT[:3, :3])
            dt_s = (stamp_ns - self._stamp_prev) * 1e-9
            noisy = dT.copy()
            noisy[:3, 3] = (dT[:3, 3] * (1 + n.odom_scale_error)
                            + self.rng.normal(0, n.odom_trans_sigma_per_m * step_m, 3))
            dyaw = n.odom_yaw_bias_radps * dt_s + self.rng.normal(0, n.odom_rot_sigma_per_rad * angle + 1e-5)
            noisy[:3, :3] = dT[:3, :3] @ rot_z(dyaw)
            self._T_odom = self._T_odom @ noisy
        self._T_true_prev, self._stamp_prev = T_cad_body, stamp_ns
        return self._T_odom.copy()

    def _sightings(self, gt, T_body_cam: np.ndarray) -> list[Sighting]:  # noqa: ANN001 - pb.GroundTruth
        n = self.noise
        out = []
        for k, feat in enumerate(gt.features_cam):
            visible = list(gt.corner_visible[4 * k: 4 * k + 4])
            if sum(visible) < n.min_visible_corners or self.rng.random() < n.miss_rate:
                continue
            corners_cam = np.array([[c.x, c.y, c.z] for c in feat.corners])
            z = corners_cam[:, 2:3]
            sigmas = np.hstack([np.full((4, 2), n.corner_sigma_m), n.depth_sigma_per_m2 * z**2])  # x, y | z (cam)
            noise = self.rng.normal(0, 1, (4, 3)) * sigmas
            corners_cam = corners_cam + noise
            corners_body = (T_body_cam[:3, :3] @ corners_cam.T).T + T_body_cam[:3, 3]
            out.append(Sighting(feat.type, corners_body, truth_id=feat.id))
        return out


class VehicleOdometry:
    """T_odom_body from the vehicle's own odometry recorded with the flight ("/odometry", e.g. a demo's flight or
    a drone's VIO), as the service takes it from the vehicle's odometry key: the sample at the frame's stamp (else
    the newest before it). `points_body` and `measure_depth` as `VisualOdometry` gives them."""

    def __init__(self, disparity: FrameDisparity | None = None, params: PerceptionParams | None = None) -> None:
        from macroloc.perception.params import PerceptionParams
        from macroloc.service.frames import StereoDepth

        p = params or PerceptionParams()
        self._depth = StereoDepth.configured(p.depth, disparity)
        self._T_odom_body: np.ndarray | None = None
        self.points_body: np.ndarray | None = None
        self.measure_depth: Callable[[], np.ndarray] | None = None
        self.dead_reckoned_s = 0.0  # the vehicle's odometry says nothing of its own losses

    def __call__(self, frame: FlightFrame, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        at_or_before = [o for o in frame.odometry if o.header.stamp_ns <= frame.stamp_ns]
        if at_or_before:
            self._T_odom_body = matrix_from_pose(at_or_before[-1].T_map_body)
        if self._T_odom_body is None:
            raise UserInputError(f"the recording's first stereo frame ({frame.stamp_ns} ns) has no vehicle "
                                 "odometry at or before it")
        info = frame.stereo.info
        rig = _rig(info)
        T_body_cam = matrix_from_pose(info.T_body_cam)
        self.points_body = self._depth(left, right, rig, T_body_cam)
        self.measure_depth = self._depth.deferred(left, right, rig, T_body_cam)
        return self._T_odom_body


class TruthFeaturesWithVisualOdometry:
    """`--observations truth-vo`: ground-truth sightings (with TruthSource's noise) but the odometry of the
    real stereo visual odometry on the recorded images: the graph against a real front end's drift."""

    def __init__(self, noise: TruthNoise | None = None, seed: int = 0, params: PerceptionParams | None = None
                 ) -> None:
        from macroloc.perception.params import PerceptionParams
        from macroloc.perception.stereo import FrameDisparity, SgbmMatcher

        self.params = p = params or PerceptionParams()
        self.truth = TruthSource(noise, seed)
        self.odometry = VisualOdometry(FrameDisparity(SgbmMatcher(p.stereo), keep=KEPT_MATCHES), p)
        self.runs_ahead = not p.odometry.rekey_at_session_keyframes  # re-keyed by the session: in its turn
        self.uses_images = True

    def ahead(self, frame: FlightFrame) -> OdometryStep:
        return OdometryStep.of(self.odometry, frame)

    def T_body_cam(self, frame: FlightFrame) -> np.ndarray:
        return self.truth.T_body_cam(frame)

    def __call__(self, frame: FlightFrame, ahead: object = None, up_body: np.ndarray | None = None) -> FrameInput:
        step = ahead if isinstance(ahead, OdometryStep) else self.ahead(frame)
        inputs = self.truth(frame)
        return FrameInput(inputs.stamp_ns, step.T_odom_body, inputs.sightings, up_body, inputs.T_body_cam,
                          step.points_body, step.dead_reckoned_s, step.measure_depth)


class PerceptionSource:
    """The perception chain (doors and windows in 3D) and the stereo visual odometry on recorded images, or the
    vehicle's own odometry where the recording carries it (`VehicleOdometry`; the service, too, takes the
    vehicle's odometry when it sends one).

    Gravity's up (`up_body`, the session's: the IMU's specific force less the odometry's acceleration) tells the
    chain which way is down; the odometry frame is the first body frame levelled by the first frame's specific
    force. The chain runs on every `detect_every`-th frame; sightings get the id of the nearest ground-truth
    feature (within 0.5 m) for scoring only.
    """

    def __init__(self, detect_every: int = 3, detector_model: Path | None = None,
                 params: PerceptionParams | None = None) -> None:
        try:
            from macroloc.perception.pipeline import Perception
        except ImportError:
            raise UserInputError("--observations perception: the perception chain (perception.pipeline) "
                                 "is not available; use --observations truth") from None
        from macroloc.perception.params import PerceptionParams
        from macroloc.perception.stereo import FrameDisparity, SgbmMatcher
        from macroloc.perception.threads import set_threads

        plan = set_threads()  # the libraries' threads (OpenCV's process-wide), as in the service
        self.params = p = params or PerceptionParams()
        self.disparity = FrameDisparity(SgbmMatcher(p.stereo), keep=KEPT_MATCHES)  # one SGBM a
        #                                                                   frame: odometry, depth points, chain
        self.perception = Perception.create(detector_model, threads=plan.onnxruntime, disparity=self.disparity,
                                            params=p)
        self.detect_every = detect_every
        self.odometry: VisualOdometry | VehicleOdometry | None = None
        self.runs_ahead = not p.odometry.rekey_at_session_keyframes  # re-keyed by the session: in its turn
        self.uses_images = True
        self._n = 0

    def ahead(self, frame: FlightFrame) -> OdometryStep:
        """The frame's images and odometry (the odometry sees the frames in order, wherever it runs)."""
        if self.odometry is None:
            self.odometry = VehicleOdometry(self.disparity, self.params) if frame.odometry else \
                VisualOdometry(self.disparity, self.params)
            log.info("odometry: %s", "the vehicle's, recorded" if frame.odometry else "stereo visual odometry")
        return OdometryStep.of(self.odometry, frame)

    def T_body_cam(self, frame: FlightFrame) -> np.ndarray:
        return matrix_from_pose(frame.stereo.info.T_body_cam)

    def __call__(self, frame: FlightFrame, ahead: object = None, up_body: np.ndarray | None = None) -> FrameInput:
        from macroloc.perception.pipeline import StereoPair
        from macroloc.service.frames import gravity_cam

        step = ahead if isinstance(ahead, OdometryStep) else self.ahead(frame)
        info = frame.stereo.info
        T_body_cam = matrix_from_pose(info.T_body_cam)
        left, right = frame.images()  # the arrays the odometry had: the frame's SGBM knows them
        sightings: list[Sighting] = []
        if self._n % self.detect_every == 0:
            rig = _rig(info)
            down_cam = gravity_cam(up_body, T_body_cam)
            result = self.perception.process(StereoPair(left, right, rig, down_cam, frame.stamp_ns))
            truth = _truth_centroids_cam(frame)
            for f in result.features:
                corners_body = (T_body_cam[:3, :3] @ f.corners_cam.T).T + T_body_cam[:3, 3]
                sightings.append(Sighting(f.type, corners_body, truth_id=_nearest_id(f.centroid_cam, truth),
                                          truncated=f.truncated))
        self._n += 1
        return FrameInput(frame.stamp_ns, step.T_odom_body, sightings, up_body, T_body_cam, step.points_body,
                          step.dead_reckoned_s, step.measure_depth)


def _truth_centroids_cam(frame: FlightFrame) -> list[tuple[str, np.ndarray]]:
    if frame.ground_truth is None:
        return []
    return [(f.id, np.mean([[c.x, c.y, c.z] for c in f.corners], axis=0)) for f in frame.ground_truth.features_cam]


def _nearest_id(centroid_cam: np.ndarray, truth: list[tuple[str, np.ndarray]], gate_m: float = 0.5) -> str | None:
    best = min(truth, key=lambda t: float(np.linalg.norm(t[1] - centroid_cam)), default=None)
    return best[0] if best is not None and float(np.linalg.norm(best[1] - centroid_cam)) < gate_m else None
