"""The walls choose among candidate poses (beyond the paper): the registrar's answer, or the poses it offers from
one to three landmarks, or those resected from far doors, each fitted to the model's walls and scored by the
flight's depth points on them and in sight of their cameras (graph.surfaces).

One door with gravity fixes the pose up to which of the model's alike doors it is and from which side: N alike doors
give 2N candidates (docs/measurements.md, "The diagnoses behind the rules"). A few points screen them, the best are
turned to the walls' heading where their doors' orientations are coarse, fitted to the walls, and checked; a
candidate is taken when it fits the walls (`surface_min_support`, `surface_max_seen_through`) and no different pose
scores within `surface_margin` of it, or the rivals are contradicted by the doors seen beyond the sighting range
(graph.far_window).

Frames: map = the flight's odometry frame, z up; cad = the model's. A candidate is a T_cad_map (4, 4). Metres.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from functools import partial
from typing import Generic, NamedTuple, Protocol, TypeVar

import numpy as np
from scipy.spatial import cKDTree

from macroloc.graph.features import CentroidsByType
from macroloc.graph.params import JudgeParams
from macroloc.graph.relocalize import Alignment
from macroloc.graph.rigid import apply, make_T, rot_z, rotation_angle_deg
from macroloc.graph.surfaces import SurfaceCheck, SurfaceIndex, align_to_surfaces

log = logging.getLogger(__name__)
V = TypeVar("V")
FarRivals = Callable[[np.ndarray, list[np.ndarray]], list[np.ndarray]]  # (T_best, rivals) -> those not contradicted


class SurfaceJudge:
    """Weighs candidate poses against the model's surfaces (see module doc)."""

    def __init__(self, surfaces: SurfaceIndex, params: JudgeParams, centroids_cad: CentroidsByType,
                 inlier_threshold_m: float, surface_fit_sigma_m: float,
                 self_maps: Callable[[], np.ndarray] = lambda: np.zeros((0, 4, 4))) -> None:
        """`centroids_cad(type)`: the model's feature centroids (N, 3); `inlier_threshold_m`: how near a CAD
        feature a turned candidate must keep a landmark (the registrar's tolerance, `RegistrationParams`);
        `surface_fit_sigma_m`: a point's distance to its wall, model against reality, in the fits (`refined`);
        `self_maps()`: the building's near-self-maps (graph.self_maps), (M, 4, 4) T_cad_cad, most voted first,
        asked for once, when first needed (`with_images`)."""
        self.surfaces = surfaces
        self.params = params
        self.inlier_threshold_m = inlier_threshold_m
        self.surface_fit_sigma_m = surface_fit_sigma_m
        self._centroids_cad = centroids_cad
        self._self_maps_of_building = self_maps
        self._self_maps: np.ndarray | None = None
        self.checks: list[tuple[int, list[float]]] = []  # (stamp_ns, score of each candidate pose)
        self.screens: list[tuple[int, list[float]]] = []  # (candidates, their screening scores, best first)
        # within one registration attempt: each candidate fitted to the walls, each fitted pose's check, once
        self._fitted: PerPose[np.ndarray] = PerPose()
        self._checked: PerPose[SurfaceCheck] = PerPose()

    def new_attempt(self) -> None:
        """A new registration attempt: the poses fitted and checked in the last one are forgotten (the points
        and the keyframes' estimates have moved since)."""
        self._fitted, self._checked = PerPose(), PerPose()

    def can_check(self, n_points: int) -> bool:
        """Whether `n_points` depth points are enough to judge poses by (`surface_min_points`)."""
        return n_points >= self.params.surface_min_points

    def contradicts(self, T_cad_map: np.ndarray, points_map: np.ndarray, origins_map: np.ndarray) -> bool:
        """Whether the walls contradict the pose T_cad_map: more than `surface_refuse_seen_through` of the depth
        points `points_map` (N, 3) would be seen through a wall from `origins_map` (N, 3), map frame."""
        check = self.check(apply(T_cad_map, points_map), origins_map, T_cad_map)
        log.info("a pose given: %.2f of %d points on surfaces, %.2f seen through walls", check.support,
                 len(points_map), check.seen_through)
        return check.seen_through > self.params.surface_refuse_seen_through

    def choose(self, result: Alignment, stamp_ns: int, points_map: np.ndarray, origins_map: np.ndarray,
               landmarks: list[tuple[str, np.ndarray]], far_rivals: FarRivals,
               walls_map: Sequence[tuple[np.ndarray, np.ndarray]] = (),
               far_explains: Callable[[np.ndarray], bool] = lambda T: False) -> Choice:
        """The pose to anchor the map with, or None, and whether it is the registrar's answer (whose matches
        then hold): the registrar's answer `result` and its candidates, checked by the walls. By: the map's depth
        points `points_map` (N, 3) seen from `origins_map` (N, 3), the confirmed landmarks as (type, centre (3,)),
        map frame (`landmarks`), and `far_rivals(T_best, rivals)`: the rivals the far sightings do not contradict.

        Each candidate is fitted to the walls (`refined`) and scored by the points on the model's surfaces and,
        with the model's walls as voxels, in sight of their cameras (SurfaceCheck.score); a candidate is taken when
        it puts `surface_min_support` of the points on the surfaces, lets at most `surface_max_seen_through` be
        seen through a wall, and every other candidate scores `surface_margin` less, or `surface_margin_unfit` less
        where that candidate does not fit the walls itself (`fits`) and every candidate explains two landmarks
        or more: a pose the walls contradict is a weaker rival, but from one door the candidates are coarse and
        the true one may fit badly (docs/measurements.md, "The walls' margins"). The registrar's 'localized'
        stands unless another candidate beats it by that margin or more than `surface_refuse_seen_through` of the
        points would have been seen through a wall (the walls contradict it), and is refused where the walls
        confirm a different pose. Few points on the surfaces alone do not refuse it: a true pose among furniture
        the model lacks puts only half of them there.

        Candidates that each explain one landmark are weighed only by the points off the confirmed landmarks'
        walls (`walls_map`: (centre, normal) per landmark, map frame; `own_wall_points`): any pose that puts a
        door on a CAD door of its size puts the wall it sits in, and its reveals, onto that door's wall, true or
        not, so those points cannot tell the candidates apart. Where fewer than `surface_min_points` are left,
        all the points weigh them, but a candidate is taken only where the far sightings explain it
        (`far_explains`: independent evidence of the place) and rule out its rivals (docs/measurements.md, "Wrong
        answers on fresh seeds").

        The best candidate's images under the building's near-self-maps that explain the landmarks as well are
        weighed too (`with_images`): a candidate is never taken over a pose the doors cannot tell from it and the
        walls never saw.

        Candidates from one landmark are first turned to the walls' heading (`turned`); where then none fits,
        those from up to `surface_turn_max_inliers` are turned too and all are weighed again. Turned, wrong poses
        fit better too, so a pose from two or three doors is turned only when it must be (docs/measurements.md,
        "Turning candidates to the walls")."""
        p = self.params
        T_reg = result.T_cad_map if result.status == "localized" else None
        walls_alone = True  # the points may single out a candidate by themselves
        if T_reg is None and walls_map and max((n for _, n in result.candidates), default=0) <= 1:
            off = ~self.own_wall_points(points_map, walls_map)
            if off.sum() >= p.surface_min_points:
                points_map, origins_map = points_map[off], origins_map[off]
            else:
                log.info("%d of %d points off the walls of the landmarks: the far sightings must explain the "
                         "candidate from one landmark", off.sum(), len(points_map))
                walls_alone = False
        if T_reg is not None:
            T_reg = self._fitted.get(T_reg, lambda T: self.refined(T, points_map))
            moved_reg = apply(T_reg, points_map)
        reg = None if T_reg is None else (T_reg, moved_reg)
        sample = self.screening_sample(points_map, origins_map)
        counts = [n for _, n in result.candidates]
        poses = self.turned(result.candidates, sample[0], 1, 1, landmarks)
        candidates, moved, checks = self._weighed(poses, reg, points_map, origins_map, sample)
        if checks and not self.fits(max(checks, key=lambda c: c.score)) \
                and any(1 < n <= p.surface_turn_max_inliers for n in counts):
            log.info("no candidate pose fits the walls as it stands: those from up to %d landmarks turned too",
                     p.surface_turn_max_inliers)
            poses = self.turned(list(zip(poses, counts, strict=True)), sample[0], 2, p.surface_turn_max_inliers,
                                landmarks)
            candidates, moved, checks = self._weighed(poses, reg, points_map, origins_map, sample)
        if not candidates:
            return Choice(None, False)
        if T_reg is None:
            self.with_images(candidates, moved, checks, points_map, origins_map, landmarks)
        score = np.array([c.score for c in checks])
        self.checks.append((stamp_ns, score.round(3).tolist()))
        log.info("surface check of %d candidate poses (%d points): support %s", len(candidates), len(points_map),
                 ", ".join(f"{c.support:.2f}" + (f" ({c.seen_through:.2f} seen through walls)"
                                                 if self.surfaces.walls is not None else "") for c in checks))
        best = int(np.argmax(score))
        relaxed = min(counts, default=0) >= 2  # a candidate from one door is coarse: the true one may fit badly
        margin = [p.surface_margin if self.fits(c) or not relaxed else p.surface_margin_unfit for c in checks]
        rivals = [T for T, m, s, d in zip(candidates, moved, score, margin, strict=True)
                  if s > score[best] - d and poses_differ(T, candidates[best], m, moved[best])]
        best_fits = self.fits(checks[best])
        if best_fits and rivals:
            rivals = far_rivals(candidates[best], rivals)
        rivalled = bool(rivals)
        confirmed = best_fits and not rivalled and (walls_alone or far_explains(candidates[best]))
        if T_reg is not None:
            i_reg = next(k for k, (T, m) in enumerate(zip(candidates, moved, strict=True))
                         if not poses_differ(T, T_reg, m, moved_reg))
            beaten = score[best] >= score[i_reg] + p.surface_margin
            contradicted = checks[i_reg].seen_through > p.surface_refuse_seen_through
            refused = beaten or contradicted or (confirmed and best != i_reg)
            tied = (candidates[best], *rivals) if rivalled else ()
            return Choice(None, False, best_fits and rivalled, tied) if refused else Choice(T_reg, True)
        return Choice(candidates[best] if confirmed else None, False, best_fits and rivalled,
                      () if confirmed or not rivalled else (candidates[best], *rivals))

    def rivals_from_one(self, T_cad_map: np.ndarray, poses: list[np.ndarray], points_map: np.ndarray,
                        origins_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]], far_rivals: FarRivals
                        ) -> list[np.ndarray]:
        """Of the `poses` (T_cad_map each, from one landmark alone), those that rival the pose `choose` took,
        `T_cad_map`: a different pose that scores within `surface_margin` of it by the same points (`points_map`
        seen from `origins_map`, map frame), or within `surface_margin_unfit` where it does not fit the walls
        itself (turned and fitted, a true pose fits them as the taken one does), screened, turned and fitted as
        `choose` weighs the candidates from one door, and that the far sightings do not contradict (`far_rivals`).

        The registrar offers the poses that explain the most landmarks. A false detection that happens to land on
        a model door under a wrong pose makes that pose explain two, while the true pose explains one, is never
        offered, and cannot rival it: the walls then confirm the wrong pose against the other wrong ones
        (docs/measurements.md, "A false door that lands on a model door")."""
        if not poses or not self.params.surface_one_landmark_rivals:
            return []
        sample = self.screening_sample(points_map, origins_map)
        turned = self.turned([(T, 1) for T in poses], sample[0], 1, 1, landmarks)
        candidates, moved, checks = self._weighed(turned, None, points_map, origins_map, sample)
        moved_taken = apply(T_cad_map, points_map)
        taken = self._checked.get(T_cad_map, partial(self.check, moved_taken, origins_map))
        p = self.params
        rivals = [T for T, m, c in zip(candidates, moved, checks, strict=True)
                  if c.score > taken.score - (p.surface_margin if self.fits(c) else p.surface_margin_unfit)
                  and poses_differ(T, T_cad_map, m, moved_taken)]
        if rivals:
            rivals = far_rivals(T_cad_map, rivals)
        if rivals:
            log.info("the pose the walls took (score %.2f) is rivalled by %d poses from one landmark alone (best %.2f)",
                     taken.score, len(rivals), max(c.score for c in checks))
        return rivals

    def _weighed(self, poses: list[np.ndarray], reg: tuple[np.ndarray, np.ndarray] | None, points_map: np.ndarray,
                 origins_map: np.ndarray, sample: tuple[np.ndarray, np.ndarray]
                 ) -> tuple[list[np.ndarray], list[np.ndarray], list[SurfaceCheck]]:
        """The candidate poses worth checking (`_screened` by the points' `sample`), each fitted to the walls,
        with the registrar's own answer (`reg`: its pose, fitted, and the points under it) first where it is none
        of them; the map's points under each (CAD frame) and each one's surface check."""
        candidates = [self._fitted.get(T, lambda T: self.refined(T, points_map))
                      for T in self._screened(poses, *sample)]
        moved = [apply(T, points_map) for T in candidates]
        if reg is not None:
            T_reg, moved_reg = reg
            if all(poses_differ(T, T_reg, m, moved_reg) for T, m in zip(candidates, moved, strict=True)):
                candidates.insert(0, T_reg)
                moved.insert(0, moved_reg)
        checks = [self._checked.get(T, partial(self.check, m, origins_map))
                  for T, m in zip(candidates, moved, strict=True)]
        return candidates, moved, checks

    def with_images(self, candidates: list[np.ndarray], moved: list[np.ndarray], checks: list[SurfaceCheck],
                    points_map: np.ndarray, origins_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]]) -> None:
        """Adds to the weighed `candidates` (T_cad_map), the points under each (`moved`, CAD frame) and their
        `checks`, in place: the images S @ T of the best one under the building's near-self-maps S
        (`self_maps`, `images`) that keep as many of the `landmarks` (type, centre in the map frame) by a same-type
        CAD feature, each fitted to the walls by `points_map` (N, 3) and checked as seen from `origins_map`
        (N, 3), where it is a different pose from every one weighed; then the same for the best image, where it
        is now the best (a self-map that is no half-turn: its image's image may be another pose still).

        The doors cannot tell such an image from the candidate: with a storey's doors and windows 180 deg
        symmetric, every pose has its half-turned twin, and only the walls may tell the two apart, if anything
        can. The registrar offers the twins of its own best pose only (graph.robust), and a few windows give
        candidates it ranks otherwise: on the duplex the best candidate's twin, the true pose, was not among
        those weighed, and the twin was taken over a poorer rival (docs/measurements.md, "The duplex's mirror
        image taken as the pose")."""
        if self.params.surface_self_map_images <= 0 or not landmarks:
            return
        extended: set[int] = set()
        for _ in range(2):
            best = int(np.argmax([c.score for c in checks]))
            if best in extended:
                return
            extended.add(best)
            for T_image in self.images(candidates[best], landmarks):
                T = self._fitted.get(T_image, lambda T: self.refined(T, points_map))
                m = apply(T, points_map)
                if all(poses_differ(T, C, m, mc) for C, mc in zip(candidates, moved, strict=True)):
                    check = self._checked.get(T, partial(self.check, m, origins_map))
                    log.info("the best candidate's image under a self-map of the building: support %.2f (%.2f "
                             "seen through walls), score %.2f", check.support, check.seen_through, check.score)
                    candidates.append(T)
                    moved.append(m)
                    checks.append(check)

    def images(self, T_cad_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]]) -> list[np.ndarray]:
        """The images S @ T_cad_map under the building's near-self-maps S (most voted first, at most
        `surface_self_map_images`) that put as many of the `landmarks` (type, centre (3,) in the map frame), and
        at least one, within `inlier_threshold_m` of a CAD feature of their type as T_cad_map does."""
        if self._self_maps is None:
            self._self_maps = np.asarray(self._self_maps_of_building(), float).reshape(-1, 4, 4)
        if not len(self._self_maps) or not landmarks:
            return []
        images = self._self_maps @ T_cad_map  # (M, 4, 4)
        explained = self._explained(np.concatenate([T_cad_map[None], images]), landmarks)
        keep = np.flatnonzero(explained[1:] >= max(1, explained[0]))[: self.params.surface_self_map_images]
        return [images[k] for k in keep]

    def _explained(self, T_cad_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]]) -> np.ndarray:
        """(H,): of the `landmarks` (type, centre in the map frame), how many each pose T_cad_map (H, 4, 4) puts
        within `inlier_threshold_m` of a CAD feature of their type."""
        count = np.zeros(len(T_cad_map), int)
        for kind, x_map in landmarks:
            centroids = self._centroids_cad(kind)
            if not len(centroids):
                continue
            x_cad = T_cad_map[:, :3, :3] @ x_map + T_cad_map[:, :3, 3]  # (H, 3)
            near, _ = cKDTree(centroids).query(x_cad, distance_upper_bound=self.inlier_threshold_m)
            count += np.isfinite(near)
        return count

    def own_wall_points(self, points_map: np.ndarray, walls_map: Sequence[tuple[np.ndarray, np.ndarray]]
                        ) -> np.ndarray:
        """Which points (N, 3) lie within `surface_own_wall_m` of one of the planes `walls_map` ((centre,
        normal) pairs, map frame): on a landmark's wall, either face, or in its opening's reveals."""
        near = np.zeros(len(points_map), dtype=bool)
        for centre, normal in walls_map:
            near |= np.abs((points_map - centre) @ normal) <= self.params.surface_own_wall_m
        return near

    def fits(self, check: SurfaceCheck) -> bool:
        """Whether a pose's surface check fits the walls: enough points on them, few seen through one."""
        p = self.params
        return check.support >= p.surface_min_support and check.seen_through <= p.surface_max_seen_through

    def screening_sample(self, points_map: np.ndarray, origins_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`surface_screen_points` of the points and their cameras, evenly drawn, to screen candidates by."""
        every = max(1, int(np.ceil(len(points_map) / self.params.surface_screen_points)))
        return points_map[::every], origins_map[::every]

    def _screened(self, poses: list[np.ndarray], pts: np.ndarray, origins: np.ndarray) -> list[np.ndarray]:
        """The candidate poses worth fitting to the walls: all of a few; of more (one door: each alike door of the
        building, from either side, most of them in rooms whose walls stand nowhere near the points), the
        `surface_screen_top` that score best by the points `pts` (`screening_sample`, seen from `origins`) as
        they are, unfitted (turned to the walls' heading before, `turned`). The points'
        support under every pose is one k-d tree query; only the best supported 3 x `surface_screen_top` have
        their lines of sight checked (most of a check's cost)."""
        p = self.params
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
        self.screens.append((len(poses), score[ranked].round(3).tolist()))
        return [poses[k] for k in supported[ranked[: p.surface_screen_top]]]

    def turned(self, candidates: list[tuple[np.ndarray, int]], pts_map: np.ndarray, fewest: int, most: int,
               landmarks: list[tuple[str, np.ndarray]]) -> list[np.ndarray]:
        """The candidate poses, each one from `fewest` to `most` landmarks turned about the vertical through a
        landmark (the one its pose puts nearest a same-type CAD feature) to the heading, within `surface_turn_deg`,
        whose unfitted support by `surface_turn_points` of the points `pts_map` is highest (ties: the least turn)
        among the headings that leave as many landmarks within `inlier_threshold_m` of a same-type CAD
        feature, searched in steps of twice `surface_turn_step_deg`, then one step either side.

        A pose from one door has the heading of that door's normal, which perception's corners get wrong by tens
        of degrees on a door seen obliquely; one from two or three doors a few metres apart, whose corners are
        coarse at range, by several degrees (docs/measurements.md, "Turning candidates to the walls"). The wall fit
        (`refined`) moves a pose only so far; the walls around a door hold its heading over metres, not over the
        door's width."""
        p = self.params
        poses = [T for T, _ in candidates]
        few = [k for k, (_, n) in enumerate(candidates) if fewest <= n <= most]
        if p.surface_turn_deg <= 0 or not few or not len(pts_map):
            return poses
        pts_map = pts_map[:: max(1, int(np.ceil(len(pts_map) / p.surface_turn_points)))]
        step = np.radians(p.surface_turn_step_deg)
        coarse = np.arange(1, int(p.surface_turn_deg / p.surface_turn_step_deg / 2) + 1) * 2 * step
        coarse = np.concatenate([[0.0], np.ravel(np.column_stack([coarse, -coarse]))])  # the least turn first
        surfaces = self.surfaces
        pivots = {k: c for k in few if (c := self._landmark_at_a_feature(poses[k], landmarks)) is not None}
        ks = list(pivots)
        if not ks:
            return poses
        pivot = np.stack([pivots[k] for k in ks])[:, None, None, :]  # (K, 1, 1, 3)
        moved = np.stack([apply(poses[k], pts_map) for k in ks])[:, None] - pivot  # (K, 1, N, 3)
        centres = np.stack([apply(poses[k], np.stack([x for _, x in landmarks]))
                            for k in ks])[:, None] - pivot  # (K, 1, L, 3)
        kinds = [kind for kind, _ in landmarks]

        def turned(turns: np.ndarray, x: np.ndarray) -> np.ndarray:  # (K, H) turns of (K, 1, M, 3) -> (K, H, M, 3)
            return np.einsum("khij,kxnj->khni", rot_z(turns), x) + pivot

        def by_a_feature(turns: np.ndarray) -> np.ndarray:  # (K, H) turns -> (K, H) landmarks by a CAD feature
            x = turned(turns, centres)
            return sum((np.min(np.linalg.norm(x[:, :, i, None, :] - self._centroids_cad(kind), axis=-1), axis=-1,
                               initial=np.inf) <= self.inlier_threshold_m).astype(int)
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

    def _landmark_at_a_feature(self, T_cad_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]]
                               ) -> np.ndarray | None:
        """The CAD-frame centre, under T_cad_map, of the landmark (type, centre in the map frame) it puts nearest a
        CAD feature of its type."""
        best, best_d = None, np.inf
        for kind, x_map in landmarks:
            x_cad = apply(T_cad_map, x_map[None])[0]
            centroids = self._centroids_cad(kind)
            d = float(np.min(np.linalg.norm(centroids - x_cad, axis=1))) if len(centroids) else np.inf
            if d < best_d:
                best, best_d = x_cad, d
        return best

    def check(self, moved: np.ndarray, origins_map: np.ndarray, T_cad_map: np.ndarray) -> SurfaceCheck:
        """The surface check of the points `moved` by T_cad_map, seen from `origins_map`."""
        return self.surfaces.check(moved, apply(T_cad_map, origins_map))

    def refined(self, T_cad_map: np.ndarray, points_map: np.ndarray) -> np.ndarray:
        """A candidate pose fitted to the walls by the map's depth points (point-to-plane, roll and pitch held near
        the candidate's and the height held: the walls hardly see the height, and a few sloped faces would set it
        alone; the floor fits after localizing take it from the doors'; a tilt the points ask for is the keyframes'
        attitude error, and the anchor is levelled about the vehicle, `PoseGraph.add_anchor`), or as it was where
        the fit fails or moves the points further than `surface_refine_m`. A pose from two or three doors' corners
        is off by tenths of a metre and a degree or two (their corners are coarse at range):
        enough to put points beyond the check's tolerance of their walls, and lines of sight through a doorway
        into its jambs. The check should judge the place a candidate stands for, not its error."""
        if self.params.surface_refine_m <= 0:
            return T_cad_map
        points_map = points_map[:: max(1, int(np.ceil(len(points_map) / 500)))]  # a pose's fit needs no more
        # the points are in the map frame, not around one camera: no range-dependent noise in their weights
        fit = align_to_surfaces(self.surfaces, points_map, T_cad_map, iterations=8, depth_sigma_per_m2=0.0,
                                max_distance_m=self.params.surface_refine_m, sigma_m=self.surface_fit_sigma_m,
                                hold_height=True)
        if fit is None:
            return T_cad_map
        moved = np.linalg.norm(apply(np.linalg.inv(T_cad_map) @ fit.T_cad_body, points_map) - points_map, axis=1)
        return fit.T_cad_body if float(moved.mean()) <= self.params.surface_refine_m else T_cad_map


class Judge(Protocol):
    """What the localizer asks of the walls (`SurfaceJudge`; `NullJudge` without a model's surfaces)."""

    def new_attempt(self) -> None: ...

    def can_check(self, n_points: int) -> bool: ...

    def contradicts(self, T_cad_map: np.ndarray, points_map: np.ndarray, origins_map: np.ndarray) -> bool: ...

    def choose(self, result: Alignment, stamp_ns: int, points_map: np.ndarray, origins_map: np.ndarray,
               landmarks: list[tuple[str, np.ndarray]], far_rivals: FarRivals,
               walls_map: Sequence[tuple[np.ndarray, np.ndarray]] = (),
               far_explains: Callable[[np.ndarray], bool] = lambda T: False) -> Choice: ...

    def rivals_from_one(self, T_cad_map: np.ndarray, poses: list[np.ndarray], points_map: np.ndarray,
                        origins_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]], far_rivals: FarRivals
                        ) -> list[np.ndarray]: ...


class NullJudge:
    """No model surfaces to judge by: no pose is ever checked, and so none is chosen by the walls (only the
    registrar's own 'localized' counts)."""

    def new_attempt(self) -> None:
        pass

    def can_check(self, n_points: int) -> bool:
        return False

    def contradicts(self, T_cad_map: np.ndarray, points_map: np.ndarray, origins_map: np.ndarray) -> bool:
        return False

    def choose(self, result: Alignment, stamp_ns: int, points_map: np.ndarray, origins_map: np.ndarray,
               landmarks: list[tuple[str, np.ndarray]], far_rivals: FarRivals,
               walls_map: Sequence[tuple[np.ndarray, np.ndarray]] = (),
               far_explains: Callable[[np.ndarray], bool] = lambda T: False) -> Choice:
        T_reg = result.T_cad_map if result.status == "localized" else None
        return Choice(T_reg, T_reg is not None)

    def rivals_from_one(self, T_cad_map: np.ndarray, poses: list[np.ndarray], points_map: np.ndarray,
                        origins_map: np.ndarray, landmarks: list[tuple[str, np.ndarray]], far_rivals: FarRivals
                        ) -> list[np.ndarray]:
        return []


class PerPose(Generic[V]):
    """Values computed once per pose (T_cad_map, equal to rounding) within one registration attempt: a stored
    map's candidates and the model's after them share poses."""

    def __init__(self) -> None:
        self._items: list[tuple[np.ndarray, V]] = []

    def get(self, T: np.ndarray, compute: Callable[[np.ndarray], V]) -> V:
        """`compute(T)`, or its value for an equal pose computed before."""
        for T_known, value in self._items:
            if same_pose(T_known, T):
                return value
        value = compute(T)
        self._items.append((T, value))
        return value


class Choice(NamedTuple):
    """The walls' verdict on a registration (`SurfaceJudge.choose`): the pose to anchor with or None,
    whether it is the registrar's own answer, whether two different candidates fit the walls alike, and (no pose
    chosen) those candidates, T_cad_map each."""

    T_cad_map: np.ndarray | None
    registrars: bool
    rivals_fit: bool = False
    rivals: tuple[np.ndarray, ...] = ()  # no pose chosen: the best candidate and those the walls fit as well


def same_pose(A: np.ndarray, B: np.ndarray, tol_m: float = 1e-3, tol_rad: float = 1e-4) -> bool:
    """Two T_cad_map equal to rounding (the same candidate offered by two registrars)."""
    return bool(np.abs(A[:3, 3] - B[:3, 3]).max() <= tol_m and np.abs(A[:3, :3] - B[:3, :3]).max() <= tol_rad)



def poses_differ(A: np.ndarray, B: np.ndarray, moved_A: np.ndarray, moved_B: np.ndarray, apart_m: float = 0.5,
                  turned_deg: float = 5.0) -> bool:
    """Two candidate T_cad_map are different poses where they place the points (`moved_A`, `moved_B`: the same
    map-frame points under each) `apart_m` apart on average, or differ in rotation by `turned_deg` (not at the
    map's origin, which may be far away)."""
    moved = float(np.linalg.norm(moved_A - moved_B, axis=1).mean())
    return moved > apart_m or rotation_angle_deg(A[:3, :3] @ B[:3, :3].T) > turned_deg
