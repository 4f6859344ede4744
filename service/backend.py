"""The service's localization backend: wire events in, `graph.localizer.Estimate` out, map snapshots.

`LocalizerBackend` feeds the pose-graph localizer (`graph.localizer.Localizer`): odometry poses are buffered by
stamp; a set of sightings (ObservedFeatures in the body, left-camera or odometry frame, or sightings made by
the perception pipeline from a stereo frame) becomes a keyframe at the odometry pose of its stamp; any other
odometry sample only moves the last estimate (`track`). The IMU's specific force, less the odometry's own
acceleration, gives "up" in the body frame (perception.gravity).

Frames: odom = the vehicle's odometry frame (the localizer's map frame), body, cam_left, cad. Metres.

Restarting from a saved map (`MapSnapshot`): where it holds keyframe views and was localized, the service's
stereo frames are placed in them by place recognition (`restored`, service.places, in service.node) from the
first frame on, before any door is seen. Otherwise `RestoredRegistrar` first checks the saved T_cad_map against
the first sightings (the vehicle's odometry usually outlives a service restart), then falls back to the landmarks
the previous run linked to the model (`StoredMapRegistrar`), then to the whole model.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.geo import GeoReference
from macroloc.graph.keyframes import KeyframePolicy
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.localizer import Estimate, Localizer, LocalizerParams, Sighting, model_registrar, stored_registrar
from macroloc.graph.mapstore import KeyframeView, StoredMap, carried_views
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import FirstOfRegistrar, Registrar
from macroloc.graph.relocalize import Alignment, KnownRect, ObservedRect
from macroloc.graph.surfaces import SurfaceIndex
from macroloc.perception.gravity import GravityEstimator
from macroloc.service.inputs import ImuIn, InputLimits, Observation, ObservationsIn, OdometryIn
from macroloc.service.places import Placed
from macroloc.service.recording import matrix_from_pose, pose_from_matrix, vector3
from macroloc.service.state import view_from_wire
from macroloc.service.wire.macroloc.v1 import macroloc_pb2 as pb

log = logging.getLogger(__name__)

STATUS_TO_WIRE = {"exploring": pb.PoseEstimate.EXPLORING, "localized": pb.PoseEstimate.LOCALIZED,
                  "ambiguous": pb.PoseEstimate.AMBIGUOUS, "degraded": pb.PoseEstimate.DEGRADED,
                  "lost": pb.PoseEstimate.LOST}
WIRE_TO_STATUS = {v: k for k, v in STATUS_TO_WIRE.items()}
ODOMETRY_MATCH_NS = 60_000_000  # sightings use the odometry sample within 60 ms of their stamp


class RestoredRegistrar:
    """Re-localization after a restart: saved T_cad_map, then the saved CAD-linked landmarks, then the model."""

    min_landmarks = 1
    candidates_from = 1

    def __init__(self, model: BuildingModel, T_cad_map_saved: np.ndarray | None, linked: list[KnownRect],
                 fallback: Registrar, agree_m: float = 0.4, params: LocalizerParams | None = None,
                 with_surfaces: bool = False) -> None:
        self.T_cad_map_saved = T_cad_map_saved
        stored = stored_registrar(model, linked, params or LocalizerParams(), with_surfaces) if linked else None
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


@dataclass
class BackendParams:
    odometry_keyframe_m: float = 1.0  # an odometry-only keyframe after this much motion without sightings
    keyframe_min_translation_m: float = 0.25  # sightings make a keyframe after this much motion,
    keyframe_min_rotation_rad: float = 0.15  # or this much turn,
    keyframe_max_interval_s: float = 2.0  # or this long; else they are skipped (a hovering vehicle adds nothing)
    localizer: LocalizerParams | None = None
    storey_hint: str | None = None  # register against this storey's doors and windows only (graph.storey_hint)
    covariance: bool = True  # each keyframe's marginal covariance (iSAM2), carried by the poses until the next


class LocalizerBackend:
    """Turns input events into localizer calls; one thread only (the service's worker)."""

    def __init__(self, model: BuildingModel, registrar: Registrar, params: BackendParams | None = None,
                 T_body_cam: np.ndarray | None = None, surfaces: SurfaceIndex | None = None) -> None:
        self.model = model
        self.params = params or BackendParams()
        self.localizer = Localizer(model, PoseGraph(), registrar, self.params.localizer, T_body_cam, surfaces)
        self.T_body_cam = np.eye(4) if T_body_cam is None else T_body_cam
        self._odometry: OrderedDict[int, np.ndarray] = OrderedDict()  # stamp_ns -> T_odom_body
        self._pending: list[ObservationsIn] = []  # sightings that arrived before the odometry of their stamp
        self.unmatched = 0  # sightings dropped: no odometry near their stamp
        self._up_body: np.ndarray | None = None
        self._gravity = GravityEstimator()
        self._accel_body: list[np.ndarray] = []  # specific forces since the last odometry sample
        self._last_keyframe_ns: int | None = None
        self._T_last_keyframe: np.ndarray | None = None
        self._keyframe_covariance: np.ndarray | None = None  # 6x6 [rot; trans], body tangent (graph.posegraph)
        p = self.params
        self._keyframe_policy = KeyframePolicy(p.keyframe_min_translation_m, p.keyframe_min_rotation_rad,
                                               p.keyframe_max_interval_s)
        self.last: Estimate | None = None
        self.restored: StoredMap | None = None  # a saved map's keyframe views and T_cad_map, for place recognition
        self.restored_localized = False  # restarted from a saved map that was localized (see `supersedes_saved`)
        self.carried: list[CarriedLandmark] = []  # a saved map's landmarks, CAD frame, kept in the next saved map
        self.graph_restarts = 0  # times the pose graph failed (indeterminate, non-finite) and started afresh

    @classmethod
    def fresh_or_restored(cls, model: BuildingModel, snapshot: pb.MapSnapshot | None, method: str = "robust",
                          params: BackendParams | None = None,
                          surfaces: SurfaceIndex | None = None) -> LocalizerBackend:
        """`surfaces`: the model's walls, to check registrations against the frames' depth (graph.surfaces)."""
        params = params or BackendParams()
        localizer = params.localizer or LocalizerParams()
        fallback = model_registrar(model, localizer, params.storey_hint, surfaces is not None, method)
        if snapshot is None:
            return cls(model, fallback, params, surfaces=surfaces)
        features = {f.id: f for f in model.features}
        linked = [KnownRect(lm.id, features[lm.id].type, feature_frame_cad(features[lm.id]))
                  for lm in snapshot.landmarks_map if lm.id in features and features[lm.id].orientation == "vertical"]
        saved_T = matrix_from_pose(snapshot.T_cad_map) if snapshot.status == pb.PoseEstimate.LOCALIZED else None
        log.info("restoring a saved map: %d linked landmarks, %d keyframe views, T_cad_map %s", len(linked),
                 len(snapshot.views), "saved" if saved_T is not None else "absent")
        backend = cls(model, RestoredRegistrar(model, saved_T, linked, fallback, params=localizer,
                                               with_surfaces=surfaces is not None), params, surfaces=surfaces)
        backend.restored_localized = saved_T is not None
        if saved_T is not None and snapshot.views:  # views with their poses, as a map carries an earlier one's
            backend.restored = StoredMap(model.sha256, saved_T, carried=[view_from_wire(v) for v in snapshot.views])
        if saved_T is not None:  # in an unlocalized map's frame they cannot be placed: dropped
            backend.carried = [CarriedLandmark(lm.type, lm.id, np.array([[c.x, c.y, c.z] for c in lm.corners])
                                               @ saved_T[:3, :3].T + saved_T[:3, 3])
                               for lm in snapshot.landmarks_map if len(lm.corners) == 4]
        return backend

    # --- inputs -------------------------------------------------------------------------------------------------

    def imu(self, ev: ImuIn) -> None:
        """A specific force sample: with the next odometry sample, it gives up in the body frame
        (perception.gravity: the odometry's own acceleration is taken out)."""
        norm = float(np.linalg.norm(ev.accel_mps2))
        if 5.0 < norm < 15.0:  # a knock or a free fall is not gravity
            self._accel_body.append(np.asarray(ev.accel_mps2, float))
            del self._accel_body[:-256]

    def odometry(self, ev: OdometryIn) -> Estimate:
        if self._accel_body:
            up = self._gravity.update(ev.stamp_ns, ev.T_map_body, np.array(self._accel_body))
            self._up_body = up if up is not None else self._up_body
            self._accel_body = []
        self._odometry[ev.stamp_ns] = ev.T_map_body
        while len(self._odometry) > 512:
            self._odometry.popitem(last=False)
        if self._pending:  # sightings waiting for this odometry (keys arrive through separate channels)
            pending, self._pending = self._pending, []
            for obs in pending:
                if self.observations(obs) is None and obs.stamp_ns < ev.stamp_ns - ODOMETRY_MATCH_NS:
                    self._pending.remove(obs)
                    self.unmatched += 1
        due = self._T_last_keyframe is None or float(np.linalg.norm(
            (np.linalg.inv(self._T_last_keyframe) @ ev.T_map_body)[:3, 3])) > self.params.odometry_keyframe_m
        return self._keyframe(ev.stamp_ns, ev.T_map_body, []) if due else self._track(ev.stamp_ns, ev.T_map_body)

    def new_time_base(self) -> None:
        """The vehicle's clock was reset: forget what is kept by stamp (the odometry buffer, sightings waiting
        for their odometry, the keyframe timer); the graph, its landmarks and T_cad_map stay."""
        self._odometry.clear()
        self._pending.clear()
        self._accel_body = []
        self._gravity = GravityEstimator()  # it differentiates the odometry over stamps; up_body is kept
        self._last_keyframe_ns = None

    def depth(self, stamp_ns: int, points_body: np.ndarray) -> None:
        """Depth points (N, 3, body frame) measured at stamp_ns: given to the next keyframe, for the surface check
        of registrations (graph.surfaces). Without odometry at that stamp they are dropped."""
        T_odom_body = self.odometry_at(stamp_ns)
        if T_odom_body is not None and len(points_body):
            self.localizer.add_depth(T_odom_body, points_body)

    def observations(self, ev: ObservationsIn) -> Estimate | None:
        """A keyframe with these sightings at the odometry pose of their stamp; None (kept pending until the
        odometry of that stamp arrives, else counted in `unmatched`) without such a pose."""
        T_odom_body = self.odometry_at(ev.stamp_ns)
        if T_odom_body is None:
            self._pending.append(ev)
            if len(self._pending) > 64:
                self._pending.pop(0)
                self.unmatched += 1
            return None
        return self.sightings(ev.stamp_ns, T_odom_body, [self._to_body(o, ev.frame_id, T_odom_body)
                                                         for o in ev.features if o.corners is not None])

    def sightings(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting],
                  placed: Placed | None = None) -> Estimate:
        """A keyframe with the sightings when the vehicle moved or time passed enough (or it is still exploring),
        else only the tracked pose: the graph grows with the flight, not with the time spent hovering. A frame
        placed in the saved map, or whose view is kept (`placed`, service.places), is always a keyframe."""
        if placed is not None and (placed.T_cad_body is not None or placed.view is not None):
            return self._keyframe(stamp_ns, T_odom_body, sightings, placed)
        if not sightings or not self._keyframe_due(stamp_ns, T_odom_body):
            return self._track(stamp_ns, T_odom_body, sightings)
        return self._keyframe(stamp_ns, T_odom_body, sightings)

    def _keyframe_due(self, stamp_ns: int, T_odom_body: np.ndarray) -> bool:
        if self._last_keyframe_ns is None or self._T_last_keyframe is None or self.localizer.status != "localized":
            return True
        return self._keyframe_policy.is_keyframe(self._T_last_keyframe, T_odom_body,
                                                 (stamp_ns - self._last_keyframe_ns) * 1e-9)

    def latest(self) -> Estimate | None:
        """The pose at the newest odometry sample (after a late keyframe changed the map), or None."""
        if not self._odometry:
            return None
        stamp_ns = next(reversed(self._odometry))
        return self._track(stamp_ns, self._odometry[stamp_ns])

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """The buffered odometry pose nearest in time to stamp_ns (within 60 ms), else None."""
        if stamp_ns in self._odometry:
            return self._odometry[stamp_ns]
        if not self._odometry or stamp_ns > next(reversed(self._odometry)):
            return None  # newer than all odometry: wait for it
        stamps = np.fromiter(self._odometry.keys(), np.int64)
        k = int(np.argmin(np.abs(stamps - stamp_ns)))
        return self._odometry[int(stamps[k])] if abs(int(stamps[k]) - stamp_ns) <= ODOMETRY_MATCH_NS else None

    # --- steps --------------------------------------------------------------------------------------------------

    def _to_body(self, obs: Observation, frame_id: str, T_odom_body: np.ndarray) -> Sighting:
        assert obs.corners is not None
        T_body_x = {"body": np.eye(4), "cam_left": self.T_body_cam, "map": np.linalg.inv(T_odom_body)}[frame_id]
        corners_body = obs.corners @ T_body_x[:3, :3].T + T_body_x[:3, 3]
        return Sighting(obs.type, corners_body, obs.id or None)

    def _keyframe(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting],
                  placed: Placed | None = None) -> Estimate:
        self._last_keyframe_ns = stamp_ns
        self._T_last_keyframe = T_odom_body
        try:
            est = self.localizer.add_keyframe(
                stamp_ns, T_odom_body, sightings, self._up_body, with_covariance=self.params.covariance,
                T_cad_body_placed=None if placed is None else placed.T_cad_body,
                view=None if placed is None else placed.view)
        except RuntimeError as exc:  # GTSAM's IndeterminantLinearSystemException and its kin
            return self._restart_graph(stamp_ns, f"the update failed ({str(exc).splitlines()[0][:120]})")
        if not _finite(est):
            return self._restart_graph(stamp_ns, "the estimate is not finite")
        est = self._remember(est)
        self._keyframe_covariance = est.covariance
        return est

    def _restart_graph(self, stamp_ns: int, why: str) -> Estimate:
        """The pose graph cannot go on: start a fresh one (this flight's landmarks are lost; the saved map and its
        place recognition stay), answer LOST for this stamp, and localize again from what comes next."""
        self.graph_restarts += 1
        log.error("pose graph restarted (%d so far): %s", self.graph_restarts, why)
        old = self.localizer
        self.localizer = Localizer(self.model, PoseGraph(), old.registrar, old.params, self.T_body_cam, old.surfaces)
        self._last_keyframe_ns, self._T_last_keyframe, self._keyframe_covariance = None, None, None
        self.last = Estimate(stamp_ns, "lost", np.eye(4))
        return self.last

    def _track(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting] | None = None) -> Estimate:
        """The pose between keyframes; sightings given here enter the graph with the next keyframe."""
        if self.localizer.graph.n_keyframes == 0:
            return self._keyframe(stamp_ns, T_odom_body, sightings or [])
        est = self.localizer.track(stamp_ns, T_odom_body, sightings)
        if not _finite(est):
            return self._restart_graph(stamp_ns, "the tracked pose is not finite")
        if est.covariance is None:  # the last keyframe's: the odometry since adds little over a keyframe interval
            est.covariance = self._keyframe_covariance
        return self._remember(est)

    def _remember(self, est: Estimate) -> Estimate:
        """Keep the newest estimate (a late keyframe for an older stamp does not replace a newer pose)."""
        if self.last is None or est.stamp_ns >= self.last.stamp_ns:
            self.last = est
        return est

    # --- outputs ------------------------------------------------------------------------------------------------

    @property
    def status(self) -> str:
        return self.localizer.status

    @property
    def up_body(self) -> np.ndarray | None:
        """Gravity's up in the body frame at the newest odometry sample (perception.gravity), when known."""
        return self._up_body

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


def _finite(est: Estimate) -> bool:
    return all(m is None or bool(np.isfinite(m).all()) for m in (est.T_map_body, est.T_cad_body, est.T_cad_map))


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
