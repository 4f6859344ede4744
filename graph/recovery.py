"""A pose that is no longer held to the model found again by the walls (beyond the paper).

Where the odometry carried the pose alone (it lost track and extrapolated), its sigma outgrows the reach of a wall
fit and of a link (`StatusParams.held_sigma_m`): neither is made, and the pose drifts with the odometry. The walls
can still tell where it is: the depth points of the keyframes since the odometry tracks again (consistent among
themselves) are moved by candidate corrections of the pose, horizontal shifts on a grid within three sigma of it,
and the walls weigh those candidates as they weigh a registration's (graph.judge: each fitted to the walls, taken
where it fits them and every other, distinct candidate scores `surface_margin` less). In a corridor the shifts
along it fit alike and none is taken. The pose taken enters the graph as a measured T_cad_body of the newest
keyframe; its sigma is then the measurement's, the pose is held again, and fits and links resume.

The doors find it too (`DoorRecovery`), where the walls do not (no depth, or walls that cannot single it out): the
landmarks first mapped since the pose was last held and seen at least twice are moved by one horizontal shift of the
pose, within 3 sigma of it; a shift is taken where it puts two of them or more (`recovery_min_doors`) each within
`cad_link_m` of a same-type model feature (each feature once), and no shift `recovery_apart_m` away from it puts as
many. One landmark alone moves nothing: a false detection near a model door is what holding the pose keeps out
(graph.anchoring, `held`), and two such that agree on one shift are far rarer. Doors alike at equal spacing (a
corridor's row) fit several shifts alike, and none is taken.

Frames: map (the flight's odometry frame, z up), body, cad (the model's). Metres.
"""

from __future__ import annotations

import logging

import numpy as np

from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.features import MacroFeature
from macroloc.graph.judge import SurfaceJudge
from macroloc.graph.landmark_map import LandmarkMap
from macroloc.graph.params import RecoveryParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.relocalize import Alignment
from macroloc.graph.rigid import apply, make_T
from macroloc.graph.surfaces import SurfaceIndex

log = logging.getLogger(__name__)


def place_found(graph: PoseGraph, params: RecoveryParams, i: int, T_cad_body: np.ndarray) -> None:
    """The pose found enters the graph as a measured T_cad_body of keyframe i (`recovery_sigma_m`, `_deg`)."""
    sigmas = np.r_[np.full(3, np.radians(params.recovery_sigma_deg)), np.full(3, params.recovery_sigma_m)]  # rot; trans
    graph.add_cad_pose(i, T_cad_body, np.diag(sigmas**-2.0))
    graph.update(extra_iterations=2)


class WallRecovery:
    """Finds a pose that is not held again by the walls (see module doc)."""

    def __init__(self, params: RecoveryParams, graph: PoseGraph, surfaces: SurfaceIndex, judge: SurfaceJudge,
                 depth: DepthWindow) -> None:
        self.params = params
        self.graph = graph
        self.surfaces = surfaces
        self.judge = judge
        self.depth = depth
        self.recoveries: list[tuple[int, float]] = []  # (stamp_ns, how far the pose was moved, m)
        self._consistent_from = 0  # the first keyframe since the odometry last extrapolated
        self._tried: tuple[int, int] | None = None  # (stamp_ns, points) of the last attempt

    def keyframe(self, i: int, dead_reckoned_s: float, held: bool) -> None:
        """Keyframe i came (its odometry extrapolated for `dead_reckoned_s` before it) and the pose is `held` or
        not: the points of a held keyframe or of one the odometry reached by extrapolating are not consistent with
        those that follow."""
        if held or dead_reckoned_s > 0.0:
            self._consistent_from = i + 1

    def attempt(self, stamp_ns: int, retry_s: float) -> bool:
        """Look for the pose among shifts of the newest keyframe's, at most every `retry_s` and only with more
        points than at the last attempt; whether one was taken."""
        if not self.params.recovery or not self.graph.has_anchor:
            return False
        points_map, origins_map = self.depth.points_map(since=self._consistent_from)
        if not self.judge.can_check(len(points_map)):
            return False
        if self._tried is not None:
            last_ns, last_points = self._tried
            if len(points_map) <= last_points or (stamp_ns - last_ns) * 1e-9 < retry_s:
                return False
        self._tried = (stamp_ns, len(points_map))
        i = self.graph.n_keyframes - 1
        T_cad_map = self.graph.T_cad_map()
        assert T_cad_map is not None
        radius_m = min(3.0 * self.graph.horizontal_sigma_m(i), self.params.recovery_max_m)
        candidates = self._candidates(T_cad_map, points_map, origins_map, radius_m)
        self.judge.new_attempt()
        choice = self.judge.choose(Alignment("not_localized", None, candidates=[(T, 0) for T in candidates]),
                                   stamp_ns, points_map, origins_map, [], lambda T_best, rivals: rivals)
        if choice.T_cad_map is None:
            log.info("the walls do not find the pose again among %d shifts within %.1f m (%d points)",
                     len(candidates), radius_m, len(points_map))
            return False
        T_map_body = self.graph.T_map_body(i)
        moved_m = float(np.linalg.norm((choice.T_cad_map @ T_map_body)[:2, 3] - (T_cad_map @ T_map_body)[:2, 3]))
        log.info("the walls found the pose again: moved %.2f m (%d points since keyframe %d)", moved_m,
                 len(points_map), self._consistent_from)
        place_found(self.graph, self.params, i, choice.T_cad_map @ T_map_body)
        self.recoveries.append((stamp_ns, moved_m))
        return True

    def _candidates(self, T_cad_map: np.ndarray, points_map: np.ndarray, origins_map: np.ndarray, radius_m: float
                    ) -> list[np.ndarray]:
        """The pose shifted horizontally on a grid of `recovery_step_m` within `radius_m`; of these, the
        `recovery_candidates` that put most points on the walls, each at least `recovery_apart_m` from the others
        (the judge compares distinct places, not neighbours on the grid)."""
        p = self.params
        n = int(np.floor(radius_m / p.recovery_step_m))
        steps = np.arange(-n, n + 1) * p.recovery_step_m
        shifts = np.array([(x, y) for x in steps for y in steps if x * x + y * y <= radius_m**2 + 1e-9])
        sample = apply(T_cad_map, self.judge.screening_sample(points_map, origins_map)[0])  # as the judge screens
        offsets = np.c_[shifts, np.zeros(len(shifts))]
        support = self.surfaces.supports(sample[None, :, :] + offsets[:, None, :])
        order = np.argsort(-support, kind="stable")
        kept: list[int] = []
        for k in order:
            if all(np.linalg.norm(shifts[k] - shifts[m]) >= p.recovery_apart_m for m in kept):
                kept.append(int(k))
            if len(kept) == p.recovery_candidates:
                break
        return [make_T(np.eye(3), offsets[k]) @ T_cad_map for k in kept]


class NullRecovery:
    """No model surfaces: nothing finds the pose again but the doors."""

    recoveries: list[tuple[int, float]] = []

    def keyframe(self, i: int, dead_reckoned_s: float, held: bool) -> None:
        pass

    def attempt(self, stamp_ns: int, retry_s: float) -> bool:
        return False


class DoorRecovery:
    """Finds a pose that is not held again by the doors mapped since (see module doc)."""

    def __init__(self, params: RecoveryParams, graph: PoseGraph, landmarks: LandmarkMap, links: dict[int, str],
                 features: dict[str, MacroFeature], link_m: float, min_sightings: int) -> None:
        """`links`: landmark key -> the CAD feature it is linked to (graph.cad_links, read as it grows);
        `link_m`: how near a landmark must come to a feature to count (`AnchorParams.cad_link_m`); `min_sightings`:
        the sightings a landmark needs to take part (`RegistrationParams.min_sightings_to_register`)."""
        self.params = params
        self.graph = graph
        self.landmarks = landmarks
        self.links = links
        self.link_m = link_m
        self.min_sightings = min_sightings
        self.recoveries: list[tuple[int, float]] = []  # (stamp_ns, how far the pose was moved, m)
        self._features = [f for f in features.values() if f.orientation == "vertical"]
        self._centroids_cad = np.array([f.centroid_cad for f in self._features]).reshape(-1, 3)
        self._types = np.array([f.type for f in self._features])
        self._mapped_when_held: set[int] = set()  # the landmarks there were when the pose was last held
        self._tried: tuple[int, ...] = ()  # the landmarks of the last attempt

    def keyframe(self, i: int, dead_reckoned_s: float, held: bool) -> None:
        """Keyframe i came and the pose is `held` or not: the landmarks mapped while it is held are not taken."""
        if held:
            self._mapped_when_held = set(self.landmarks.landmarks)

    def attempt(self, stamp_ns: int, retry_s: float) -> bool:
        """Look for the pose among the shifts that put the newly mapped landmarks on model features, when they
        changed since the last attempt; whether one was taken."""
        if not self.params.recovery or not self.graph.has_anchor:
            return False
        keys = tuple(j for j in self.landmarks.confirmed(self.min_sightings)
                     if j not in self._mapped_when_held and j not in self.links)
        if len(keys) < self.params.recovery_min_doors or keys == self._tried:
            return False
        self._tried = keys
        i = self.graph.n_keyframes - 1
        T_cad_map = self.graph.T_cad_map()
        assert T_cad_map is not None
        radius_m = min(3.0 * self.graph.horizontal_sigma_m(i), self.params.recovery_max_m)
        xyz_cad = np.array([(T_cad_map @ self.graph.T_map_rect(j))[:3, 3] for j in keys])
        kinds = [self.landmarks.landmarks[j].type for j in keys]
        shift, support, rival = self._best_shift(xyz_cad, kinds, radius_m)
        if shift is None or support < self.params.recovery_min_doors or rival >= support:
            log.info("the doors do not find the pose again: of %d mapped since it was held, the best shift within "
                     "%.1f m puts %d on the model's, another at least %.1f m from it %d", len(keys), radius_m,
                     support, self.params.recovery_apart_m, rival)
            return False
        T_map_body = self.graph.T_map_body(i)
        T_cad_body = make_T(np.eye(3), np.r_[shift, 0.0]) @ T_cad_map @ T_map_body
        moved_m = float(np.linalg.norm(shift))
        log.info("the doors found the pose again: moved %.2f m (%d of %d landmarks mapped since it was held)",
                 moved_m, support, len(keys))
        place_found(self.graph, self.params, i, T_cad_body)
        self.recoveries.append((stamp_ns, moved_m))
        return True

    def _best_shift(self, xyz_cad: np.ndarray, kinds: list[str], radius_m: float
                    ) -> tuple[np.ndarray | None, int, int]:
        """(the horizontal shift (2,) that puts most landmarks on a same-type feature, refined as their mean
        offset; how many it puts there; the most any shift at least `recovery_apart_m` from it puts there).
        Candidate shifts: each landmark onto each same-type feature within reach, and no shift at all."""
        offsets = self._centroids_cad[None, :, :] - xyz_cad[:, None, :]  # (landmarks, features, 3)
        same = self._types[None, :] == np.array(kinds)[:, None]
        reach = same & (np.abs(offsets[..., 2]) <= self.link_m) & \
            (np.linalg.norm(offsets[..., :2], axis=2) <= radius_m + self.link_m)
        shifts = np.vstack([np.zeros((1, 2)), offsets[reach][:, :2]])
        shifts = shifts[np.linalg.norm(shifts, axis=1) <= radius_m + 1e-9]
        scored = [(self._put(offsets, same, shift), shift) for shift in shifts]  # the zero shift is always one
        pairs, best = max(scored, key=lambda s: (len(s[0]), -float(np.linalg.norm(s[1]))))
        apart_m = self.params.recovery_apart_m
        rival = max((len(q) for q, shift in scored if np.linalg.norm(shift - best) >= apart_m), default=0)
        if not pairs:
            return None, 0, rival
        refined = np.mean([offsets[a, f, :2] for a, f in pairs], axis=0)
        return refined, len(pairs), rival

    def _put(self, offsets: np.ndarray, same: np.ndarray, shift: np.ndarray) -> list[tuple[int, int]]:
        """The (landmark, feature) pairs the shift puts within `link_m` of each other, same type, each landmark and
        each feature once (the nearest pairs first)."""
        d = np.linalg.norm(offsets - np.r_[shift, 0.0], axis=2)
        d[~same] = np.inf
        pairs: list[tuple[int, int]] = []
        used_l: set[int] = set()
        used_f: set[int] = set()
        for a, f in zip(*np.unravel_index(np.argsort(d, axis=None), d.shape), strict=True):
            if d[a, f] > self.link_m:
                break
            if a not in used_l and f not in used_f:
                pairs.append((int(a), int(f)))
                used_l.add(int(a))
                used_f.add(int(f))
        return pairs
