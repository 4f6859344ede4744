"""One generative model of what is observed, and the posterior over pose hypotheses it gives (issue 58).

Given a pose T (map' -> CAD), the observations are generated thus (docs/algorithm.md, "The posterior"):

* every model feature in view is detected with probability 1 - p_miss (missed with p_miss);
* a detection reports the feature's type, swapped door <-> window with probability p_swap; its centroid with a
  Gaussian error of sigma_c per axis (the corner noise averaged over 4 corners, and the CAD model's own accuracy);
  its two side lengths with sigma_s each; its wall normal within sigma_n (radians, the angle to the feature's);
* false detections come as a Poisson process on the walls: their expected number is `false_detection_fraction`
  of the observations; each lies on a wall (across it, the same Gaussian as a true detection's centroid), along
  the walls uniformly over `wall_per_feature_m` metres of wall per observation (the building's own spacing), either
  type; with probability `false_alike_fraction` it looks like one of the building's doors and windows (height and
  sides drawn from theirs, with the noise), else its centre lies uniformly in a band of `false_band_m` of height
  and its two sides uniformly over `false_size_area_m2` square metres of sizes.

The likelihood of all observations under T (one observation per feature, the assignment that maximises it):
  L(T) = prod_matched (1 - p_miss) p_type g(residuals) * prod_unmatched lambda * prod_missed p_miss,
g the Gaussian densities above, lambda the false-detection density at the observation (the Poisson process's
e^-Lambda is the same for every pose and cancels), "missed" the model features in view that no observation
matches: in view = within `view_margin_m` (in plan) of the convex hull of the matched observations' centroids under
T and within `view_band_m` of their heights (the area the pose says was surveyed).
The posterior is over the distinct poses the search found (a uniform prior over them) plus one hypothesis
"none of them" (every observation a false detection): P(T_k) = L_k / sum L. Decision (`decide`): `localized`
when the best pose's posterior is at least 1 - epsilon; `ambiguous` when two or more distinct poses hold at
least 1 - epsilon between them (each listed with its probability); `not_localized` otherwise.
Frames: observations in map', features in CAD, metres, radians. Pure: numpy only (the model's k-d tree aside).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from macroloc.graph.model_index import ModelIndex
from macroloc.graph.params import ObservationModel
from macroloc.graph.verify import ObservedShapes, one_per_feature

__all__ = ["ObservationModel", "PoseEvidence", "Posterior", "Sigmas", "decide", "pose_evidence", "pose_posterior",
           "posterior"]

LOG_2PI = float(np.log(2.0 * np.pi))
NEGLIGIBLE_LOG = 50.0  # a pose this far below the likeliest in log-likelihood holds < e^-50 of the posterior


@dataclass(frozen=True)
class PoseEvidence:
    """Per pose (K): its log-likelihood, matched CAD feature per observation ((K, N); -1: a false detection),
    the number of features in view it predicts and of those missed (-1: not asked, the pose being negligible:
    its log-likelihood is then the bound without misses)."""

    loglik: np.ndarray
    match: np.ndarray
    in_view: np.ndarray
    missed: np.ndarray


@dataclass(frozen=True)
class Sigmas:
    """The noise model of one observation set: centroid per axis, side length, normal floor (m, m, rad)."""

    centroid_m: float
    size_m: float
    normal_floor_rad: float

    @classmethod
    def of(cls, shapes: ObservedShapes, model: ObservationModel) -> Sigmas:
        """From the rectangles' closure (`ObservedShapes.corner_sigma_m`, per axis) or the floor, whichever is
        larger: a centroid averages 4 corners (sigma / 2), plus the CAD model's own accuracy; a side is known to
        the corner sigma (two opposite edges averaged), at least the size floor."""
        corner = max(shapes.corner_sigma_m, model.corner_sigma_floor_m)
        return cls(float(np.hypot(corner / 2.0, model.cad_sigma_m)), max(corner, model.size_sigma_floor_m),
                   float(np.radians(model.normal_sigma_floor_deg)))


def false_detection_logdensity(shapes: ObservedShapes, sig: Sigmas, model: ObservationModel,
                               wall_m: float) -> np.ndarray:
    """log lambda per observation (N,), where no pose says where it is: the expected number of false detections
    (fraction x N) times the density of one at the observation: across its wall the centroid's Gaussian at its
    peak, along the walls 1 / (wall per observation x N), either type (1/2), its normal its wall's (the Gaussian's
    peak; `wall_m`: metres of wall per observation), and, with no building frame to say which heights and sizes
    are a door's, its centre uniformly in `false_band_m` of height and (a rectangle) its sides uniformly over
    `false_size_area_m2`. N cancels."""
    return _false_base(shapes, sig, model, wall_m) - np.log(model.false_band_m) - np.where(
        shapes.has_rect, np.log(model.false_size_area_m2), 0.0)


def _false_base(shapes: ObservedShapes, sig: Sigmas, model: ObservationModel, wall_m: float) -> np.ndarray:
    """`false_detection_logdensity` but for the height and the sides (N,); `wall_m`: wall per observation."""
    per = (np.log(model.false_detection_fraction) - np.log(wall_m) - np.log(2.0)
           - 0.5 * LOG_2PI - np.log(sig.centroid_m))
    rect = -LOG_2PI - 2.0 * np.log(_normal_sigma(shapes, sig))
    return per + np.where(shapes.has_rect, rect, 0.0)


def false_detection_logdensity_at(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, sig: Sigmas,
                                  model: ObservationModel) -> np.ndarray:
    """log lambda per pose T (K, 4, 4) and observation (K, N): as `false_detection_logdensity`, but a false
    detection looks, with probability `false_alike_fraction`, like one of the building's own doors and windows (a
    detector fires on what looks like them): its height (CAD, under the pose) and sides drawn from the building's
    features (either type, all alike), with the noise (`_alike_logdensity`); else any height and size as there."""
    wall_m = wall_per_feature_m(index, model)
    generic = -np.log(model.false_band_m) - np.where(shapes.has_rect, np.log(model.false_size_area_m2), 0.0)
    a = model.false_alike_fraction
    shape = np.logaddexp(np.log(a) + _alike_logdensity(T, shapes, index, sig), np.log1p(-a) + generic[None])
    return _false_base(shapes, sig, model, wall_m)[None] + shape


@dataclass(frozen=True)
class _BuildingTables:
    """What the model needs of a building alone: its wall per feature (m) and its features' (height, short side,
    long side) rounded to 1 cm, each once, with the log of its share (U, 3), (U,)."""

    wall_m: float
    alike: np.ndarray
    alike_logw: np.ndarray


TABLES_VERSION = 1  # bump when _building_arrays changes: the disk cache is keyed by it


def _tables(index: ModelIndex) -> _BuildingTables:
    """`_BuildingTables` of the index: computed once per building (and storey index), held by the index and cached
    on disk (`ModelIndex.asset`); `prepare` builds them before a registration's timed block."""
    a = index.asset(f"posterior-v{TABLES_VERSION}", _building_arrays)
    return _BuildingTables(float(a["wall_m"]), a["alike"], a["alike_logw"])


def prepare(index: ModelIndex) -> None:
    """Build (or read) what the model needs of the index's building alone, ahead of a registration."""
    _tables(index)


def _building_arrays(index: ModelIndex) -> dict[str, np.ndarray]:
    short = np.minimum(index.len_u, index.len_v)
    long_ = np.maximum(index.len_u, index.len_v)
    table, counts = np.unique(np.round(np.column_stack([index.centroids[:, 2], short, long_]), 2), axis=0,
                              return_counts=True)
    return {"wall_m": np.array(_measured_wall_m(index)), "alike": table, "alike_logw": np.log(counts / counts.sum())}


def wall_per_feature_m(index: ModelIndex, model: ObservationModel) -> float:
    """Metres of wall per door or window: `model.wall_per_feature_m`, or where that is 0, the building's own
    (`_measured_wall_m`). The surveyed walls hold one feature per this many metres, and false detections fall
    along them."""
    return model.wall_per_feature_m if model.wall_per_feature_m > 0 else _tables(index).wall_m


def _measured_wall_m(index: ModelIndex) -> float:
    """The median distance from a wall feature to the next one on the same wall line (among its 8 nearest within
    15 m: normals within 25 degrees, within 0.3 m of the line, heights within 1.5 m, 0.3 m apart in plan at least:
    closer, one opening), features without one left out; 10 m where none has one."""
    c, nrm = index.centroids, index.normals
    k = min(9, len(c))
    d, j = index.tree_all.query(c, k=k, distance_upper_bound=15.0)  # the nearest 8 others within 15 m
    found = np.isfinite(d) & (j != np.arange(len(c))[:, None])
    jj = np.where(found, j, 0)
    off = c[jj] - c[:, None]  # (M, k, 3)
    wall = np.abs(nrm[:, 2]) < 0.5
    parallel = np.abs(np.einsum("mkc,mc->mk", nrm[jj], nrm)) > np.cos(np.radians(25.0))
    plan = np.linalg.norm(off[..., :2], axis=2)
    same = (found & wall[:, None] & wall[jj] & parallel & (np.abs(np.einsum("mkc,mc->mk", off, nrm)) < 0.3)
            & (np.abs(off[..., 2]) < 1.5) & (plan > 0.3))
    gaps = np.where(same, plan, np.inf).min(axis=1)
    gaps = gaps[np.isfinite(gaps)]
    return float(np.median(gaps)) if len(gaps) else 10.0


def _alike_logdensity(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, sig: Sigmas) -> np.ndarray:
    """log of the mean over the building's features m of N(z - z_m; s_c) N(short - short_m; s_s) N(long - long_m;
    s_s) (sides only for a rectangle), z the observation's centroid height under each pose T: (K, N)."""
    tables = _tables(index)
    table, w = tables.alike, tables.alike_logw
    z = np.einsum("kj,nj->kn", T[:, 2, :3], shapes.centroids) + T[:, None, 2, 3]  # (K, N) CAD heights
    s_c, s_s = sig.centroid_m, sig.size_m
    lz = -0.5 * LOG_2PI - np.log(s_c) - 0.5 * ((z[..., None] - table[:, 0]) / s_c) ** 2  # (K, N, U)
    o_short = np.minimum(shapes.len_a, shapes.len_b)[:, None]
    o_long = np.maximum(shapes.len_a, shapes.len_b)[:, None]
    ls = -LOG_2PI - 2.0 * np.log(s_s) - 0.5 * (((o_short - table[:, 1]) / s_s) ** 2
                                               + ((o_long - table[:, 2]) / s_s) ** 2)  # (N, U)
    ls = np.where(shapes.has_rect[:, None], ls, 0.0)
    return np.logaddexp.reduce(lz + ls[None] + w, axis=2)


def _normal_sigma(shapes: ObservedShapes, sig: Sigmas) -> np.ndarray:
    """A rectangle's wall normal sigma (N,), radians: the corner sigma (2 x the centroid's) over its shorter side,
    at least the floor (graph.verify's rule)."""
    short = np.maximum(np.minimum(shapes.len_a, shapes.len_b), 1e-3)
    return np.maximum(2.0 * sig.centroid_m / short, sig.normal_floor_rad)


def match_logdensity(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, sig: Sigmas,
                     model: ObservationModel) -> tuple[np.ndarray, np.ndarray]:
    """Per pose T (K, 4, 4) and observation: the log-density of its best CAD feature within the gate explaining it
    (log (1 - p_miss) + log p_type + the Gaussian log-densities of the centroid (3-D), sides and normal), and
    that feature ((K, N); -1 / -inf where none within the gate)."""
    n, K = len(shapes.centroids), len(T)
    if n == 0 or len(index.features) == 0:
        return np.full((K, n), -np.inf), np.full((K, n), -1)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    moved = np.matmul(shapes.centroids[None], Rt) + T[:, None, :3, 3]
    k = min(model.neighbours, len(index.features))
    gate_m = model.gate_sigmas * sig.centroid_m * np.sqrt(3.0)
    d, j = index.tree_all.query(moved.reshape(-1, 3), k=k, distance_upper_bound=gate_m)
    d, j = d.reshape(K, n, k), j.reshape(K, n, k)
    found = np.isfinite(d)
    jj = np.where(found, j, 0)
    s_c = sig.centroid_m
    logp = -1.5 * LOG_2PI - 3.0 * np.log(s_c) - 0.5 * (np.where(found, d, 0.0) / s_c) ** 2
    same = index.type_codes[jj] == shapes.types[None, :, None]
    logp = logp + np.log(1.0 - model.miss_probability) + np.where(same, np.log(1.0 - model.swap_probability),
                                                                   np.log(model.swap_probability))
    # a rectangle: its normal (up to sign) and its two sides, as graph.verify pairs them
    n_obs = np.matmul(shapes.normals[None], Rt)
    cos = np.abs(np.einsum("pnc,pnkc->pnk", n_obs, index.normals[jj]))
    theta = np.arccos(np.clip(cos, -1.0, 1.0))
    s_n = _normal_sigma(shapes, sig)[None, :, None]
    a_cad, b_cad = np.matmul(shapes.edge_a[None], Rt), np.matmul(shapes.edge_b[None], Rt)
    u = index.edge_u[jj]
    a_is_u = np.abs(np.einsum("pnc,pnkc->pnk", a_cad, u)) >= np.abs(np.einsum("pnc,pnkc->pnk", b_cad, u))
    la, lb = shapes.len_a[None, :, None], shapes.len_b[None, :, None]
    du = np.where(a_is_u, la, lb) - index.len_u[jj]
    dv = np.where(a_is_u, lb, la) - index.len_v[jj]
    # sides: two 1-D Gaussians; the normal: a 2-D Gaussian on the sphere about the feature's (per steradian)
    rect_logp = (-2.0 * LOG_2PI - 2.0 * np.log(sig.size_m) - 2.0 * np.log(s_n)
                 - 0.5 * ((du / sig.size_m) ** 2 + (dv / sig.size_m) ** 2 + (theta / s_n) ** 2))
    g = model.gate_sigmas
    ok = found & (~shapes.has_rect[None, :, None] | ((theta < g * s_n) & (np.abs(du) < g * sig.size_m)
                                                      & (np.abs(dv) < g * sig.size_m)))
    logp = np.where(ok, logp + np.where(shapes.has_rect[None, :, None], rect_logp, 0.0), -np.inf)
    best = np.argmax(logp, axis=2)[..., None]
    out = np.take_along_axis(logp, best, axis=2)[..., 0]
    feat = np.where(np.isfinite(out), np.take_along_axis(jj, best, axis=2)[..., 0], -1)
    return out, feat


def features_in_view(T: np.ndarray, matched: np.ndarray, shapes: ObservedShapes, index: ModelIndex,
                     model: ObservationModel, hulls: dict[bytes, tuple[np.ndarray, np.ndarray]] | None = None
                     ) -> np.ndarray:
    """Indices of the CAD features in view under one pose T (4, 4): within view_margin_m (plan) of the convex hull
    of the matched observations' centroids (CAD) and within view_band_m of their heights. `hulls`: a cache of the
    hulls' edges (`_hull_edges`) of matched sets in the observations' own frame, for the poses of one search (a
    level pose turns about z, so the hull of the moved centroids in plan is the moved hull: one hull per matched
    set, not per pose, its edges' normals turned and offsets moved)."""
    if not matched.any():
        return np.zeros(0, dtype=int)
    p = shapes.centroids[matched] @ T[:3, :3].T + T[:3, 3]
    edges = None
    if hulls is not None and T[2, 2] >= 1.0 - 1e-12:  # level (upright): the plan hull moves with the pose
        key = matched.tobytes()
        if key not in hulls:
            hulls[key] = _hull_edges(_hull_ccw(shapes.centroids[matched][:, :2]))
        normal, offset = hulls[key]
        if len(normal):  # its edges' outward normals turn with the pose, and their offsets move with it
            normal = normal @ T[:2, :2].T
            edges = (normal, offset + normal @ T[:2, 3])
    lo_z, hi_z = p[:, 2].min() - model.view_band_m, p[:, 2].max() + model.view_band_m
    centre = p[:, :2].mean(axis=0)
    radius = float(np.linalg.norm(p[:, :2] - centre, axis=1).max()) + model.view_margin_m
    cand = np.array(index.tree_all.query_ball_point([*centre, (lo_z + hi_z) / 2.0],
                                                    np.hypot(radius, (hi_z - lo_z) / 2.0)), dtype=int)
    if not len(cand):
        return cand
    c = index.centroids[cand]
    band = (c[:, 2] >= lo_z) & (c[:, 2] <= hi_z)
    cand, c = cand[band], c[band]
    if edges is not None:
        return cand[np.all(c[:, :2] @ edges[0].T - edges[1] <= model.view_margin_m, axis=1)]
    return cand[_within_hull(p[:, :2], c[:, :2], model.view_margin_m)]


def _hull_edges(hull: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The outward unit normals (H, 2) of a counter-clockwise hull's edges (`_hull_ccw`) and their offsets (H,): a
    point x is within m of the hull where x . normal - offset <= m for every edge; none where the hull is a segment
    or a point (fewer than 3 vertices)."""
    if len(hull) < 3:
        return np.zeros((0, 2)), np.zeros(0)
    edge = np.roll(hull, -1, axis=0) - hull
    normal = np.column_stack([edge[:, 1], -edge[:, 0]]) / np.linalg.norm(edge, axis=1)[:, None]
    return normal, np.einsum("ec,ec->e", normal, hull)


def _hull_ccw(points: np.ndarray) -> np.ndarray:
    """The convex hull's vertices (H, 2), counter-clockwise, of points (P, 2) (Andrew's monotone chain; fewer than
    3 where they are collinear)."""
    p = np.unique(np.round(points, 9), axis=0)  # sorted by x, then y
    if len(p) < 3:
        return p

    def half(pts: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for q in pts:
            while len(out) >= 2 and _turn(out[-2], out[-1], q) <= 1e-12:
                out.pop()
            out.append(q)
        return out

    lower, upper = half(p), half(p[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """z of (a - o) x (b - o): > 0 where o -> a -> b turns left."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _within_hull(points: np.ndarray, query: np.ndarray, margin: float, hull: np.ndarray | None = None
                 ) -> np.ndarray:
    """Whether each query point (M, 2) lies within `margin` of the convex hull of points (P, 2) (a segment or a
    point where they are collinear or one); `hull`: that hull (`_hull_ccw`), where it is known."""
    hull = _hull_ccw(points) if hull is None else hull
    if len(hull) >= 3:
        normal, offset = _hull_edges(hull)
        return np.all(query @ normal.T - offset <= margin, axis=1)
    a = points[np.argmin(points @ (points[-1] - points[0]))]
    b = points[np.argmax(points @ (points[-1] - points[0]))]
    ab = b - a
    s = np.clip((query - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(query - (a + s[:, None] * ab), axis=1) <= margin


def pose_evidence(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, model: ObservationModel,
                  sig: Sigmas | None = None) -> PoseEvidence:
    """The log-likelihood L(T) of the module doc for each pose T (K, 4, 4) (map' -> CAD)."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    sig = sig or Sigmas.of(shapes, model)
    log_fd = false_detection_logdensity_at(T, shapes, index, sig, model)
    log_m, feat = match_logdensity(T, shapes, index, sig, model)
    gain = log_m - log_fd
    cand = np.where(gain > 0, feat, -1)
    keep = one_per_feature(cand, np.where(gain > 0, gain, 0.0))
    match = np.where(keep, cand, -1)
    ll = np.where(keep, log_m, log_fd).sum(axis=1)  # misses aside: an upper bound
    in_view, missed = np.full(len(T), -1), np.full(len(T), -1)
    best = -np.inf
    hulls: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
    for k in np.argsort(-ll, kind="stable"):  # a pose NEGLIGIBLE_LOG below the likeliest so far: its misses unasked
        if ll[k] < best - NEGLIGIBLE_LOG:
            break
        view = features_in_view(T[k], keep[k], shapes, index, model, hulls)
        in_view[k] = len(view)
        missed[k] = len(view) - int(np.isin(view, match[k][keep[k]], assume_unique=True).sum())
        ll[k] += missed[k] * np.log(model.miss_probability)
        best = max(best, float(ll[k]))
    return PoseEvidence(ll, match, in_view, missed)


def posterior(loglik: np.ndarray, null_loglik: float) -> tuple[np.ndarray, float]:
    """P(T_k | observations) for poses of log-likelihoods `loglik` (K,) and the hypothesis 'none of them'
    (`null_loglik`), under a uniform prior: (probabilities (K,), P(none))."""
    all_ll = np.append(np.asarray(loglik, dtype=float), null_loglik)
    p = np.exp(all_ll - np.logaddexp.reduce(all_ll))
    return p[:-1], float(p[-1])


def decide(probabilities: np.ndarray, epsilon: float) -> tuple[str, list[int]]:
    """The rule (module doc) on the distinct poses' posteriors: status and the poses it names, most probable first
    (`localized`: the best; `ambiguous`: the fewest poses, two or more, that hold 1 - epsilon; else none)."""
    order = np.argsort(-np.asarray(probabilities), kind="stable")
    if not len(order):
        return "not_localized", []
    if probabilities[order[0]] >= 1.0 - epsilon:
        return "localized", [int(order[0])]
    cum = np.cumsum(np.asarray(probabilities)[order])
    enough = np.flatnonzero(cum >= 1.0 - epsilon)
    if len(enough):
        return "ambiguous", [int(k) for k in order[: enough[0] + 1]]
    return "not_localized", []


@dataclass(frozen=True)
class Posterior:
    """The posterior over the distinct poses of a candidate list: `kept` (indices into it, most probable first),
    their probabilities, log-likelihoods, observations explained and features missed, P('none of them'), and the
    rule's status with the poses it names (indices into the candidate list)."""

    kept: list[int]
    probabilities: np.ndarray
    loglik: np.ndarray
    explained: np.ndarray
    missed: np.ndarray
    none: float
    status: str
    named: list[int]

    def to_json(self, poses_cad_map: list[np.ndarray], min_probability: float = 1e-4, most: int = 8) -> dict:
        """The JSON form: the poses (T_cad_map given per kept pose, in `kept`'s order) with probability at least
        `min_probability` (at most `most`), P(none), and `verdict`: the status the probabilities give (`decide`;
        the registration's answer also asks its minimum support of the best pose)."""
        listed = [{"T_cad_map": np.round(T, 6).tolist(), "probability": round(float(p), 6),
                   "explained": int(e), "missed": int(m), "loglik": round(float(ll), 3)}
                  for T, p, e, m, ll in zip(poses_cad_map, self.probabilities, self.explained, self.missed,
                                            self.loglik, strict=True) if p >= min_probability][:most]
        return {"verdict": self.status, "poses": listed, "none": round(self.none, 6)}


def pose_posterior(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, model: ObservationModel,
                   distinct: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> Posterior:
    """The posterior (module doc) over candidate poses T (K, 4, 4) (map' -> CAD): each pose once (a candidate that
    `distinct(T, anchor (P, 3))`, (K, K) bool, finds alike to a likelier one is the same pose found twice,
    anchor: the likeliest pose's matched observations), then `decide`."""
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    sig = Sigmas.of(shapes, model)
    ev = pose_evidence(T, shapes, index, model, sig)
    null = float(false_detection_logdensity(shapes, sig, model, wall_per_feature_m(index, model)).sum())
    order = np.argsort(-ev.loglik, kind="stable")
    kept: list[int] = []
    if len(order):
        first = ev.match[order[0]] >= 0
        anchor = shapes.centroids[first] if first.any() else shapes.centroids
        pairs = distinct(T, anchor)
        free = np.ones(len(T), dtype=bool)  # not alike to a kept pose
        for k in order:
            if free[k]:
                kept.append(int(k))
                free &= pairs[k]
    p, p_none = posterior(ev.loglik[kept], null)
    status, named = decide(p, model.epsilon)
    return Posterior(kept, p, ev.loglik[kept], (ev.match[kept] >= 0).sum(axis=1), ev.missed[kept], p_none, status,
                     [kept[i] for i in named])
