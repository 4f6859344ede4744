"""The doors and windows seen beyond the sighting range, while the flight is not yet localized.

Such a sighting makes no landmark (a stereo pair places a door 13 m away to a metre along its line of sight),
but its bearing is good to a fraction of a degree: it checks candidate poses (`explained`, `not_contradicted`),
and two of them seen from one camera resect the pose before any door came within range (`resected`,
`graph.far`). The window keeps the recent keyframes' far sightings in their body frames; they are taken into the
map frame at the keyframes' current estimates whenever they are used.

Frames: body (x forward, y left, z up), map (the flight's odometry frame, z up), cad (the model's). Metres.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from typing import Protocol

import numpy as np

from macroloc.graph.far import refined_by_bearings, resection_candidates, resection_spread_m
from macroloc.graph.features import CentroidsByType
from macroloc.graph.params import FarParams, Ranges
from macroloc.graph.relocalize import Alignment, distinct_poses
from macroloc.graph.rigid import apply, make_T, rot_z

log = logging.getLogger(__name__)


class RangeSigma(Protocol):
    """A sighting's position sigma (m) at a range (m), or at each of an array of ranges."""

    def __call__(self, range_m: Ranges, /) -> Ranges: ...


FarMap = tuple[np.ndarray, np.ndarray, np.ndarray]  # types (K,), their keyframes' cameras (K, 3), centroids (K, 3)


class FarSightings:
    """The far sightings of the newest `keyframes` keyframes (see module doc)."""

    def __init__(self, params: FarParams, keyframes: int, position_sigma_m: RangeSigma,
                 viewer_body: np.ndarray, centroids_cad: CentroidsByType,
                 T_map_body: Callable[[int], np.ndarray]) -> None:
        """`keyframes`: how many recent keyframes' far sightings are kept; `position_sigma_m(range_m)`: a
        sighting's position sigma at a range, m (`LandmarkParams.position_sigma_m`); `viewer_body` (3,): the
        camera's position in the body frame; `centroids_cad(type)`: the model's feature centroids (N, 3);
        `T_map_body(i)`: keyframe i's current estimate (the pose graph's)."""
        self.params = params
        self.position_sigma_m = position_sigma_m
        self._viewer_body = viewer_body
        self._centroids_cad = centroids_cad
        self._T_map_body = T_map_body
        # (keyframe, types (K,), centroids (K, 3) body frame)
        self._window: deque[tuple[int, list[str], np.ndarray]] = deque(maxlen=keyframes)

    def add(self, i: int, kinds: list[str], centroids_body: np.ndarray) -> None:
        """Keyframe i's far sightings: their types and centroids (K, 3), body frame."""
        self._window.append((i, kinds, centroids_body))

    def __len__(self) -> int:
        return sum(len(kinds) for _, kinds, _ in self._window)

    def in_map(self) -> FarMap | None:
        """The window's far sightings: types (K,), their keyframes' cameras (K, 3) and their centroids (K, 3),
        map frame, at the keyframes' current estimates; None with fewer than `far_min_sightings`."""
        if len(self) < self.params.far_min_sightings:
            return None
        kinds, cameras, centroids = [], [], []
        for i, kinds_i, centroids_body in self._window:
            T_map_body = self._T_map_body(i)
            kinds += kinds_i
            cameras.append(np.repeat(apply(T_map_body, self._viewer_body[None]), len(kinds_i), axis=0))
            centroids.append(apply(T_map_body, centroids_body))
        return np.array(kinds), np.vstack(cameras), np.vstack(centroids)

    def pairs(self) -> list[tuple[np.ndarray, tuple[str, str], np.ndarray]]:
        """Per keyframe of the window, oldest first, the widest pair in horizontal bearing from its camera of its
        own far sightings where that is `far_pair_min_deg` or more: (camera (3,), their types, their centroids
        (2, 3)), map frame. Where no keyframe has such a pair, one of its own sightings with any other of the
        window (another keyframe's, taken into the map frame at that keyframe's estimate: two doors need not be in
        view at once); a pair seen from one camera pose goes first, as it carries no odometry drift."""
        seen = []
        for i, kinds, centroids_body in self._window:
            T_map_body = self._T_map_body(i)
            seen.append((i, apply(T_map_body, self._viewer_body[None])[0], kinds, apply(T_map_body, centroids_body)))
        all_kinds = [k for _, _, kinds, _ in seen for k in kinds]
        if len(all_kinds) < 2:
            return []
        all_centroids = np.vstack([c for _, _, _, c in seen])
        owner = np.concatenate([np.full(len(kinds), i) for i, _, kinds, _ in seen])
        min_rad = np.radians(self.params.far_pair_min_deg)
        for across in (False, True):
            pairs = []
            for i, camera, _, _ in seen:
                own = np.flatnonzero(owner == i)
                other = np.arange(len(owner)) if across else own
                if not len(own) or len(other) < 2:
                    continue
                bearing = np.arctan2(all_centroids[:, 1] - camera[1], all_centroids[:, 0] - camera[0])
                apart = np.abs((bearing[own][:, None] - bearing[other][None] + np.pi) % (2 * np.pi) - np.pi)
                a_own, b_other = (int(v) for v in np.unravel_index(int(np.argmax(apart)), apart.shape))
                if apart[a_own, b_other] >= min_rad:
                    a, b = int(own[a_own]), int(other[b_other])
                    pairs.append((camera, (all_kinds[a], all_kinds[b]), all_centroids[np.array([a, b])]))
            if pairs:
                return pairs
        return []

    def fractions(self, T_cad_map: np.ndarray, far: FarMap) -> np.ndarray:
        """The fraction of the far sightings `far` (`in_map`) that each of H poses T_cad_map (H, 4, 4) explains as
        it stands (see `explained`), (H,)."""
        p = self.params
        kinds, cameras_map, centroids_map = far
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
            near = np.abs(d - r) <= 3 * self.position_sigma_m(r)
            explained += np.any(aside & up & near, axis=2).sum(axis=1)
        return explained / len(kinds)

    def explained(self, T_cad_map: np.ndarray, far: FarMap, T_map_newest: np.ndarray) -> float:
        """The fraction of the far sightings (`far`, from `in_map`) that the pose T_cad_map explains, turned about
        the newest keyframe's camera (its body at T_map_newest) by up to `far_turn_deg` (`far_turn_step_deg`
        steps) to the heading that explains most: a same-type CAD feature lies within `far_bearing_deg` of the
        sighting's horizontal bearing from its keyframe's camera, `far_elevation_deg` of its elevation and 3 of
        its sigmas (`sighting_sigma_m`) of its horizontal range. A stereo pair places a door 15 m away to a metre
        along its line of sight but to a fraction of a degree across it: the bearings tell apart poses that the
        walls near by fit alike. The candidate's heading is known less well (from one door and the walls, a
        degree or two off), hence the turn. The elevation is allowed more: the vertical is the weak part of a
        candidate from one door (the walls' fit holds its height), and a door a storey up or down is still far
        outside it (docs/measurements.md, "Far sightings' tolerances")."""
        p = self.params
        pivot = apply(T_cad_map @ T_map_newest, self._viewer_body[None])[0]
        n_turns = int(round(p.far_turn_deg / p.far_turn_step_deg)) if p.far_turn_step_deg > 0 else 0
        turns = [rot_z(np.radians(k * p.far_turn_step_deg)) for k in range(-n_turns, n_turns + 1)]
        return float(self.fractions(np.array([make_T(R, pivot - R @ pivot) @ T_cad_map for R in turns]), far).max())

    def explains(self, T_cad_map: np.ndarray, T_map_newest: np.ndarray) -> bool:
        """Whether there are far sightings (`far_min_sightings`) and the pose explains `far_min_explained` of them."""
        far = self.in_map()
        return far is not None and self.explained(T_cad_map, far, T_map_newest) >= self.params.far_min_explained

    def not_contradicted(self, T_best: np.ndarray, rivals: list[np.ndarray], T_map_newest: np.ndarray
                         ) -> list[np.ndarray]:
        """The rival poses that the far sightings do not contradict: all of them unless the best pose explains
        `far_min_explained` of the far sightings; then those explaining at least `far_margin` less are dropped."""
        p = self.params
        far = self.in_map()
        if far is None:
            return rivals
        f_best = self.explained(T_best, far, T_map_newest)
        if f_best < p.far_min_explained:
            return rivals
        f_rivals = [self.explained(T, far, T_map_newest) for T in rivals]
        log.info("far sightings: the best candidate pose explains %.2f of them, its rivals on the walls %s",
                 f_best, ", ".join(f"{f:.2f}" for f in f_rivals))
        return [T for T, f in zip(rivals, f_rivals, strict=True) if f > f_best - p.far_margin]

    def resected(self, far: FarMap | None) -> Alignment:
        """Candidate poses from the far sightings alone, before any landmark (`far_resection`): from each of the
        newest `far_pairs` keyframes that saw a far door or window `far_pair_min_deg` apart in bearing from another
        (seen by it or by another keyframe of the window, `pairs`), the widest such pair matched to every pair of
        same-type features of the model (`graph.far`), where its ranges leave the camera no more than `far_place_m`
        to move (`resection_spread_m`: else the truth need not be among the candidates, and the walls would choose
        among wrong ones); those explaining `far_min_explained` of the far sightings (`fractions`,
        `far_resection_sightings` of them, evenly drawn), one of each place (`far_place_m`, 5 deg), most explaining
        first. None is the registrar's answer: the walls choose (graph.judge), with the full margin (no landmark
        vouches for any of them). `far`: `in_map`. A flight that
        sees doors only beyond the sighting range for its first seconds is localized by them
        (docs/measurements.md, "Far sightings' tolerances")."""
        p = self.params
        if far is None:
            return Alignment("not_localized", None)
        every = max(1, int(np.ceil(len(far[0]) / p.far_resection_sightings)))
        far = (far[0][::every], far[1][::every], far[2][::every])
        poses = []
        for camera_map, kinds, centroids_map in self.pairs()[-p.far_pairs:]:
            spread_m = resection_spread_m(camera_map, centroids_map, self.position_sigma_m)
            if spread_m > p.far_place_m:  # one pose per pair of CAD features would stand for none of its places
                log.info("far sightings %.1f and %.1f m away: their ranges leave the camera %.1f m to move, more "
                         "than a place", *np.linalg.norm(centroids_map - camera_map, axis=1), spread_m)
                continue
            poses.append(resection_candidates(camera_map, centroids_map, self._centroids_cad(kinds[0]),
                                              self._centroids_cad(kinds[1]), self.position_sigma_m,
                                              same_features=kinds[0] == kinds[1]))
        if not poses or not sum(len(T) for T in poses):
            return Alignment("not_localized", None)
        T_all = np.concatenate(poses)
        explained = np.concatenate([self.fractions(T_all[k:k + 256], far) for k in range(0, len(T_all), 256)])
        order = [k for k in np.argsort(-explained, kind="stable") if explained[k] >= p.far_min_explained]
        kept = distinct_poses(T_all, order, trans_m=p.far_place_m, angle_rad=np.radians(5.0))
        log.info("resection from far sightings: %d candidate poses, %d explaining %.2f of %d far sightings, %d "
                 "places", len(T_all), len(order), p.far_min_explained, len(far[0]), len(kept))
        if not kept:
            return Alignment("not_localized", None)
        return Alignment("ambiguous", None, candidates=[(T, 0) for T in kept])

    def refined(self, T_cad_map: np.ndarray, far: FarMap | None) -> tuple[np.ndarray, np.ndarray | None]:
        """A pose resected from far sightings, fitted to all of the window's far sightings' bearings (`graph.far`):
        one pair's coarse ranges put it tenths of a metre off, the keyframes' bearings triangulate it. `far`:
        `in_map`. With it, the fit's sigmas [m, rad] (None where too few were explained)."""
        p = self.params
        if far is None:
            return T_cad_map, None
        kinds, cameras, centroids = far
        features = {str(k): self._centroids_cad(str(k)) for k in np.unique(kinds)}
        return refined_by_bearings(T_cad_map, cameras, centroids, kinds, features, np.radians(p.far_bearing_sigma_deg),
                                   self.position_sigma_m, np.radians(p.far_bearing_deg))
