"""The one per-frame front end of `serve` and `replay` (kiss-icp's `register_frame`): the vehicle's input events
in, `graph.localizer.Estimate` out. The service's worker hands it every event it takes (service.node), and the
offline replay hands it the same events made from a recording (service.offline.replay), so that a replay runs the
path the service runs.

`FrontEnd.handle(event)` takes the typed events of service.inputs, in the order the vehicle sent them:
- `ImuIn`: a specific force sample, to the loop (gravity's up with the next odometry pose: perception.gravity).
- `OdometryIn`: the vehicle's odometry pose: buffered by stamp, to the loop, then the sightings that waited for
  it, then a frame of its own (no sightings).
- `ObservationsIn`: doors/windows sent by the vehicle (body, left-camera or odometry frame): a frame at the
  odometry pose of their stamp, kept pending until that pose arrives.
- `StereoIn`: a stereo frame, once each: decoded, its camera geometry taken from its CameraInfo, perceived (every
  `perceive_every`-th frame: the cadence, the same in serve and replay), its depth points (the vehicle's depth image
  where the frame carries one and the model's walls are known, else the pipeline's stereo depth, measured when it
  becomes a keyframe), place recognition (service.places), then the loop's update at the odometry pose of its
  stamp.
- `PriorIn` (the operator's prior, graph.prior) and `ClockReset` (the vehicle's clock restarted).

Frames: odom = the vehicle's odometry frame (the localizer's map frame), body, cam_left, cad. Metres.

Restarting from a saved map (`restored`): service.saved_map, the one restore path of `serve` and `replay --map`
(place recognition in its keyframe views from the first frame on, its T_cad_map, its CAD-linked landmarks).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.geo import GeoReference
from macroloc.graph.localizer import Estimate, Localizer, Sighting
from macroloc.graph.mapstore import PlacedView
from macroloc.graph.prior import PosePrior, storey_band_m
from macroloc.graph.surfaces import SurfaceIndex
from macroloc.perception.params import DepthPointsParams, PlaceParams
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame, pose_from_matrix, vector3
from macroloc.service.config import MacrolocConfig
from macroloc.service.frame_answers import ODOMETRY_MATCH_NS, OdometryBuffer
from macroloc.service.frames import (
    FramePipeline,
    NullPipeline,
    StereoDepth,
    calibrated,
    configured_pipeline,
    depth_points_body,
    stereo_rig,
    stereo_T_body_cam,
)
from macroloc.service.inputs import (
    ClockReset,
    ImuIn,
    InputLimits,
    Observation,
    ObservationsIn,
    OdometryIn,
    PriorIn,
    StereoIn,
)
from macroloc.service.localizer_loop import FrameIn, LocalizerLoop, loop_from_config
from macroloc.service.places import KeyframePlaces, Placed
from macroloc.service.saved_map import STATUS_TO_WIRE, SavedMap, map_snapshot, saved_views, supersedes
from macroloc.service.visual_odometry import VisualOdometry

if TYPE_CHECKING:
    from macroloc.service.config import MacrolocConfig

log = logging.getLogger(__name__)

WIRE_TO_STATUS = {v: k for k, v in STATUS_TO_WIRE.items()}


@dataclass(frozen=True)
class _Pending:
    """Sightings that arrived before the odometry of their stamp: made body-frame once that pose is known."""

    stamp_ns: int
    to_body: Callable[[np.ndarray], list[Sighting]]  # T_odom_body -> the sightings, body frame


@dataclass(frozen=True)
class FrontEndParams:
    """The per-frame path's own settings: `perceive_every` ([perception] detect_every: the chain runs on every n-th
    stereo frame, counted from the first, the same in serve and replay); `depth` ([perception.depth]: the points
    taken of a vehicle's depth image); `place` ([perception.place]: place recognition in a saved map's views)."""

    perceive_every: int = 1
    depth: DepthPointsParams = field(default_factory=DepthPointsParams)
    place: PlaceParams | None = None

    @classmethod
    def configured(cls, cfg: MacrolocConfig) -> FrontEndParams:
        chain = cfg.perception.to_params()
        return cls(cfg.perception.detect_every, chain.depth, chain.place)


class FrontEnd:
    """See module doc: the vehicle's events into frames of its `LocalizerLoop` (service.localizer_loop): odometry by
    stamp, sightings waiting for the odometry of their stamp, stereo frames perceived; the IMU and each odometry
    sample go to the localizer loop as they come (it estimates gravity's up). One thread only (the service's worker, the
    replay's loop)."""

    def __init__(self, model: BuildingModel, loop: LocalizerLoop,
                 T_body_cam: np.ndarray | None = None, pipeline: FramePipeline | None = None,
                 params: FrontEndParams | None = None, visual: VisualOdometry | None = None) -> None:
        """`T_body_cam`: the left camera in the body frame, for sightings sent in the cam_left frame; `pipeline`:
        the perception chain on stereo frames (none: frames give a pose from the odometry only, sightings come as
        observations), whose frames also give stereo depth points ([perception.depth], on its SGBM); `visual`: the
        odometry strategy where the vehicle sends none (service.visual_odometry: the stereo frames and the IMU),
        whose own depth points then serve."""
        self.model = model
        self.loop = loop
        self.T_body_cam = np.eye(4) if T_body_cam is None else T_body_cam
        self.pipeline: FramePipeline = pipeline or NullPipeline()
        self.params = params or FrontEndParams()
        self.visual = visual
        self.stereo_depth = StereoDepth.configured(self.params.depth, self.pipeline.disparity) \
            if not isinstance(self.pipeline, NullPipeline) else None  # stereo depth comes with the chain
        self._imu: list[pb.Imu] = []  # the IMU's samples since the last stereo frame, for the visual odometry
        self.places = KeyframePlaces(None, keep_views=True, config=self.params.place)  # `fresh_or_restored`'s
        self.sightings: list[Sighting] = []  # the last stereo frame's perceived doors and windows, body frame
        self._stereo_frames = 0  # stereo frames taken, for the cadence
        self._odometry = OdometryBuffer()  # stamp_ns -> T_odom_body
        self._pending: list[_Pending] = []  # sightings that arrived before the odometry of their stamp
        self.unmatched = 0  # sightings dropped: no odometry near their stamp
        self.keyframe_updates, self.keyframe_update_ms_total = 0, 0.0  # the pose graph's updates at keyframes
        self.restored: SavedMap | None = None  # the saved map this run started from (service.saved_map)

    @classmethod
    def fresh_or_restored(cls, model: BuildingModel, snapshot: pb.MapSnapshot | SavedMap | None,
                          cfg: MacrolocConfig | None = None,
                          surfaces: SurfaceIndex | None = None, pipeline: FramePipeline | None = None,
                          T_body_cam: np.ndarray | None = None) -> FrontEnd:
        """The front end on a localizer loop from the config (service.localizer_loop.loop_from_config; the defaults,
        with the environment's MACROLOC_* over them, without one), with covariance; `surfaces`: the model's walls, to
        check registrations against the frames' depth (graph.surfaces)."""
        cfg = cfg or MacrolocConfig()
        chain = cfg.perception.to_params()
        params = FrontEndParams.configured(cfg)
        shared = pipeline.disparity if pipeline is not None else None
        visual = VisualOdometry(shared, chain) if cfg.service.odometry == "visual" else None  # type: ignore[arg-type]

        def front_end(loop: LocalizerLoop) -> FrontEnd:
            return cls(model, loop, T_body_cam, pipeline, params, visual)

        if snapshot is None:
            return front_end(loop_from_config(cfg, model, surfaces=surfaces, covariance=True))
        saved = snapshot if isinstance(snapshot, SavedMap) else SavedMap.from_snapshot(snapshot, model)
        restored = front_end(loop_from_config(cfg, model, saved=saved, surfaces=surfaces, covariance=True))
        restored.restored = saved
        restored.places = KeyframePlaces(saved, keep_views=True, config=params.place)
        return restored

    # --- inputs -------------------------------------------------------------------------------------------------

    def imu(self, ev: ImuIn) -> None:
        """A specific force sample, to the localizer loop: with the next odometry sample it gives up in the body frame;
        kept for the visual odometry's next frame where it runs."""
        self.loop.imu(np.asarray(ev.accel_mps2, float))
        if self.visual is not None:
            imu = pb.Imu(accel_mps2=vector3(ev.accel_mps2), gyro_radps=vector3(ev.gyro_radps))
            imu.header.stamp_ns = ev.stamp_ns
            self._imu.append(imu)

    def odometry(self, ev: OdometryIn) -> Estimate:
        """An odometry sample: to the localizer loop (gravity's up), then the sightings that waited for it, then its own
        frame (no sightings)."""
        self._odometry_pose(ev.stamp_ns, ev.T_map_body)
        return self.loop.frame(FrameIn(ev.stamp_ns, ev.T_map_body, []))

    def _odometry_pose(self, stamp_ns: int, T_odom_body: np.ndarray) -> None:
        """An odometry pose (the vehicle's, or the visual odometry's of a stereo frame): to the loop (gravity's
        up) and the buffer, then the sightings that waited for it, each a frame at its own stamp."""
        self.loop.odometry(stamp_ns, T_odom_body)
        self._odometry.add(stamp_ns, T_odom_body)
        if self._pending:  # sightings waiting for this odometry (keys arrive through separate channels)
            pending, self._pending = self._pending, []
            for p in pending:
                T_odom_at = self.odometry_at(p.stamp_ns)
                if T_odom_at is not None:
                    self.loop.frame(FrameIn(p.stamp_ns, T_odom_at, p.to_body(T_odom_at)))
                elif p.stamp_ns < stamp_ns - ODOMETRY_MATCH_NS:
                    self.unmatched += 1
                else:
                    self._pending.append(p)

    def new_time_base(self) -> None:
        """The vehicle's clock was reset: forget what is kept by stamp (the odometry buffer, sightings waiting
        for their odometry, the keyframe timer); the graph, its landmarks and T_cad_map stay."""
        self._odometry.clear()
        self._pending.clear()
        self.loop.new_time_base()  # with gravity's history: it differentiates the odometry over stamps

    def depth(self, stamp_ns: int, points_body: np.ndarray) -> None:
        """Depth points (N, 3, body frame) measured at stamp_ns: given to the next keyframe, for the surface check
        of registrations (graph.surfaces). Without odometry at that stamp they are dropped."""
        T_odom_body = self.odometry_at(stamp_ns)
        if T_odom_body is not None:
            self.loop.add_depth(T_odom_body, points_body)

    def observations(self, ev: ObservationsIn) -> Estimate | None:
        """Sightings from the wire (body, left-camera or odometry frame): a frame at the odometry pose of their
        stamp; None (kept pending until the odometry of that stamp arrives, else counted in `unmatched`) without
        such a pose."""
        def to_body(T_odom_body: np.ndarray) -> list[Sighting]:
            return [self._to_body(o, ev.frame_id, T_odom_body) for o in ev.features if o.corners is not None]

        return self._sightings_frame(ev.stamp_ns, to_body)

    def stereo(self, ev: StereoIn) -> Estimate | None:
        """A stereo frame (see module doc), its images decoded once, where the work needs them: its odometry where
        the visual odometry runs, perceived where the cadence says, its depth points and place, then a frame of the
        localizer loop at the odometry pose of its stamp. Without that pose, its sightings wait for it (its depth and
        place are dropped) and the answer is the pose tracked at the last estimate's (None before any).
        `sightings` holds what it perceived."""
        frame, stamp_ns = ev.frame, ev.stamp_ns
        flight_frame = FlightFrame(stamp_ns, frame, imu=self._imu)  # its `images()` decode the pair once
        self._imu = []
        measurable, T_body_cam = calibrated(frame), stereo_T_body_cam(frame)
        points_body: np.ndarray | None = None
        measure_depth: Callable[[], np.ndarray] | None = None
        dead_reckoned_s = 0.0
        if self.visual is not None and measurable:  # its pose first: gravity's up comes with it
            self._odometry_pose(stamp_ns, self.visual(flight_frame, *flight_frame.images()))
            v = self.visual
            points_body, measure_depth, dead_reckoned_s = v.points_body, v.measure_depth, v.dead_reckoned_s
        elif self.stereo_depth is not None and measurable:
            (left, right), rig = flight_frame.images(), stereo_rig(frame)
            points_body = self.stereo_depth(left, right, rig, T_body_cam)
            measure_depth = self.stereo_depth.deferred(left, right, rig, T_body_cam)
        due = self._stereo_frames % self.params.perceive_every == 0
        self._stereo_frames += 1
        up_body = self.up_body  # the loop's, from the IMU: which way is down for the chain
        self.sightings = self.pipeline(frame, up_body, flight_frame.images) if due else []
        if frame.HasField("depth") and self.localizer.surfaces is not None:  # the vehicle's depth image
            d = self.params.depth
            points_body, measure_depth = depth_points_body(frame, d.depth_image_stride_px, d.max_range_m), None
        T_odom_body = self.odometry_at(stamp_ns)
        if T_odom_body is None:
            if self.sightings:
                sightings = self.sightings
                self._sightings_frame(stamp_ns, lambda _: sightings)
            return None if self.last is None else self.loop.pose_at(stamp_ns, self.last.T_map_body)
        placed = self._place(flight_frame, T_odom_body, T_body_cam, up_body)
        return self.loop.frame(FrameIn(stamp_ns, T_odom_body, self.sightings, points_body=points_body,
                                          dead_reckoned_s=dead_reckoned_s, placed=placed,
                                          measure_depth=measure_depth))

    def _place(self, frame: FlightFrame, T_odom_body: np.ndarray, T_body_cam: np.ndarray,
               up_body: np.ndarray | None) -> Placed | None:
        """Place recognition on the frame (service.places): its pose in the saved map while not localized, its view
        to keep for the next one; None where neither applies (no calibration, or nothing due)."""
        placed = self.places.at_frame(frame, T_odom_body, T_body_cam, up_body, self.status)
        return placed if placed.T_cad_body is not None or placed.view is not None else None

    def handle(self, event: object) -> Estimate | None:
        """One input event of the vehicle (module doc), in the order sent: its estimate, where it gives one."""
        if isinstance(event, ImuIn):
            self.imu(event)
            return None
        if isinstance(event, ClockReset):
            self.new_time_base()
            return None
        if isinstance(event, PriorIn):
            self.prior(event)
            return None
        answer = self._estimate(event)
        if answer is not None and self.loop.keyframe:
            self.keyframe_updates += 1
            self.keyframe_update_ms_total += answer.update_ms
        return answer

    def _estimate(self, event: object) -> Estimate | None:
        if isinstance(event, StereoIn):
            return self.stereo(event)
        if isinstance(event, OdometryIn):
            return self.odometry(event)
        if isinstance(event, ObservationsIn):
            return self.observations(event)
        raise TypeError(f"not an input event of the front end: {type(event).__name__}")

    def _sightings_frame(self, stamp_ns: int, to_body: Callable[[np.ndarray], list[Sighting]]) -> Estimate | None:
        T_odom_body = self.odometry_at(stamp_ns)
        if T_odom_body is None:
            self._pending.append(_Pending(stamp_ns, to_body))
            if len(self._pending) > 64:
                self._pending.pop(0)
                self.unmatched += 1
            return None
        return self.loop.frame(FrameIn(stamp_ns, T_odom_body, to_body(T_odom_body)))

    def prior(self, ev: PriorIn) -> str | None:
        """The operator's prior (graph.prior) to the localizer: a pose becomes T_cad_map = T_cad_body times the inverse
        of the odometry's T_map_body at its stamp (the newest where there is none at it: an operator's prior is
        coarse); a storey, its band of heights. Returns why it was refused (a drop kind), else None."""
        band = None
        if ev.storey is not None:
            if ev.storey not in self.model.storey_elevations_m:
                return "initialpose/unknown_storey"
            band = storey_band_m(self.model, ev.storey)
        T_cad_map = None
        if ev.T_cad_body is not None:
            T_odom_body = self._odometry.at(ev.stamp_ns, newest_if_later=True) if ev.stamp_ns else None
            if T_odom_body is None:
                T_odom_body = self._odometry.at(np.iinfo(np.int64).max, newest_if_later=True)
            if T_odom_body is None:
                return "initialpose/no_odometry"
            T_cad_map = ev.T_cad_body @ np.linalg.inv(T_odom_body)
        prior = PosePrior(T_cad_map, ev.sigma_xy_m, ev.sigma_yaw_rad, ev.storey, band)
        self.loop.localizer.set_prior(prior)
        log.info("operator's prior: %s (%s)", prior.describe(), self.status)
        return None

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """The buffered odometry pose nearest in time to stamp_ns (within 60 ms), else None (also where stamp_ns is
        newer than all: wait for it)."""
        return self._odometry.at(stamp_ns)

    def _to_body(self, obs: Observation, frame_id: str, T_odom_body: np.ndarray) -> Sighting:
        assert obs.corners is not None
        T_body_x = {"body": np.eye(4), "cam_left": self.T_body_cam, "map": np.linalg.inv(T_odom_body)}[frame_id]
        corners_body = obs.corners @ T_body_x[:3, :3].T + T_body_x[:3, 3]
        return Sighting(obs.type, corners_body, obs.id or None)

    # --- outputs ------------------------------------------------------------------------------------------------

    @property
    def localizer(self) -> Localizer:
        return self.loop.localizer

    @property
    def last(self) -> Estimate | None:
        """The newest estimate (a late keyframe for an older stamp does not replace a newer pose)."""
        return self.loop.last

    @property
    def isam_update_ms_mean(self) -> float:
        """The mean time of the pose graph's update at a keyframe so far, ms (0 before the first)."""
        return self.keyframe_update_ms_total / self.keyframe_updates if self.keyframe_updates else 0.0

    @property
    def graph_restarts(self) -> int:
        """Times the pose graph failed (indeterminate, non-finite) and started afresh."""
        return self.loop.restarts

    @property
    def status(self) -> str:
        return self.localizer.status

    def rival_poses(self) -> list[np.ndarray]:
        """T_cad_body (4x4) of each rival pose the last 'ambiguous' registration left apart (graph.anchoring's
        rivals, T_cad_map, at the newest estimate's T_map_body); none while not ambiguous or before any estimate."""
        last = self.last
        if last is None:
            return []
        return [T_cad_map @ last.T_map_body for T_cad_map in self.localizer.anchoring.rivals]

    @property
    def up_body(self) -> np.ndarray | None:
        """Gravity's up in the body frame at the newest odometry sample (the loop's), when known."""
        return self.loop.up_body

    def snapshot(self, building: str, sha256: str) -> pb.MapSnapshot:
        """The map as saved and served (service.saved_map.map_snapshot)."""
        return map_snapshot(self.localizer, self.last, self.restored, building, sha256)

    def supersedes_saved(self) -> bool:
        """Whether this run's map should replace the saved one it was restarted from (service.saved_map)."""
        return supersedes(self.localizer, self.restored)

    def saved_views(self) -> list[PlacedView]:
        """The keyframe views its saved map keeps, (T_map_body, view) (service.saved_map)."""
        return saved_views(self.localizer, self.restored)


def make_front_end(cfg: MacrolocConfig, model: BuildingModel, surfaces: SurfaceIndex | None,
                   snapshot: pb.MapSnapshot | SavedMap | None = None) -> FrontEnd:
    """THE factory of the per-frame path, the one `serve` and `replay` build: the localizer loop from the config, with
    covariance (service.localizer_loop.loop_from_config), restored from a saved map where given, the perception chain
    where [service] perception asks for it (service.frames.configured_pipeline), [perception] detect_every's
    cadence; `surfaces`: the model's walls ([graph] surface_check), None without."""
    return FrontEnd.fresh_or_restored(model, snapshot, cfg, surfaces, configured_pipeline(cfg))


def plausible(est: Estimate, limits: InputLimits) -> bool:
    """True when the estimate may be published as it is: no CAD pose, or a finite T_cad_body whose position lies
    within the model's bounds plus margin (`limits.inside_cad`), with a finite T_cad_map and covariance."""
    T = est.T_cad_body
    if T is None:
        return True
    finite = np.isfinite(T).all() and (est.T_cad_map is None or np.isfinite(est.T_cad_map).all()) and \
        (est.covariance is None or np.isfinite(est.covariance).all())
    return bool(finite) and limits.inside_cad(T[:3, 3])


def pose_message(est: Estimate, storey: str = "", geo: GeoReference | None = None) -> pb.PoseEstimate:
    """A PoseEstimate (frame cad; before localization T_cad_body is absent and status EXPLORING); with the model's
    geo-reference, also the body in ENU at the site's origin and its latitude/longitude/altitude (WGS84)."""
    msg = pb.PoseEstimate(status=STATUS_TO_WIRE[est.status], storey=storey, inliers=est.inliers)
    msg.header.stamp_ns = est.stamp_ns
    msg.header.frame_id = "cad"
    if est.T_cad_body is not None:
        msg.T_cad_body.CopyFrom(pose_from_matrix(est.T_cad_body))
        if geo is not None:
            msg.T_enu_body.CopyFrom(pose_from_matrix(geo.T_enu_cad() @ est.T_cad_body))
            lat, lon, alt = geo.wgs84(est.T_cad_body[:3, 3])[0]
            msg.wgs84.CopyFrom(pb.GeoPoint(latitude_deg=lat, longitude_deg=lon, altitude_m=alt))
    if est.T_cad_map is not None:
        msg.T_cad_map.CopyFrom(pose_from_matrix(est.T_cad_map))
    if est.covariance is not None:
        msg.covariance.extend(np.asarray(est.covariance, float).ravel().tolist())
    return msg
