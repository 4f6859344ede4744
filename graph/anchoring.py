"""Anchoring the map to the building model: registration attempts while exploring, keyframes placed in a stored
map, and the status that follows.

While not localized, the confirmed landmarks are registered to the model (the registrar, graph.registrar) when a
landmark was confirmed since the last attempt, or, with the surface check, when `surface_retry_s` passed and more
depth points came in: the walls decide as they are seen. With no landmark yet, candidate poses are resected from
the doors seen beyond the sighting range (graph.far_window). The registrar's answer and candidates are weighed
against the walls (graph.judge); where the walls confirm none of them, the next registrar's are (a saved map's
few poses first, the whole model's after: `FirstOfRegistrar`). A pose taken anchors the graph, the anchoring
keyframe is fitted to the walls (graph.surface_fit), and the registration's matches and then every landmark near
a CAD feature are linked (graph.cad_links).

Frames: map (the flight's odometry frame, z up), body, cad (the model's); T_cad_map maps map points into cad.
"""

from __future__ import annotations

import logging
from typing import Protocol

import numpy as np

from macroloc.graph.cad_links import CadLinks
from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.far_window import FarSightings
from macroloc.graph.judge import Choice, Judge
from macroloc.graph.landmark_map import LandmarkMap
from macroloc.graph.params import AnchorParams, FarParams, RegistrationParams, StatusParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.prior import PosePrior
from macroloc.graph.registrar import Registrar
from macroloc.graph.relocalize import Alignment, ObservedRect
from macroloc.graph.robust import RobustParams

log = logging.getLogger(__name__)


class Fitter(Protocol):
    """The keyframes' fits to the model's surfaces (graph.surface_fit)."""

    def anchored_at(self, i: int) -> None: ...

    def fit_newest(self, anchoring: bool = False) -> None: ...


class Anchoring:
    """The map's anchoring to the model and the status (see module doc)."""

    def __init__(self, params: RegistrationParams, anchor: AnchorParams, far_params: FarParams,
                 status: StatusParams, graph: PoseGraph, registrar: Registrar, judge: Judge, depth: DepthWindow,
                 far: FarSightings, landmarks: LandmarkMap, links: CadLinks, fitter: Fitter) -> None:
        self.params, self.anchor, self.far_params, self.status_params = params, anchor, far_params, status
        self.graph, self.registrar, self.judge = graph, registrar, judge
        self.depth, self.far, self.landmarks, self.links, self.fitter = depth, far, landmarks, links, fitter
        self.status = "exploring"  # exploring | localized | ambiguous | degraded | lost
        self.inliers = 0
        self.rivals: list[np.ndarray] = []  # T_cad_map of the poses the last 'ambiguous' registration left apart
        self.registrations: list[tuple[int, str]] = []  # (stamp_ns, status) of every registration attempt
        self.placed: list[int] = []  # keyframes placed in a saved map (place recognition) and taken
        self._registered_with = 0
        self._registered_at: tuple[int, int] = (0, 0)  # (stamp_ns, depth points) of the last registration
        self._held = True  # whether the pose was held (`held`) when last asked
        self.prior: PosePrior | None = None  # the operator's (graph.prior): picks among tied poses only
        self.by_prior: list[int] = []  # stamps of the registrations the prior decided

    def set_prior(self, prior: PosePrior | None) -> None:
        """The operator's prior (graph.prior; None: forget it). While not localized the next keyframe registers
        again, for the prior to choose among what the registration leaves tied; it never skips the registration."""
        self.prior = prior
        self._registered_with, self._registered_at = 0, (0, -1)

    def confirmed(self) -> list[int]:
        """The landmarks seen often enough (`min_sightings_to_register`) to take part in a registration."""
        return self.landmarks.confirmed(self.params.min_sightings_to_register)

    def can_check_surfaces(self) -> bool:
        return self.judge.can_check(self.depth.n_points)

    def should_register(self, stamp_ns: int) -> bool:
        """While not localized: when a landmark was confirmed since the last attempt, or (with the surface
        check) when `surface_retry_s` passed and more depth points came in: the walls decide as they are seen."""
        if self.status not in ("exploring", "ambiguous"):
            return False
        n = len(self.confirmed())
        if not self.can_check_surfaces():
            return n >= self.registrar.min_landmarks and n > self._registered_with
        last_ns, last_points = self._registered_at
        retry_s = self.params.surface_retry_s
        more_walls = (stamp_ns - last_ns) * 1e-9 >= retry_s and self.depth.n_points > last_points
        if n < self.registrar.candidates_from:
            return more_walls and self.far_params.far_resection and len(self.far) >= self.far_params.far_min_sightings
        return n > self._registered_with or more_walls

    def register(self, stamp_ns: int) -> None:
        """Register the map's landmarks (or, with none, the far sightings) to the model; on success anchor the
        graph to the CAD frame."""
        keys = self.confirmed()
        observed, corners = self.landmarks.observed(keys)
        far = None if keys else self.far.in_map()  # resecting from far sightings: once for the attempt
        result = self.registrar(observed, corners) if keys else self.far.resected(far)
        self.judge.new_attempt()
        choice = self._choose(result, stamp_ns)
        # the walls confirm none of the candidates: the next registrar's, unless two of these fit the walls alike
        # and the next one's candidates hold them (`Alignment.fallback_holds_these`): it cannot tell them apart
        # either. Otherwise a fuller registrar may (the model's doors that a saved map lacks), or may answer
        # 'localized' by itself.
        while choice.T_cad_map is None and not (choice.rivals_fit and result.fallback_holds_these) \
                and result.fallback is not None:
            result = result.fallback()
            choice = self._choose(result, stamp_ns)
        if choice.T_cad_map is not None and not choice.registrars and len(keys) >= 2:
            choice = self._unrivalled_by_one(choice, keys, observed, corners)
        T_cad_map, registrars = choice.T_cad_map, choice.registrars
        if T_cad_map is None and self.prior is not None and result.status == "ambiguous":
            T_cad_map = self.prior.pick(self._tied(choice, result), self.graph.T_map_body(self.graph.n_keyframes - 1))
            if T_cad_map is not None:
                self.by_prior.append(stamp_ns)
                log.info("the prior (%s) picked one of the poses the registration left tied", self.prior.describe())
        far_sigmas = None
        if T_cad_map is not None and not keys:
            T_cad_map, far_sigmas = self.far.refined(T_cad_map, far)
        self._registered_with = len(keys)
        self._registered_at = (stamp_ns, self.depth.n_points)
        self.inliers = result.inliers
        if T_cad_map is None:
            status = "exploring" if result.status == "not_localized" else "ambiguous"
            self.registrations.append((stamp_ns, status))
            self.status = status
            self.rivals = (list(choice.rivals) or rival_poses(result)) if status == "ambiguous" else []
            log.info("registration of %d landmarks: %s (%d inliers)", len(keys), result.status, result.inliers)
            return
        self.registrations.append((stamp_ns, "localized"))
        self.rivals = []
        log.info("localized with %d inliers of %d landmarks (%d matches)", result.inliers, len(keys),
                 len(result.matches))
        self.graph.add_anchor(np.linalg.inv(T_cad_map))
        self.fitter.anchored_at(self.graph.n_keyframes - 1)
        self.fitter.fit_newest(anchoring=True)  # at the pose the walls chose, before the doors' links
        if not keys:  # resected from far doors: their bearings hold the pose while no door does
            self._add_far_pose(T_cad_map, far_sigmas)
        if registrars:  # the registrar's own pose (fitted to the walls): its matches hold
            for j, fid in result.matches:
                self.links.link(j, fid, T_cad_map)
        self.status = "localized"
        self.links.last_link_ns = stamp_ns
        self.graph.update(extra_iterations=2)
        self.links.link_new(self.landmarks.landmarks, stamp_ns)

    def _unrivalled_by_one(self, choice: Choice, keys: list[int], observed: list[ObservedRect],
                           corners: list[np.ndarray]) -> Choice:
        """The walls' choice among candidates from several landmarks (`choice`), or none where a pose from one
        of the landmarks alone rivals it (`Judge.rivals_from_one`): then the two are left tied. Any one landmark
        may be a false detection that a wrong pose puts on a model door; asked only where a landmark the pose puts
        by a CAD feature differs from it in size (`_sizes_alike`): a true landmark of the feature's size on it is
        evidence that the pose from one landmark lacks (Office_A's seed 5901: a false door 1.52 m wide on a door
        1.07 m wide, docs/measurements.md, "A false door that lands on a model door")."""
        assert choice.T_cad_map is not None
        if self._sizes_alike(choice.T_cad_map, keys):
            return choice
        poses = [np.asarray(T, float) for lm, c in zip(observed, corners, strict=True)
                 for T, _ in self.registrar([lm], [c]).candidates]
        points_map, origins_map = self.depth.points_map()
        T_newest = self.graph.T_map_body(self.graph.n_keyframes - 1)
        rivals = self.judge.rivals_from_one(
            choice.T_cad_map, poses, points_map, origins_map, self.landmarks.centres_map(keys),
            lambda T_best, rivals: self.far.not_contradicted(T_best, rivals, T_newest))
        if not rivals:
            return choice
        return Choice(None, False, True, (choice.T_cad_map, *rivals))

    def _sizes_alike(self, T_cad_map: np.ndarray, keys: list[int]) -> bool:
        """Whether every landmark of `keys` that T_cad_map puts within `inlier_threshold_m` of a CAD feature has
        that feature's width and height within the registration's `size_tolerance_m` (the rule by which a
        rectangle is alike to a feature, graph.robust; a side cut by the image border in every sighting: at
        least the feature's less the tolerance)."""
        tolerance_m = RobustParams().size_tolerance_m  # the flight's registrar keeps the method's default
        features = [f for f in self.links.features.values() if f.orientation == "vertical"]
        if not features:
            return True
        centroids = np.stack([f.centroid_cad for f in features])
        for j in keys:
            x_cad = (T_cad_map @ self.graph.T_map_rect(j))[:3, 3]
            d = np.linalg.norm(centroids - x_cad, axis=1)
            k = int(np.argmin(d))
            if d[k] > self.params.inlier_threshold_m:
                continue
            lm, f = self.landmarks.landmarks[j], features[k]
            for size, cad, cut in zip(lm.size_m(), (f.width_m, f.height_m), lm.cut(), strict=True):
                if (size < cad - tolerance_m) if cut else abs(size - cad) >= tolerance_m:
                    return False
        return True

    def _tied(self, choice: Choice, result: Alignment) -> list[np.ndarray]:
        """The poses an 'ambiguous' attempt left tied, for a prior to pick from (graph.prior): with the walls, their
        tied candidates where the best fits them (`Choice.rivals_fit`); without, the registration's candidates
        that explain as many landmarks as the best, if that is `min_landmarks` or more (each an answer by itself
        but for the others)."""
        if self.can_check_surfaces():
            return list(choice.rivals) if choice.rivals_fit else []
        most = max((n for _, n in result.candidates), default=0)
        if most < self.registrar.min_landmarks:
            return []
        return [np.asarray(T, float) for T, n in result.candidates if n == most]

    def _choose(self, result: Alignment, stamp_ns: int) -> Choice:
        """The registrar's answer and candidates weighed against the walls (graph.judge); without enough depth
        points only the registrar's own 'localized' counts."""
        T_reg = result.T_cad_map if result.status == "localized" else None
        if not self.can_check_surfaces():
            return Choice(T_reg, T_reg is not None)
        points_map, origins_map = self.depth.points_map()
        T_newest = self.graph.T_map_body(self.graph.n_keyframes - 1)
        confirmed = self.confirmed()
        return self.judge.choose(result, stamp_ns, points_map, origins_map, self.landmarks.centres_map(confirmed),
                                 lambda T_best, rivals: self.far.not_contradicted(T_best, rivals, T_newest),
                                 self.landmarks.walls_map(confirmed), lambda T: self.far.explains(T, T_newest))

    def _add_far_pose(self, T_cad_map: np.ndarray, sigmas: np.ndarray | None) -> None:
        """The newest keyframe's pose resected from far sightings (`FarSightings.refined`) as a measurement in the
        CAD frame: its horizontal position and heading with the bearings' sigmas (`sigmas`, [m, rad]; none where
        they were too few), its height with `far_height_sigma_m` (the far doors' elevations: the walls do not see
        it), roll and pitch left to gravity. Without it, fits to walls far away would move the pose off the
        bearings' and, with no door to hold it, its height would wander
        (docs/measurements.md, "The far resection's pose holds the keyframe")."""
        i = self.graph.n_keyframes - 1
        information = np.zeros((6, 6))  # [rot; trans], body tangent
        if sigmas is not None:
            information[2, 2] = sigmas[1] ** -2.0
            information[3, 3] = information[4, 4] = sigmas[0] ** -2.0
        information[5, 5] = self.far_params.far_height_sigma_m ** -2.0
        self.graph.add_cad_pose(i, T_cad_map @ self.graph.T_map_body(i), information)

    def place(self, i: int, stamp_ns: int, T_cad_body: np.ndarray) -> None:
        """Keyframe i placed in a saved map (its pose there times the map's T_cad_map): before the graph is
        anchored, it anchors it, unless the walls contradict it (`SurfaceJudge.contradicts`); then (and once
        anchored) it enters the graph as a measured T_cad_body, robustly, and counts as a CAD-linked sighting for
        the status: the saved map's keyframes were linked to the model."""
        if not self.graph.has_anchor:
            T_cad_map = T_cad_body @ np.linalg.inv(self.graph.T_map_body(i))
            if self.can_check_surfaces() and self.judge.contradicts(T_cad_map, *self.depth.points_map()):
                return
            log.info("localized by place recognition in the saved map")
            self.graph.add_anchor(np.linalg.inv(T_cad_map))
            self.fitter.anchored_at(i)
            self.registrations.append((stamp_ns, "localized"))
            self.status = "localized"
        a = self.anchor
        sigmas = np.r_[np.full(3, np.radians(a.placed_sigma_deg)), np.full(3, a.placed_sigma_m)]  # [rot; trans]
        self.graph.add_cad_pose(i, T_cad_body, np.diag(sigmas**-2.0))
        self.placed.append(i)
        self.links.last_link_ns = stamp_ns
        self.graph.update(extra_iterations=2)
        self.links.link_new(self.landmarks.landmarks, stamp_ns)

    def held(self) -> bool:
        """Whether the graph is anchored and the newest keyframe's horizontal sigma is within `held_sigma_m`: a
        wall fit or a link by proximity is a local association, right only where the pose is known within its
        reach. A pose the odometry carried alone (dead-reckoned, loosened) is not: a fit from there may lock onto
        another wall and a false door may land by a model door, and either would then hold the wrong pose with a
        small sigma (docs/measurements.md, "A pose the odometry carried alone: not held")."""
        if not self.graph.has_anchor:
            return False
        sigma_m = self.graph.horizontal_sigma_m(self.graph.n_keyframes - 1)
        held = sigma_m <= self.status_params.held_sigma_m
        if held != self._held:
            log.info("the pose is %s: horizontal sigma %.2f m (limit %.2f m)", "held again" if held else
                     "no longer held, no wall fits or new links", sigma_m, self.status_params.held_sigma_m)
        self._held = held
        return held

    def update_status(self, stamp_ns: int) -> None:
        """Localized, degraded or lost by how long no CAD-linked landmark was seen (`StatusParams`); degraded at
        least while the pose is not held (`held`)."""
        last_ns = self.links.last_link_ns
        if self.status not in ("localized", "degraded", "lost") or last_ns is None:
            return
        silent_s = (stamp_ns - last_ns) * 1e-9
        p = self.status_params
        self.status = "lost" if silent_s > p.lost_after_s else \
            "degraded" if silent_s > p.degraded_after_s or not self.held() else "localized"


def rival_poses(result: Alignment) -> list[np.ndarray]:
    """The T_cad_map an 'ambiguous' registration could not tell apart, where the walls named none (`Choice.rivals`):
    its candidates that explain as many landmarks as the best (a symmetric building's images of the true pose),
    else its own best pose alone."""
    if result.candidates:
        most = max(n for _, n in result.candidates)
        return [np.asarray(T, float) for T, n in result.candidates if n == most]
    return [] if result.T_cad_map is None else [np.asarray(result.T_cad_map, float)]
