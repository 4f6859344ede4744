"""A pose that is no longer held to the model found again by the walls (beyond the paper).

Where the odometry carried the pose alone (it lost track and extrapolated), its sigma outgrows the reach of a wall
fit and of a link (`StatusParams.held_sigma_m`): neither is made, and the pose drifts with the odometry. The walls
can still tell where it is: the depth points of the keyframes since the odometry tracks again (consistent among
themselves) are moved by candidate corrections of the pose, horizontal shifts on a grid within three sigma of it,
and the walls weigh those candidates as they weigh a registration's (graph.judge: each fitted to the walls, taken
where it fits them and every other, distinct candidate scores `surface_margin` less). In a corridor the shifts
along it fit alike and none is taken. The pose taken enters the graph as a measured T_cad_body of the newest
keyframe; its sigma is then the measurement's, the pose is held again, and fits and links resume.

Frames: map (the flight's odometry frame, z up), body, cad (the model's). Metres.
"""

from __future__ import annotations

import logging

import numpy as np

from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.judge import SurfaceJudge
from macroloc.graph.params import RecoveryParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.relocalize import Alignment
from macroloc.graph.rigid import apply, make_T
from macroloc.graph.surfaces import SurfaceIndex

log = logging.getLogger(__name__)


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
        p = self.params
        sigmas = np.r_[np.full(3, np.radians(p.recovery_sigma_deg)), np.full(3, p.recovery_sigma_m)]  # [rot; trans]
        self.graph.add_cad_pose(i, choice.T_cad_map @ T_map_body, np.diag(sigmas**-2.0))
        self.graph.update(extra_iterations=2)
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
