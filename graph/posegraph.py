"""The pose graph: keyframes, rectangle landmarks and the CAD anchor in GTSAM iSAM2.

Variables (all gtsam.Pose3):
  X(i)  T_map_body of keyframe i              (map = this flight's odometry frame, z up from gravity)
  L(j)  T_map_rect of landmark j              (a door or window, see graph.landmarks)
  A(0)  T_map_cad, the CAD anchor              (the localization result is its inverse, T_cad_map)

Factors (all built-in, so the real-time path never calls Python):
  PriorFactorPose3(X(0))                       fixes the map frame at the first keyframe
  BetweenFactorPose3(X(i-1), X(i), T_prev_curr) odometry
  PriorFactorPose3(X(i)), roll/pitch only     gravity (yaw and translation free)
  BetweenFactorPose3(X(i), L(j), T_body_rect)  a sighting of landmark j from keyframe i
  PriorFactorPose3(A(0))                       keeps the anchor level (both frames are gravity-aligned) and,
                                               weakly, its yaw and position determined whatever its links
  BetweenFactorPose3(A(0), X(i), T_cad_body)   robust (Huber): keyframe i's depth fitted to the model's walls
  BetweenFactorPose3(A(0), L(j), T_cad_feature) robust (Cauchy): landmark j is the CAD feature
      (between(T_map_cad, T_map_rect) = T_cad_map T_map_rect = T_cad_rect, so the anchor is stored as
       T_map_cad and no inverse-direction trap arises)

Every `update()` hands iSAM2 only the factors and values added since the previous one; with `record_batch`,
`batch_graph()` returns everything ever added so a batch optimiser can be checked against iSAM2 (the oracle test).

Bounded cost over a mission (`IsamSettings.window_keyframes`, issue 37). iSAM2 holding every keyframe walks all
of them in each update: its relinearisation check and its back-substitution (the anchor and the doors sit at the
root of the Bayes tree, and each keyframe hangs below them) grow with the flight, the more so where a wall fit ties
every keyframe to the anchor (bench/bench_posegraph.py --long [--wall-fits]). With a window of W keyframes iSAM2
holds the newest W to W + K keyframes (K = `marginalise_every`): every K keyframes the oldest K are marginalised at
once, as gtsam's IncrementalFixedLagSmoother does (an update re-eliminating every variable, those keyframes first,
then `marginalizeLeaves`: their factors become a linear prior on the next keyframe, the doors they saw and the
anchor, whose linearisation points gtsam then fixes), once per K keyframes, not per keyframe. Unlike that
smoother, the anchor and the newest keyframe are eliminated last, at the root, in every update: the covariance of
T_cad_body (the service's, each keyframe) stays the root clique's (0.2 ms, 11 ms with the smoother at 700
keyframes). A marginalised keyframe's last estimate is kept and read by `T_map_body(i)` as before; a factor on one
raises. The anchor is never marginalised. A landmark is marginalised with the keyframes once no live keyframe
sees it (`IsamSettings.marginalise_landmarks`): otherwise the marginalised keyframes' prior joins every door they
saw into one clique with the anchor, which each sighting re-eliminates, and the cost grows with the doors mapped
(the building's area). Its CAD links are removed from iSAM2 first, so the anchor keeps no linear prior from doors
out of sight (a prior on the anchor would fix its linearisation point for the rest of the mission, and the links
come back below); the information lost is that of the door's own links while it is out of sight, never counted
twice. Its last estimate and marginal covariance are kept: `T_map_rect(j)` reads them, so the saved map and
registration still see every door. Seen again (or linked again), it re-enters as a variable at that estimate with
its links; a door never linked re-enters with a prior of that covariance instead, which treats it as independent
of the window (the approximation of a localization map's landmarks). The window rule is the localizer's, not the
building's: it adds factors to the newest keyframe only and reads back the keyframes of its depth and
far-sighting windows (`surface_window_keyframes`, 60), so W >= 60 keeps all it reads live; the cost then
depends on the doors in view, not on the flight's length or the building's size.
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np

from macroloc.graph.params import IsamSettings
from macroloc.graph.rigid import levelled_about

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X
L = gtsam.symbol_shorthand.L
A = gtsam.symbol_shorthand.A
ANCHOR = A(0)
_X_CHR, _L_CHR = ord("x"), ord("l")  # a gtsam.Symbol key: its character in the top byte, ...
_INDEX_MASK = (1 << 56) - 1  # ... its index below

# Pose3 sigmas are in GTSAM's tangent order [rot (rad) x3; trans (m) x3].
# The first keyframe fixes the map frame's yaw and origin; its roll and pitch are the odometry's first guess (one
# frame's specific force, a few degrees off while the vehicle accelerates): loose, for gravity's priors to correct.
FIRST_POSE_SIGMAS = np.array([0.2, 0.2, 1e-3, 1e-3, 1e-3, 1e-3])
GRAVITY_SIGMAS = np.array([0.01, 0.01, 1e3, 1e4, 1e4, 1e4])  # roll, pitch from gravity; the rest free
SIGHTING_SIGMAS = np.array([0.05, 0.05, 0.05, 0.05, 0.05, 0.05])  # 3 deg, 5 cm at 1 m (scaled by range)
CAD_LINK_SIGMAS = np.array([0.05, 0.05, 0.05, 0.05, 0.05, 0.05])  # model vs. reality: 3 deg, 5 cm
CAD_LINK_POSITION_SIGMAS = np.array([1e3, 1e3, 1e3, 0.05, 0.05, 0.05])  # a link of the position only
# The map's z is gravity's (the keyframes' gravity priors) and the model's z is up: T_map_cad turns about z only.
# Its roll and pitch are held to 0 as tightly as one keyframe's gravity; yaw and position only weakly (A(0)
# determined at any time): those are the links' and the wall fits' to say.
ANCHOR_PRIOR_SIGMAS = np.array([0.01, 0.01, 0.5, 5.0, 5.0, 5.0])
CAD_LINK_CAUCHY_K = 2.0  # whitened residual where the Cauchy loss halves a link's weight


def pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=float))


def diagonal(sigmas: np.ndarray) -> gtsam.noiseModel.Diagonal:
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=float))


def robust(sigmas: np.ndarray, cauchy_k: float = CAD_LINK_CAUCHY_K) -> gtsam.noiseModel.Robust:
    """Cauchy loss over a diagonal model: a wrong CAD match far from the estimate weighs ~ (k / r)^2."""
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k), diagonal(sigmas))


class PoseGraph:
    """Incremental keyframe graph; a thin typed layer over iSAM2 that speaks 4x4 numpy transforms."""

    def __init__(self, settings: IsamSettings | None = None, record_batch: bool = False) -> None:
        """`record_batch`: keep every factor and initial guess ever added, for `batch_graph` (tests: the oracle
        check against a batch optimiser). Off in the service: the record grows with the mission (28 MB over 8,000
        keyframes of bench_posegraph's loop, 70 % of what the process grew by)."""
        self.settings = settings = settings or IsamSettings()
        self.record_batch = record_batch
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(settings.relinearize_threshold)
        params.relinearizeSkip = settings.relinearize_skip
        self.window = max(0, int(settings.window_keyframes))
        self.chunk = max(1, int(settings.marginalise_every))
        self.marginalise_landmarks = bool(settings.marginalise_landmarks)
        self._isam = gtsam.ISAM2(params)
        self._marginalised: dict[int, np.ndarray] = {}  # keyframe -> its last estimate T_map_body, once marginalised
        self.live_from = 0  # the oldest keyframe still a variable (all older ones are in `_marginalised`)
        self.last_reeliminated = 0  # variables iSAM2 re-eliminated in the last update (all its steps): the work done
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._all_factors = gtsam.NonlinearFactorGraph()
        self._all_values = gtsam.Values()
        self.n_keyframes = 0
        self.landmarks: set[int] = set()  # every landmark ever added, live or marginalised
        self._last_seen: dict[int, int] = {}  # landmark -> the newest keyframe with a factor on it (or added at)
        # A marginalised landmark -> its last T_map_rect, 6x6 marginal covariance and CAD-link factors (removed)
        self._out: dict[int, tuple[np.ndarray, np.ndarray, list[gtsam.NonlinearFactor]]] = {}
        self._links: dict[int, list[tuple[int, gtsam.NonlinearFactor]]] = {}  # landmark -> (iSAM2 index, link)
        self._pending_links: list[tuple[int, int]] = []  # (position in the new factors, landmark) until the update
        self.has_anchor = False
        self.last_update_ms = 0.0
        self.last_update_cpu_ms = 0.0  # process CPU time of the update: immune to a busy machine's scheduling
        self._updates = 0  # iSAM2 updates so far: what the marginals depend on
        self._covariance: tuple[tuple[int, int, bool], np.ndarray] | None = None  # the last one, by what it read

    # --- adding variables and factors (buffered until update) -----------------------------------------------

    def _live(self, i: int) -> int:
        """X(i), where keyframe i is still a variable: a factor on a marginalised keyframe cannot be added."""
        if i < self.live_from:
            raise ValueError(f"keyframe {i} was marginalised (window {self.window}, oldest kept {self.live_from})")
        return X(i)

    def _add(self, factor: gtsam.NonlinearFactor) -> None:
        self._new_factors.add(factor)
        if self.record_batch:
            self._all_factors.add(factor)

    def _insert(self, key: int, T: np.ndarray) -> None:
        self._new_values.insert(key, pose3(T))
        if self.record_batch:
            self._all_values.insert(key, pose3(T))

    def add_first_keyframe(self, T_map_body: np.ndarray) -> int:
        """Keyframe 0 defines the map frame: a tight prior at `T_map_body` (4x4)."""
        self._insert(X(0), T_map_body)
        self._add(gtsam.PriorFactorPose3(X(0), pose3(T_map_body), diagonal(FIRST_POSE_SIGMAS)))
        self.n_keyframes = 1
        return 0

    def add_keyframe(self, T_prev_curr: np.ndarray, odometry_sigmas: np.ndarray,
                     T_map_body_guess: np.ndarray) -> int:
        """Keyframe i = n with an odometry factor from keyframe i-1 (T_prev_curr 4x4, sigmas [rot; trans])."""
        i = self.n_keyframes
        self._insert(X(i), T_map_body_guess)
        self._add(gtsam.BetweenFactorPose3(self._live(i - 1), X(i), pose3(T_prev_curr), diagonal(odometry_sigmas)))
        self.n_keyframes += 1
        return i

    def add_gravity(self, i: int, T_map_body_level: np.ndarray) -> None:
        """Roll and pitch of keyframe i from gravity: `T_map_body_level` has the measured attitude."""
        self._add(gtsam.PriorFactorPose3(self._live(i), pose3(T_map_body_level), diagonal(GRAVITY_SIGMAS)))

    def add_landmark(self, j: int, T_map_rect_guess: np.ndarray) -> None:
        self._insert(L(j), T_map_rect_guess)
        self.landmarks.add(j)
        self._last_seen[j] = self.n_keyframes - 1

    def add_sighting(self, i: int, j: int, T_body_rect: np.ndarray, sigmas: np.ndarray = SIGHTING_SIGMAS) -> None:
        """Landmark j seen from keyframe i as T_body_rect (4x4)."""
        self._enter(j)
        self._add(gtsam.BetweenFactorPose3(self._live(i), L(j), pose3(T_body_rect), diagonal(sigmas)))
        self._last_seen[j] = max(self._last_seen[j], i)

    def _enter(self, j: int) -> None:
        """Landmark j a variable again, if it was marginalised: at its last estimate with its CAD links, or, never
        linked, with a prior of its last marginal covariance (iSAM2's alone: the batch graph holds all its factors
        already)."""
        if j not in self._out:
            return
        T, covariance, links = self._out.pop(j)
        self._new_values.insert(L(j), pose3(T))
        if not links:
            covariance = (covariance + covariance.T) / 2.0 + 1e-12 * np.eye(6)  # symmetric, positive definite
            self._new_factors.add(gtsam.PriorFactorPose3(L(j), pose3(T),
                                                         gtsam.noiseModel.Gaussian.Covariance(covariance)))
        for link in links:
            self._pending_links.append((int(self._new_factors.size()), j))
            self._new_factors.add(link)
        self._last_seen[j] = self.n_keyframes - 1

    def add_anchor(self, T_map_cad_guess: np.ndarray) -> None:
        """The CAD anchor variable A(0) = T_map_cad, initialised from a registration, levelled (see
        ANCHOR_PRIOR_SIGMAS) about the newest keyframe: a guess tilted by a degree or two (a pose fitted to walls)
        keeps the vehicle where it placed it, not the CAD origin, tens of metres away (levelled about that, a 2 deg
        tilt moved the vehicle 0.85 m down: docs/measurements.md, "Issue 56: the service's accuracy mended")."""
        p_map = self.T_map_body(self.n_keyframes - 1)[:3, 3] if self.n_keyframes else np.zeros(3)
        T_level = np.linalg.inv(levelled_about(np.linalg.inv(T_map_cad_guess), p_map))
        self._insert(ANCHOR, T_level)
        self._add(gtsam.PriorFactorPose3(ANCHOR, pose3(T_level), diagonal(ANCHOR_PRIOR_SIGMAS)))
        self.has_anchor = True

    def add_cad_pose(self, i: int, T_cad_body: np.ndarray, information: np.ndarray, huber_k: float = 1.5) -> None:
        """Keyframe i's pose in the CAD frame, measured (depth against the model's surfaces, graph.surfaces),
        with its 6 x 6 information [rot; trans]: between(T_map_cad, T_map_body) = T_cad_body. Huber-robust."""
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k),
                                               gtsam.noiseModel.Gaussian.Information(np.asarray(information, float)))
        self._add(gtsam.BetweenFactorPose3(ANCHOR, self._live(i), pose3(T_cad_body), noise))

    def add_cad_link(self, j: int, T_cad_rect: np.ndarray, sigmas: np.ndarray = CAD_LINK_SIGMAS) -> None:
        """Landmark j is the CAD feature with frame T_cad_rect (robust: a wrong match loses its weight)."""
        self._enter(j)
        self._pending_links.append((int(self._new_factors.size()), j))
        self._add(gtsam.BetweenFactorPose3(ANCHOR, L(j), pose3(T_cad_rect), robust(sigmas)))

    # --- solving ----------------------------------------------------------------------------------------------

    def update(self, extra_iterations: int = 0) -> float:
        """Pass only the new factors and values to iSAM2; returns the update time in ms."""
        start, start_cpu = time.perf_counter(), time.process_time()
        leaving = self._leaving()
        result = self._marginalise(leaving) if leaving else self._update_rooted()
        indices = result.getNewFactorsIndices()
        for position, j in self._pending_links:
            self._links.setdefault(j, []).append((int(indices[position]), self._new_factors.at(position)))
        self._pending_links = []
        self.last_reeliminated = result.getVariablesReeliminated()
        for _ in range(extra_iterations):
            self.last_reeliminated += self._isam.update().getVariablesReeliminated()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._updates += 1
        self.last_update_ms = (time.perf_counter() - start) * 1e3
        self.last_update_cpu_ms = (time.process_time() - start_cpu) * 1e3
        return self.last_update_ms

    def _leaving(self) -> range:
        """The keyframes to marginalise in this update: with a window, those of the chunks (of `chunk` keyframes)
        that ended more than `window` keyframes before the newest's chunk began."""
        if not self.window:
            return range(0)
        newest = self.n_keyframes - 1
        stop = self.live_from
        while stop < newest and self._chunk_start(stop) < self._chunk_start(newest) - self.window:
            stop += 1
        return range(self.live_from, stop)

    def _update_rooted(self) -> gtsam.ISAM2Result:
        """iSAM2's update, with a window: the anchor and the newest keyframe eliminated last, at the root (see
        `_marginalise`; two groups: CCOLAMD takes group numbers below the variables' count)."""
        if not self.window or self.n_keyframes < 2 or self._new_factors.size() == 0:
            return self._isam.update(self._new_factors, self._new_values)
        groups = gtsam.KeyGroupMap()
        for key in (ANCHOR, X(self.n_keyframes - 1)) if self.has_anchor else (X(self.n_keyframes - 1),):
            groups.insert2(key, 1)
        return self._isam.update(self._new_factors, self._new_values, constrainedKeys=groups)

    def _chunk_start(self, i: int) -> int:
        return i - i % self.chunk

    def _marginalise(self, leaving: range) -> gtsam.ISAM2Result:
        """The update that marginalises the keyframes `leaving` (their estimates before it kept): every variable
        re-eliminated, those keyframes first (then they are the Bayes tree's leaves, which iSAM2 marginalises),
        the anchor and the newest keyframe last (at the root: the covariance of T_cad_body, the service's at each
        keyframe, is then the root clique's, not a walk down the tree: gtsam's IncrementalFixedLagSmoother, which
        orders them anywhere, made it 11 ms instead of 0.3 at 700 keyframes). Once per chunk, not per keyframe."""
        for i in leaving:
            self._marginalised[i] = self._value(X(i))
        linking = {j for _, j in self._pending_links}
        unseen = sorted(j for j, seen in self._last_seen.items()
                        if seen < leaving.stop and j not in self._out and j not in linking) \
            if self.marginalise_landmarks else []
        removed = [index for j in unseen for index, _ in self._links.get(j, [])]
        old = {X(i) for i in leaving} | {L(j) for j in unseen}
        last = {ANCHOR, X(self.n_keyframes - 1)}
        groups, everything = gtsam.KeyGroupMap(), gtsam.KeyList()
        for key in [*self._isam.getLinearizationPoint().keys(), *self._new_values.keys()]:
            groups.insert2(key, 0 if key in old else 2 if key in last else 1)
            everything.push_back(key)
        result = self._isam.update(self._new_factors, self._new_values, removeFactorIndices=removed,
                                   constrainedKeys=groups, extraReelimKeys=everything)
        for j in unseen:
            self._out[j] = (self._isam.calculateEstimatePose3(L(j)).matrix(),
                            np.asarray(self._isam.marginalCovariance(L(j))),
                            [link for _, link in self._links.pop(j, [])])
        leaves = gtsam.KeyList()
        for key in sorted(old):
            leaves.push_back(key)
        self._isam.marginalizeLeaves(leaves)
        self.live_from = leaving.stop
        return result

    @property
    def marginalised_landmarks(self) -> set[int]:
        """The landmarks out of the window now (read at their last estimate; each re-enters when seen again)."""
        return set(self._out)

    @property
    def isam(self) -> gtsam.ISAM2:
        """The iSAM2 holding the live variables."""
        return self._isam

    def n_variables(self) -> int:
        """The variables iSAM2 holds (keyframes in the window, landmarks, anchor): what its updates walk. O(n)."""
        return int(self._isam.getLinearizationPoint().size())

    def batch_graph(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """Every factor ever added, with the initial guesses: for a batch optimisation of the same problem
        (`record_batch` only)."""
        if not self.record_batch:
            raise ValueError("PoseGraph(record_batch=True) keeps every factor for a batch optimisation")
        return self._all_factors, self._all_values

    # --- reading the estimate ---------------------------------------------------------------------------------

    def T_map_body(self, i: int) -> np.ndarray:
        return self._value(X(i))

    def T_map_rect(self, j: int) -> np.ndarray:
        return self._value(L(j))

    def T_cad_map(self) -> np.ndarray | None:
        return np.linalg.inv(self._value(ANCHOR)) if self.has_anchor else None

    def _value(self, key: int) -> np.ndarray:
        """The current estimate of one variable (iSAM2's, the initial guess of one not yet solved, or a
        marginalised keyframe's last estimate)."""
        if self._new_values.exists(key):
            return self._new_values.atPose3(key).matrix()
        if key >> 56 == _X_CHR and key & _INDEX_MASK < self.live_from:
            return self._marginalised[key & _INDEX_MASK]
        if key >> 56 == _L_CHR and key & _INDEX_MASK in self._out:
            return self._out[key & _INDEX_MASK][0].copy()
        return self._isam.calculateEstimatePose3(key).matrix()

    def estimate(self) -> gtsam.Values:
        """All variables' current estimates, marginalised keyframes' and landmarks' their last (for tests and
        reports; O(n))."""
        values = self._isam.calculateEstimate()
        for i, T in self._marginalised.items():
            values.insert(X(i), pose3(T))
        for j, (T, _, _) in self._out.items():
            values.insert(L(j), pose3(T))
        return values

    def covariance_cad_body(self, i: int) -> np.ndarray:
        """6x6 covariance of T_cad_body of keyframe i in its body tangent space, [rot; trans] (marginals).

        T_cad_body = between(T_map_cad, T_map_body); the joint marginal of A(0) and X(i) is propagated through
        the Jacobians of `between`. Before registration: the covariance of T_map_body. It changes only with an
        iSAM2 update, so it is computed once per update and keyframe (the held rule, the status and the estimate
        each read it: ~1 ms once the doors mapped share the Bayes tree's root, docs/measurements.md).
        """
        read = (i, self._updates, self.has_anchor)
        if self._covariance is None or self._covariance[0] != read:
            self._covariance = read, self._covariance_cad_body(i)
        return self._covariance[1].copy()

    def _covariance_cad_body(self, i: int) -> np.ndarray:
        isam = self.isam
        if not self.has_anchor:
            return np.asarray(isam.marginalCovariance(self._live(i)))
        keys = gtsam.KeyVector([ANCHOR, self._live(i)])
        joint = isam.jointMarginalCovariance(keys).fullMatrix()
        H1, H2 = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
        anchor, pose = isam.calculateEstimatePose3(ANCHOR), isam.calculateEstimatePose3(X(i))
        anchor.between(pose, H1, H2)
        J = np.hstack([H1, H2])
        return J @ joint @ J.T

    def horizontal_sigma_m(self, i: int) -> float:
        """Keyframe i's horizontal position sigma in the CAD frame (metres, the worst horizontal direction): the
        translation block of `covariance_cad_body`, turned from the body's tangent into the CAD frame."""
        T_cad_map = self.T_cad_map()
        assert T_cad_map is not None, "the graph is not anchored"
        R_cad_body = (T_cad_map @ self.T_map_body(i))[:3, :3]
        C_cad = R_cad_body @ self.covariance_cad_body(i)[3:, 3:] @ R_cad_body.T
        return float(np.sqrt(max(np.linalg.eigvalsh(C_cad[:2, :2])[-1], 0.0)))
