"""The localizer: the paper's loop over keyframes, as a thin orchestrator over the pose graph.

Per keyframe: predict the pose from odometry, level it with gravity, add the sightings of doors and windows
as landmark factors (re-observations or new landmarks), update iSAM2 with the new factors only, register the
map to the building model while exploring, link newly seen landmarks to their CAD features once localized and fit
the keyframe's depth to the walls and the floor while the pose is held to the model (or, where it is not, find it
again by the walls or the doors), and return the pose in the CAD frame with its status.

Its components: the landmark map (graph.landmark_map: sightings into landmarks), the anchoring (graph.anchoring:
registration attempts through the registrar, graph.registrar, and keyframes placed in a saved map), the
landmarks' links to the model (graph.cad_links), the keyframes' fits to the walls (graph.surface_fit), the recent
keyframes' depth points (graph.depth_window), the walls' and the doors' recovery of a pose no longer held
(graph.recovery) and far sightings (graph.far_window: bearings of doors beyond the sighting range, and the
resection from them), and the judge (graph.judge; a null one without the model's
surfaces), which weighs the registrar's candidate poses against the model's walls and the lines of sight through
them (graph.surfaces).

Frames: map = this flight's odometry frame with z up (gravity); body = x forward, y left, z up;
cad = the model. Sightings arrive with their 4 corners in the body frame, metres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from macroloc.graph.anchoring import Anchoring
from macroloc.graph.cad_links import CadLinks
from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.far_window import FarSightings
from macroloc.graph.features import BuildingModel, CentroidsByType
from macroloc.graph.judge import Judge, NullJudge, SurfaceJudge
from macroloc.graph.landmark_map import LandmarkMap
from macroloc.graph.mapstore import KeyframeView
from macroloc.graph.model_index import index_for
from macroloc.graph.params import LocalizerParams, RegistrationParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.prior import PosePrior
from macroloc.graph.recovery import DoorRecovery, NullRecovery, WallRecovery
from macroloc.graph.registrar import ModelRegistrar, Registrar, SavedMapRegistrar
from macroloc.graph.relocalize import KnownRect
from macroloc.graph.rigid import apply, levelled
from macroloc.graph.sightings import Landmark, Sighting
from macroloc.graph.surface_fit import NullFitter, SurfaceFitter
from macroloc.graph.surfaces import SurfaceIndex, band_points, floor_points

__all__ = ["Estimate", "Landmark", "Localizer", "LocalizerParams", "Sighting", "model_registrar", "stored_registrar"]

log = logging.getLogger(__name__)

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass
class Estimate:
    """What the localizer says after a keyframe (or a frame between keyframes)."""

    stamp_ns: int
    status: str  # exploring | localized | ambiguous | degraded | lost
    T_map_body: np.ndarray
    T_cad_body: np.ndarray | None = None
    T_cad_map: np.ndarray | None = None
    covariance: np.ndarray | None = None  # 6x6 [rot; trans] of T_cad_body (or T_map_body before), body tangent
    inliers: int = 0
    keyframe: int = -1
    update_ms: float = 0.0
    matches: dict[int, str] = field(default_factory=dict)  # landmark key -> CAD feature id


class Localizer:
    """Keyframe-by-keyframe localization in the building model (see module doc)."""

    def __init__(self, model: BuildingModel, graph: PoseGraph, registrar: Registrar,
                 params: LocalizerParams | None = None, T_body_cam: np.ndarray | None = None,
                 surfaces: SurfaceIndex | None = None) -> None:
        """`surfaces`: the model's walls, to check registrations against the depth points given with keyframes
        (graph.surfaces); the registrar should then try from `verified_min_landmarks` landmarks."""
        self.model = model
        self.surfaces = surfaces
        self.graph = graph
        self.registrar = registrar
        self.params = p = params or LocalizerParams()
        self.viewer_body = (np.eye(4) if T_body_cam is None else T_body_cam)[:3, 3]
        self.features = {f.id: f for f in model.features}
        centroids_cad = CentroidsByType(self.features.values())
        # the components: the recent keyframes' depth points and far sightings, the walls' judgement and fits,
        # the landmarks, their links to the model, and the anchoring that registers them
        self.depth = DepthWindow(p.depth.surface_window_keyframes, self.viewer_body, graph.T_map_body)
        self.far = FarSightings(p.far, p.depth.surface_window_keyframes, p.landmarks.position_sigma_m,
                                self.viewer_body, centroids_cad, graph.T_map_body)
        judge = None if surfaces is None else SurfaceJudge(
            surfaces, p.judge, centroids_cad, p.registration.inlier_threshold_m, p.fit.surface_fit_sigma_m,
            lambda: index_for(model).self_maps().transforms())
        self.judge: Judge = NullJudge() if judge is None else judge
        self.fitter = NullFitter() if surfaces is None else SurfaceFitter(p.fit, graph, self.depth, surfaces)
        self.map = LandmarkMap(p.landmarks, graph, self.viewer_body)
        self.cad_links = CadLinks(p.anchor, graph, self.features)
        self.anchoring = Anchoring(p.registration, p.anchor, p.far, p.status, graph, registrar, self.judge,
                                   self.depth, self.far, self.map, self.cad_links, self.fitter)
        self.recovery: WallRecovery | NullRecovery = NullRecovery() if surfaces is None or judge is None else \
            WallRecovery(p.recovery, graph, surfaces, judge, self.depth)
        self.door_recovery = DoorRecovery(p.recovery, graph, self.map, self.cad_links.links, self.features,
                                          p.anchor.cad_link_m, p.registration.min_sightings_to_register)
        self.keyframe_stamps_ns: list[int] = []
        self.views: dict[int, KeyframeView] = {}  # keyframe -> what place recognition keeps of it, where given
        self._T_odom_prev: np.ndarray | None = None
        self._carried: list[tuple[np.ndarray, list[Sighting]]] = []  # (T_odom_body, sightings) since the keyframe
        self._pending_depth: tuple[np.ndarray, np.ndarray] | None = None  # (T_odom_body, points_body): newest since it

    # --- the loop ---------------------------------------------------------------------------------------------

    def add_keyframe(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting],
                     up_body: np.ndarray | None = None, with_covariance: bool = False,
                     points_body: np.ndarray | None = None, T_cad_body_placed: np.ndarray | None = None,
                     view: KeyframeView | None = None, dead_reckoned_s: float = 0.0) -> Estimate:
        """One keyframe: odometry pose T_odom_body (4x4, odometry frame z up), sightings, gravity's up (body),
        and optionally 3-D points (N, 3) the camera measured at this keyframe, body frame (stereo depth); without
        them, the newest given to `add_depth` since the last keyframe. `T_cad_body_placed`: this keyframe's pose
        in the CAD frame as place recognition in a saved map found it (perception.place), when it did; `view`:
        what place recognition keeps of it, for the saved map (service.saved_map). `dead_reckoned_s`: the
        seconds since the last keyframe that the odometry lost track and only extrapolated its pose; the odometry
        factor's translation sigma grows by `odometry_dead_reckoned_sigma_mps` for each: an extrapolated pose is
        no measurement (docs/measurements.md, "Dead-reckoned odometry is loosened")."""
        frames = [*self._carry_to(T_odom_body), list(sightings)]
        points_body = self._depth_at(T_odom_body, points_body)
        i, T_map_body = self._predict(T_odom_body, dead_reckoned_s)
        self._keep(i, stamp_ns, view)
        up_body = self._add_gravity(i, T_map_body, up_body)
        self._add_depth(i, points_body, up_body)
        self._add_sightings(i, T_map_body, frames, up_body, stamp_ns)
        self.graph.update()
        if T_cad_body_placed is not None:
            self.anchoring.place(i, stamp_ns, T_cad_body_placed)
        if self.anchoring.should_register(stamp_ns):
            self.anchoring.register(stamp_ns)
        elif self.graph.has_anchor:
            held = self.anchoring.held()
            self.recovery.keyframe(i, dead_reckoned_s, held)
            self.door_recovery.keyframe(i, dead_reckoned_s, held)
            if held:  # local associations only where the pose is known within their reach
                self.cad_links.link_new(self.map.landmarks, stamp_ns)
                self.fitter.fit_newest()
            elif not self.recovery.attempt(stamp_ns, self.params.registration.surface_retry_s):
                self.door_recovery.attempt(stamp_ns, self.params.registration.surface_retry_s)
        self.anchoring.update_status(stamp_ns)
        return self._estimate(stamp_ns, i, with_covariance)

    def track(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting] | None = None) -> Estimate:
        """A frame between keyframes: the last keyframe's estimate moved by the odometry since then. Its
        sightings are kept and enter the graph with the next keyframe, moved into that keyframe's body frame by
        the odometry between the two (a few tenths of a second: its error is far below a sighting's)."""
        i = self.graph.n_keyframes - 1
        assert self._T_odom_prev is not None, "track() before the first keyframe"
        if sightings:
            self._carried.append((T_odom_body, list(sightings)))
        T_map_body = self.graph.T_map_body(i) @ np.linalg.inv(self._T_odom_prev) @ T_odom_body
        return self._estimate_at(stamp_ns, i, T_map_body)

    def add_depth(self, T_odom_body: np.ndarray, points_body: np.ndarray) -> None:
        """Depth points (N, 3, body frame) measured at odometry pose T_odom_body between keyframes: the newest
        enter with the next keyframe, moved into its body frame (as `track`'s sightings are)."""
        self._pending_depth = (np.asarray(T_odom_body, float), np.asarray(points_body, float))

    def set_prior(self, prior: PosePrior | None) -> None:
        """The operator's prior on the pose (graph.prior): it picks among the poses a registration leaves tied,
        never more (None: forget it)."""
        self.anchoring.set_prior(prior)

    # --- what the components hold -----------------------------------------------------------------------------

    @property
    def status(self) -> str:
        """exploring | localized | ambiguous | degraded | lost"""
        return self.anchoring.status

    @property
    def inliers(self) -> int:
        return self.anchoring.inliers

    @property
    def rivals(self) -> list[np.ndarray]:
        """While 'ambiguous': the T_cad_map (4x4) of the poses the last registration could not tell apart."""
        return self.anchoring.rivals

    @property
    def registrations(self) -> list[tuple[int, str]]:
        """(stamp_ns, status) of every registration attempt."""
        return self.anchoring.registrations

    @property
    def placed(self) -> list[int]:
        """The keyframes placed in a saved map (place recognition) and taken."""
        return self.anchoring.placed

    @property
    def landmarks(self) -> dict[int, Landmark]:
        return self.map.landmarks

    @property
    def links(self) -> dict[int, str]:
        """Landmark key -> CAD feature id."""
        return self.cad_links.links

    @property
    def duplicates(self) -> int:
        """Sightings dropped: their landmark was seen in the same frame already."""
        return self.map.duplicates

    @property
    def surface_fits(self) -> int:
        """Keyframes whose depth was fitted to the walls (and floor)."""
        return self.fitter.fits

    def _confirmed(self) -> list[int]:
        return self.anchoring.confirmed()

    def landmark_centres_map(self) -> list[tuple[str, np.ndarray]]:
        """The confirmed landmarks as (type, centre (3,) in the map frame), in key order."""
        return self.map.centres_map(self._confirmed())

    # --- steps ------------------------------------------------------------------------------------------------

    def _carry_to(self, T_odom_kf: np.ndarray) -> list[list[Sighting]]:
        """The sightings kept since the last keyframe, frame by frame, in the body frame of the keyframe at
        T_odom_kf."""
        carried: list[list[Sighting]] = []
        for T_odom_body, sightings in self._carried:
            T_kf_body = np.linalg.inv(T_odom_kf) @ T_odom_body
            carried.append([replace(s, corners_body=apply(T_kf_body, s.corners_body)) for s in sightings])
        self._carried = []
        return carried

    def _depth_at(self, T_odom_body: np.ndarray, points_body: np.ndarray | None) -> np.ndarray | None:
        """The keyframe's depth points (N, 3, body frame): those given with it, else the newest given since the
        last keyframe, moved into its body frame by the odometry."""
        depth, self._pending_depth = self._pending_depth, None
        if points_body is None and depth is not None:
            points_body = apply(np.linalg.inv(T_odom_body) @ depth[0], depth[1])
        return points_body

    def _predict(self, T_odom_body: np.ndarray, dead_reckoned_s: float = 0.0) -> tuple[int, np.ndarray]:
        """A new keyframe at the odometry's prediction, with the odometry factor (`OdometryFactorParams`)."""
        if self._T_odom_prev is None:
            self._T_odom_prev = T_odom_body
            return self.graph.add_first_keyframe(T_odom_body), T_odom_body  # map = odometry frame at start
        T_prev_curr = np.linalg.inv(self._T_odom_prev) @ T_odom_body
        T_map_body = self.graph.T_map_body(self.graph.n_keyframes - 1) @ T_prev_curr
        travelled = float(np.linalg.norm(T_prev_curr[:3, 3])) + 0.05  # + a floor: hovering still drifts
        p = self.params.odometry
        sigma_m = np.hypot(p.odometry_sigma_per_m * travelled, p.odometry_dead_reckoned_sigma_mps * dead_reckoned_s)
        sigmas = np.r_[np.full(3, p.odometry_rot_sigma_per_m * travelled), np.full(3, sigma_m)]  # [rot; trans]
        self._T_odom_prev = T_odom_body
        return self.graph.add_keyframe(T_prev_curr, sigmas, T_map_body), T_map_body

    def _keep(self, i: int, stamp_ns: int, view: KeyframeView | None) -> None:
        """Keyframe i's stamp and place-recognition view, for the map this flight saves (service.saved_map)."""
        self.keyframe_stamps_ns.append(stamp_ns)
        if view is not None:
            self.views[i] = view

    def _add_gravity(self, i: int, T_map_body: np.ndarray, up_body: np.ndarray | None) -> np.ndarray:
        """A roll/pitch prior when the IMU gives up; returns up in the body frame (estimated when not given)."""
        if up_body is None:
            return T_map_body[:3, :3].T @ Z_UP
        up_body = np.asarray(up_body, float) / np.linalg.norm(up_body)
        self.graph.add_gravity(i, levelled(T_map_body, up_body))
        return up_body

    def _add_depth(self, i: int, points_body: np.ndarray | None, up_body: np.ndarray) -> None:
        """Keyframe i's depth points into the window (with the model's surfaces to check them against)."""
        if points_body is not None and self.surfaces is not None and len(points_body):
            self.depth.add(i, band_points(points_body, up_body, seed=i), floor_points(points_body, up_body, seed=i))

    def _add_sightings(self, i: int, T_map_body: np.ndarray, frames: list[list[Sighting]], up_body: np.ndarray,
                       stamp_ns: int) -> None:
        """The sightings of the frames since the last keyframe and of the keyframe's own into the landmark map;
        those beyond the sighting range into the far window while the graph is not anchored."""
        far, reobserved = self.map.add_frames(i, T_map_body, frames, up_body)
        self.cad_links.seen(reobserved, stamp_ns)
        if far and not self.graph.has_anchor:
            self.far.add(i, [s.type for s in far], np.array([s.corners_body.mean(axis=0) for s in far]))

    # --- output -----------------------------------------------------------------------------------------------

    def _estimate(self, stamp_ns: int, i: int, with_covariance: bool) -> Estimate:
        est = self._estimate_at(stamp_ns, i, self.graph.T_map_body(i))
        est.update_ms = self.graph.last_update_ms
        if with_covariance:
            est.covariance = self.graph.covariance_cad_body(i)
        return est

    def _estimate_at(self, stamp_ns: int, i: int, T_map_body: np.ndarray) -> Estimate:
        T_cad_map = self.graph.T_cad_map()
        T_cad_body = None if T_cad_map is None else T_cad_map @ T_map_body
        return Estimate(stamp_ns, self.status, T_map_body, T_cad_body, T_cad_map, inliers=self.inliers, keyframe=i,
                        matches=dict(self.links))


def model_registrar(model: BuildingModel, params: RegistrationParams, storey_hint: str | None = None,
                    with_surfaces: bool = False, method: str = "robust") -> ModelRegistrar:
    """The registrar against the whole model, from the localizer's registration parameters (one place for replay
    and the service): candidates from `verified_min_landmarks` on when the surface check can decide among them.
    Then it also seeds hypotheses from every landmark (up to its `max_seeds`), not only until a pose explains
    `registration_early_stop` of them: with false and misplaced doors among the landmarks, two seeds can both be
    wrong, and a wrong pose explaining half of them would stop the search before the true pose is hypothesised
    (docs/measurements.md, "Seeding every landmark")."""
    early_stop = params.registration_early_stop if with_surfaces and method == "robust" else None
    return ModelRegistrar(model, method=method, storey_hint=storey_hint,
                          min_landmarks=params.registration_min_landmarks,
                          inlier_threshold_m=params.inlier_threshold_m,
                          candidates_from=params.verified_min_landmarks if with_surfaces else None,
                          early_stop_fraction=early_stop)


def stored_registrar(model: BuildingModel, known: list[KnownRect], params: RegistrationParams,
                     with_surfaces: bool = False) -> SavedMapRegistrar:
    """The registrar against a saved map's CAD-linked features (re-localization): localized from two agreeing
    landmarks; with the surface check, candidate poses from `verified_min_landmarks` on, for the walls."""
    return SavedMapRegistrar(known, min_landmarks=2, model=model,
                              candidates_from=params.verified_min_landmarks if with_surfaces else None)
