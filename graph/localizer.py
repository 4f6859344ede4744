"""The localizer: the paper's loop over keyframes, as a thin orchestrator over the pose graph.

Per keyframe: predict the pose from odometry, level it with gravity, add the sightings of doors and windows
as landmark factors (re-observations or new landmarks), update iSAM2 with the new factors only, register the
map to the building model while exploring (the candidate poses checked against the model's walls, and the
lines of sight through them, where the keyframes bring depth points, graph.surfaces, and against the bearings of
the doors seen beyond the sighting range), link newly seen landmarks
to their CAD features once localized and fit the keyframe's depth to the walls and the floor, and return the
pose in the CAD frame with its status.

Frames: map = this flight's odometry frame with z up (gravity); body = x forward, y left, z up;
cad = the model. Sightings arrive with their 4 corners in the body frame, metres.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Generic, NamedTuple, TypeVar

import numpy as np

from graph.far import refined_by_bearings, resection_candidates
from graph.features import BuildingModel
from graph.landmarks import closer_flip, feature_frame_cad, is_vertical, observed_frame
from graph.mapstore import KeyframeView, StoredLandmark, StoredMap
from graph.posegraph import CAD_LINK_POSITION_SIGMAS, CAD_LINK_SIGMAS, PoseGraph
from graph.registrar import ModelRegistrar, Registrar, StoredMapRegistrar
from graph.relocalize import Alignment, KnownRect, ObservedRect, distinct_poses
from graph.rigid import apply, levelled, make_T, rot_z, rotation_angle_deg
from graph.surfaces import SurfaceCheck, SurfaceIndex, align_to_surfaces, band_points, floor_points

log = logging.getLogger(__name__)
V = TypeVar("V")
Ranges = TypeVar("Ranges", float, np.ndarray)

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Sighting:
    """A door/window seen in one frame: type and corners (4, 3) in the body frame (any order), metres.

    truncated: (sideways, vertically) cut by the image border; the corners on that side are the border's, not
    the opening's, so the position along that axis is known only roughly (see LocalizerParams.truncated_sigma_m).
    """

    type: str
    corners_body: np.ndarray
    truth_id: str | None = None  # ground truth (simulated flights), for scoring only: never used to match
    truncated: tuple[bool, bool] = (False, False)


@dataclass(frozen=True)
class LocalizerParams:
    associate_m: float = 0.6  # a sighting within this of a same-type landmark re-observes it
    cad_link_m: float = 0.5  # once localized: a landmark within this of a same-type CAD feature is linked ...
    cad_link_max_turn_deg: float = 8.0  # ... its orientation too where it lies within this of the feature's
    odometry_sigma_per_m: float = 0.03  # translation sigma per metre travelled (drift model of the odometry)
    odometry_rot_sigma_per_m: float = 0.01  # rad per metre travelled
    odometry_dead_reckoned_sigma_mps: float = 0.5  # translation sigma per second the odometry lost track and only
    #                                               extrapolated (a drone's speed it could not see change)
    sighting_sigma_m: tuple[float, float] = (0.03, 0.004)  # sigma = a + b * range^2 (stereo) of a sighting's position
    sighting_sigma_rad: tuple[float, float] = (0.03, 0.012)  # same for its orientation (plane of noisy corners)
    truncated_sigma_m: float = 0.5  # position sigma along an axis on which the sighting is cut by the image border
    max_range_m: float = 7.0  # sightings further away are no landmarks: their corners are too coarse ...
    far_range_m: float = 20.0  # ... but up to this range their bearings check candidate poses (`_far_explained`):
    far_bearing_deg: float = 3.0  # a far sighting is explained where a same-type CAD feature lies within this
    #                               horizontal bearing of it, seen from the keyframe's camera, and 3 sigmas of its range
    far_elevation_deg: float = 5.0  # ... and within this of its elevation (a one-door candidate's height is coarse)
    far_turn_deg: float = 2.0  # ... turning the candidate pose by up to this (`far_turn_step_deg` steps) to do so
    far_turn_step_deg: float = 0.5  # (its heading, from a door or two and the walls, is ~2 deg off)
    far_min_sightings: int = 10  # with this many far sightings in the window, a candidate pose explaining
    far_min_explained: float = 0.8  # at least this fraction of them is not rivalled by one explaining
    far_margin: float = 0.4  # this much less (the surfaces' margin aside)
    far_resection: bool = True  # with no landmark yet, candidate poses from two far doors seen from one camera
    far_pair_min_deg: float = 10.0  # ... at least this far apart in bearing (graph.far), in the newest
    far_pairs: int = 3  # ... this many keyframes that saw such a pair, the widest pair of each (`_resected`)
    far_resection_sightings: int = 60  # the candidates are judged by this many of the far sightings, evenly drawn
    far_height_sigma_m: float = 0.2  # the pose taken holds the anchoring keyframe's height with this sigma ...
    far_bearing_sigma_deg: float = 0.5  # ... and is fitted to the far bearings with this one (`_far_refined`)
    min_sightings_to_register: int = 2  # a landmark seen once (a passing false detection?) waits
    registration_tolerance_m: float = 0.6  # the model registrar's inlier / ambiguity tolerance (see GraphConfig)
    registration_min_landmarks: int = 4  # the model registrar answers 'localized' from this many landmarks ...
    registration_early_stop: float = 1.0  # with the surface check, it stops seeding hypotheses once a pose explains
    #                                       this fraction of the landmarks (1.0: never; see `model_registrar`)
    verified_min_landmarks: int = 1  # ... and offers candidate poses from this many, for the surface check
    surface_window_keyframes: int = 60  # the depth points of this many recent keyframes check a registration
    surface_min_points: int = 200  # fewer points than this: no check (the registration needs the landmarks above)
    surface_min_support: float = 0.9  # a pose must put this fraction of the points on the model's surfaces ...
    surface_margin: float = 0.3  # ... and every other candidate pose this much less (of points on surfaces and in
    #                               sight, with the model's walls: SurfaceCheck.score) ...
    surface_margin_unfit: float = 0.15  # ... or this much less where that pose does not fit the walls itself
    #                                     (candidates from two landmarks or more: `_choose_by_surfaces`) ...
    surface_max_seen_through: float = 0.1  # ... and let at most this fraction be seen through a wall
    surface_refuse_seen_through: float = 0.25  # a registrar's own answer is refused where more are seen through one
    surface_retry_s: float = 1.0  # with no new landmark, the check is retried this often as the walls come in view
    surface_refine_m: float = 0.6  # each candidate pose is first fitted to the walls, moving the points at most this
    surface_screen_top: int = 8  # of more candidates (one door: every alike door of the model, from both sides),
    surface_screen_points: int = 200  # only the best this many by these many points, unfitted, are fitted and checked
    surface_turn_deg: float = 24.0  # a candidate pose from one door is first turned about it, within this and by
    surface_turn_step_deg: float = 3.0  # these steps, to the heading that puts most points on the walls (`_turned`)
    surface_turn_points: int = 100  # ... judged by this many points; where no candidate then fits the walls, so is
    surface_turn_max_inliers: int = 3  # one from up to this many doors, keeping as many by a CAD feature
    surface_fit: bool = True  # once localized, each keyframe's depth points fitted to the walls join the graph
    surface_fit_max_correction_m: float = 0.5  # a fit that moves the pose further is not trusted (wrong wall) ...
    surface_fit_max_turn_deg: float = 5.0  # ... nor one that turns it further ...
    surface_fit_settling_turn_deg: float = 10.0  # ... but this far in the first keyframes after localizing, while the
    surface_fit_settling_keyframes: int = 10  # pose's heading is the few doors' it was found by (one: ~6 deg off)
    surface_fit_sigma_m: float = 0.05  # a fitted point's distance to its wall, model against reality (m)
    placed_sigma_m: float = 0.15  # a keyframe placed in a stored map (place recognition): its pose's sigmas in
    placed_sigma_deg: float = 2.0  # the CAD frame, the stored keyframe's error and PnP's together
    degraded_after_s: float = 10.0  # localized but no CAD-linked sighting for this long
    lost_after_s: float = 30.0


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


@dataclass
class Landmark:
    """A door or window of this flight; its pose is the graph's (T_map_rect). Its size, which the registration
    compares with the model's (graph.robust, `size_tolerance_m`), is the median of its sightings' sides: the width
    over the sightings not cut by the image border sideways, the height over those not cut at the top or bottom
    (over all of them where every one is cut: a cut side is short). One sighting's is not enough: perception sees
    the doors of a corridor obliquely (65-75 deg off their normal) and with their frames, and the first sightings of
    two 1.07 m doors were 1.64 and 1.58 m wide (`macroloc demo --observations perception`, seed 0), so the true
    doors were no candidates for them and the walls chose among wrong ones. By 4.9 s the first had been seen 1.17 m
    wide too: its median, 1.41 m, passes, and seeded from it the true pose is a candidate (the second stays 1.58 m)."""

    key: int
    type: str
    sides_m: list[tuple[float, float, bool, bool]]  # each sighting's (width, height, cut sideways, cut vertically)
    truth_id: str | None = None  # scoring only

    @classmethod
    def first_seen(cls, key: int, kind: str, corners: np.ndarray, truncated: tuple[bool, bool],
                   truth_id: str | None = None) -> Landmark:
        landmark = cls(key, kind, [], truth_id)
        landmark.add_sighting(corners, truncated)
        return landmark

    @property
    def n_sightings(self) -> int:
        return len(self.sides_m)

    def add_sighting(self, corners: np.ndarray, truncated: tuple[bool, bool]) -> None:
        """A sighting's corners (4, 3) in order around the rectangle, in a frame whose z is up (the map's), and
        whether it was cut (sideways, vertically)."""
        self.sides_m.append((*_sides_m(corners), bool(truncated[0]), bool(truncated[1])))

    def size_m(self) -> tuple[float, float]:
        """(width, height), metres."""
        sides = np.array(self.sides_m, float)
        whole = sides[:, 2:] == 0
        width, height = (float(np.median(sides[whole[:, k], k] if whole[:, k].any() else sides[:, k])) for k in (0, 1))
        return width, height

    def corners(self, T_x_rect: np.ndarray) -> np.ndarray:
        """The rectangle (4, 3) of `size_m` about the landmark's frame T_x_rect (axes u along the wall, n, z up)."""
        (w, h), u, z = self.size_m(), T_x_rect[:3, 0], T_x_rect[:3, 2]
        return T_x_rect[:3, 3] + np.array([-w * u + h * z, w * u + h * z, w * u - h * z, -w * u - h * z]) / 2.0


def _sides_m(corners: np.ndarray) -> tuple[float, float]:
    """(horizontal, vertical) side of a rectangle's corners (4, 3), in order around it, z up: the edge from the
    first corner to the second or to the fourth, whichever is more level, and the other."""
    p = np.asarray(corners, float)
    level, upright = p[1] - p[0], p[3] - p[0]
    if abs(level[2]) > abs(upright[2]):
        level, upright = upright, level
    return float(np.linalg.norm(level)), float(np.linalg.norm(upright))


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
        self.params = params or LocalizerParams()
        self.viewer_body = (np.eye(4) if T_body_cam is None else T_body_cam)[:3, 3]
        self.features = {f.id: f for f in model.features}
        self._feature_centroids: dict[str, np.ndarray] = {}  # type -> centroids (N, 3), CAD frame
        self.landmarks: dict[int, Landmark] = {}
        self.links: dict[int, str] = {}  # landmark key -> CAD feature id
        self.status = "exploring"
        self.inliers = 0
        self.registrations: list[tuple[int, str]] = []  # (stamp_ns, status) of every registration attempt
        self.keyframe_stamps_ns: list[int] = []
        self.views: dict[int, KeyframeView] = {}  # keyframe -> what place recognition keeps of it, where given
        self.placed: list[int] = []  # keyframes placed in a stored map (place recognition) and taken
        self._T_odom_prev: np.ndarray | None = None
        self._last_link_ns: int | None = None
        self._registered_with = 0
        self._anchored_at: int | None = None  # the keyframe at which the graph was anchored to the model
        self._registered_at: tuple[int, int] = (0, 0)  # (stamp_ns, depth points) of the last registration
        self._carried: list[tuple[np.ndarray, list[Sighting]]] = []  # (T_odom_body, sightings) since the keyframe
        self._depth: tuple[np.ndarray, np.ndarray] | None = None  # (T_odom_body, points_body): newest since it
        # (keyframe, points at the camera's height, points below it: the floor), body frame
        self._points: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=self.params.surface_window_keyframes)
        # (keyframe, types (K,), centroids (K, 3) body frame) of the sightings beyond max_range_m, recent keyframes'
        self._far: deque[tuple[int, list[str], np.ndarray]] = deque(maxlen=self.params.surface_window_keyframes)
        self.surface_checks: list[tuple[int, list[float]]] = []  # (stamp_ns, score of each candidate pose)
        # within one registration attempt: each candidate fitted to the walls, each fitted pose's check, once
        self._fitted: _PerPose[np.ndarray] = _PerPose()
        self._checked: _PerPose[SurfaceCheck] = _PerPose()
        self.surface_screens: list[tuple[int, list[float]]] = []  # (candidates, their screening scores, best first)
        self.surface_fits = 0  # keyframes whose depth was fitted to the walls (and floor)
        self._fit_tried_at = -1  # the newest keyframe whose depth points a fit to the walls was tried with
        self.duplicates = 0  # sightings dropped: their landmark was seen in the same frame already

    # --- the loop ---------------------------------------------------------------------------------------------

    def add_keyframe(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting],
                     up_body: np.ndarray | None = None, with_covariance: bool = False,
                     points_body: np.ndarray | None = None, T_cad_body_placed: np.ndarray | None = None,
                     view: KeyframeView | None = None, dead_reckoned_s: float = 0.0) -> Estimate:
        """One keyframe: odometry pose T_odom_body (4x4, odometry frame z up), sightings, gravity's up (body),
        and optionally 3-D points (N, 3) the camera measured at this keyframe, body frame (stereo depth); without
        them, the newest given to `add_depth` since the last keyframe. `T_cad_body_placed`: this keyframe's pose
        in the CAD frame as place recognition in a stored map found it (perception.place), when it did; `view`:
        what place recognition keeps of it, for the map this flight saves (`stored_map`). `dead_reckoned_s`: the
        seconds since the last keyframe that the odometry lost track and only extrapolated its pose; the odometry
        factor's translation sigma grows by `odometry_dead_reckoned_sigma_mps` for each (perception Jasmin-Sun
        seed 8: 3.8 s facing a wall 0.26-0.34 m away, nearer than stereo measures, extrapolated 0.78 m wrong;
        trusted at ~1 cm, it held a flight localized before it 0.5-0.8 m off for 30 s)."""
        carried = self._carry_to(T_odom_body)
        depth, self._depth = self._depth, None
        if points_body is None and depth is not None:  # into this keyframe's body frame, by the odometry
            points_body = apply(np.linalg.inv(T_odom_body) @ depth[0], depth[1])
        i, T_map_body = self._predict(T_odom_body, dead_reckoned_s)
        self.keyframe_stamps_ns.append(stamp_ns)
        if view is not None:
            self.views[i] = view
        up_body = self._add_gravity(i, T_map_body, up_body)
        if points_body is not None and self.surfaces is not None and len(points_body):
            self._points.append((i, band_points(points_body, up_body, seed=i),
                                 floor_points(points_body, up_body, seed=i)))
        self._add_sightings(i, T_map_body, [*carried, list(sightings)], up_body, stamp_ns)
        self.graph.update()
        if T_cad_body_placed is not None:
            self._add_placed(i, stamp_ns, T_cad_body_placed)
        if self._should_register(stamp_ns):
            self._register(stamp_ns)
        elif self.graph.has_anchor:
            self._link_new_landmarks(stamp_ns)
        self._fit_newest_to_surfaces()
        self._update_status(stamp_ns)
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
        self._depth = (np.asarray(T_odom_body, float), np.asarray(points_body, float))

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

    def _predict(self, T_odom_body: np.ndarray, dead_reckoned_s: float = 0.0) -> tuple[int, np.ndarray]:
        if self._T_odom_prev is None:
            self._T_odom_prev = T_odom_body
            return self.graph.add_first_keyframe(T_odom_body), T_odom_body  # map = odometry frame at start
        T_prev_curr = np.linalg.inv(self._T_odom_prev) @ T_odom_body
        T_map_body = self.graph.T_map_body(self.graph.n_keyframes - 1) @ T_prev_curr
        travelled = float(np.linalg.norm(T_prev_curr[:3, 3])) + 0.05  # + a floor: hovering still drifts
        p = self.params
        sigma_m = np.hypot(p.odometry_sigma_per_m * travelled, p.odometry_dead_reckoned_sigma_mps * dead_reckoned_s)
        sigmas = np.r_[np.full(3, p.odometry_rot_sigma_per_m * travelled), np.full(3, sigma_m)]  # [rot; trans]
        self._T_odom_prev = T_odom_body
        return self.graph.add_keyframe(T_prev_curr, sigmas, T_map_body), T_map_body

    def _add_gravity(self, i: int, T_map_body: np.ndarray, up_body: np.ndarray | None) -> np.ndarray:
        """A roll/pitch prior when the IMU gives up; returns up in the body frame (estimated when not given)."""
        if up_body is None:
            return T_map_body[:3, :3].T @ Z_UP
        up_body = np.asarray(up_body, float) / np.linalg.norm(up_body)
        self.graph.add_gravity(i, levelled(T_map_body, up_body))
        return up_body

    def _add_sightings(self, i: int, T_map_body: np.ndarray, frames: list[list[Sighting]], up_body: np.ndarray,
                       stamp_ns: int) -> None:
        """The sightings of the frames since the last keyframe and of the keyframe's own, frame by frame. A frame
        sees a door once: a second detection of the same landmark in one frame (overlapping boxes of one door)
        is dropped, so that it neither counts as a second sighting (`min_sightings_to_register`) nor doubles the
        weight of its factor."""
        far: list[Sighting] = []
        for sightings in frames:
            seen: set[int] = set()
            for s in sightings:
                j = self._add_sighting(i, T_map_body, s, up_body, stamp_ns, seen, far)
                if j is not None:
                    seen.add(j)
        if far and not self.graph.has_anchor:
            self._far.append((i, [s.type for s in far], np.array([s.corners_body.mean(axis=0) for s in far])))

    def _add_sighting(self, i: int, T_map_body: np.ndarray, s: Sighting, up_body: np.ndarray, stamp_ns: int,
                      seen: set[int], far: list[Sighting]) -> int | None:
        """One sighting into the graph (a new landmark or a re-observation); its landmark's key, or None where it
        was not taken (not upright, out of range: then into `far` up to `far_range_m`, or its landmark `seen` in
        the same frame already)."""
        p = self.params
        if not is_vertical(s.corners_body, up_body):
            return None
        T_body_rect = observed_frame(s.corners_body, up_body, self.viewer_body)
        rng = float(np.linalg.norm(T_body_rect[:3, 3] - self.viewer_body))
        if rng > p.max_range_m:
            if rng <= p.far_range_m:
                far.append(s)
            return None
        T_map_rect = T_map_body @ T_body_rect
        j = self._associate(s.type, T_map_rect)
        corners_map = apply(T_map_body, s.corners_body)
        if j is None:
            j = len(self.landmarks)
            self.landmarks[j] = Landmark.first_seen(j, s.type, corners_map, s.truncated, s.truth_id)
            self.graph.add_landmark(j, T_map_rect)
        elif j in seen:
            self.duplicates += 1
            return None
        else:
            self.landmarks[j].add_sighting(corners_map, s.truncated)
            T_body_rect = np.linalg.inv(T_map_body) @ closer_flip(T_map_rect, self.graph.T_map_rect(j))
            if j in self.links:
                self._last_link_ns = stamp_ns
        self.graph.add_sighting(i, j, T_body_rect, self._sighting_sigmas(s, rng))
        return j

    def _sighting_sigmas(self, s: Sighting, range_m: float) -> np.ndarray:
        """[rot; trans] sigmas of a sighting, the translation along the rectangle's own axes (u along the wall,
        n its normal, z up): stereo noise grows with range squared; a side cut by the image border is loose."""
        p = self.params
        sigma_m = self._sighting_sigma_m(range_m)
        trans = np.full(3, sigma_m)
        if s.truncated[0]:
            trans[0] = max(sigma_m, p.truncated_sigma_m)
        if s.truncated[1]:
            trans[2] = max(sigma_m, p.truncated_sigma_m)
        return np.r_[np.full(3, p.sighting_sigma_rad[0] + p.sighting_sigma_rad[1] * range_m**2), trans]

    def _sighting_sigma_m(self, range_m: Ranges) -> Ranges:
        """A sighting's position sigma at a range (stereo: it grows with range squared), metres; of each of an
        array of ranges too."""
        a, b = self.params.sighting_sigma_m
        return a + b * range_m**2

    def _associate(self, kind: str, T_map_rect: np.ndarray) -> int | None:
        """The same-type landmark nearest to the sighting within `associate_m`, or None (a new landmark)."""
        best, best_d = None, self.params.associate_m
        for j, lm in self.landmarks.items():
            if lm.type != kind:
                continue
            T_j = self.graph.T_map_rect(j)
            d = float(np.linalg.norm(T_j[:3, 3] - T_map_rect[:3, 3]))
            if d < best_d and abs(float(np.dot(T_j[:3, 1], T_map_rect[:3, 1]))) > 0.8:
                best, best_d = j, d
        return best

    def _confirmed(self) -> list[int]:
        """Landmarks seen often enough to take part in a registration."""
        return [j for j, lm in sorted(self.landmarks.items())
                if lm.n_sightings >= self.params.min_sightings_to_register]

    def _should_register(self, stamp_ns: int) -> bool:
        """While not localized: when a landmark was confirmed since the last attempt, or (with the surface
        check) when `surface_retry_s` passed and more depth points came in: the walls decide as they are seen."""
        if self.status not in ("exploring", "ambiguous"):
            return False
        n = len(self._confirmed())
        if not self._can_check_surfaces():
            return n >= self.registrar.min_landmarks and n > self._registered_with
        last_ns, last_points = self._registered_at
        more_walls = (stamp_ns - last_ns) * 1e-9 >= self.params.surface_retry_s and self._n_points() > last_points
        if n < self.registrar.candidates_from:
            return more_walls and self.params.far_resection and self._n_far() >= self.params.far_min_sightings
        return n > self._registered_with or more_walls

    def _n_points(self) -> int:
        return sum(len(p) for _, p, _ in self._points)

    def _can_check_surfaces(self) -> bool:
        return self.surfaces is not None and self._n_points() >= self.params.surface_min_points

    def _points_map(self, at_most: int = 2000) -> tuple[np.ndarray, np.ndarray]:
        """The recent keyframes' depth points (N, 3) in the map frame, at the keyframes' current estimates, and
        the camera each was seen from (N, 3); `at_most` of them, evenly drawn (a support known to ~1 % is
        enough, and each point costs a k-d tree query and a line of sight)."""
        points, origins = [np.zeros((0, 3))], [np.zeros((0, 3))]
        for i, p, _ in self._points:
            if len(p):
                T_map_body = self.graph.T_map_body(i)
                points.append(apply(T_map_body, p))
                origins.append(np.repeat(apply(T_map_body, self.viewer_body[None]), len(p), axis=0))
        every = max(1, int(np.ceil(sum(len(p) for p in points) / at_most)))
        return np.vstack(points)[::every], np.vstack(origins)[::every]

    def _choose_by_surfaces(self, result: Alignment, stamp_ns: int) -> _Choice:
        """The pose to anchor the map with, or None, and whether it is the registrar's answer (whose matches
        then hold): the registrar's answer, checked by the walls (graph.surfaces).

        Without depth points only the registrar's own 'localized' counts. With them, each candidate is fitted to
        the walls (`_refined`) and scored by the points on the model's surfaces and, with the model's walls as
        voxels, in sight of their cameras (SurfaceCheck.score); a candidate is taken when it puts
        `surface_min_support` of the points on the surfaces, lets at most `surface_max_seen_through` be seen
        through a wall, and every other candidate scores `surface_margin` less, or `surface_margin_unfit` less
        where that candidate does not fit the walls itself (`_fits`) and every candidate explains two landmarks
        or more (a pose the walls contradict is a weaker rival: perception demo seed 1, a corridor 18.6 m along
        put 0.71-0.86 of the points on the walls against the true pose's 0.97-0.99, and held the status
        ambiguous 15 s at 0.14-0.29 below it; from one door the candidates are coarse and the true one may fit
        badly: on the duplex it was 2.8 deg off, 42 % of its points seen through a wall, its twin 0.994); the
        registrar's 'localized'
        stands unless another candidate beats it by that margin or more than `surface_refuse_seen_through` of the
        points would have been seen through a wall (the walls contradict it), and is refused where the walls
        confirm a different pose. Few points on the surfaces alone do not refuse it: a true pose among furniture
        the model lacks puts only half of them there.

        Candidates from one landmark are first turned to the walls' heading (`_turned`); where then none fits,
        those from up to `surface_turn_max_inliers` are turned too and all are weighed again. Turned, wrong poses
        fit better too (`truth`, Office_A seed 4: wrong two-door poses from 0.45-0.59 to 0.67-0.73 against the true
        0.96, rivals within the margin), so a pose from two or three doors is turned only when it must be."""
        p = self.params
        T_reg = result.T_cad_map if result.status == "localized" else None
        if not self._can_check_surfaces():
            return _Choice(T_reg, T_reg is not None)
        assert self.surfaces is not None
        points_map, origins_map = self._points_map()
        if T_reg is not None:
            T_reg = self._fitted.get(T_reg, lambda T: self._refined(T, points_map))
            moved_reg = apply(T_reg, points_map)
        reg = None if T_reg is None else (T_reg, moved_reg)
        sample = self._screening_sample(points_map, origins_map)
        counts = [n for _, n in result.candidates]
        poses = self._turned(result.candidates, sample[0], 1, 1)
        candidates, moved, checks = self._weighed(poses, reg, points_map, origins_map, sample)
        if checks and not self._fits(max(checks, key=lambda c: c.score)) \
                and any(1 < n <= p.surface_turn_max_inliers for n in counts):
            log.info("no candidate pose fits the walls as it stands: those from up to %d landmarks turned too",
                     p.surface_turn_max_inliers)
            poses = self._turned(list(zip(poses, counts, strict=True)), sample[0], 2, p.surface_turn_max_inliers)
            candidates, moved, checks = self._weighed(poses, reg, points_map, origins_map, sample)
        if not candidates:
            return _Choice(None, False)
        score = np.array([c.score for c in checks])
        self.surface_checks.append((stamp_ns, score.round(3).tolist()))
        log.info("surface check of %d candidate poses (%d points): support %s", len(candidates), len(points_map),
                 ", ".join(f"{c.support:.2f}" + (f" ({c.seen_through:.2f} seen through walls)"
                                                 if self.surfaces.walls is not None else "") for c in checks))
        best = int(np.argmax(score))
        relaxed = min(counts, default=0) >= 2  # a candidate from one door is coarse: the true one may fit badly
        margin = [p.surface_margin if self._fits(c) or not relaxed else p.surface_margin_unfit for c in checks]
        rivals = [T for T, m, s, d in zip(candidates, moved, score, margin, strict=True)
                  if s > score[best] - d and _poses_differ(T, candidates[best], m, moved[best])]
        fits = self._fits(checks[best])
        if fits and rivals:
            rivals = self._not_contradicted_by_far(candidates[best], rivals)
        rivalled = bool(rivals)
        confirmed = fits and not rivalled
        if T_reg is not None:
            i_reg = next(k for k, (T, m) in enumerate(zip(candidates, moved, strict=True))
                         if not _poses_differ(T, T_reg, m, moved_reg))
            beaten = score[best] >= score[i_reg] + p.surface_margin
            contradicted = checks[i_reg].seen_through > p.surface_refuse_seen_through
            return _Choice(None, False, fits and rivalled) if beaten or contradicted or (confirmed and best != i_reg) \
                else _Choice(T_reg, True)
        return _Choice(candidates[best] if confirmed else None, False, fits and rivalled)

    def _weighed(self, poses: list[np.ndarray], reg: tuple[np.ndarray, np.ndarray] | None, points_map: np.ndarray,
                 origins_map: np.ndarray, sample: tuple[np.ndarray, np.ndarray]
                 ) -> tuple[list[np.ndarray], list[np.ndarray], list[SurfaceCheck]]:
        """The candidate poses worth checking (`_screened` by the points' `sample`), each fitted to the walls,
        with the registrar's own answer (`reg`: its pose, fitted, and the points under it) first where it is none
        of them; the map's points under each (CAD frame) and each one's surface check."""
        candidates = [self._fitted.get(T, lambda T: self._refined(T, points_map))
                      for T in self._screened(poses, *sample)]
        moved = [apply(T, points_map) for T in candidates]
        if reg is not None:
            T_reg, moved_reg = reg
            if all(_poses_differ(T, T_reg, m, moved_reg) for T, m in zip(candidates, moved, strict=True)):
                candidates.insert(0, T_reg)
                moved.insert(0, moved_reg)
        checks = [self._checked.get(T, partial(self._check, m, origins_map))
                  for T, m in zip(candidates, moved, strict=True)]
        return candidates, moved, checks

    def _fits(self, check: SurfaceCheck) -> bool:
        """Whether a pose's surface check fits the walls: enough points on them, few seen through one."""
        p = self.params
        return check.support >= p.surface_min_support and check.seen_through <= p.surface_max_seen_through

    def _not_contradicted_by_far(self, T_best: np.ndarray, rivals: list[np.ndarray]) -> list[np.ndarray]:
        """The rival poses that the far sightings do not contradict: all of them unless the best pose explains
        `far_min_explained` of the far sightings; then those explaining at least `far_margin` less are dropped."""
        p = self.params
        far = self._far_map()
        if far is None:
            return rivals
        f_best = self._far_explained(T_best, far)
        if f_best < p.far_min_explained:
            return rivals
        f_rivals = [self._far_explained(T, far) for T in rivals]
        log.info("far sightings: the best candidate pose explains %.2f of them, its rivals on the walls %s",
                 f_best, ", ".join(f"{f:.2f}" for f in f_rivals))
        return [T for T, f in zip(rivals, f_rivals, strict=True) if f > f_best - p.far_margin]

    def _resected(self, far: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> Alignment:
        """Candidate poses from the far sightings alone, before any landmark (`far_resection`): from each of the
        newest `far_pairs` keyframes that saw two far doors or windows `far_pair_min_deg` apart in bearing, the
        widest such pair matched to every pair of same-type features of the model (`graph.far`); those explaining
        `far_min_explained` of the far sightings (`_far_fractions`, `far_resection_sightings` of them, evenly
        drawn), one of each place (1 m, 5 deg), most explaining first. None is the registrar's answer: the walls
        choose (`_choose_by_surfaces`), with the full margin (no landmark vouches for any of them).

        Office_A seed 2 (`truth`) sees no door within the sighting range for 14 s, but three beyond it, 13 m away,
        from the first seconds: at 3 s the true pose is among 1310 candidates from one pair (0.15 m and 0.6 deg
        off), 368 places explain the far sightings, and the walls set it apart. `far`: `_far_map`."""
        p = self.params
        if far is None:
            return Alignment("not_localized", None)
        every = max(1, int(np.ceil(len(far[0]) / p.far_resection_sightings)))
        far = (far[0][::every], far[1][::every], far[2][::every])
        poses = []
        for camera_map, kinds, centroids_map in self._far_pairs()[-p.far_pairs:]:
            poses.append(resection_candidates(camera_map, centroids_map, self._centroids_cad(kinds[0]),
                                              self._centroids_cad(kinds[1]), self._sighting_sigma_m,
                                              same_features=kinds[0] == kinds[1]))
        if not poses or not sum(len(T) for T in poses):
            return Alignment("not_localized", None)
        T_all = np.concatenate(poses)
        explained = np.concatenate([self._far_fractions(T_all[k:k + 256], *far) for k in range(0, len(T_all), 256)])
        order = [k for k in np.argsort(-explained, kind="stable") if explained[k] >= p.far_min_explained]
        kept = distinct_poses(T_all, order, angle_rad=np.radians(5.0))
        log.info("resection from far sightings: %d candidate poses, %d explaining %.2f of %d far sightings, %d "
                 "places", len(T_all), len(order), p.far_min_explained, len(far[0]), len(kept))
        if not kept:
            return Alignment("not_localized", None)
        return Alignment("ambiguous", None, candidates=[(T, 0) for T in kept])

    def _far_refined(self, T_cad_map: np.ndarray, far: tuple[np.ndarray, np.ndarray, np.ndarray] | None
                     ) -> tuple[np.ndarray, np.ndarray | None]:
        """A pose resected from far sightings, fitted to all of the window's far sightings' bearings (`graph.far`):
        one pair's coarse ranges put it 0.15-0.3 m off (`truth`, Office_A seed 2), the keyframes' bearings
        triangulate it. `far`: `_far_map`."""
        p = self.params
        if far is None:
            return T_cad_map, None
        kinds, cameras, centroids = far
        features = {str(k): self._centroids_cad(str(k)) for k in np.unique(kinds)}
        return refined_by_bearings(T_cad_map, cameras, centroids, kinds, features, np.radians(p.far_bearing_sigma_deg),
                                   self._sighting_sigma_m, np.radians(p.far_bearing_deg))

    def _add_far_pose(self, T_cad_map: np.ndarray, sigmas: np.ndarray | None) -> None:
        """The newest keyframe's pose resected from far sightings (`_far_refined`) as a measurement in the CAD
        frame: its horizontal position and heading with the bearings' sigmas (`sigmas`, [m, rad]; none where
        they were too few), its height with `far_height_sigma_m` (the far doors' elevations: the walls do not see
        it), roll and pitch left to gravity. Without it (`truth`, Office_A seed 2) the first fits to far walls
        8 m away moved the pose 0.2 m off the bearings' (0.27 m off before the bearings' fit, 0.05 m after), and
        with no door to hold it the height wandered up to 1.1 m in the 10 s before a door came within range."""
        p = self.params
        i = self.graph.n_keyframes - 1
        information = np.zeros((6, 6))
        if sigmas is not None:
            information[2, 2] = sigmas[1] ** -2.0
            information[3, 3] = information[4, 4] = sigmas[0] ** -2.0
        information[5, 5] = p.far_height_sigma_m ** -2.0
        self.graph.add_cad_pose(i, T_cad_map @ self.graph.T_map_body(i), information)

    def _far_pairs(self) -> list[tuple[np.ndarray, tuple[str, str], np.ndarray]]:
        """Per keyframe of the far window, oldest first, the widest pair of its far sightings in horizontal
        bearing where that is `far_pair_min_deg` or more: (camera (3,), their types, their centroids (2, 3)),
        map frame."""
        pairs = []
        for i, kinds, centroids_body in self._far:
            if len(kinds) < 2:
                continue
            T_map_body = self.graph.T_map_body(i)
            camera = apply(T_map_body, self.viewer_body[None])[0]
            centroids = apply(T_map_body, centroids_body)
            bearing = np.arctan2(centroids[:, 1] - camera[1], centroids[:, 0] - camera[0])
            apart = np.abs((bearing[:, None] - bearing[None] + np.pi) % (2 * np.pi) - np.pi)
            a, b = np.unravel_index(int(np.argmax(apart)), apart.shape)
            if apart[a, b] >= np.radians(self.params.far_pair_min_deg):
                pairs.append((camera, (kinds[a], kinds[b]), centroids[[a, b]]))
        return pairs

    def _far_explained(self, T_cad_map: np.ndarray, far: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
        """The fraction of the window's far sightings (`far`, from `_far_map`) that the pose T_cad_map explains,
        turned about the newest keyframe's camera by up to `far_turn_deg` (`far_turn_step_deg` steps) to the
        heading that explains most: a same-type CAD feature lies within `far_bearing_deg` of the sighting's
        horizontal bearing from its keyframe's camera, `far_elevation_deg` of its elevation and 3 of its sigmas
        (`sighting_sigma_m`) of its horizontal range. A stereo pair
        places a door 15 m away to a metre along its line of sight but to a fraction of a degree across it: the
        bearings tell apart poses that the walls near by fit alike. The candidate's heading is known less well:
        from one door and the walls it is ~2 deg off (`perception`, Office_A seed 4: the one-door candidate, 1.9 deg
        off, explained 0.56 of its 16 far sightings as it stood and 0.94 turned; the true pose 0.69, the rest of the
        boxes 3-5 deg aside), hence the turn. The elevation is
        allowed more: the vertical is the weak part of a candidate from one door (the walls' fit holds its
        height). With the visual odometry (truth-vo, Office_A seed 4) the true one-door candidate put the far
        doors 2.5-3.6 deg low at 8 m and 0.2-1.4 deg aside; the two-door one 0.04 deg low. A door a storey up or
        down is 17 deg or more off at 10 m."""
        p = self.params
        pivot = apply(T_cad_map @ self.graph.T_map_body(self.graph.n_keyframes - 1), self.viewer_body[None])[0]
        n_turns = int(round(p.far_turn_deg / p.far_turn_step_deg)) if p.far_turn_step_deg > 0 else 0
        turns = [rot_z(np.radians(k * p.far_turn_step_deg)) for k in range(-n_turns, n_turns + 1)]
        return float(self._far_fractions(np.array([make_T(R, pivot - R @ pivot) @ T_cad_map for R in turns]),
                                         *far).max())

    def _far_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The window's far sightings: types (K,), their keyframes' cameras (K, 3) and their centroids (K, 3),
        map frame, at the keyframes' current estimates; None with fewer than `far_min_sightings`."""
        if self._n_far() < self.params.far_min_sightings:
            return None
        kinds, cameras, centroids = [], [], []
        for i, kinds_i, centroids_body in self._far:
            T_map_body = self.graph.T_map_body(i)
            kinds += kinds_i
            cameras.append(np.repeat(apply(T_map_body, self.viewer_body[None]), len(kinds_i), axis=0))
            centroids.append(apply(T_map_body, centroids_body))
        return np.array(kinds), np.vstack(cameras), np.vstack(centroids)

    def _n_far(self) -> int:
        return sum(len(kinds) for _, kinds, _ in self._far)

    def _far_fractions(self, T_cad_map: np.ndarray, kinds: np.ndarray, cameras_map: np.ndarray,
                       centroids_map: np.ndarray) -> np.ndarray:
        """The fraction of the far sightings (`_far_map`) that each of H poses T_cad_map (H, 4, 4) explains as it
        stands (see `_far_explained`), (H,)."""
        p = self.params
        cos_tol = float(np.cos(np.radians(p.far_bearing_deg)))
        elevation_tol = float(np.radians(p.far_elevation_deg))
        R, t = T_cad_map[:, :3, :3], T_cad_map[:, None, :3, 3]
        cameras = np.einsum("hij,kj->hki", R, cameras_map) + t  # (H, K, 3)
        rays = np.einsum("hij,kj->hki", R, centroids_map) + t - cameras
        explained = np.zeros(len(T_cad_map))
        for kind in np.unique(kinds):
            mine = kinds == kind
            ray = rays[:, mine]  # (H, k, 3)
            to_features = self._centroids_cad(str(kind))[None, None] - cameras[:, mine][:, :, None]  # (H, k, F, 3)
            r = np.linalg.norm(ray[..., :2], axis=-1)[..., None]  # (H, k, 1)
            d = np.linalg.norm(to_features[..., :2], axis=-1)  # (H, k, F)
            aside = np.einsum("hkfi,hki->hkf", to_features[..., :2], ray[..., :2]) >= cos_tol * d * r
            up = np.abs(np.arctan2(to_features[..., 2], d) - np.arctan2(ray[..., 2:3], r)) <= elevation_tol
            near = np.abs(d - r) <= 3 * self._sighting_sigma_m(r)
            explained += np.any(aside & up & near, axis=2).sum(axis=1)
        return explained / len(kinds)

    def _centroids_cad(self, kind: str) -> np.ndarray:
        """The centroids (N, 3) of the model's features of a type, CAD frame."""
        if kind not in self._feature_centroids:
            self._feature_centroids[kind] = np.array([f.centroid_cad for f in self.features.values()
                                                      if f.type == kind]).reshape(-1, 3)
        return self._feature_centroids[kind]

    def _screening_sample(self, points_map: np.ndarray, origins_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`surface_screen_points` of the points and their cameras, evenly drawn, to screen candidates by."""
        every = max(1, int(np.ceil(len(points_map) / self.params.surface_screen_points)))
        return points_map[::every], origins_map[::every]

    def _screened(self, poses: list[np.ndarray], pts: np.ndarray, origins: np.ndarray) -> list[np.ndarray]:
        """The candidate poses worth fitting to the walls: all of a few; of more (one door: each alike door of the
        building, from either side, most of them in rooms whose walls stand nowhere near the points), the
        `surface_screen_top` that score best by the points `pts` (`_screening_sample`, seen from `origins`) as
        they are, unfitted (turned to the walls' heading before, `_turned`). The points'
        support under every pose is one k-d tree query; only the best supported 3 x `surface_screen_top` have
        their lines of sight checked (most of a check's cost)."""
        p = self.params
        assert self.surfaces is not None
        if len(poses) <= p.surface_screen_top:
            return poses
        R = np.stack([T[:3, :3] for T in poses])
        t = np.stack([T[:3, 3] for T in poses])
        support = self.surfaces.supports(np.einsum("hij,nj->hni", R, pts) + t[:, None, :])
        supported = np.argsort(-support, kind="stable")[: 3 * p.surface_screen_top]
        score = np.array([self.surfaces.check(apply(poses[k], pts), apply(poses[k], origins)).score
                          for k in supported])
        ranked = np.argsort(-score, kind="stable")
        log.debug("screened %d candidate poses by %d points: best %s", len(poses), len(pts),
                  score[ranked[: p.surface_screen_top]].round(2).tolist())
        self.surface_screens.append((len(poses), score[ranked].round(3).tolist()))
        return [poses[k] for k in supported[ranked[: p.surface_screen_top]]]

    def _turned(self, candidates: list[tuple[np.ndarray, int]], pts_map: np.ndarray, fewest: int,
                most: int) -> list[np.ndarray]:
        """The candidate poses, each one from `fewest` to `most` landmarks turned about the vertical through a
        landmark (the one its pose puts nearest a same-type CAD feature) to the heading, within `surface_turn_deg`,
        whose unfitted support by `surface_turn_points` of the points `pts_map` is highest (ties: the least turn)
        among the headings that leave as many landmarks within `registration_tolerance_m` of a same-type CAD
        feature, searched in steps of twice `surface_turn_step_deg`, then one step either side.

        A pose from one door has the heading of that door's normal, which perception's corners get wrong by
        ~20 deg on a door seen obliquely (Office_A seed 4: a door seen through another doorway, whose jamb hides
        one of its sides; its normal was off by a median 18 deg in 69 sightings over 16 s, 66 of them the same
        way); one from two or three doors a few metres apart, whose corners are coarse at range, by 5-13 deg
        (Office_A seed 5: 1.45 m and 12.9 deg, then 0.6 m and 5.3 deg). The wall fit (`_refined`) moves a pose
        only so far; the walls around a door hold its heading over metres, not over the door's width."""
        p = self.params
        poses = [T for T, _ in candidates]
        few = [k for k, (_, n) in enumerate(candidates) if fewest <= n <= most]
        if p.surface_turn_deg <= 0 or not few or not len(pts_map):
            return poses
        pts_map = pts_map[:: max(1, int(np.ceil(len(pts_map) / p.surface_turn_points)))]
        step = np.radians(p.surface_turn_step_deg)
        coarse = np.arange(1, int(p.surface_turn_deg / p.surface_turn_step_deg / 2) + 1) * 2 * step
        coarse = np.concatenate([[0.0], np.ravel(np.column_stack([coarse, -coarse]))])  # the least turn first
        confirmed = self._confirmed()
        centres_map = {j: self.graph.T_map_rect(j)[:3, 3] for j in confirmed}
        surfaces = self.surfaces
        assert surfaces is not None
        pivots = {k: c for k in few if (c := self._landmark_at_a_feature(poses[k], centres_map)) is not None}
        ks = list(pivots)
        if not ks:
            return poses
        pivot = np.stack([pivots[k] for k in ks])[:, None, None, :]  # (K, 1, 1, 3)
        moved = np.stack([apply(poses[k], pts_map) for k in ks])[:, None] - pivot  # (K, 1, N, 3)
        landmarks = np.stack([apply(poses[k], np.stack(list(centres_map.values())))
                              for k in ks])[:, None] - pivot  # (K, 1, L, 3)
        kinds = [self.landmarks[j].type for j in confirmed]

        def turned(turns: np.ndarray, x: np.ndarray) -> np.ndarray:  # (K, H) turns of (K, 1, M, 3) -> (K, H, M, 3)
            return np.einsum("khij,kxnj->khni", rot_z(turns), x) + pivot

        def by_a_feature(turns: np.ndarray) -> np.ndarray:  # (K, H) turns -> (K, H) landmarks by a CAD feature
            x = turned(turns, landmarks)
            return sum((np.min(np.linalg.norm(x[:, :, i, None, :] - self._centroids_cad(kind), axis=-1), axis=-1,
                               initial=np.inf) <= p.registration_tolerance_m).astype(int)
                       for i, kind in enumerate(kinds))

        def supports(turns: np.ndarray) -> np.ndarray:  # (K, H) turns -> (K, H) supports, -1 where doors are lost
            x = turned(turns, moved)
            support = surfaces.supports(x.reshape(-1, *x.shape[2:])).reshape(turns.shape)
            return np.where(by_a_feature(turns) >= explained, support, -1.0)

        explained = by_a_feature(np.zeros((len(ks), 1)))  # (K, 1), as the candidates stand
        support = supports(np.broadcast_to(coarse, (len(ks), len(coarse))))
        best = np.argmax(support, axis=1)  # the first of the best: the least turn
        fine = coarse[best][:, None] + np.array([-step, step])  # then a step either side of the best
        support_fine = supports(fine)
        better = support_fine.max(axis=1) > support[np.arange(len(ks)), best]
        turn = np.where(better, fine[np.arange(len(ks)), np.argmax(support_fine, axis=1)], coarse[best])
        for k, theta, c in zip(ks, turn, pivot[:, 0, 0], strict=True):
            if theta != 0.0:
                R = rot_z(theta)
                poses[k] = make_T(R, c - R @ c) @ poses[k]
        return poses

    def _landmark_at_a_feature(self, T_cad_map: np.ndarray, centres_map: dict[int, np.ndarray]) -> np.ndarray | None:
        """The CAD-frame centre, under T_cad_map, of the landmark it puts nearest a CAD feature of its type."""
        best, best_d = None, np.inf
        for j, x_map in centres_map.items():
            x_cad = apply(T_cad_map, x_map[None])[0]
            centroids = self._centroids_cad(self.landmarks[j].type)
            d = float(np.min(np.linalg.norm(centroids - x_cad, axis=1))) if len(centroids) else np.inf
            if d < best_d:
                best, best_d = x_cad, d
        return best

    def _check(self, moved: np.ndarray, origins_map: np.ndarray, T_cad_map: np.ndarray) -> SurfaceCheck:
        """The surface check of the points `moved` by T_cad_map, seen from `origins_map`."""
        assert self.surfaces is not None
        return self.surfaces.check(moved, apply(T_cad_map, origins_map))

    def _refined(self, T_cad_map: np.ndarray, points_map: np.ndarray) -> np.ndarray:
        """A candidate pose fitted to the walls by the map's depth points (point-to-plane, roll, pitch and height
        held: the walls hardly see the height, and a few sloped faces would set it alone; the floor fits after
        localizing take it from the doors'), or as it was where the fit fails or moves the points further than
        `surface_refine_m`. A pose from two or
        three doors' corners is off by tenths of a metre and a degree or two (their corners are coarse at range):
        enough to put points beyond the check's tolerance of their walls, and lines of sight through a doorway
        into its jambs. The check should judge the place a candidate stands for, not its error."""
        if self.params.surface_refine_m <= 0:
            return T_cad_map
        assert self.surfaces is not None
        points_map = points_map[:: max(1, int(np.ceil(len(points_map) / 500)))]  # a pose's fit needs no more
        # the points are in the map frame, not around one camera: no range-dependent noise in their weights
        fit = align_to_surfaces(self.surfaces, points_map, T_cad_map, iterations=8, depth_sigma_per_m2=0.0,
                                max_distance_m=self.params.surface_refine_m, sigma_m=self.params.surface_fit_sigma_m,
                                hold_height=True)
        if fit is None:
            return T_cad_map
        moved = np.linalg.norm(apply(np.linalg.inv(T_cad_map) @ fit.T_cad_body, points_map) - points_map, axis=1)
        return fit.T_cad_body if float(moved.mean()) <= self.params.surface_refine_m else T_cad_map

    def _register(self, stamp_ns: int) -> None:
        """Register the map's landmarks to the model; on success anchor the graph to the CAD frame."""
        keys = self._confirmed()
        observed = [ObservedRect(j, self.landmarks[j].type, self.graph.T_map_rect(j)) for j in keys]
        corners = [self.landmarks[o.key].corners(o.T_map_rect) for o in observed]
        far = None if keys else self._far_map()  # resecting from far sightings: once for the attempt
        result = self.registrar(observed, corners) if keys else self._resected(far)
        self._fitted, self._checked = _PerPose(), _PerPose()
        choice = self._choose_by_surfaces(result, stamp_ns)
        # the walls confirm none of the candidates: the next registrar's, unless two of these fit the walls alike
        # and the next one's candidates hold them (`Alignment.fallback_holds_these`): it cannot tell them apart
        # either. Otherwise a fuller registrar may (the model's doors that a stored map lacks), or may answer
        # 'localized' by itself.
        while choice.T_cad_map is None and not (choice.rivals_fit and result.fallback_holds_these) \
                and result.fallback is not None:
            result = result.fallback()
            choice = self._choose_by_surfaces(result, stamp_ns)
        T_cad_map, registrars = choice.T_cad_map, choice.registrars
        far_sigmas = None
        if T_cad_map is not None and not keys:
            T_cad_map, far_sigmas = self._far_refined(T_cad_map, far)
        self._registered_with = len(keys)
        self._registered_at = (stamp_ns, self._n_points())
        self.inliers = result.inliers
        if T_cad_map is None:
            status = "exploring" if result.status == "not_localized" else "ambiguous"
            self.registrations.append((stamp_ns, status))
            self.status = status
            log.info("registration of %d landmarks: %s (%d inliers)", len(keys), result.status, result.inliers)
            return
        self.registrations.append((stamp_ns, "localized"))
        log.info("localized with %d inliers of %d landmarks (%d matches)", result.inliers, len(keys),
                 len(result.matches))
        self.graph.add_anchor(np.linalg.inv(T_cad_map))
        self._anchored_at = self.graph.n_keyframes - 1
        self._fit_newest_to_surfaces(anchoring=True)  # at the pose the walls chose, before the doors' links
        if not keys:  # resected from far doors: their bearings hold the pose while no door does
            self._add_far_pose(T_cad_map, far_sigmas)
        if registrars:  # the registrar's own pose (fitted to the walls): its matches hold
            for j, fid in result.matches:
                self._link(j, fid, T_cad_map)
        self.status = "localized"
        self._last_link_ns = stamp_ns
        self.graph.update(extra_iterations=2)
        self._link_new_landmarks(stamp_ns)

    def _add_placed(self, i: int, stamp_ns: int, T_cad_body: np.ndarray) -> None:
        """Keyframe i placed in a stored map (its pose there times the map's T_cad_map): before the graph is
        anchored, it anchors it, unless more than `surface_refuse_seen_through` of the depth points would be seen
        through a wall; then (and once anchored) it enters the graph as a measured T_cad_body, robustly, and
        counts as a CAD-linked sighting for the status: the stored map's keyframes were linked to the model."""
        p = self.params
        if not self.graph.has_anchor:
            T_cad_map = T_cad_body @ np.linalg.inv(self.graph.T_map_body(i))
            if self._can_check_surfaces():
                points_map, origins_map = self._points_map()
                check = self._check(apply(T_cad_map, points_map), origins_map, T_cad_map)
                log.info("placed in the stored map: %.2f of %d points on surfaces, %.2f seen through walls",
                         check.support, len(points_map), check.seen_through)
                if check.seen_through > p.surface_refuse_seen_through:
                    return
            log.info("localized by place recognition in the stored map")
            self.graph.add_anchor(np.linalg.inv(T_cad_map))
            self._anchored_at = i
            self.registrations.append((stamp_ns, "localized"))
            self.status = "localized"
        sigmas = np.r_[np.full(3, np.radians(p.placed_sigma_deg)), np.full(3, p.placed_sigma_m)]  # [rot; trans]
        self.graph.add_cad_pose(i, T_cad_body, np.diag(sigmas**-2.0))
        self.placed.append(i)
        self._last_link_ns = stamp_ns
        self.graph.update(extra_iterations=2)
        self._link_new_landmarks(stamp_ns)

    def _fit_newest_to_surfaces(self, anchoring: bool = False) -> None:
        """The newest keyframe fitted to the walls (`_fit_to_surfaces`), once, where it has depth points and the
        graph is anchored. On the keyframe that anchors it (`anchoring`), before the doors found in the
        registration are linked, and to the walls alone, its height held: linked first, the pose is where their
        coarse positions put it, and the fit from there may be refused as too large (perception, Office_A seed 5:
        three doors linked by their positions put the pose 0.6 m and 5.3 deg from where the walls chose it, 0.16 m
        and 0.6 deg from the truth); the height is the doors' (the candidate's was the registration's, and
        perception's floor points put Office_A seed 7's 0.15 m low there). That fit takes the window's points,
        those the pose was chosen and fitted by (`_refined`), not the keyframe's alone: on its 300 points a fit
        moved `truth` Office_A seed 5's (noise seed 2) pose from 0.13 to 0.50 m off, too far for its door to be
        linked, and the flight's height then sank 0.67 m until the next doors (APE 0.112 m; 0.078 m now)."""
        i = self.graph.n_keyframes - 1
        if not self.graph.has_anchor or not self._points or self._points[-1][0] != i or self._fit_tried_at == i:
            return
        self._fit_tried_at = i
        _, points_body, floor_body = self._points[-1]
        if anchoring:  # the window's points, as the candidate was chosen and fitted by (`_refined`)
            points_body = apply(np.linalg.inv(self.graph.T_map_body(i)), self._points_map()[0])
        self._fit_to_surfaces(i, points_body, floor_body if not anchoring else None)

    def _fit_to_surfaces(self, i: int, points_body: np.ndarray, floor_body: np.ndarray | None) -> None:
        """Keyframe i's depth points fitted to the model's walls and floors (point-to-plane) enter the graph as a
        measured T_cad_body with the fit's information: the walls hold the pose where the doors' corners are
        coarse, the floor holds its height; without floor points (`floor_body` None) the height is held as it is."""
        T_cad_map = self.graph.T_cad_map()
        if not self.params.surface_fit or self.surfaces is None or T_cad_map is None:
            return
        T_guess = T_cad_map @ self.graph.T_map_body(i)
        fit = align_to_surfaces(self.surfaces, points_body, T_guess, floor_body,
                                sigma_m=self.params.surface_fit_sigma_m, hold_height=floor_body is None)
        if fit is None:
            return
        step = np.linalg.inv(T_guess) @ fit.T_cad_body
        if np.linalg.norm(step[:3, 3]) > self.params.surface_fit_max_correction_m or \
                rotation_angle_deg(step[:3, :3]) > self._max_fit_turn_deg(i):
            return
        self.graph.add_cad_pose(i, fit.T_cad_body, fit.information)
        self.graph.update()
        self.surface_fits += 1

    def _max_fit_turn_deg(self, i: int) -> float:
        """How far a fit to the walls may turn keyframe i's pose: further while the pose settles after localizing
        (a pose found by one door carries that door's orientation error, a few degrees, until the walls turn it
        back), less once it is held by the walls and more doors (a larger turn is then a fit to a wrong wall)."""
        p = self.params
        settling = self._anchored_at is not None and i - self._anchored_at < p.surface_fit_settling_keyframes
        return p.surface_fit_settling_turn_deg if settling else p.surface_fit_max_turn_deg

    def _link_new_landmarks(self, stamp_ns: int) -> None:
        """Landmarks not yet linked that lie within `cad_link_m` of a same-type CAD feature are linked."""
        T_cad_map = self.graph.T_cad_map()
        assert T_cad_map is not None
        linked = set(self.links.values())
        added = False
        for j, lm in self.landmarks.items():
            if j in self.links:
                continue
            T_cad_rect = T_cad_map @ self.graph.T_map_rect(j)
            fid = self._nearest_feature(lm.type, T_cad_rect[:3, 3], exclude=linked)
            if fid is not None:
                self._link(j, fid, T_cad_map)
                linked.add(fid)
                added = True
                self._last_link_ns = stamp_ns
        if added:
            self.graph.update()

    def _nearest_feature(self, kind: str, xyz_cad: np.ndarray, exclude: set[str]) -> str | None:
        best, best_d = None, self.params.cad_link_m
        for f in self.features.values():
            if f.type != kind or f.orientation != "vertical" or f.id in exclude:
                continue
            d = float(np.linalg.norm(f.centroid_cad - xyz_cad))
            if d < best_d:
                best, best_d = f.id, d
        return best

    def _link(self, j: int, fid: str, T_cad_map: np.ndarray) -> None:
        """Landmark j is CAD feature `fid`: its position, and its orientation where the landmark's lies within
        `cad_link_max_turn_deg` of the feature's. A door's orientation is its corners' plane, and a door seen
        obliquely through another doorway, one side hidden by that doorway's jamb, had it a median 18 deg off,
        nearly always the same way (perception, Office_A seed 4). Linked by its orientation, that door turned
        the flight to fit it (yaw 12-16 deg off after localizing, 2.8 m APE: the walls' fits refuse such a
        turn); by its position only, the walls and the odometry keep the heading."""
        feature = self.features.get(fid)
        if feature is None or feature.orientation != "vertical":
            return
        T_cad_pred = T_cad_map @ self.graph.T_map_rect(j)
        T_cad_rect = closer_flip(feature_frame_cad(feature), T_cad_pred)
        turn_deg = rotation_angle_deg(T_cad_rect[:3, :3].T @ T_cad_pred[:3, :3])
        oriented = turn_deg <= self.params.cad_link_max_turn_deg
        if not oriented:
            log.info("landmark %d linked to %s by its position only: its orientation is %.1f deg off", j, fid,
                     turn_deg)
        self.graph.add_cad_link(j, T_cad_rect, CAD_LINK_SIGMAS if oriented else CAD_LINK_POSITION_SIGMAS)
        self.links[j] = fid

    def _update_status(self, stamp_ns: int) -> None:
        if self.status not in ("localized", "degraded", "lost") or self._last_link_ns is None:
            return
        silent_s = (stamp_ns - self._last_link_ns) * 1e-9
        p = self.params
        self.status = "lost" if silent_s > p.lost_after_s else "degraded" if silent_s > p.degraded_after_s \
            else "localized"

    def stored_map(self) -> StoredMap:
        """This flight's map for a later flight to re-localize into (graph.mapstore)."""
        T_cad_map = self.graph.T_cad_map()
        keyframes = [(s, self.graph.T_map_body(i)) for i, s in enumerate(self.keyframe_stamps_ns)]
        poses = {j: self.graph.T_map_rect(j) for j in self.landmarks}
        landmarks = [StoredLandmark(j, lm.type, poses[j], lm.corners(poses[j]), self.links.get(j))
                     for j, lm in self.landmarks.items()]
        return StoredMap(self.model.sha256, T_cad_map, keyframes, landmarks, dict(self.views))

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


def model_registrar(model: BuildingModel, params: LocalizerParams, storey_hint: str | None = None,
                    with_surfaces: bool = False, method: str = "robust") -> ModelRegistrar:
    """The registrar against the whole model, from the localizer's parameters (one place for replay and the
    service): candidates from `verified_min_landmarks` on when the surface check can decide among them. Then it
    also seeds hypotheses from every landmark (up to its `max_seeds`), not only until a pose explains half of them
    (`registration_early_stop`): with perception's false and misplaced doors, two seeds can both be wrong, and
    a wrong pose explaining half the landmarks at a 0.6 m tolerance then stops the search with the true pose
    never hypothesised (perception, Office_A seed 7: 4 of 7 landmarks, `ambiguous` from 8.8 to 15.6 s, the walls
    refusing every candidate; seeded from all, the walls took the true pose at 5.6 s)."""
    seeding = {"early_stop_fraction": params.registration_early_stop} if with_surfaces and method == "robust" else {}
    return ModelRegistrar(model, method=method, storey_hint=storey_hint,
                          min_landmarks=params.registration_min_landmarks, tolerance_m=params.registration_tolerance_m,
                          candidates_from=params.verified_min_landmarks if with_surfaces else None, **seeding)


class _PerPose(Generic[V]):
    """Values computed once per pose (T_cad_map, equal to rounding) within one registration attempt: a stored
    map's candidates and the model's after them share poses."""

    def __init__(self) -> None:
        self._items: list[tuple[np.ndarray, V]] = []

    def get(self, T: np.ndarray, compute: Callable[[np.ndarray], V]) -> V:
        """`compute(T)`, or its value for an equal pose computed before."""
        for T_known, value in self._items:
            if _same_pose(T_known, T):
                return value
        value = compute(T)
        self._items.append((T, value))
        return value


class _Choice(NamedTuple):
    """The walls' verdict on a registration (`Localizer._choose_by_surfaces`): the pose to anchor with or None,
    whether it is the registrar's own answer, and whether two different candidates fit the walls alike."""

    T_cad_map: np.ndarray | None
    registrars: bool
    rivals_fit: bool = False


def _same_pose(A: np.ndarray, B: np.ndarray, tol_m: float = 1e-3, tol_rad: float = 1e-4) -> bool:
    """Two T_cad_map equal to rounding (the same candidate offered by two registrars)."""
    return bool(np.abs(A[:3, 3] - B[:3, 3]).max() <= tol_m and np.abs(A[:3, :3] - B[:3, :3]).max() <= tol_rad)


def stored_registrar(model: BuildingModel, known: list[KnownRect], params: LocalizerParams,
                     with_surfaces: bool = False) -> StoredMapRegistrar:
    """The registrar against a stored map's CAD-linked features (re-localization): localized from two agreeing
    landmarks; with the surface check, candidate poses from `verified_min_landmarks` on, for the walls."""
    return StoredMapRegistrar(known, min_landmarks=2, model=model,
                              candidates_from=params.verified_min_landmarks if with_surfaces else None)


def _poses_differ(A: np.ndarray, B: np.ndarray, moved_A: np.ndarray, moved_B: np.ndarray, apart_m: float = 0.5,
                  turned_deg: float = 5.0) -> bool:
    """Two candidate T_cad_map are different poses where they place the points (`moved_A`, `moved_B`: the same
    map-frame points under each) `apart_m` apart on average, or differ in rotation by `turned_deg` (not at the
    map's origin, which may be far away)."""
    moved = float(np.linalg.norm(moved_A - moved_B, axis=1).mean())
    return moved > apart_m or rotation_angle_deg(A[:3, :3] @ B[:3, :3].T) > turned_deg
