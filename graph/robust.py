"""The default registration: rectangle-seeded pose hypotheses, verification, and an honest ambiguity test.

Why it beats the paper's method: the paper trusts one descriptor match per observation, and its
descriptor changes whenever the observed neighbourhood differs from the model's (a missed or false detection
among the 5 nearest neighbours re-codes every feature around it). Here a single observed door or window
rectangle already fixes a pose up to its symmetry (2 poses with gravity, 4–8 without), so every observed
rectangle is tried against every CAD feature of the same type and compatible size; each hypothesis is
verified by all observations (centroid within a tolerance of a CAD feature of the same type), the best are
refined with all corners (yaw + translation when gravity is known, full SE(3) otherwise), and the best
pose is only reported `localized` when no *different* pose explains the observations about as well.

Frames: observations in `map`, features in `cad`; gravity-aligned `map'` = R_g map with gravity -> -z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graph.features import FEATURE_TYPES
from graph.model_index import ModelIndex
from graph.observations import Observation, ObservationSet
from graph.registration import RegistrationResult, corner_correspondences, majority_storey
from graph.rigid import apply, make_T, rotation_aligning, rotation_angle_deg, weighted_rigid_fit, yaw_rigid_fit

GRAVITY_CAD = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class RobustParams:
    inlier_threshold_m: float = 0.30  # a refined pose explains an observation within this distance
    size_tolerance_m: float = 0.35  # observed vs CAD rectangle side lengths
    coarse_base_m: float = 0.45  # coarse verification tolerance: base + slope x distance from the seed
    coarse_slope: float = 0.12
    max_seeds: int = 8  # observed rectangles used to generate hypotheses, at most
    min_seeds: int = 2  # seeds added per round (refinement runs after each round)
    early_stop_fraction: float = 0.5  # stop seeding once a refined pose explains this fraction
    refine_top: int = 6  # distinct coarse hypotheses refined (a symmetric rival scores like the best: it is kept)
    scan_top: int = 300  # coarse hypotheses scanned for distinct ones
    refine_iterations: int = 3
    gravity_tolerance_deg: float = 15.0
    ambiguity_ratio: float = 0.85  # second distinct pose with >= ratio x the best support -> ambiguous
    distinct_m: float = 0.5  # poses that move the matched observations by more than this are different ...
    distinct_deg: float = 5.0  # ... and so are poses whose rotations differ by more than this
    min_inlier_fraction: float = 0.35  # a pose explaining fewer of the observations is not trusted
    min_inliers: int = 3
    seed: int = 0


@dataclass
class _Rect:
    centre: np.ndarray
    a: np.ndarray  # unit edge direction
    b: np.ndarray  # unit edge direction, orthogonal to a
    la: float
    lb: float


def rectangle_edges(corners: np.ndarray) -> _Rect:
    """Edge frame of 4 rectangle corners given in any order (the diagonal of corner 0 is its farthest corner)."""
    p = np.asarray(corners, dtype=float)
    opp = 1 + int(np.argmax(np.linalg.norm(p[1:] - p[0], axis=1)))
    i, j = [k for k in (1, 2, 3) if k != opp]
    e1 = ((p[i] - p[0]) + (p[opp] - p[j])) / 2.0
    e2 = ((p[j] - p[0]) + (p[opp] - p[i])) / 2.0
    la, lb = float(np.linalg.norm(e1)), float(np.linalg.norm(e2))
    # nearest orthonormal pair to (e1/la, e2/lb): polar decomposition of the 3x2 matrix
    M = np.stack([e1 / max(la, 1e-9), e2 / max(lb, 1e-9)], axis=1)
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    Q = U @ Vt
    return _Rect(p.mean(axis=0), Q[:, 0], Q[:, 1], la, lb)


def _seed_hypotheses(rect: _Rect, cand: np.ndarray, index: ModelIndex, params: RobustParams,
                     gravity_known: bool) -> tuple[np.ndarray, np.ndarray]:
    """All rotations R (H, 3, 3) and translations t (H, 3) that put `rect` onto a candidate CAD rectangle."""
    tol = params.size_tolerance_m
    Rs, ts = [], []
    M_obs = np.stack([rect.a, rect.b, np.cross(rect.a, rect.b)], axis=1)  # columns
    for swap in (False, True):
        U = index.edge_v[cand] if swap else index.edge_u[cand]
        V = index.edge_u[cand] if swap else index.edge_v[cand]
        lu = index.len_v[cand] if swap else index.len_u[cand]
        lv = index.len_u[cand] if swap else index.len_v[cand]
        ok = (np.abs(lu - rect.la) < tol) & (np.abs(lv - rect.lb) < tol)
        if not ok.any():
            continue
        U, V, c_cad = U[ok], V[ok], index.centroids[cand][ok]
        for s1 in (1.0, -1.0):
            for s2 in (1.0, -1.0):
                Mc = np.stack([s1 * U, s2 * V, s1 * s2 * np.cross(U, V)], axis=2)  # (h, 3, 3) columns
                R = Mc @ M_obs.T
                if gravity_known:  # map' is gravity-aligned: R must keep +z up
                    keep = R[:, 2, 2] > np.cos(np.radians(params.gravity_tolerance_deg))
                    R, cc = R[keep], c_cad[keep]
                else:
                    cc = c_cad
                Rs.append(R)
                ts.append(cc - R @ rect.centre)
    if not Rs:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    return np.concatenate(Rs), np.concatenate(ts)


def _nearest_same_type(points: np.ndarray, types: np.ndarray, index: ModelIndex,
                       upper_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """For points (..., N, 3) with per-observation types (N,): distance to and index of the nearest CAD feature
    of the same type (inf / -1 where there is none within `upper_m`)."""
    shape = points.shape[:-1]
    flat = points.reshape(-1, 3)
    codes = np.broadcast_to(_type_codes(types), shape).reshape(-1)
    dist = np.full(len(flat), np.inf)
    idx = np.full(len(flat), -1, dtype=np.int64)
    for code, kind in enumerate(FEATURE_TYPES):
        tree = index.trees.get(kind)
        sel = codes == code
        if tree is not None and sel.any():
            d, j = tree.query(flat[sel], distance_upper_bound=upper_m)
            found = np.isfinite(d)
            dist[np.flatnonzero(sel)[found]] = d[found]
            idx[np.flatnonzero(sel)[found]] = index.type_indices[kind][j[found]]
    return dist.reshape(shape), idx.reshape(shape)


def _type_codes(types: np.ndarray) -> np.ndarray:
    """Feature types as small integers (index into FEATURE_TYPES); string compares are slow in hot loops."""
    return np.array([FEATURE_TYPES.index(t) for t in types], dtype=np.int8)


def _support(d: np.ndarray, tau: np.ndarray | float) -> np.ndarray:
    """Truncated-quadratic (MSAC) support of residuals d against tolerance tau, summed over the last axis."""
    r = d / tau
    return np.where(r < 1.0, 1.0 - r * r, 0.0).sum(axis=-1)


@dataclass
class _Pose:
    T: np.ndarray  # T_cad_map'
    inliers: np.ndarray  # (N,) bool
    match: np.ndarray  # (N,) CAD index
    score: float


def _refine(T: np.ndarray, obs: list[Observation], c_obs: np.ndarray, types: np.ndarray, index: ModelIndex,
            params: RobustParams, gravity_known: bool) -> _Pose:
    for _ in range(params.refine_iterations):
        d, j = _nearest_same_type(apply(T, c_obs), types, index)
        inl = d < params.inlier_threshold_m * 1.5
        if inl.sum() < 2:
            break
        pairs = _one_to_one([(i, int(j[i])) for i in np.flatnonzero(inl)], d)
        src, dst = corner_correspondences(T, obs, pairs, index)
        if len(src) < 3:
            break
        T = yaw_rigid_fit(src, dst) if gravity_known else weighted_rigid_fit(src, dst)
    d, j = _nearest_same_type(apply(T, c_obs), types, index)
    inl = d < params.inlier_threshold_m
    pairs = _one_to_one([(i, int(j[i])) for i in np.flatnonzero(inl)], d)
    keep = np.zeros(len(obs), dtype=bool)
    keep[[i for i, _ in pairs]] = True
    return _Pose(T, keep, j, float(_support(np.where(keep, d, np.inf), params.inlier_threshold_m)))


def _one_to_one(pairs: list[tuple[int, int]], d: np.ndarray) -> list[tuple[int, int]]:
    """Keep, for each CAD feature, only the closest observation claiming it."""
    best: dict[int, int] = {}
    for i, j in pairs:
        if j not in best or d[i] < d[best[j]]:
            best[j] = i
    return sorted((i, j) for j, i in best.items())


def _distinct_top(order: np.ndarray, moved: np.ndarray, params: RobustParams) -> list[int]:
    """The best hypotheses (in `order`) that differ pairwise: mean displacement of the observations > distinct_m/2."""
    chosen: list[int] = []
    for h in order:
        if all(np.linalg.norm(moved[h] - moved[c], axis=1).mean() > params.distinct_m / 2 for c in chosen):
            chosen.append(int(h))
            if len(chosen) == params.refine_top:
                break
    return chosen


@dataclass
class _Prepared:
    """Observations in the gravity-aligned map' frame (identity when gravity is unknown)."""

    obs: list[Observation]
    centroids: np.ndarray  # (N, 3) map'
    types: np.ndarray  # (N,)
    T_mp_m: np.ndarray  # map -> map'
    gravity_known: bool


def _prepare(obs_set: ObservationSet) -> _Prepared:
    gravity_known = obs_set.gravity_map is not None
    R_g = rotation_aligning(obs_set.gravity_map, GRAVITY_CAD) if gravity_known else np.eye(3)
    obs = [Observation(o.type, R_g @ o.centroid_map, None if o.corners_map is None else o.corners_map @ R_g.T)
           for o in obs_set.observations]
    return _Prepared(obs, np.array([o.centroid_map for o in obs]).reshape(-1, 3), np.array([o.type for o in obs]),
                     make_T(R_g, np.zeros(3)), gravity_known)


@dataclass
class _Hypotheses:
    R: np.ndarray  # (H, 3, 3)  T_cad_map' rotations
    t: np.ndarray  # (H, 3)
    moved: np.ndarray  # (H, N, 3) observed centroids under each hypothesis, CAD
    coarse: np.ndarray  # (H,) coarse support

    def extend(self, other: _Hypotheses) -> _Hypotheses:
        return _Hypotheses(*(np.concatenate([a, b]) for a, b in
                             zip((self.R, self.t, self.moved, self.coarse),
                                 (other.R, other.t, other.moved, other.coarse), strict=True)))


def _coarse(seed: int, prep: _Prepared, index: ModelIndex, params: RobustParams) -> _Hypotheses:
    """Hypotheses of one observed rectangle against every compatible CAD feature, coarsely verified by all
    observations; the tolerance grows with the distance from the seed (one rectangle gives the rotation only
    to a few degrees)."""
    o = prep.obs[seed]
    R, t = _seed_hypotheses(rectangle_edges(o.corners_map), index.type_indices[o.type], index, params,
                            prep.gravity_known)
    moved = np.einsum("hij,nj->hni", R, prep.centroids) + t[:, None, :]
    tau = params.coarse_base_m + params.coarse_slope * np.linalg.norm(prep.centroids - prep.centroids[seed], axis=1)
    d, _ = _nearest_same_type(moved, prep.types, index, upper_m=float(tau.max()))
    return _Hypotheses(R, t, moved, _support(d, tau))


def _distinct(a: _Pose, b: _Pose, anchor: np.ndarray, params: RobustParams) -> bool:
    """Two poses are different when they move the anchor points apart or differ in rotation."""
    moved_apart = np.linalg.norm(apply(a.T, anchor) - apply(b.T, anchor), axis=1).mean() > params.distinct_m
    return bool(moved_apart or rotation_angle_deg(a.T[:3, :3] @ b.T[:3, :3].T) > params.distinct_deg)


def register_robust(index: ModelIndex, obs_set: ObservationSet, params: RobustParams) -> RegistrationResult:
    """Hypothesise from observed rectangles, verify, refine, and answer only when no rival pose is as good."""
    prep = _prepare(obs_set)
    n = len(prep.obs)
    rect_ids = [i for i, o in enumerate(prep.obs) if o.corners_map is not None and o.type in index.trees]
    if n == 0 or not rect_ids:
        return RegistrationResult("not_localized", None, [], 0, None,
                                  diagnostics={"reason": "no observed door/window rectangle"})
    seeds = np.random.default_rng(params.seed).permutation(rect_ids)[: params.max_seeds]
    hyps = _Hypotheses(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, n, 3)), np.zeros(0))
    poses: list[_Pose] = []
    used = 0
    for start in range(0, len(seeds), params.min_seeds):
        for s in seeds[start:start + params.min_seeds]:
            hyps = hyps.extend(_coarse(int(s), prep, index, params))
        used = min(len(seeds), start + params.min_seeds)
        if len(hyps.R) == 0:
            continue
        top = _distinct_top(np.argsort(-hyps.coarse, kind="stable")[: params.scan_top], hyps.moved, params)
        poses = sorted((_refine(make_T(hyps.R[h], hyps.t[h]), prep.obs, prep.centroids, prep.types, index, params,
                                prep.gravity_known) for h in top), key=lambda p: -p.score)
        if poses[0].inliers.sum() >= params.early_stop_fraction * n:
            break  # well supported; its symmetric rivals come from the same seeds
    return _decide(poses, prep, index, params, {"hypotheses": int(len(hyps.R)), "seeds": used})


def _decide(poses: list[_Pose], prep: _Prepared, index: ModelIndex, params: RobustParams,
            diag: dict) -> RegistrationResult:
    n = len(prep.obs)
    if not poses:
        return RegistrationResult("not_localized", None, [], 0, None, diagnostics=diag)
    best = poses[0]
    n_best = int(best.inliers.sum())
    diag.update(best_support=round(best.score, 3), best_inliers=n_best)
    if n_best < max(params.min_inliers, params.min_inlier_fraction * n):
        return RegistrationResult("not_localized", None, [], n_best, None, diagnostics=diag)
    anchor = prep.centroids[best.inliers]
    rivals = [p for p in poses[1:] if _distinct(best, p, anchor, params)]
    rival = max(rivals, key=lambda p: p.score) if rivals else None
    diag.update(rival_support=round(rival.score, 3) if rival else 0.0,
                rival_inliers=int(rival.inliers.sum()) if rival else 0)
    pairs = [(int(i), int(best.match[i])) for i in np.flatnonzero(best.inliers)]
    T_cad_map = best.T @ prep.T_mp_m
    storey = majority_storey(index, [j for _, j in pairs])
    matches = [(i, index.features[j].id) for i, j in pairs]
    if rival is not None and rival.score >= params.ambiguity_ratio * best.score:
        return RegistrationResult("ambiguous", T_cad_map, matches, n_best, storey,
                                  alternatives=[rival.T @ prep.T_mp_m], diagnostics=diag)
    return RegistrationResult("localized", T_cad_map, matches, n_best, storey, diagnostics=diag)
