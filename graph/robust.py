"""The default registration: rectangle-seeded pose hypotheses, verification, and an honest ambiguity test.

Why it beats the paper's method: the paper trusts one descriptor match per observation, and its
descriptor changes whenever the observed neighbourhood differs from the model's (a missed or false detection
among the 5 nearest neighbours re-codes every feature around it). Here a single observed door or window
rectangle already fixes a pose up to its symmetry (2 poses with gravity, 4–8 without), so every observed
rectangle is tried against every CAD feature of the same type and compatible size; each hypothesis is
verified by all observations (centroid within a tolerance of a CAD feature of the same type), the best are
refined with all corners (yaw + translation when gravity is known, full SE(3) otherwise), and the best
pose is only reported `localized` when no *different* pose explains the observations about as well (an MLESAC
log-likelihood within `ambiguity_loglik_margin`; every hypothesis is searched for such a rival).

Frames: observations in `map`, features in `cad`; gravity-aligned `map'` = R_g map with gravity -> -z.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from macroloc.graph.features import FEATURE_TYPES
from macroloc.graph.model_index import TYPE_SEPARATION_M, ModelIndex
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.registration import RegistrationResult, corner_correspondences, majority_storey
from macroloc.graph.rigid import (
    apply,
    levelled,
    make_T,
    rotation_aligning,
    rotation_angle_deg,
    weighted_rigid_fit,
    yaw_rigid_fit,
)

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
    refine_iterations: int = 2
    gravity_tolerance_deg: float = 15.0
    ambiguity_tau_m: float = 0.30  # an observation farther than this from any CAD feature explains nothing
    ambiguity_loglik_margin: float = 5.0  # a distinct pose this close in log-likelihood -> ambiguous (e^5 ~ 150x)
    noise_floor_m: float = 0.05  # lower bound of the 3-D residual RMS used as the noise scale
    distinct_m: float = 0.5  # poses that move the matched observations by more than this are different ...
    distinct_deg: float = 5.0  # ... and so are poses whose rotations differ by more than this
    pair_min_baseline_m: float = 2.0  # pair hypotheses (gravity known) need observations this far apart ...
    pair_max_baseline_m: float = 30.0  # ... and CAD pairs up to this far apart are considered
    pair_tolerance_m: float = 0.35  # horizontal distance / height difference agreement of a pair
    coarse_observations: int = 12  # observations nearest the seed used to rank its hypotheses
    polish_tau_m: float = 0.45  # tolerance of the ranking after the vectorised polishing step
    rival_candidates: int = 4  # best-supported distinct hypotheses refined when looking for a rival
    min_inlier_fraction: float = 0.35  # a pose explaining fewer of the observations is not trusted
    cross_type_weight: float = 0.5  # an observation on a feature of the other type (door/window confusion) counts half
    min_inliers: int = 3
    min_inliers_without_gravity: int = 4  # 6 DoF from few noisy rectangles: ask for more support
    # Below this many inliers the answer is only candidates for other evidence (the walls) to choose among: then
    # they are every distinct hypothesis that explains as many observations as the best, or one fewer (down to
    # two), not the refined few (a building with many alike door pairs offers dozens, and the truth must be among
    # them, also where one observation is a false detection that a wrong pose happens to explain: Office_A seed 6,
    # perception, at 3.2 s the truth explained two of three, wrong poses all three, and the walls, offered no true
    # pose, found one that fitted them at 0.90-0.92). 0: the refined few.
    complete_below: int = 0
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


def single_rectangle_poses(index: ModelIndex, kind: str, corners_map: np.ndarray,
                           params: RobustParams | None = None, among: set[str] | None = None) -> list[np.ndarray]:
    """Every level T_cad_map that puts one observed rectangle (corners (4, 3) in a map frame whose z is up) onto a
    CAD feature of its type and size (`among`: only the features of these ids): with gravity, one door or window
    fixes the pose up to which of the alike features it is and from which side it is seen (two poses per
    feature). Nothing here can tell them apart; the walls can (graph.localizer's surface check)."""
    params = params or RobustParams()
    if not index.has_type(kind):
        return []
    cand = index.type_indices[kind]
    if among is not None:
        cand = np.array([i for i in cand if index.features[i].id in among], dtype=int)
        if not len(cand):
            return []
    rect = rectangle_edges(corners_map)
    R, t = _seed_hypotheses(rect, cand, index, params, gravity_known=True)
    poses = []
    for r, v in zip(R, t, strict=True):
        T = levelled(make_T(r, v))  # levelled about the rectangle's centre, which stays on its feature's
        T[:3, 3] = r @ rect.centre + v - T[:3, :3] @ rect.centre
        poses.append(T)
    return poses


def _nearest_same_type(points: np.ndarray, types: np.ndarray, index: ModelIndex,
                       upper_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """For points (..., N, 3) with per-observation types (N,): distance to and index of the nearest CAD feature
    of the same type (inf / -1 where there is none within `upper_m`)."""
    shape = points.shape[:-1]
    # One query in the type-lifted 4-D space (x, y, z, type x TYPE_SEPARATION_M): features of another type are
    # farther than any tolerance, so the nearest within `upper_m` is always of the same type.
    codes = np.broadcast_to(_type_codes(types), shape).reshape(-1, 1) * TYPE_SEPARATION_M
    lifted = np.concatenate([points.reshape(-1, 3), codes], axis=1)
    d, j = index.tree_typed.query(lifted, distance_upper_bound=min(upper_m, TYPE_SEPARATION_M / 2))
    found = np.isfinite(d)
    idx = np.where(found, j, -1)
    return d.reshape(shape), idx.reshape(shape)


def _type_codes(types: np.ndarray) -> np.ndarray:
    """Feature types as small integers (index into FEATURE_TYPES); string compares are slow in hot loops.
    Integer arrays (already codes) pass through."""
    if types.dtype.kind in "iu":
        return types
    return np.array([FEATURE_TYPES.index(t) for t in types], dtype=np.int8)


def _support(d: np.ndarray, tau: np.ndarray | float) -> np.ndarray:
    """Truncated-quadratic (MSAC) support of residuals d against tolerance tau, per observation (last axis)."""
    r = d / tau
    return np.where(r < 1.0, 1.0 - r * r, 0.0)


@dataclass
class _Pose:
    T: np.ndarray  # T_cad_map'
    inliers: np.ndarray  # (N,) bool
    match: np.ndarray  # (N,) CAD index
    score: float


def _explain(T: np.ndarray, c_obs: np.ndarray, types: np.ndarray, index: ModelIndex, tau_m: float,
             cross_type_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """Per observation: its support under T (truncated quadratic of the distance to the nearest CAD feature of the
    same type; a feature of the other type counts `cross_type_weight` as much — detectors confuse doors and
    windows) and the CAD feature that gives it (-1: none within tau_m)."""
    moved = apply(T, c_obs)
    d_same, j_same = _nearest_same_type(moved, types, index, upper_m=tau_m)
    s_same = np.where(d_same < tau_m, 1.0 - (d_same / tau_m) ** 2, 0.0)
    d_any, j_any = index.tree_all.query(moved, distance_upper_bound=tau_m)
    s_any = cross_type_weight * np.where(d_any < tau_m, 1.0 - (np.minimum(d_any, tau_m) / tau_m) ** 2, 0.0)
    use_any = s_any > s_same
    return np.where(use_any, s_any, s_same), np.where(use_any, j_any, j_same)


def _refine(T: np.ndarray, obs: list[Observation], c_obs: np.ndarray, types: np.ndarray, index: ModelIndex,
            params: RobustParams, gravity_known: bool) -> _Pose:
    for _ in range(params.refine_iterations):
        s, j = _explain(T, c_obs, types, index, params.inlier_threshold_m * 1.5, params.cross_type_weight)
        if (s > 0).sum() < 2:
            break
        pairs = _one_to_one([(int(i), int(j[i])) for i in np.flatnonzero(s > 0)], -s)
        src, dst = corner_correspondences(T, obs, pairs, index)
        if len(src) < 3:
            break
        T = yaw_rigid_fit(src, dst) if gravity_known else weighted_rigid_fit(src, dst)
    s, j = _explain(T, c_obs, types, index, params.inlier_threshold_m, params.cross_type_weight)
    pairs = _one_to_one([(int(i), int(j[i])) for i in np.flatnonzero(s > 0)], -s)
    keep = np.zeros(len(obs), dtype=bool)
    keep[[i for i, _ in pairs]] = True
    return _Pose(T, keep, j, float(np.where(keep, s, 0.0).sum()))


def _one_to_one(pairs: list[tuple[int, int]], d: np.ndarray) -> list[tuple[int, int]]:
    """Keep, for each CAD feature, only the observation of least cost `d` claiming it."""
    best: dict[int, int] = {}
    for i, j in pairs:
        if j not in best or d[i] < d[best[j]]:
            best[j] = i
    return sorted((i, j) for j, i in best.items())


def _distinct_top(order: np.ndarray, moved: np.ndarray, params: RobustParams, rotations: np.ndarray | None = None,
                  kept: Sequence[tuple[np.ndarray, np.ndarray]] = (), limit: int | None = None) -> list[int]:
    """The best hypotheses (in `order`; at most `limit`, default refine_top) that differ from each other and from the
    poses `kept` ((rotation (3, 3), moved observations (N, 3)) pairs): the mean displacement of the observations
    (`moved`, (H, N, 3)) exceeds distinct_m / 2, or, given the hypotheses' `rotations` (H, 3, 3), they turn more than
    distinct_deg (two doors in one wall, seen from either side, stay where they are)."""
    limit = params.refine_top if limit is None else limit
    cos_max = np.cos(np.radians(params.distinct_deg))
    chosen: list[int] = []
    chosen_R = [R for R, _ in kept]
    chosen_moved = [m for _, m in kept]
    for h in order:
        if len(chosen) == limit:
            break
        if chosen_moved:
            apart = np.linalg.norm(np.stack(chosen_moved) - moved[h][None], axis=2).mean(axis=1)
            alike = apart <= params.distinct_m / 2
            if rotations is not None:
                alike &= (np.einsum("kij,ij->k", np.stack(chosen_R), rotations[h]) - 1.0) / 2.0 >= cos_max
            if alike.any():
                continue
        chosen.append(int(h))
        chosen_moved.append(moved[h])
        if rotations is not None:
            chosen_R.append(rotations[h])
    return chosen


@dataclass
class _Prepared:
    """Observations in the gravity-aligned map' frame (identity when gravity is unknown)."""

    obs: list[Observation]
    centroids: np.ndarray  # (N, 3) map'
    types: np.ndarray  # (N,) int8 codes into FEATURE_TYPES
    T_mp_m: np.ndarray  # map -> map'
    gravity_known: bool


def _prepare(obs_set: ObservationSet) -> _Prepared:
    gravity_known = obs_set.gravity_map is not None
    R_g = rotation_aligning(obs_set.gravity_map, GRAVITY_CAD) if obs_set.gravity_map is not None else np.eye(3)
    obs = [Observation(o.type, R_g @ o.centroid_map, None if o.corners_map is None else o.corners_map @ R_g.T)
           for o in obs_set.observations]
    return _Prepared(obs, np.array([o.centroid_map for o in obs]).reshape(-1, 3),
                     _type_codes(np.array([o.type for o in obs])), make_T(R_g, np.zeros(3)), gravity_known)


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
    """Hypotheses of one observed rectangle against every compatible CAD feature (and, with gravity, of the seed
    and its farthest observation against CAD pairs: the only hypotheses a centroid-only seed gives), coarsely
    verified by the observations; the tolerance grows with the distance from the seed (one rectangle gives the
    rotation only to a few degrees)."""
    o = prep.obs[seed]
    R, t = np.zeros((0, 3, 3)), np.zeros((0, 3))
    if o.corners_map is not None:
        R, t = _seed_hypotheses(rectangle_edges(o.corners_map), index.type_indices[o.type], index, params,
                                prep.gravity_known)
    if prep.gravity_known and len(prep.obs) > 1:
        R2, t2 = _pair_hypotheses(seed, prep, index, params)
        R, t = np.concatenate([R, R2]), np.concatenate([t, t2])
    # Verify on the observations nearest the seed only (the k-d queries dominate the cost; the final
    # refinement and the decision use every observation).
    r_seed = np.linalg.norm(prep.centroids - prep.centroids[seed], axis=1)
    near = np.argsort(r_seed, kind="stable")[: params.coarse_observations]
    c_near, types_near = prep.centroids[near], prep.types[near]
    moved = np.einsum("hij,nj->hni", R, c_near) + t[:, None, :]
    tau = params.coarse_base_m + params.coarse_slope * r_seed[near]
    d_same, j_same = _nearest_same_type(moved, types_near, index, upper_m=float(tau.max()))
    R, t = _polish(R, t, c_near, prep.gravity_known, index, j_same, _support(d_same, tau))
    moved = np.einsum("hij,nj->hni", R, c_near) + t[:, None, :]
    tau_p = params.polish_tau_m
    d_same, _ = _nearest_same_type(moved, types_near, index, upper_m=tau_p)
    d_any, _ = index.tree_all.query(moved, distance_upper_bound=tau_p)
    support = np.maximum(_support(d_same, tau_p), params.cross_type_weight * _support(d_any, tau_p)).sum(axis=-1)
    return _Hypotheses(R, t, np.einsum("hij,nj->hni", R, prep.centroids) + t[:, None, :], support)


def _pair_hypotheses(seed: int, prep: _Prepared, index: ModelIndex,
                     params: RobustParams) -> tuple[np.ndarray, np.ndarray]:
    """With gravity: yaw + translation from the seed and its farthest observation matched to every CAD pair of the
    same types, horizontal distance and height difference (a baseline of metres fixes the yaw far better than a
    small, noisy rectangle does)."""
    c = prep.centroids
    partner = int(np.argmax(np.linalg.norm(c[:, :2] - c[seed, :2], axis=1)))
    v_obs = c[partner] - c[seed]
    d_obs = float(np.linalg.norm(v_obs[:2]))
    if d_obs < params.pair_min_baseline_m:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    pairs = index.pairs_within(params.pair_max_baseline_m)
    tol = params.pair_tolerance_m
    ok = ((index.type_codes[pairs.i] == prep.types[seed]) & (index.type_codes[pairs.j] == prep.types[partner])
          & (np.abs(pairs.d_xy - d_obs) < tol) & (np.abs(pairs.dz - v_obs[2]) < tol))
    i, j, v = pairs.i[ok], pairs.j[ok], pairs.v[ok]
    yaw = np.arctan2(v[:, 1], v[:, 0]) - np.arctan2(v_obs[1], v_obs[0])
    cs, sn = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = cs, -sn, sn, cs, 1.0
    mid_obs = (c[seed] + c[partner]) / 2.0
    mid_cad = (index.centroids[i] + index.centroids[j]) / 2.0
    return R, mid_cad - R @ mid_obs


def _polish(R: np.ndarray, t: np.ndarray, centroids: np.ndarray, gravity_known: bool, index: ModelIndex,
            match: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One vectorised least-squares step for every hypothesis at once: refit (R, t) to the centroids it matched
    (weights w, (H, N)). A single rectangle gives the rotation to a few degrees only; after this step the
    hypotheses are accurate enough to be ranked and compared with tight tolerances."""
    a = centroids[None, :, :]  # (1, N, 3) map'
    b = index.centroids[np.maximum(match, 0)]  # (H, N, 3) CAD
    w = np.where(match >= 0, w, 0.0)
    w_sum = w.sum(axis=1)
    ok = (w > 0).sum(axis=1) >= (2 if gravity_known else 3)
    ws = np.maximum(w_sum, 1e-12)[:, None]
    a_bar = (w[:, :, None] * a).sum(axis=1) / ws
    b_bar = (w[:, :, None] * b).sum(axis=1) / ws
    x, y = a - a_bar[:, None, :], b - b_bar[:, None, :]
    if gravity_known:  # yaw about +z only
        s_cos = (w * (x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1])).sum(axis=1)
        s_sin = (w * (x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0])).sum(axis=1)
        yaw = np.arctan2(s_sin, s_cos)
        c, s = np.cos(yaw), np.sin(yaw)
        R_new = np.zeros_like(R)
        R_new[:, 0, 0], R_new[:, 0, 1], R_new[:, 1, 0], R_new[:, 1, 1], R_new[:, 2, 2] = c, -s, s, c, 1.0
    else:  # eqs. (12)-(16), batched, reflection-safe
        S = np.einsum("hn,hni,hnj->hij", w, x, y)
        U, sv, Vt = np.linalg.svd(S)
        V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
        D = np.broadcast_to(np.eye(3), R.shape).copy()
        D[:, 2, 2] = np.sign(np.linalg.det(V @ Ut)) + (np.linalg.det(V @ Ut) == 0)
        R_new = V @ D @ Ut
        ok &= sv[:, 1] > 1e-3 * np.maximum(sv[:, 0], 1e-12)  # collinear matches leave a rotation free
    t_new = b_bar - np.einsum("hij,hj->hi", R_new, a_bar)
    return np.where(ok[:, None, None], R_new, R), np.where(ok[:, None], t_new, t)


def _distinct(a: _Pose, b: _Pose, anchor: np.ndarray, params: RobustParams) -> bool:
    """Two poses are different when they move the anchor points apart or differ in rotation."""
    moved_apart = np.linalg.norm(apply(a.T, anchor) - apply(b.T, anchor), axis=1).mean() > params.distinct_m
    return bool(moved_apart or rotation_angle_deg(a.T[:3, :3] @ b.T[:3, :3].T) > params.distinct_deg)


def register_robust(index: ModelIndex, obs_set: ObservationSet, params: RobustParams) -> RegistrationResult:
    """Hypothesise from observed rectangles, verify, refine, and answer only when no rival pose is as good."""
    prep = _prepare(obs_set)
    n = len(prep.obs)
    rect_ids = [i for i, o in enumerate(prep.obs) if o.corners_map is not None and index.has_type(o.type)]
    if not rect_ids and prep.gravity_known:  # centroids only: pair hypotheses (gravity fixes all but yaw)
        rect_ids = [i for i, o in enumerate(prep.obs) if index.has_type(o.type)]
    if n == 0 or not rect_ids:
        return RegistrationResult("not_localized", None, [], 0, None, diagnostics={
            "reason": "no observed door/window rectangle (centroid-only observations need gravity)"})
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
    return _decide(poses, hyps, prep, index, params, {"hypotheses": int(len(hyps.R)), "seeds": used})


def _rms(T: np.ndarray, prep: _Prepared, index: ModelIndex, params: RobustParams) -> float:
    """RMS distance, metres, of the observations a pose explains (same type, within ambiguity_tau_m)."""
    d, _ = _nearest_same_type(apply(T, prep.centroids), prep.types, index, upper_m=params.ambiguity_tau_m)
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d * d))) if len(d) else np.inf


def _rival_candidates(best: _Pose, hyps: _Hypotheses, prep: _Prepared, index: ModelIndex,
                      params: RobustParams) -> list[int]:
    """Hypotheses different from `best` whose evidence could rival it, best first (all hypotheses are searched:
    a symmetric building can offer many equally good poses, and one of them is enough to answer 'ambiguous')."""
    if len(hyps.R) == 0:
        return []
    anchor = prep.centroids[best.inliers]
    apart = np.linalg.norm(hyps.moved[:, best.inliers] - apply(best.T, anchor)[None], axis=2).mean(axis=1)
    cos = (np.einsum("hij,ij->h", hyps.R, best.T[:3, :3]) - 1.0) / 2.0
    turned = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    distinct = (apart > params.distinct_m) | (turned > params.distinct_deg)
    support = np.where(distinct, hyps.coarse, -1.0)  # the polished support ranks the rivals
    order = np.argsort(-support, kind="stable")
    return _distinct_top(order[support[order] > 0][: params.scan_top], hyps.moved, params)[: params.rival_candidates]


def _decide(poses: list[_Pose], hyps: _Hypotheses, prep: _Prepared, index: ModelIndex, params: RobustParams,
            diag: dict) -> RegistrationResult:
    """The best pose, unless a different pose is about as likely (MLESAC log-likelihood within a margin)."""
    n = len(prep.obs)
    if not poses:
        return RegistrationResult("not_localized", None, [], 0, None, diagnostics=diag)
    first = poses[0]
    extra = [_refine(make_T(hyps.R[h], hyps.t[h]), prep.obs, prep.centroids, prep.types, index, params,
                     prep.gravity_known) for h in _rival_candidates(first, hyps, prep, index, params)]
    candidates = poses + extra
    s2 = max(_rms(first.T, prep, index, params) ** 2, params.noise_floor_m**2)  # 3-D residual variance
    ll = [_loglik(p.T, prep, index, params, s2) for p in candidates]
    best = candidates[int(np.argmax(ll))]
    n_best = int(best.inliers.sum())
    diag.update(best_support=round(best.score, 3), best_inliers=n_best, best_loglik=round(max(ll), 2),
                noise_rms_m=round(float(np.sqrt(s2)), 4))
    min_inliers = params.min_inliers if prep.gravity_known else params.min_inliers_without_gravity
    if n_best < max(min_inliers, params.min_inlier_fraction * n):
        return RegistrationResult("not_localized", None, [], n_best, None, diagnostics=diag)
    anchor = prep.centroids[best.inliers]
    rivals = [(lp, p) for lp, p in zip(ll, candidates, strict=True) if _distinct(best, p, anchor, params)]
    ll_rival, rival = max(rivals, key=lambda r: r[0]) if rivals else (-np.inf, None)
    diag.update(rival_loglik=round(float(ll_rival), 2) if rival is not None else None,
                rival_inliers=int(rival.inliers.sum()) if rival is not None else 0)
    pairs = [(int(i), int(best.match[i])) for i in np.flatnonzero(best.inliers)]
    T_cad_map = best.T @ prep.T_mp_m
    distinct: list[_Pose] = []
    for p in [best] + sorted(candidates, key=lambda c: -int(c.inliers.sum())):
        if p.inliers.sum() >= min_inliers and all(_distinct(q, p, anchor, params) for q in distinct):
            distinct.append(p)
    candidate_poses = [(q.T @ prep.T_mp_m, int(q.inliers.sum())) for q in distinct]
    if n_best < params.complete_below:
        kept = [(q.T[:3, :3], apply(q.T, prep.centroids)) for q in distinct]
        candidate_poses += [(make_T(hyps.R[h], hyps.t[h]) @ prep.T_mp_m, n_best)
                            for h in _alike_hypotheses(hyps, max(2, n_best - 1), kept, prep, index, params)]
    storey = majority_storey(index, [j for _, j in pairs])
    matches = [(i, index.features[j].id) for i, j in pairs]
    if rival is not None and ll_rival >= max(ll) - params.ambiguity_loglik_margin:
        diag["rival_storey"] = majority_storey(index, [int(rival.match[i]) for i in np.flatnonzero(rival.inliers)])
        # No matches: they would name one of the competing poses' features as if it were known.
        return RegistrationResult("ambiguous", T_cad_map, [], n_best, storey,
                                  alternatives=[rival.T @ prep.T_mp_m], diagnostics=diag, candidates=candidate_poses)
    return RegistrationResult("localized", T_cad_map, matches, n_best, storey, diagnostics=diag,
                              candidates=candidate_poses)


def _alike_hypotheses(hyps: _Hypotheses, n_explained: int, kept: list[tuple[np.ndarray, np.ndarray]],
                      prep: _Prepared, index: ModelIndex, params: RobustParams) -> list[int]:
    """Every hypothesis that explains `n_explained` observations (same type, within ambiguity_tau_m) and differs
    (`_distinct_top`, by displacement or turn) from the poses `kept` and from each other, best supported first."""
    if len(hyps.R) == 0:
        return []
    d, _ = _nearest_same_type(hyps.moved, prep.types, index, upper_m=params.ambiguity_tau_m)
    order = np.argsort(-hyps.coarse, kind="stable")
    order = order[np.isfinite(d[order]).sum(axis=1) >= n_explained]
    return _distinct_top(order, hyps.moved, params, rotations=hyps.R, kept=kept, limit=len(order))


def _loglik(T: np.ndarray, prep: _Prepared, index: ModelIndex, params: RobustParams, s2: float) -> float:
    """MLESAC-style log-likelihood ratio of a pose against 'every observation is an outlier': each observation
    within ambiguity_tau_m of a CAD feature adds (tau^2 - d^2) / (2 s^2) (zero at the tolerance, so an outlier and
    a barely-explained observation weigh the same); one explained only by a feature of the other type adds
    cross_type_weight times that."""
    tau = params.ambiguity_tau_m
    moved = apply(T, prep.centroids)
    d_same, _ = _nearest_same_type(moved, prep.types, index, upper_m=tau)
    d_any, _ = index.tree_all.query(moved, distance_upper_bound=tau)
    term = lambda d: np.where(d < tau, (tau * tau - np.minimum(d, tau) ** 2) / (2.0 * s2), 0.0)  # noqa: E731
    return float(np.maximum(term(d_same), params.cross_type_weight * term(d_any)).sum())
