"""The default registration: rectangle-seeded pose hypotheses, verification, and an honest ambiguity test.

Why it beats the paper's method: the paper trusts one descriptor match per observation, and its
descriptor changes whenever the observed neighbourhood differs from the model's (a missed or false detection
among the 5 nearest neighbours re-codes every feature around it). Here a single observed door or window
rectangle already fixes a pose up to its symmetry (2 poses with gravity, 4–8 without), so every observed
rectangle is tried against every CAD feature of the same type and compatible size; each hypothesis is
verified by all observations (`graph.verify`: centroid, wall normal, width and height under an estimated noise
model, false detections as an outlier process), the best are refined with all corners (yaw + translation when
gravity is known, full SE(3) otherwise), and the best pose is only reported `localized` when no *different*
pose comes within the rival margin (`rival_margin`); the rivals always scored include each seed observation's
best pose and the best pose's images under the building's near-self-maps (`graph.self_maps`).

Frames: observations in `map`, features in `cad`; gravity-aligned `map'` = R_g map with gravity -> -z.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from macroloc.graph.features import FEATURE_TYPES
from macroloc.graph.model_index import TYPE_SEPARATION_M, ModelIndex
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.params import RobustParams
from macroloc.graph.posterior import pose_posterior
from macroloc.graph.posterior import prepare as prepare_posterior
from macroloc.graph.rectangle import unordered_edges
from macroloc.graph.registration_types import RegistrationResult, majority_storey
from macroloc.graph.rigid import (
    apply,
    levelled,
    make_T,
    rot_z,
    rotation_aligning,
    weighted_rigid_fits,
    yaw_rigid_fits,
)
from macroloc.graph.verify import (
    Noise,
    ObservedShapes,
    Verdict,
    chance_term,
    full_term,
    observed_shapes,
    one_per_feature,
    verify,
    verify_all,
)

GRAVITY_CAD = np.array([0.0, 0.0, -1.0])
NEAREST_ANY = 4  # `_nearest_both` asks for this many nearest features (exact for any value; more, rarely asked)
FITTED_CLOSURE_M = 1e-3  # a rectangle that closes this well was fitted, not measured: no sensor is this exact


@dataclass
class _Rect:
    centre: np.ndarray
    a: np.ndarray  # unit edge direction
    b: np.ndarray  # unit edge direction, orthogonal to a
    la: float
    lb: float


def rectangle_edges(corners: np.ndarray) -> _Rect:
    """Edge frame of 4 rectangle corners given in any order (`graph.rectangle.unordered_edges`)."""
    p = np.asarray(corners, dtype=float)
    a, b, la, lb, _ = unordered_edges(p[None])
    return _Rect(p.mean(axis=0), a[0], b[0], float(la[0]), float(lb[0]))


def _seed_hypotheses(rect: _Rect, cand: np.ndarray, index: ModelIndex, params: RobustParams,
                     gravity_known: bool, at_least: tuple[bool, bool] = (False, False)
                     ) -> tuple[np.ndarray, np.ndarray]:
    """All rotations R (H, 3, 3) and translations t (H, 3) that put `rect` onto a candidate CAD rectangle of its
    size within `size_tolerance_m`; `at_least`: rect's side a (b) is a lower bound of the feature's."""
    tol = params.size_tolerance_m

    def alike(l_cad: np.ndarray, l_obs: float, lower_bound: bool) -> np.ndarray:
        return l_cad > l_obs - tol if lower_bound else np.abs(l_cad - l_obs) < tol

    Rs, ts = [], []
    M_obs = np.stack([rect.a, rect.b, np.cross(rect.a, rect.b)], axis=1)  # columns
    for swap in (False, True):
        U = index.edge_v[cand] if swap else index.edge_u[cand]
        V = index.edge_u[cand] if swap else index.edge_v[cand]
        lu = index.len_v[cand] if swap else index.len_u[cand]
        lv = index.len_u[cand] if swap else index.len_v[cand]
        ok = alike(lu, rect.la, at_least[0]) & alike(lv, rect.lb, at_least[1])
        if not ok.any():
            continue
        U, V, c_cad = U[ok], V[ok], index.centroids[cand][ok]
        W = np.cross(U, V)
        for s1 in (1.0, -1.0):
            for s2 in (1.0, -1.0):
                Mc = np.stack([s1 * U, s2 * V, s1 * s2 * W], axis=2)  # (h, 3, 3) columns
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
                           params: RobustParams | None = None, among: set[str] | None = None,
                           cut: tuple[bool, bool] = (False, False)) -> list[np.ndarray]:
    """Every level T_cad_map that puts one observed rectangle (corners (4, 3) in a map frame whose z is up) onto a
    CAD feature of its type and size (`among`: only the features of these ids): with gravity, one door or window
    fixes the pose up to which of the alike features it is and from which side it is seen (two poses per
    feature). Nothing here can tell them apart; the walls can (graph.localizer's surface check). `cut`: the
    rectangle's (horizontal, vertical) side is a cut one, short of the opening's (every sighting was cut by the
    image border there): a feature at least that long less `size_tolerance_m` is alike along it (a door passed at
    1-2 m fills the frame: docs/measurements.md, "A door cut by the image border in every sighting")."""
    params = params or RobustParams()
    if not index.has_type(kind):
        return []
    cand = index.type_indices[kind]
    if among is not None:
        cand = np.array([i for i in cand if index.features[i].id in among], dtype=int)
        if not len(cand):
            return []
    rect = rectangle_edges(corners_map)
    a_level = abs(rect.a[2]) < abs(rect.b[2])  # rect.a the horizontal side
    at_least = (cut[0], cut[1]) if a_level else (cut[1], cut[0])
    R, t = _seed_hypotheses(rect, cand, index, params, gravity_known=True, at_least=at_least)
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


def _nearest_both(points: np.ndarray, types: np.ndarray, index: ModelIndex, upper_m: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`_nearest_same_type` and the nearest CAD feature of any type (distance, index; inf / len(features) where none
    within `upper_m`, as `cKDTree.query` gives them) in one query: the `NEAREST_ANY` nearest features within
    `upper_m` hold the nearest of the same type unless all of them are taken by other types (then it is asked for)."""
    shape = points.shape[:-1]
    flat = points.reshape(-1, 3)
    codes = np.broadcast_to(_type_codes(types), shape).reshape(-1)
    k = min(NEAREST_ANY, len(index.features))
    d, j = index.tree_all.query(flat, k=k, distance_upper_bound=upper_m)
    d, j = d.reshape(-1, k), j.reshape(-1, k)
    found = np.isfinite(d)
    same = found & (index.type_codes[np.where(found, j, 0)] == codes[:, None])
    has = same.any(axis=1)
    first = np.argmax(same, axis=1)
    rows = np.arange(len(flat))
    d_same = np.where(has, d[rows, first], np.inf)
    j_same = np.where(has, j[rows, first], -1)
    full = found[:, -1] & ~has  # every one of the k is of another type: the same type may lie farther
    if full.any():
        d_same[full], j_same[full] = _nearest_same_type(flat[full], codes[full], index, upper_m)
    return d_same.reshape(shape), j_same.reshape(shape), d[:, 0].reshape(shape), j[:, 0].reshape(shape)


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


def _explain(moved: np.ndarray, types: np.ndarray, index: ModelIndex, tau_m: float,
             cross_type_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """Per observation (moved: (..., N, 3) centroids, CAD): its support (truncated quadratic of the distance to the
    nearest CAD feature of the same type; a feature of the other type counts `cross_type_weight` as much —
    detectors confuse doors and windows) and the CAD feature that gives it (-1: none within tau_m)."""
    d_same, j_same, d_any, j_any = _nearest_both(moved, types, index, tau_m)
    s_same = np.where(d_same < tau_m, 1.0 - (d_same / tau_m) ** 2, 0.0)
    s_any = cross_type_weight * np.where(d_any < tau_m, 1.0 - (np.minimum(d_any, tau_m) / tau_m) ** 2, 0.0)
    use_any = s_any > s_same
    return np.where(use_any, s_any, s_same), np.where(use_any, j_any, j_same)


def _refine_all(T: Sequence[np.ndarray], prep: _Prepared, index: ModelIndex, params: RobustParams) -> list[_Pose]:
    """Each pose T (map' -> CAD) refined: `refine_iterations` times, every observation matched to the CAD feature
    that explains it best (`_explain` at 1.5 inlier_threshold_m, one observation per feature) and the pose refitted
    to the matched corners (centroids where an observation has none; yaw + translation when gravity is known, else
    SE(3)); a pose stops where fewer than 2 observations or 3 points match. Then its inliers within
    inlier_threshold_m (one per feature) and their summed support. All poses at once; each result is the pose's
    own."""
    if len(T) == 0:
        return []
    T_all = np.array(T, dtype=float).reshape(-1, 4, 4)
    points, base_w = _corner_points(prep)
    active = np.ones(len(T_all), dtype=bool)
    fit = yaw_rigid_fits if prep.gravity_known else weighted_rigid_fits
    for _ in range(params.refine_iterations):
        s, j = _explain(_moved(T_all, prep.centroids), prep.types, index, params.inlier_threshold_m * 1.5,
                        params.cross_type_weight)
        active &= (s > 0).sum(axis=1) >= 2
        keep = one_per_feature(np.where(s > 0, j, -1), s) & active[:, None]
        w = keep[:, :, None] * base_w[None]  # (H, N, 4)
        active &= w.sum(axis=(1, 2)) >= 3
        if not active.any():
            break
        dst = _matched_corners(T_all[active], points, prep.shapes.has_rect, j[active], index)
        h = len(dst)
        T_all[active] = fit(np.broadcast_to(points.reshape(1, -1, 3), (h, points.size // 3, 3)),
                            dst.reshape(h, -1, 3), w[active].reshape(h, -1))
    s, j = _explain(_moved(T_all, prep.centroids), prep.types, index, params.inlier_threshold_m,
                    params.cross_type_weight)
    keep = one_per_feature(np.where(s > 0, j, -1), s)
    score = np.where(keep, s, 0.0).sum(axis=1)
    return [_Pose(T_all[k].copy(), keep[k], j[k], float(score[k])) for k in range(len(T_all))]


def _moved(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) under each pose T (H, 4, 4): (H, N, 3)."""
    return np.matmul(points[None], np.swapaxes(T[:, :3, :3], 1, 2)) + T[:, None, :3, 3]


def _corner_points(prep: _Prepared) -> tuple[np.ndarray, np.ndarray]:
    """The points a refinement fits, per observation (N, 4, 3) map': its four corners, or its centroid (first slot)
    where it has none; and their weights (N, 4): 1, or 0 for the unused slots."""
    points = np.repeat(prep.centroids[:, None, :], 4, axis=1)
    w = np.zeros((len(prep.obs), 4))
    w[:, 0] = 1.0
    for i, o in enumerate(prep.obs):
        if o.corners_map is not None:
            points[i] = np.asarray(o.corners_map, dtype=float).reshape(4, 3)
            w[i] = 1.0
    return points, w


def _matched_corners(T: np.ndarray, points: np.ndarray, has_rect: np.ndarray, match: np.ndarray,
                     index: ModelIndex) -> np.ndarray:
    """Per pose (T: (H, 4, 4)) and observation, the CAD points its `_corner_points` pair with under the pose: each
    observed corner's nearest corner of its matched feature (`match`, (H, N); corners come unordered), or the
    feature's centroid for a centroid-only observation. (H, N, 4, 3)."""
    jj = np.maximum(match, 0)
    cc = index.corners[jj]  # (H, N, 4, 3) CAD
    moved = _moved(T, points.reshape(-1, 3)).reshape(cc.shape)
    nearest = np.argmin(np.linalg.norm(moved[:, :, :, None, :] - cc[:, :, None, :, :], axis=4), axis=3)
    dst = np.take_along_axis(cc, nearest[..., None], axis=2)
    return np.where(has_rect[None, :, None, None], dst, index.centroids[jj][:, :, None, :])


def _distinct_top(order: np.ndarray, moved: np.ndarray, params: RobustParams, rotations: np.ndarray | None = None,
                  kept: Sequence[tuple[np.ndarray, np.ndarray]] = (), limit: int | None = None) -> list[int]:
    """The best hypotheses (in `order`; at most `limit`, default refine_top) that differ from each other and from the
    poses `kept` ((rotation (3, 3), moved observations (N, 3)) pairs): the mean displacement of the observations
    (`moved`, (H, N, 3)) exceeds distinct_m / 2, or, given the hypotheses' `rotations` (H, 3, 3), they turn more than
    distinct_deg (two doors in one wall, seen from either side, stay where they are)."""
    limit = params.refine_top if limit is None else limit
    cos_max = np.cos(np.radians(params.distinct_deg))
    order = np.asarray(order, dtype=int)
    alive = np.ones(len(order), dtype=bool)
    mean = moved[order].mean(axis=1)  # the mean displacement is at least the displacement of the mean

    def drop_alike(R: np.ndarray | None, m: np.ndarray) -> None:  # every hypothesis still in play alike (R, m)
        rows = np.flatnonzero(alive)
        rows = rows[np.linalg.norm(mean[rows] - m.mean(axis=0), axis=1) <= params.distinct_m / 2 + 1e-9]
        alike = np.linalg.norm(moved[order[rows]] - m[None], axis=2).mean(axis=1) <= params.distinct_m / 2
        if rotations is not None and R is not None:
            alike &= (np.einsum("kij,ij->k", rotations[order[rows]], R) - 1.0) / 2.0 >= cos_max
        alive[rows[alike]] = False

    for R, m in kept:
        drop_alike(R, m)
    chosen: list[int] = []
    while len(chosen) < limit and alive.any():
        k = int(np.argmax(alive))  # the best left
        h = int(order[k])
        chosen.append(h)
        alive[k] = False
        drop_alike(None if rotations is None else rotations[h], moved[h])
    return chosen


@dataclass
class _Prepared:
    """Observations in the gravity-aligned map' frame (identity when gravity is unknown)."""

    obs: list[Observation]
    centroids: np.ndarray  # (N, 3) map'
    types: np.ndarray  # (N,) int8 codes into FEATURE_TYPES
    T_mp_m: np.ndarray  # map -> map'
    gravity_known: bool
    shapes: ObservedShapes

    def rect(self, i: int) -> _Rect:
        """Observation i's rectangle (it has corners), as `rectangle_edges` gives it."""
        sh = self.shapes
        return _Rect(np.asarray(self.obs[i].corners_map, dtype=float).mean(axis=0), sh.edge_a[i], sh.edge_b[i],
                     float(sh.len_a[i]), float(sh.len_b[i]))


def _prepare(obs_set: ObservationSet) -> _Prepared:
    gravity_known = obs_set.gravity_map is not None
    R_g = rotation_aligning(obs_set.gravity_map, GRAVITY_CAD) if obs_set.gravity_map is not None else np.eye(3)
    obs = [Observation(o.type, R_g @ o.centroid_map, None if o.corners_map is None else o.corners_map @ R_g.T)
           for o in obs_set.observations]
    types = _type_codes(np.array([o.type for o in obs]))
    return _Prepared(obs, np.array([o.centroid_map for o in obs]).reshape(-1, 3), types, make_T(R_g, np.zeros(3)),
                     gravity_known, observed_shapes(obs, types))


@dataclass
class _Hypotheses:
    R: np.ndarray  # (H, 3, 3)  T_cad_map' rotations
    t: np.ndarray  # (H, 3)
    moved: np.ndarray  # (H, N, 3) observed centroids under each hypothesis, CAD
    coarse: np.ndarray  # (H,) coarse support
    seed: np.ndarray  # (H,) the observation whose hypothesis it is

    def extend(self, other: _Hypotheses) -> _Hypotheses:
        return _Hypotheses(*(np.concatenate([a, b]) for a, b in
                             zip((self.R, self.t, self.moved, self.coarse, self.seed),
                                 (other.R, other.t, other.moved, other.coarse, other.seed), strict=True)))


def _coarse(seed: int, prep: _Prepared, index: ModelIndex, params: RobustParams) -> _Hypotheses:
    """Hypotheses of one observed rectangle against every compatible CAD feature (and, with gravity, of the seed
    and its farthest observation against CAD pairs: the only hypotheses a centroid-only seed gives), coarsely
    verified by the observations; the tolerance grows with the distance from the seed (one rectangle gives the
    rotation only to a few degrees)."""
    o = prep.obs[seed]
    R, t = np.zeros((0, 3, 3)), np.zeros((0, 3))
    cand = seed_candidates(seed, prep, index, params)
    if o.corners_map is not None:
        R, t = _seed_hypotheses(prep.rect(seed), cand, index, params, prep.gravity_known)
    if prep.gravity_known and len(prep.obs) > 1:
        R2, t2 = _pair_hypotheses(seed, prep, index, params,
                                  None if len(cand) == len(index.type_indices[o.type]) else cand)
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
    d_same, _, d_any, _ = _nearest_both(moved, types_near, index, tau_p)
    support = np.maximum(_support(d_same, tau_p), params.cross_type_weight * _support(d_any, tau_p)).sum(axis=-1)
    return _Hypotheses(R, t, np.einsum("hij,nj->hni", R, prep.centroids) + t[:, None, :], support,
                       np.full(len(R), seed, dtype=int))


def seed_candidates(seed: int, prep: _Prepared, index: ModelIndex, params: RobustParams) -> np.ndarray:
    """The CAD features (indices) a seed observation is tried against: every one of its type, or, with
    `prune_top`, gravity and a rectangle observed, the `prune_top` of compatible size whose layout
    (`graph.layout`: the neighbours around, by height difference, horizontal distance, same wall or not, and
    type) explains most of the observed neighbours, the closest in size first among equals (the cost then no
    longer grows with the building). Not where fewer observations than `complete_below` ask for every pose."""
    o = prep.obs[seed]
    cand = index.type_indices[o.type]
    if not params.prune_top or len(cand) <= params.prune_top or o.corners_map is None or not prep.gravity_known:
        return cand
    if len(prep.obs) < params.complete_below:  # every pose was asked for (the walls choose among them): a layout
        return cand  # of so few observations would rank the candidates by little more than chance
    rect = prep.rect(seed)
    tol = params.size_tolerance_m
    lu, lv = index.len_u[cand], index.len_v[cand]
    miss = np.minimum(np.abs(lu - rect.la) + np.abs(lv - rect.lb), np.abs(lv - rect.la) + np.abs(lu - rect.lb))
    fits = (((np.abs(lu - rect.la) < tol) & (np.abs(lv - rect.lb) < tol))
            | ((np.abs(lv - rect.la) < tol) & (np.abs(lu - rect.lb) < tol)))
    cand, miss = cand[fits], miss[fits]
    if len(cand) <= params.prune_top:
        return cand
    lay = index.layout()
    off = np.delete(prep.centroids, seed, axis=0) - prep.centroids[seed]
    near = np.linalg.norm(off, axis=1) <= lay.params.radius_m
    normal = np.cross(rect.a, rect.b)
    hist = lay.histogram(off[near], normal / max(np.linalg.norm(normal), 1e-9),
                         np.delete(prep.types, seed)[near])
    order = np.lexsort((miss, -lay.scores(hist, cand)))
    return cand[order[: params.prune_top]]


def _pair_hypotheses(seed: int, prep: _Prepared, index: ModelIndex, params: RobustParams,
                     among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """With gravity: yaw + translation from the seed and its farthest observation matched to every CAD pair of the
    same types, horizontal distance and height difference (a baseline of metres fixes the yaw far better than a
    small, noisy rectangle does); `among`: only the pairs whose first feature is one of these (the seed's
    candidates, `seed_candidates`)."""
    c = prep.centroids
    partner = int(np.argmax(np.linalg.norm(c[:, :2] - c[seed, :2], axis=1)))
    v_obs = c[partner] - c[seed]
    d_obs = float(np.linalg.norm(v_obs[:2]))
    if d_obs < params.pair_min_baseline_m:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    pairs = index.pairs_within(params.pair_max_baseline_m)
    rows = np.arange(len(pairs.i)) if among is None else index.pairs_of(params.pair_max_baseline_m, among)
    tol = params.pair_tolerance_m
    rows = rows[(np.abs(pairs.d_xy[rows] - d_obs) < tol) & (np.abs(pairs.dz[rows] - v_obs[2]) < tol)]
    rows = rows[(index.type_codes[pairs.i[rows]] == prep.types[seed])
                & (index.type_codes[pairs.j[rows]] == prep.types[partner])]
    i, j, v = pairs.i[rows], pairs.j[rows], pairs.v[rows]
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


def prepare(index: ModelIndex, params: RobustParams) -> None:
    """Build (or read from the disk cache) what `register_robust` needs of the index's building alone, so that its
    timed block builds none of it: the pair table of `params.pair_max_baseline_m` and the posterior's tables."""
    index.prepare_pairs(params.pair_max_baseline_m)
    prepare_posterior(index)


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
    hyps = _Hypotheses(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, n, 3)), np.zeros(0), np.zeros(0, int))
    poses: list[_Pose] = []
    verdicts: list[Verdict] = []  # of poses[:refine_top] under the noise model of poses[0]
    used = 0
    for start in range(0, len(seeds), params.min_seeds):
        for s in seeds[start:start + params.min_seeds]:
            hyps = hyps.extend(_coarse(int(s), prep, index, params))
        used = min(len(seeds), start + params.min_seeds)
        if len(hyps.R) == 0:
            continue
        top = _distinct_top(np.argsort(-hyps.coarse, kind="stable")[: params.scan_top], hyps.moved, params)
        poses = sorted(_refine_all([make_T(hyps.R[h], hyps.t[h]) for h in top], prep, index, params),
                       key=lambda p: -p.score)
        noise = _prior_noise(poses[0], prep, index, params)
        verdicts = _verify_all(poses[: params.refine_top], prep, index, noise, params)
        if max(v.n_inliers for v in verdicts[:3]) >= params.early_stop_fraction * n and params.decision != "posterior":
            break  # well supported; its symmetric rivals come from the same seeds (the posterior, over the poses
            #        found, asks for every seed: docs/measurements.md, "Issue 58")
    images: list[_Pose] = []
    if poses:
        ref = poses[int(np.argmax([v.loglik for v in verdicts]))]
        images = _layout_images(ref, prep, index, params)
    return _decide(poses + images, hyps, prep, index, params,
                   {"hypotheses": int(len(hyps.R)), "seeds": used, "images": len(images)},
                   (noise, verdicts) if poses else None)


def _fitted_rms(d: np.ndarray, gravity_known: bool) -> float | None:
    """RMS of the 3-D residuals d (m) corrected for the degrees of freedom the pose was fitted with (4 with gravity,
    6 without; 3 residuals an observation): from a few observations the fitted pose absorbs much of the noise,
    and the noise model must not shrink. None where they are too few to tell."""
    dof = 4 if gravity_known else 6
    if 3 * len(d) <= dof:
        return None
    return float(np.sqrt(np.sum(d * d) / (len(d) - dof / 3.0)))


def _rms(T: np.ndarray, prep: _Prepared, index: ModelIndex, params: RobustParams) -> float:
    """`_fitted_rms` of the observations a pose explains (same type, within ambiguity_tau_m); inf where too few."""
    d, _ = _nearest_same_type(apply(T, prep.centroids), prep.types, index, upper_m=params.ambiguity_tau_m)
    rms = _fitted_rms(d[np.isfinite(d)], prep.gravity_known)
    return np.inf if rms is None else rms


def _prior_noise(first: _Pose, prep: _Prepared, index: ModelIndex, params: RobustParams) -> Noise:
    """The noise model before a pose is chosen: from the rectangles' closure where three or more were observed (it
    needs no pose, so a wrong first pose cannot loosen it), else from the RMS residual of the `first` pose
    (`_rms`); never below noise_floor_m. A closure below `FITTED_CLOSURE_M` is a fitted rectangle's (the pose
    graph's landmarks are one: its graph pose and the median of its sightings' sides), which shows no noise: then
    the residual too."""
    if prep.shapes.has_rect.sum() >= 3 and prep.shapes.corner_sigma_m > FITTED_CLOSURE_M:
        s = prep.shapes.corner_sigma_m * np.sqrt(3.0) / 2.0
    else:
        rms = _rms(first.T, prep, index, params)
        s = rms if np.isfinite(rms) else params.ambiguity_tau_m / 3.0
    return Noise.from_rms(max(s, params.noise_floor_m), params.verify, prep.shapes.corner_sigma_m)


def _verify(T: np.ndarray, prep: _Prepared, index: ModelIndex, noise: Noise, params: RobustParams) -> Verdict:
    """`graph.verify.verify` of the pose T (map' -> CAD) on the prepared observations."""
    return verify(T, prep.shapes, index, noise, params.ambiguity_tau_m, params.cross_type_weight, params.verify)


def _verify_all(poses: Sequence[_Pose | np.ndarray], prep: _Prepared, index: ModelIndex, noise: Noise,
                params: RobustParams) -> list[Verdict]:
    """`_verify` of each pose (a `_Pose` or a 4x4 T), all at once."""
    if not poses:
        return []
    T = np.stack([p.T if isinstance(p, _Pose) else p for p in poses])
    return verify_all(T, prep.shapes, index, noise, params.ambiguity_tau_m, params.cross_type_weight, params.verify)


def _matched_rms(T: np.ndarray, verdict: Verdict, prep: _Prepared, index: ModelIndex) -> float:
    """`_fitted_rms` of a pose's inliers' distances to their matched features; 0 where too few."""
    d = np.linalg.norm(apply(T, prep.centroids[verdict.inlier]) - index.centroids[verdict.match[verdict.inlier]],
                       axis=1)
    return _fitted_rms(d, prep.gravity_known) or 0.0


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
            diag: dict, judged: tuple[Noise, list[Verdict]] | None = None) -> RegistrationResult:
    """The best pose by verification (`graph.verify`), unless a different pose comes within the rival margin
    (`rival_margin`): then 'ambiguous' with the rivals listed. The rivals always scored: the refined candidates,
    the best pose of each seed observation's own hypotheses, and every self-map image of the best pose that maps
    at least half of its matches (`graph.self_maps`). `judged`: the noise model of poses[0] and the verdicts of the
    first poses under it, where already known."""
    n = len(prep.obs)
    if not poses:
        return RegistrationResult("not_localized", None, [], 0, None, diagnostics=diag)
    first = poses[0]
    noise, verdicts = judged if judged is not None else (_prior_noise(first, prep, index, params), [])
    rival_h = _rival_candidates(first, hyps, prep, index, params) + _seed_bests(first, hyps, prep, index, params, noise)
    candidates = poses + _refine_all([make_T(hyps.R[h], hyps.t[h]) for h in rival_h], prep, index, params)
    verdicts = verdicts + _verify_all(candidates[len(verdicts):], prep, index, noise, params)
    k_best = int(np.argmax([v.loglik for v in verdicts]))
    best, v_best = candidates[k_best], verdicts[k_best]
    images = _self_map_images(best.T, v_best, prep, index, params)
    candidates += images
    verdicts += _verify_all(images, prep, index, noise, params)
    k_best = int(np.argmax([v.loglik for v in verdicts]))
    # the noise model again, from the best pose's own matches (the first guess took any near feature), and every
    # candidate judged by it
    prior = noise
    noise = Noise.from_rms(max(_matched_rms(candidates[k_best].T, verdicts[k_best], prep, index), params.noise_floor_m),
                           params.verify, prep.shapes.corner_sigma_m)
    if abs(noise.centroid_rms_m - prior.centroid_rms_m) > 0.05 * prior.centroid_rms_m:  # else the same verdicts
        verdicts = _verify_all(candidates, prep, index, noise, params)
    k_best = int(np.argmax([v.loglik for v in verdicts]))
    post = pose_posterior(np.stack([p.T for p in candidates]), prep.shapes, index, params.observation,
                          lambda T, anchor: _distinct_pairs(T, anchor, params))
    # The posterior is over the poses found. Without gravity the search can miss the truth, and three rectangles
    # fit a wrong pose (docs/measurements.md, "Issue 58"): there, below min_inliers_without_gravity, today's rule.
    by_posterior = params.decision == "posterior" and (
        prep.gravity_known or (len(post.kept) > 0 and int(post.explained[0]) >= params.min_inliers_without_gravity))
    if by_posterior and post.named:  # the posterior's best pose is the answer's
        k_best = post.named[0]
    best, v_best = candidates[k_best], verdicts[k_best]
    n_best = v_best.n_inliers
    margin = rival_margin(v_best, prep, index, noise, params)
    diag.update(best_support=round(best.score, 3), best_inliers=n_best, best_loglik=round(v_best.loglik, 2),
                noise_rms_m=round(noise.centroid_rms_m, 4), rival_margin=round(margin(n_best), 2),
                rivals_scored=len(candidates))
    all_rects = bool(v_best.inlier.any() and prep.shapes.has_rect[v_best.inlier].all())
    min_inliers = params.min_inliers if prep.gravity_known or all_rects else params.min_inliers_without_gravity
    post_json = post.to_json([candidates[k].T @ prep.T_mp_m for k in post.kept])
    if n_best < max(min_inliers, params.min_inlier_fraction * n) or (by_posterior and post.status == "not_localized"):
        return RegistrationResult("not_localized", None, [], n_best, None, diagnostics=diag, posterior=post_json)
    anchor = prep.centroids[v_best.inlier]
    distinct_pairs = _distinct_pairs(np.stack([p.T for p in candidates]), anchor, params)
    scored = sorted(range(len(candidates)), key=lambda k: -verdicts[k].loglik)
    rivals = [k for k in scored if candidates[k] is not best and distinct_pairs[k_best, k]]
    # the rivals within the margin, each pose once
    close = [(verdicts[k], candidates[k]) for k in _each_pose_once(
        distinct_pairs, rivals, lambda k: verdicts[k].loglik >= v_best.loglik - margin(verdicts[k].n_inliers))]
    if by_posterior:  # the poses that share the posterior's mass, or none
        close = [(verdicts[k], candidates[k]) for k in post.named[1:]]
    diag.update(rival_loglik=round(verdicts[rivals[0]].loglik, 2) if rivals else None,
                rival_inliers=verdicts[rivals[0]].n_inliers if rivals else 0)
    pairs = [(int(i), int(v_best.match[i])) for i in np.flatnonzero(v_best.inlier)]
    T_cad_map = best.T @ prep.T_mp_m
    by_inliers = [k_best, *sorted(range(len(candidates)), key=lambda k: -verdicts[k].n_inliers)]
    distinct_k = _each_pose_once(distinct_pairs, by_inliers, lambda k: verdicts[k].n_inliers >= min_inliers)
    distinct = [candidates[k].T for k in distinct_k]
    candidate_poses = [(candidates[k].T @ prep.T_mp_m, verdicts[k].n_inliers) for k in distinct_k]
    if n_best < params.complete_below:
        kept = [(T[:3, :3], apply(T, prep.centroids)) for T in distinct]
        candidate_poses += [(make_T(hyps.R[h], hyps.t[h]) @ prep.T_mp_m, n_best)
                            for h in _alike_hypotheses(hyps, max(2, n_best - 1), kept, prep, index, params)]
    storey = majority_storey(index, [j for _, j in pairs])
    matches = [(i, index.features[j].id) for i, j in pairs]
    if close:
        v_r = close[0][0]
        diag["rival_storey"] = majority_storey(index, [int(j) for j in v_r.match[v_r.inlier]])
        # No matches: they would name one of the competing poses' features as if it were known.
        return RegistrationResult("ambiguous", T_cad_map, [], n_best, storey,
                                  alternatives=[p.T @ prep.T_mp_m for _, p in close], diagnostics=diag,
                                  candidates=candidate_poses, posterior=post_json)
    return RegistrationResult("localized", T_cad_map, matches, n_best, storey, diagnostics=diag,
                              candidates=candidate_poses, posterior=post_json)


@dataclass(frozen=True)
class RivalMargin:
    """`rival_margin`'s rule for one best pose: the worth of the chance landings, and the spread per rival."""

    landings: float  # k times the best pose's mean term
    dof: int  # d
    best_inliers: int  # n_best

    def __call__(self, rival_inliers: int) -> float:
        return self.landings + 2.0 * float(np.sqrt(self.dof / 2.0 * (self.best_inliers + rival_inliers)))


def rival_margin(best: Verdict, prep: _Prepared, index: ModelIndex, noise: Noise, params: RobustParams
                 ) -> RivalMargin:
    """The log-likelihood a different pose explaining n_rival observations must stay below the best's for the
    answer to be 'localized': `rival_margin(...)(n_rival)`.

    Rule: the worth of k chance landings (`graph.verify.chance_term`, at most the best pose's mean term), plus
    twice the spread that noise alone gives the difference of the two poses' log-likelihoods (each explained
    observation's term varies as half a chi-square with d dof, variance d / 2, independently: sd
    sqrt(d / 2 (n_best + n_rival)), d = 6 for a rectangle: 3 position, 1 normal, 2 sides; 3 for a centroid), k the
    number of false
    detections landing on a feature of their type by chance that is exceeded with probability `landing_alpha` at
    most (a Poisson count of mean mu): a pose that beats its rival only by such landings is not known (a storey
    pair turned 180 degrees, one door more in one of them, a false detection on it). A wrong answer needs, besides,
    a rival that explains the true observations as well (a self-map): alpha bounds only the landings.
    mu = eps n p: of the n observations eps n are false detections (the verification's prior), and detectors fire
    on walls, as the features sit on walls, so one lands within the position gate (radius r, from the noise
    model) of a feature of its type with probability p = 2 r / L, L the spacing of same-type features around the
    observations (the median distance of each to its nearest same-type neighbour, in plan). The margin grows
    with the noise (through r) and with the number of observations (through mu and the spread)."""
    n = len(prep.obs)
    dof = 6 if best.inlier.any() and prep.shapes.has_rect[best.inlier].mean() >= 0.5 else 3
    if best.n_inliers < 2:
        return RivalMargin(full_term(bool(prep.shapes.has_rect.mean() >= 0.5) if n else False, params.verify),
                           dof, 0)
    unit = best.loglik / best.n_inliers
    matched = index.centroids[best.match[best.inlier]]  # the footprint, CAD: the matched features and around
    lo, hi = matched.min(axis=0) - [1.0, 1.0, 1.5], matched.max(axis=0) + [1.0, 1.0, 1.5]
    around = np.flatnonzero(np.all((index.centroids >= lo) & (index.centroids <= hi), axis=1))
    spacing = []
    for code in np.unique(index.type_codes[around]):
        mine = index.centroids[around[index.type_codes[around] == code], :2]
        if len(mine) >= 2:
            spacing.append(cKDTree(mine).query(mine, k=2)[0][:, 1])
    gate_m = noise.position_gate_m(params.verify)
    spacing_m = max(float(np.median(np.concatenate(spacing))), 2.0 * gate_m) if spacing else np.inf
    mu = params.verify.false_detection_rate * n * 2.0 * gate_m / spacing_m  # no alike feature around: 0
    landing = min(unit, chance_term(dof == 6, params.verify))  # what a chance landing adds, at most the mean
    return RivalMargin(_poisson_quantile(mu, params.landing_alpha) * landing, dof, best.n_inliers)


def _poisson_quantile(mu: float, alpha: float) -> int:
    """The smallest k with P(N > k) <= alpha for N ~ Poisson(mu)."""
    k, p, cdf = 0, np.exp(-mu), np.exp(-mu)
    while 1.0 - cdf > alpha:
        k += 1
        p *= mu / k
        cdf += p
    return k


def _distinct_T(A: np.ndarray, B: np.ndarray, anchor: np.ndarray, params: RobustParams) -> np.ndarray:
    """Per pose A (K, 4, 4): whether it differs from the pose B (4x4): it moves the anchor points (M, 3) apart by
    more than distinct_m on average, or turns by more than distinct_deg. (K,) bool."""
    D = np.asarray(A) - B  # apply(A, p) - apply(B, p) = p (R_A - R_B)^T + (t_A - t_B): one product per pose
    diff = np.matmul(anchor[None], np.swapaxes(D[:, :3, :3], 1, 2)) + D[:, None, :3, 3]
    moved_apart = np.sqrt(np.einsum("kij,kij->ki", diff, diff)).sum(axis=1) > params.distinct_m * len(anchor)
    cos = (np.einsum("kij,ij->k", A[:, :3, :3], B[:3, :3]) - 1.0) / 2.0  # trace(R_A R_B^T) = 1 + 2 cos(angle)
    return moved_apart | (np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) > params.distinct_deg)


def _distinct_pairs(T: np.ndarray, anchor: np.ndarray, params: RobustParams) -> np.ndarray:
    """(K, K) bool: `_distinct_T` of each pose of T (K, 4, 4) against each other. The anchor's centroid moved
    apart by more than distinct_m decides most pairs (the mean of the points' displacements is at least the
    displacement of their mean), or a turn by more than distinct_deg; `_distinct_T` the rest, row by row."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    centre = anchor.mean(axis=0) if len(anchor) else np.zeros(3)
    moved = T[:, :3, :3] @ centre + T[:, :3, 3]  # (K, 3)
    gap = np.linalg.norm(moved[:, None] - moved[None], axis=2)
    cos = (np.einsum("kij,lij->kl", T[:, :3, :3], T[:, :3, :3]) - 1.0) / 2.0
    out = (gap > params.distinct_m) | (np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) > params.distinct_deg)
    for k in np.flatnonzero((~out).sum(axis=1) > 1):  # a row with an undecided pair besides the pose itself
        undecided = np.flatnonzero(~out[k])
        out[k, undecided] = _distinct_T(T[undecided], T[k], anchor, params)
    return out


def _each_pose_once(distinct: np.ndarray, order: Sequence[int],
                    eligible: Callable[[int], bool] = lambda k: True) -> list[int]:
    """Of K poses, in `order`, those `eligible` that are distinct from every one kept before (`distinct`: (K, K)
    bool, `_distinct_pairs`)."""
    free = np.ones(len(distinct), dtype=bool)  # not alike to a kept pose
    kept: list[int] = []
    for k in order:
        if free[k] and eligible(k):
            kept.append(k)
            free &= distinct[k]
    return kept


def _seed_bests(first: _Pose, hyps: _Hypotheses, prep: _Prepared, index: ModelIndex, params: RobustParams,
                noise: Noise) -> list[int]:
    """Per seed observation: among its best distinct coarse hypotheses (`seed_rivals`, different from `first`), the
    one the verification (under `noise`) prefers, to be refined and scored (a pose that centroid coincidences
    outrank is still scored)."""
    kept = [(first.T[:3, :3], apply(first.T, prep.centroids))]
    tops = []
    for seed in np.unique(hyps.seed):
        own = np.flatnonzero(hyps.seed == seed)
        order = own[np.argsort(-hyps.coarse[own], kind="stable")][: params.scan_top]
        top = _distinct_top(order, hyps.moved, params, rotations=hyps.R, kept=kept, limit=params.seed_rivals)
        if top:
            tops.append(top)
    flat = [h for top in tops for h in top]
    logliks = iter([v.loglik for v in _verify_all([make_T(hyps.R[h], hyps.t[h]) for h in flat], prep, index,
                                                   noise, params)])
    return [top[int(np.argmax([next(logliks) for _ in top]))] for top in tops]


def _self_map_images(T: np.ndarray, verdict: Verdict, prep: _Prepared, index: ModelIndex,
                     params: RobustParams) -> list[_Pose]:
    """S @ T, refined, for the building's self-maps S that put at least half of the pose's matched features onto
    alike ones (the most such first, `rival_self_maps` of them)."""
    maps = index.self_maps()
    matched = verdict.match[verdict.inlier]
    if not len(maps.votes) or len(matched) < 2:
        return []
    count = maps.lands[:, matched].sum(axis=1)
    order = np.argsort(-count, kind="stable")
    order = order[count[order] >= max(2, len(matched) / 2.0)][: params.rival_self_maps]
    S_all = maps.transforms()
    return _refine_all([S_all[m] @ T for m in order], prep, index, params)


def _layout_images(best: _Pose, prep: _Prepared, index: ModelIndex, params: RobustParams) -> list[_Pose]:
    """Every image S @ best.T of the best pose under a yaw + shift S of the CAD frame that puts at least
    `image_min_fraction` of its matched features within `image_landing_m` of features of their type: complete,
    not a sample (a building of repeated units has one per unit, and the truth may be any of them).

    Found by an index, not a search over the building: a few matched features (anchors: those with the most
    matched features around, `image_anchor_gap_m` apart; a missing one in an image is made up by the others)
    each propose the S that put them onto their alike features (same type
    and size, and a `graph.layout` histogram that explains at least `image_alike_fraction` of the anchor's
    relations to the other matched features; the yaw from the wall normals, either sign), and every proposal is
    checked on all matched features at once (one k-d query).
    Each image is then polished to the observations (`_polish`, vectorised) and returned for `_decide` to
    judge beside the others."""
    matched = np.unique(best.match[best.inliers])
    matched = matched[matched >= 0]
    if len(matched) < 2:
        return []
    lay = index.layout()
    c_f = index.centroids[matched]
    heading = np.arctan2(index.normals[:, 1], index.normals[:, 0])
    wall = np.abs(index.normals[:, 2]) < 0.5
    gap = np.linalg.norm(c_f[:, None] - c_f[None], axis=2)
    richness = (gap <= lay.params.radius_m).sum(axis=1)  # the matched features around: the stricter the test
    chosen: list[int] = []
    for k in np.argsort(-richness, kind="stable"):
        if len(chosen) == params.image_anchors:
            break
        if all(gap[k, c] >= params.image_anchor_gap_m for c in chosen):
            chosen.append(int(k))
    tol = params.size_tolerance_m
    yaws, shifts = [], []
    for a in matched[chosen]:
        if not wall[a]:
            continue
        cand = index.type_indices[index.types[a]]
        cand = cand[wall[cand] & (((np.abs(index.len_u[cand] - index.len_u[a]) < tol)
                                   & (np.abs(index.len_v[cand] - index.len_v[a]) < tol))
                                  | ((np.abs(index.len_u[cand] - index.len_v[a]) < tol)
                                     & (np.abs(index.len_v[cand] - index.len_u[a]) < tol)))]
        off = np.delete(c_f, np.flatnonzero(matched == a), axis=0) - index.centroids[a]
        near = np.linalg.norm(off, axis=1) <= lay.params.radius_m
        hist = lay.histogram(off[near], index.normals[a], np.delete(index.type_codes[matched],
                                                                     np.flatnonzero(matched == a))[near])
        cand = cand[lay.explained(hist, cand) >= max(2.0, params.image_alike_fraction * near.sum())]
        for flip in (0.0, np.pi):
            yaw = heading[cand] - heading[a] + flip
            R = rot_z(yaw)
            yaws.append(yaw)
            shifts.append(index.centroids[cand] - R @ index.centroids[a])
    if not yaws:
        return []
    yaw, shift = np.concatenate(yaws), np.concatenate(shifts)
    # several anchors propose the same image: once each; then a first check on the anchors alone (an image that
    # can rival the best lands nearly all matched features: two of the anchors at least)
    key = np.column_stack([np.round(np.degrees((yaw + np.pi) % (2.0 * np.pi)) / 2.0), np.round(shift / 0.25)])
    _, first = np.unique(key, axis=0, return_index=True)
    yaw, shift = yaw[first], shift[first]
    if len(chosen) >= 2:
        c_a = c_f[chosen]
        moved = np.einsum("kij,nj->kni", rot_z(yaw), c_a) + shift[:, None, :]
        d, _ = _nearest_same_type(moved, index.type_codes[matched[chosen]], index, upper_m=params.image_landing_m)
        ok = np.isfinite(d).sum(axis=1) >= 2
        yaw, shift = yaw[ok], shift[ok]
    # then on `image_check` matched features spread over the footprint (the anchors first, then farthest-point)
    check = list(chosen)
    while len(check) < min(params.image_check, len(matched)):
        check.append(int(np.argmax(np.min(gap[:, check], axis=1))))
    c_c = c_f[check]
    R = rot_z(yaw)
    moved = np.einsum("kij,nj->kni", R, c_c) + shift[:, None, :]
    d, _ = _nearest_same_type(moved, index.type_codes[matched[check]], index, upper_m=params.image_landing_m)
    lands = np.isfinite(d).sum(axis=1)
    apart = np.linalg.norm(moved - c_c[None], axis=2).mean(axis=1)
    turned = np.abs((yaw + np.pi) % (2.0 * np.pi) - np.pi)
    keep = ((lands >= max(2.0, params.image_min_fraction * len(check)))
            & ((apart > params.distinct_m) | (np.degrees(turned) > params.distinct_deg)))
    if not keep.any():
        return []
    yaw, shift = yaw[keep], shift[keep]
    key = np.column_stack([np.round(np.degrees((yaw + np.pi) % (2.0 * np.pi)) / 2.0), np.round(shift / 0.5)])
    _, first = np.unique(key, axis=0, return_index=True)
    first = np.sort(first)
    S = np.broadcast_to(np.eye(4), (len(first), 4, 4)).copy()
    S[:, :3, :3] = rot_z(yaw[first])
    S[:, :3, 3] = shift[first]
    T = S @ best.T
    Rk, tk = T[:, :3, :3], T[:, :3, 3]
    tau = params.inlier_threshold_m * 1.5
    for _ in range(params.refine_iterations):
        moved = np.einsum("kij,nj->kni", Rk, prep.centroids) + tk[:, None, :]
        d, j = _nearest_same_type(moved, prep.types, index, upper_m=tau)
        Rk, tk = _polish(Rk, tk, prep.centroids, prep.gravity_known, index, j, _support(d, tau))
    Rk, tk = np.concatenate([Rk, best.T[None, :3, :3]]), np.concatenate([tk, best.T[None, :3, 3]])
    moved = np.einsum("kij,nj->kni", Rk, prep.centroids) + tk[:, None, :]
    d, j = _nearest_same_type(moved, prep.types, index, upper_m=params.inlier_threshold_m)
    s = _support(np.minimum(d, params.inlier_threshold_m), params.inlier_threshold_m)
    # the rival margin of the best pose, in observations: an image explaining (within the verification's
    # position gate) fewer than the best of them and the pose less that (and image_slack) cannot come within it
    noise = _prior_noise(best, prep, index, params)
    explained = (d <= noise.position_gate_m(params.verify)).sum(axis=1)
    v = _verify(best.T, prep, index, noise, params)
    unit = v.loglik / v.n_inliers if v.n_inliers and v.loglik > 0 else np.inf
    slack = rival_margin(v, prep, index, noise, params)(v.n_inliers) / unit + params.image_slack
    keep = np.flatnonzero(explained[:-1] >= explained.max() - slack)  # an image may beat the best: the truth
    return [_Pose(make_T(Rk[k], tk[k]), s[k] > 0, j[k], float(s[k].sum())) for k in keep]


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
