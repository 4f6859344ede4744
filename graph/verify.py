"""Verification of a pose by what a rectangle is: position, wall normal, width and height, under a noise model.

A match of an observation to a CAD feature supports a pose only if, under the pose, the observation's centroid,
wall normal (up to its sign, a convention), and its two side lengths all agree with the feature's within
`gate_sigmas` standard deviations of the noise model; a match to a feature of the other type (detectors confuse
doors and windows) counts `cross_type_weight` as much. Each observation is either a detection of a CAD feature
(probability 1 - eps) or a false detection (eps), uniform in space; its log-likelihood ratio against 'a false
detection' is log(1 + (1 - eps) / eps * exp(x)), where x is the Gaussian log-density ratio of its residuals
relative to the gate (x = sum over residuals r of (g^2 - (r / sigma)^2) / 2, the centroid's 3-D residual
against its chi-square gate; zero where every residual is at its gate). An observation that matches nothing
adds 0: false detections and missed features cost nothing by themselves, so a pose is judged by the evidence
it explains, never by counting alone.

Noise model: the corner noise sigma_c per axis is the larger of what the observed rectangles show by themselves
(a parallelogram's closure p0 - p1 - p3 + p2 is the sum of four corners' noise: variance 4 sigma_c^2 per axis)
and what the best pose's RMS centroid residual s (3-D, metres) shows (sigma_c = 2 s / sqrt 3 per axis: a centroid
averages four corners); s is taken as the larger of the two as well; a side's length is known to sigma_c, and
the wall normal of a rectangle with shorter side l to sigma_c / l radians; floors keep the model from being
stricter than the CAD model's own accuracy.
Frames: observations in map', features in CAD (T: map' -> CAD), metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.graph.model_index import ModelIndex
from macroloc.graph.observations import Observation
from macroloc.graph.params import VerifyParams
from macroloc.graph.rectangle import unordered_edges


@dataclass(frozen=True)
class ObservedShapes:
    """Per observation (N), map': centroids (N, 3), type codes (N,), whether it has corners (N,), the unit edge
    directions a, b (N, 3) and lengths (N,) of its rectangle (zero where it has none), its unit normal (N, 3)."""

    centroids: np.ndarray
    types: np.ndarray
    has_rect: np.ndarray
    edge_a: np.ndarray
    edge_b: np.ndarray
    len_a: np.ndarray
    len_b: np.ndarray
    normals: np.ndarray
    corner_sigma_m: float  # from the rectangles' closure (0 without rectangles)


def observed_shapes(obs: list[Observation], types: np.ndarray) -> ObservedShapes:
    """The shapes of observations (map' frame) with integer type codes (N,); rectangles as in
    `graph.rectangle.unordered_edges` (corners in any order), all at once."""
    n = len(obs)
    a, b, la, lb = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros(n)
    has = np.array([o.corners_map is not None for o in obs], dtype=bool)
    centroids = np.array([o.centroid_map for o in obs], dtype=float).reshape(-1, 3)
    sigma_c = 0.0
    rows = np.flatnonzero(has)
    if len(rows):
        p = np.stack([np.asarray(obs[i].corners_map, dtype=float) for i in rows])  # (R, 4, 3)
        a[rows], b[rows], la[rows], lb[rows], closure = unordered_edges(p)
        # |closure|^2 / (4 sigma_c^2) is chi-square with 3 degrees of freedom (median 2.366): the median is robust
        # to the odd rectangle that is no parallelogram
        sigma_c = float(np.sqrt(np.median(np.sum(closure**2, axis=1)) / (4.0 * 2.366)))
    return ObservedShapes(centroids, types, has, a, b, la, lb, np.cross(a, b), sigma_c)


@dataclass(frozen=True)
class Noise:
    """The noise model: centroid RMS s_m (3-D), corner sigma per axis, floors (see module doc)."""

    centroid_rms_m: float
    corner_sigma_m: float
    size_sigma_m: float

    @classmethod
    def from_rms(cls, centroid_rms_m: float, params: VerifyParams, corner_sigma_m: float = 0.0) -> Noise:
        """From the RMS centroid residual (3-D) and the corner sigma the rectangles show (0: unknown)."""
        corner = max(2.0 * centroid_rms_m / np.sqrt(3.0), corner_sigma_m)
        return cls(max(centroid_rms_m, corner * np.sqrt(3.0) / 2.0), corner, max(corner, params.size_floor_m))

    def position_gate_m(self, params: VerifyParams) -> float:
        """The largest centroid distance, metres, of a match: sqrt(chi2) per-axis sigmas."""
        return float(np.sqrt(params.position_gate_chi2) * self.centroid_rms_m / np.sqrt(3.0))


@dataclass(frozen=True)
class Verdict:
    """Per observation: its log-likelihood ratio term (N,), its CAD feature (N,; -1: none) and whether it is an
    inlier (N,; one observation per CAD feature)."""

    term: np.ndarray
    match: np.ndarray
    inlier: np.ndarray

    @property
    def loglik(self) -> float:
        return float(self.term.sum())

    @property
    def n_inliers(self) -> int:
        return int(self.inlier.sum())


def verify(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, noise: Noise, tau_m: float,
           cross_type_weight: float, params: VerifyParams) -> Verdict:
    """Verdict of the pose T (map' -> CAD, 4x4) on the observations (see module doc); `tau_m` bounds the centroid
    distance of a match whatever the noise model."""
    return verify_all(np.asarray(T, dtype=float)[None], shapes, index, noise, tau_m, cross_type_weight, params)[0]


def verify_all(T: np.ndarray, shapes: ObservedShapes, index: ModelIndex, noise: Noise, tau_m: float,
               cross_type_weight: float, params: VerifyParams) -> list[Verdict]:
    """`verify` of each pose T (K, 4, 4) at once: each verdict is the pose's own (vectorised over poses)."""
    n, n_poses = len(shapes.centroids), len(T)
    if n == 0 or len(index.features) == 0:
        return [Verdict(np.zeros(n), np.full(n, -1), np.zeros(n, dtype=bool)) for _ in range(n_poses)]
    R, t = T[:, :3, :3], T[:, :3, 3]
    Rt = np.swapaxes(R, 1, 2)
    moved = np.matmul(shapes.centroids[None], Rt) + t[:, None, :]  # (K, N, 3) CAD
    g = params.gate_sigmas
    gate_m = min(tau_m, noise.position_gate_m(params))
    k = min(params.neighbours, len(index.features))
    d, j = index.tree_all.query(moved.reshape(-1, 3), k=k, distance_upper_bound=gate_m)
    d, j = d.reshape(n_poses, n, k), j.reshape(n_poses, n, k)
    found = np.isfinite(d)
    jj = np.where(found, j, 0)
    sigma_axis = noise.centroid_rms_m / np.sqrt(3.0)  # the 3-D RMS is sqrt(3) times the per-axis sigma
    x = (params.position_gate_chi2 - (np.where(found, d, 0.0) / sigma_axis) ** 2) / 2.0
    ok = found.copy()
    # wall normal, up to its sign
    n_obs = np.matmul(shapes.normals[None], Rt)  # (K, N, 3) CAD
    cos = np.abs(np.einsum("pnc,pnkc->pnk", n_obs, index.normals[jj]))
    theta = np.arccos(np.clip(cos, -1.0, 1.0))
    short = np.maximum(np.minimum(shapes.len_a, shapes.len_b), 1e-3)
    sigma_n = np.maximum(noise.corner_sigma_m / short, np.radians(params.normal_floor_deg))[None, :, None]
    # side lengths: the observed edge most parallel to the feature's u edge is its width
    a_cad, b_cad = np.matmul(shapes.edge_a[None], Rt), np.matmul(shapes.edge_b[None], Rt)
    u = index.edge_u[jj]
    a_is_u = np.abs(np.einsum("pnc,pnkc->pnk", a_cad, u)) >= np.abs(np.einsum("pnc,pnkc->pnk", b_cad, u))
    lu, lv = index.len_u[jj], index.len_v[jj]
    la, lb = shapes.len_a[None, :, None], shapes.len_b[None, :, None]
    du = np.where(a_is_u, la - lu, lb - lu)
    dv = np.where(a_is_u, lb - lv, la - lv)
    r_n, r_u, r_v = theta / sigma_n, du / noise.size_sigma_m, dv / noise.size_sigma_m
    rect = shapes.has_rect[None, :, None]
    ok &= ~rect | ((r_n < g) & (np.abs(r_u) < g) & (np.abs(r_v) < g))
    x = x + np.where(rect, (3.0 * g * g - r_n**2 - r_u**2 - r_v**2) / 2.0, 0.0)
    eps = params.false_detection_rate
    same = index.type_codes[jj] == shapes.types[None, :, None]
    weight = np.where(same, 1.0, cross_type_weight)
    term_k = np.where(ok, weight * np.logaddexp(0.0, np.log((1.0 - eps) / eps) + x), 0.0)
    best = np.argmax(term_k, axis=2)[..., None]
    term = np.take_along_axis(term_k, best, axis=2)[..., 0]
    match = np.where(term > 0, np.take_along_axis(jj, best, axis=2)[..., 0], -1)
    inlier = one_per_feature(match, term)
    term = np.where(inlier, term, 0.0)
    match = np.where(inlier, match, -1)
    return [Verdict(term[p], match[p], inlier[p]) for p in range(n_poses)]


def one_per_feature(match: np.ndarray, worth: np.ndarray) -> np.ndarray:
    """Per pose (rows of match / worth, (K, N)): which observations keep their CAD feature `match` (>= 0) when
    each feature keeps one observation: the one of greatest `worth`, the first among equals."""
    keep = np.zeros(match.shape, dtype=bool)
    rows, cols = np.nonzero(match >= 0)
    if len(rows) == 0:
        return keep
    m = match[rows, cols]
    order = np.lexsort((cols, -worth[rows, cols], m, rows))
    rows, cols, m = rows[order], cols[order], m[order]
    first = np.ones(len(rows), dtype=bool)
    first[1:] = (rows[1:] != rows[:-1]) | (m[1:] != m[:-1])
    keep[rows[first], cols[first]] = True
    return keep


def full_term(has_rect: bool, params: VerifyParams) -> float:
    """The term of one observation (a rectangle, or a centroid only) explained with zero residuals, same type."""
    x = params.position_gate_chi2 / 2.0 + (3 * params.gate_sigmas**2 / 2.0 if has_rect else 0.0)
    eps = params.false_detection_rate
    return float(np.logaddexp(0.0, np.log((1.0 - eps) / eps) + x))


def chance_term(has_rect: bool, params: VerifyParams) -> float:
    """The mean term of a false detection that lands on a feature by chance: its centroid uniform in the gate's
    ball (so its squared residual is 3/5 of the gate's), and, a rectangle, its normal and sides uniform within
    their gates (each squared residual a third of the gate's); same type. Less than a true match's: a chance
    landing rarely sits at the centre of the gate."""
    x = params.position_gate_chi2 / 2.0 * (1.0 - 3.0 / 5.0)
    if has_rect:
        x += 3 * params.gate_sigmas**2 / 2.0 * (1.0 - 1.0 / 3.0)
    eps = params.false_detection_rate
    return float(np.logaddexp(0.0, np.log((1.0 - eps) / eps) + x))
