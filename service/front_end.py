"""The one per-frame front end of `serve` and `replay` (kiss-icp's `register_frame`): the vehicle's input events
in, `graph.localizer.Estimate` out. The service's worker hands it every event it takes (service.node), and the
offline replay hands it the same events made from a recording (service.offline.replay), so that a replay runs the
path the service runs.

`FrontEnd.handle(event)` takes the typed events of service.inputs, in the order the vehicle sent them:
- `ImuIn`: a specific force sample, to the session (gravity's up with the next odometry pose: perception.gravity).
- `OdometryIn`: the vehicle's odometry pose: buffered by stamp, to the session, then the sightings that waited for
  it, then a frame of its own (no sightings).
- `ObservationsIn`: doors/windows sent by the vehicle (body, left-camera or odometry frame): a frame at the
  odometry pose of their stamp, kept pending until that pose arrives.
- `StereoIn`: a stereo frame, once each: decoded, its camera geometry taken from its CameraInfo, perceived (every
  `perceive_every`-th frame: the cadence, the same in serve and replay), its depth points (the vehicle's depth image
  where the frame carries one and the model's walls are known, else the pipeline's stereo depth, measured when it
  becomes a keyframe), place recognition (service.places), then the session's update at the odometry pose of its
  stamp.
- `PriorIn` (the operator's prior, graph.prior) and `ClockReset` (the vehicle's clock restarted).

Frames: odom = the vehicle's odometry frame (the localizer's map frame), body, cam_left, cad. Metres.

Restarting from a saved map (`MapSnapshot`): where it holds keyframe views and was localized, the stereo frames
are placed in them by place recognition (`restored`, service.places) from the first frame on, before any door is
seen. Otherwise `RestoredRegistrar` first checks the saved T_cad_map against the first sightings (the vehicle's
odometry usually outlives a service restart), then falls back to the landmarks the previous run linked to the
model (`StoredMapRegistrar`), then to the whole model.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.graph.features import BuildingModel
from macroloc.graph.geo import GeoReference
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.localizer import Estimate, Localizer, LocalizerParams, Sighting, model_registrar, stored_registrar
from macroloc.graph.mapstore import KeyframeView, StoredMap, carried_views
from macroloc.graph.registrar import FirstOfRegistrar, Registrar
from macroloc.graph.relocalize import Alignment, KnownRect, ObservedRect
from macroloc.graph.surfaces import SurfaceIndex
from macroloc.perception.params import DepthPointsParams, PlaceParams
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose, pose_from_matrix, vector3
from macroloc.service.frame_answers import ODOMETRY_MATCH_NS, OdometryBuffer
from macroloc.service.frames import FramePipeline, NullPipeline, depth_points_body
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
from macroloc.service.places import KeyframePlaces, Placed
from macroloc.service.session import FrameIn, LocalizationSession, SessionSettings, session_from_config
from macroloc.service.state import view_from_wire

if TYPE_CHECKING:
    from macroloc.service.config import MacrolocConfig

log = logging.getLogger(__name__)

STATUS_TO_WIRE = {"exploring": pb.PoseEstimate.EXPLORING, "localized": pb.PoseEstimate.LOCALIZED,
                  "ambiguous": pb.PoseEstimate.AMBIGUOUS, "degraded": pb.PoseEstimate.DEGRADED,
                  "lost": pb.PoseEstimate.LOST}
WIRE_TO_STATUS = {v: k for k, v in STATUS_TO_WIRE.items()}


class RestoredRegistrar:
    """Re-localization after a restart: saved T_cad_map, then the saved CAD-linked landmarks, then the model."""

    min_landmarks = 1
    candidates_from = 1

    def __init__(self, model: BuildingModel, T_cad_map_saved: np.ndarray | None, linked: list[KnownRect],
                 fallback: Registrar, agree_m: float = 0.4, params: LocalizerParams | None = None,
                 with_surfaces: bool = False) -> None:
        self.T_cad_map_saved = T_cad_map_saved
        stored = stored_registrar(model, linked, (params or LocalizerParams()).registration, with_surfaces) \
            if linked else None
        # the saved landmarks' few poses first (checked by the walls), the whole model's where they fail
        self.chain: Registrar = FirstOfRegistrar([stored, fallback]) if stored is not None else fallback
        self.agree_m = agree_m
        self._known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features
                       if f.orientation == "vertical"]
        self._known_xyz = np.array([k.T_cad_rect[:3, 3] for k in self._known]).reshape(-1, 3)

    def __call__(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        if self.T_cad_map_saved is not None:
            matches = self._agreeing(landmarks)
            if len(matches) >= max(1, int(np.ceil(0.6 * len(landmarks)))):
                saved = Alignment("localized", self.T_cad_map_saved, matches, len(matches))
                saved.fallback = lambda: self._registered(landmarks, corners_map)  # where the walls refuse it
                return saved
        return self._registered(landmarks, corners_map)

    def _registered(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        if len(landmarks) >= self.chain.candidates_from:
            return self.chain(landmarks, corners_map)
        return Alignment("not_localized", None)

    def _agreeing(self, landmarks: list[ObservedRect]) -> list[tuple[int, str]]:
        assert self.T_cad_map_saved is not None
        matches = []
        for lm in landmarks:
            xyz_cad = (self.T_cad_map_saved @ lm.T_map_rect)[:3, 3]
            d = np.linalg.norm(self._known_xyz - xyz_cad, axis=1)
            for k in np.argsort(d)[:3]:
                if d[k] < self.agree_m and self._known[k].type == lm.type:
                    matches.append((lm.key, self._known[k].id))
                    break
        return matches


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


class FrontEnd:
    """See module doc: the vehicle's events into frames of its `LocalizationSession` (service.session): odometry by
    stamp, sightings waiting for the odometry of their stamp, stereo frames perceived; the IMU and each odometry
    sample go to the session as they come (it estimates gravity's up). One thread only (the service's worker, the
    replay's loop)."""

    def __init__(self, model: BuildingModel, session: LocalizationSession,
                 T_body_cam: np.ndarray | None = None, pipeline: FramePipeline | None = None,
                 params: FrontEndParams | None = None) -> None:
        """`T_body_cam`: the left camera in the body frame, for sightings sent in the cam_left frame and stereo
        frames whose CameraInfo carries none; `pipeline`: the perception chain on stereo frames (none: frames give
        a pose from the odometry only, sightings come as observations)."""
        self.model = model
        self.session = session
        self.T_body_cam = np.eye(4) if T_body_cam is None else T_body_cam
        self.pipeline: FramePipeline = pipeline or NullPipeline()
        self.params = params or FrontEndParams()
        self.places = KeyframePlaces(None, keep_views=True, config=self.params.place)  # a saved map's: `fresh_or_restored`
        self.sightings: list[Sighting] = []  # the last stereo frame's perceived doors and windows, body frame
        self._stereo_frames = 0  # stereo frames taken, for the cadence
        self._odometry = OdometryBuffer()  # stamp_ns -> T_odom_body
        self._pending: list[_Pending] = []  # sightings that arrived before the odometry of their stamp
        self.unmatched = 0  # sightings dropped: no odometry near their stamp
        self.restored: StoredMap | None = None  # a saved map's keyframe views and T_cad_map, for place recognition
        self.restored_localized = False  # restarted from a saved map that was localized (see `supersedes_saved`)
        self.carried: list[CarriedLandmark] = []  # a saved map's landmarks, CAD frame, kept in the next saved map

    @classmethod
    def fresh_or_restored(cls, model: BuildingModel, snapshot: pb.MapSnapshot | None,
                          cfg: MacrolocConfig | None = None,
                          surfaces: SurfaceIndex | None = None, pipeline: FramePipeline | None = None,
                          T_body_cam: np.ndarray | None = None) -> FrontEnd:
        """The backend on a session from the config (service.session.session_from_config; the defaults, with the
        environment's MACROLOC_* over them, without one), with covariance; `surfaces`: the model's walls, to check
        registrations against the frames' depth (graph.surfaces)."""
        from macroloc.service.config import MacrolocConfig

        cfg = cfg or MacrolocConfig()
        chain = cfg.perception.to_params()
        params = FrontEndParams(cfg.perception.detect_every, chain.depth, chain.place)

        def front_end(session: LocalizationSession) -> FrontEnd:
            return cls(model, session, T_body_cam, pipeline, params)

        if snapshot is None:
            return front_end(session_from_config(cfg, model, surfaces=surfaces, covariance=True))
        features = {f.id: f for f in model.features}
        linked = [KnownRect(lm.id, features[lm.id].type, feature_frame_cad(features[lm.id]))
                  for lm in snapshot.landmarks_map if lm.id in features and features[lm.id].orientation == "vertical"]
        saved_T = matrix_from_pose(snapshot.T_cad_map) if snapshot.status == pb.PoseEstimate.LOCALIZED else None
        log.info("restoring a saved map: %d linked landmarks, %d keyframe views, T_cad_map %s", len(linked),
                 len(snapshot.views), "saved" if saved_T is not None else "absent")

        def restored(s: SessionSettings) -> Registrar:
            fallback = model_registrar(model, s.localizer.registration, s.storey_hint, surfaces is not None, s.method)
            return RestoredRegistrar(model, saved_T, linked, fallback, params=s.localizer,
                                     with_surfaces=surfaces is not None)

        backend = front_end(session_from_config(cfg, model, surfaces=surfaces, registrar=restored, covariance=True))
        backend.restored_localized = saved_T is not None
        if saved_T is not None and snapshot.views:  # views with their poses, as a map carries an earlier one's
            backend.restored = StoredMap(model.sha256, saved_T, carried=[view_from_wire(v) for v in snapshot.views])
            backend.places = KeyframePlaces(backend.restored, keep_views=True, config=params.place)
        if saved_T is not None:  # in an unlocalized map's frame they cannot be placed: dropped
            backend.carried = [CarriedLandmark(lm.type, lm.id, np.array([[c.x, c.y, c.z] for c in lm.corners])
                                               @ saved_T[:3, :3].T + saved_T[:3, 3])
                               for lm in snapshot.landmarks_map if len(lm.corners) == 4]
        return backend

    # --- inputs -------------------------------------------------------------------------------------------------

    def imu(self, ev: ImuIn) -> None:
        """A specific force sample, to the session: with the next odometry sample it gives up in the body frame."""
        self.session.imu(np.asarray(ev.accel_mps2, float))

    def odometry(self, ev: OdometryIn) -> Estimate:
        """An odometry sample: to the session (gravity's up), then the sightings that waited for it, then its own
        frame (no sightings)."""
        self.session.odometry(ev.stamp_ns, ev.T_map_body)
        self._odometry.add(ev.stamp_ns, ev.T_map_body)
        if self._pending:  # sightings waiting for this odometry (keys arrive through separate channels)
            pending, self._pending = self._pending, []
            for p in pending:
                T_odom_body = self.odometry_at(p.stamp_ns)
                if T_odom_body is not None:
                    self.session.frame(FrameIn(p.stamp_ns, T_odom_body, p.to_body(T_odom_body)))
                elif p.stamp_ns < ev.stamp_ns - ODOMETRY_MATCH_NS:
                    self.unmatched += 1
                else:
                    self._pending.append(p)
        return self.session.frame(FrameIn(ev.stamp_ns, ev.T_map_body, []))

    def new_time_base(self) -> None:
        """The vehicle's clock was reset: forget what is kept by stamp (the odometry buffer, sightings waiting
        for their odometry, the keyframe timer); the graph, its landmarks and T_cad_map stay."""
        self._odometry.clear()
        self._pending.clear()
        self.session.new_time_base()  # with gravity's history: it differentiates the odometry over stamps

    def depth(self, stamp_ns: int, points_body: np.ndarray) -> None:
        """Depth points (N, 3, body frame) measured at stamp_ns: given to the next keyframe, for the surface check
        of registrations (graph.surfaces). Without odometry at that stamp they are dropped."""
        T_odom_body = self.odometry_at(stamp_ns)
        if T_odom_body is not None:
            self.session.add_depth(T_odom_body, points_body)

    def observations(self, ev: ObservationsIn) -> Estimate | None:
        """Sightings from the wire (body, left-camera or odometry frame): a frame at the odometry pose of their
        stamp; None (kept pending until the odometry of that stamp arrives, else counted in `unmatched`) without
        such a pose."""
        def to_body(T_odom_body: np.ndarray) -> list[Sighting]:
            return [self._to_body(o, ev.frame_id, T_odom_body) for o in ev.features if o.corners is not None]

        return self._sightings_frame(ev.stamp_ns, to_body)

    def stereo(self, ev: StereoIn) -> Estimate | None:
        """A stereo frame (see module doc): perceived where the cadence says, its depth points and place, then a
        frame of the session at the odometry pose of its stamp. Without that pose, its sightings wait for it (its
        depth and place are dropped) and the answer is the pose tracked at the last estimate's (None before
        any). `sightings` holds what it perceived."""
        frame, stamp_ns = ev.frame, ev.stamp_ns
        due = self._stereo_frames % self.params.perceive_every == 0
        self._stereo_frames += 1
        up_body = self.up_body  # the session's, from the IMU: which way is down for the chain
        self.sightings = self.pipeline(frame, up_body) if due else []
        points_body = self.pipeline.points_body if due else None  # the chain's own stereo depth, when it measured
        measure_depth = self.pipeline.measure_depth if due else None  # ... or will for a keyframe
        T_odom_body = self.odometry_at(stamp_ns)
        if frame.HasField("depth") and self.localizer.surfaces is not None:  # the vehicle's depth image
            d = self.params.depth
            points_body, measure_depth = depth_points_body(frame, d.depth_image_stride_px, d.max_range_m), None
        if T_odom_body is None:
            if self.sightings:
                sightings = self.sightings
                self._sightings_frame(stamp_ns, lambda _: sightings)
            return None if self.last is None else self.session.pose_at(stamp_ns, self.last.T_map_body)
        placed = self._place(frame, stamp_ns, T_odom_body, up_body)
        return self.session.frame(FrameIn(stamp_ns, T_odom_body, self.sightings, points_body=points_body,
                                          placed=placed, measure_depth=measure_depth))

    def _place(self, frame: pb.StereoFrame, stamp_ns: int, T_odom_body: np.ndarray,
               up_body: np.ndarray | None) -> Placed | None:
        """Place recognition on the frame (service.places): its pose in the saved map while not localized, its view
        to keep for the next one; None where neither applies (no calibration, or nothing due)."""
        info = frame.info
        T_body_cam = matrix_from_pose(info.T_body_cam) if info.HasField("T_body_cam") else forward_stereo_T_body_cam()
        placed = self.places.at_frame(frame, stamp_ns, T_odom_body, T_body_cam, up_body, self.status)
        return placed if placed.T_cad_body is not None or placed.view is not None else None

    def handle(self, event: object) -> Estimate | None:
        """One input event of the vehicle (module doc), in the order sent: its estimate, where it gives one."""
        if isinstance(event, StereoIn):
            return self.stereo(event)
        if isinstance(event, OdometryIn):
            return self.odometry(event)
        if isinstance(event, ObservationsIn):
            return self.observations(event)
        if isinstance(event, ImuIn):
            self.imu(event)
        elif isinstance(event, ClockReset):
            self.new_time_base()
        elif isinstance(event, PriorIn):
            self.prior(event)
        else:
            raise TypeError(f"not an input event of the front end: {type(event).__name__}")
        return None

    def _sightings_frame(self, stamp_ns: int, to_body: Callable[[np.ndarray], list[Sighting]]) -> Estimate | None:
        T_odom_body = self.odometry_at(stamp_ns)
        if T_odom_body is None:
            self._pending.append(_Pending(stamp_ns, to_body))
            if len(self._pending) > 64:
                self._pending.pop(0)
                self.unmatched += 1
            return None
        return self.session.frame(FrameIn(stamp_ns, T_odom_body, to_body(T_odom_body)))

    def prior(self, ev: PriorIn) -> str | None:
        """The operator's prior (graph.prior) to the localizer: a pose becomes T_cad_map = T_cad_body times the inverse
        of the odometry's T_map_body at its stamp (the newest where there is none at it: an operator's prior is
        coarse); a storey, its band of heights. Returns why it was refused (a drop kind), else None."""
        from macroloc.graph.prior import PosePrior, storey_band_m

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
        self.session.localizer.set_prior(prior)
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
        return self.session.localizer

    @property
    def last(self) -> Estimate | None:
        """The newest estimate (a late keyframe for an older stamp does not replace a newer pose)."""
        return self.session.last

    @property
    def graph_restarts(self) -> int:
        """Times the pose graph failed (indeterminate, non-finite) and started afresh."""
        return self.session.restarts

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
        """Gravity's up in the body frame at the newest odometry sample (the session's), when known."""
        return self.session.up_body

    def snapshot(self, building: str, sha256: str) -> pb.MapSnapshot:
        """The map as saved and served: landmarks (odom frame) with their CAD links, T_cad_map, last pose (the
        saved state adds `saved_views`)."""
        loc = self.localizer
        snap = pb.MapSnapshot(building=building, building_sha256=sha256, status=STATUS_TO_WIRE[loc.status],
                              keyframes=loc.graph.n_keyframes)
        snap.header.frame_id = "map"
        T_cad_map = loc.graph.T_cad_map()
        if T_cad_map is not None:
            snap.T_cad_map.CopyFrom(pose_from_matrix(T_cad_map))
        if self.last is not None:
            snap.header.stamp_ns = self.last.stamp_ns
            snap.T_map_body.CopyFrom(pose_from_matrix(self.last.T_map_body))
            snap.storey = _storey_of(self.model, self.last.matches)
        own = []
        for j, lm in loc.landmarks.items():
            f = snap.landmarks_map.add(type=lm.type, id=loc.links.get(j, ""))
            corners = lm.corners(loc.graph.T_map_rect(j))
            f.corners.extend(vector3(c) for c in corners)
            own.append((lm.type, f.id, np.asarray(corners).mean(axis=0)))
        if T_cad_map is not None:
            for kind, feature_id, corners_map in carried_landmarks(self.carried, own, np.linalg.inv(T_cad_map)):
                snap.landmarks_map.add(type=kind, id=feature_id).corners.extend(vector3(c) for c in corners_map)
        return snap

    def supersedes_saved(self) -> bool:
        """Whether this run's map should replace the saved one it was restarted from: not before this run is
        localized, where that one was (a restart that is stopped before it finds itself would otherwise lose
        the saved map, its links to the model and its views)."""
        return not self.restored_localized or self.localizer.graph.has_anchor

    def saved_views(self) -> list[tuple[np.ndarray, KeyframeView]]:
        """The keyframe views a saved map keeps for place recognition, (T_map_body, view): this run's, and the
        restored map's where this run has none near, in this run's map frame, once it is localized."""
        loc = self.localizer
        own = [(loc.graph.T_map_body(i), v) for i, v in sorted(loc.views.items())]
        T_cad_map = loc.graph.T_cad_map()
        if self.restored is not None and T_cad_map is not None:  # what a later restart can be placed by
            return own + carried_views(own, T_cad_map, self.restored)
        return own


@dataclass(frozen=True)
class CarriedLandmark:
    """A landmark of an earlier flight's saved map: type, linked CAD feature id ("" if none), corners (4, 3)."""

    type: str
    id: str
    corners_cad: np.ndarray


SAME_LANDMARK_M = 0.5  # two doors or windows of one building are a frame width apart at least (> 0.6 m)


def carried_landmarks(carried: list[CarriedLandmark], own: list[tuple[str, str, np.ndarray]],
                      T_map_cad: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """The earlier map's landmarks this flight has not seen, as (type, id, corners_map (4, 3)) in this flight's map
    frame: one linked to a CAD feature this flight also links, or of the same type with its
    centroid within SAME_LANDMARK_M of one of this flight's (`own`: type, id, centroid_map), is the same one."""
    out = []
    own_ids = {i for _, i, _ in own if i}
    for lm in carried:
        corners_map = lm.corners_cad @ T_map_cad[:3, :3].T + T_map_cad[:3, 3]
        centroid = corners_map.mean(axis=0)
        if (lm.id and lm.id in own_ids) or any(t == lm.type and np.linalg.norm(c - centroid) < SAME_LANDMARK_M
                                               for t, _, c in own):
            continue
        out.append((lm.type, lm.id, corners_map))
    return out


def _storey_of(model: BuildingModel, matches: dict[int, str]) -> str:
    storeys = {f.id: f.storey for f in model.features}
    names = [str(storeys[fid]) for fid in matches.values() if storeys.get(fid)]
    return max(set(names), key=names.count) if names else ""


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
