"""Candidate poses from the doors seen beyond the sighting range: a resection from two bearings.

Before any door has come within the sighting range (`LocalizerParams.max_range_m`), the doors further away are
already in view, and a stereo pair places each along its line of sight only to a metre at 13 m but across it to a
fraction of a degree. Two of them seen from one camera give two horizontal bearings and two coarse ranges; matched
to two same-type features of the model, the camera lies where the two features are seen that far apart in
bearing (the inscribed angle), at the ranges nearest those measured. The map frame is levelled by gravity, so a
pose is a heading and a translation: one per ordered pair of features whose distance the two ranges allow.

Frames: map = the flight's odometry frame, z up; cad = the model's. Metres, radians.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from macroloc.graph.rigid import rot_z


def resection_candidates(camera_map: np.ndarray, centroids_map: np.ndarray, features_a_cad: np.ndarray,
                         features_b_cad: np.ndarray, range_sigma_m: Callable[[float], float],
                         max_cost: float = 11.8, height_tolerance_m: float = 0.5, range_steps: int = 41,
                         same_features: bool = False) -> np.ndarray:
    """The poses T_cad_map (H, 4, 4) under which two sightings seen from one camera (`camera_map` (3,), their
    centroids `centroids_map` (2, 3)) are two of the model's features, the first any of `features_a_cad` (A, 3),
    the second any of `features_b_cad` (B, 3) (`same_features`: the same list, and a feature is not both).

    For each pair of features, the two horizontal ranges that put them their distance apart along the two
    bearings are the ones nearest the measured ranges in their sigmas (`range_sigma_m(range)`), searched over
    +-3 sigmas of the first in `range_steps`; a pair is dropped where that costs more than `max_cost` (the sum
    of the two squared normalised range errors) or where the features' height difference and the sightings' (at
    those ranges and their measured elevations) differ by more than `height_tolerance_m`."""
    c, r_hat, u, tan_e, sigma = _bearings(camera_map, centroids_map, range_sigma_m)
    A = np.asarray(features_a_cad, float).reshape(-1, 3)
    B = np.asarray(features_b_cad, float).reshape(-1, 3)
    grid_a, grid_b = np.meshgrid(np.arange(len(A)), np.arange(len(B)), indexing="ij")
    ka, kb = grid_a.ravel(), grid_b.ravel()
    if same_features:
        ka, kb = ka[ka != kb], kb[ka != kb]
    Da, Db = A[ka], B[kb]
    d = np.linalg.norm(Db[:, :2] - Da[:, :2], axis=1)  # (N,)
    ra, rb, cost = _range_pairs(d, r_hat, u, sigma, range_steps)
    cost = cost.reshape(len(d), -1)
    best = np.argmin(cost, axis=1)
    ok = cost[np.arange(len(d)), best] <= max_cost
    s_best, root_best = np.divmod(best, 2)
    r_a = ra[s_best][ok]
    r_b = rb[np.arange(len(d)), s_best, root_best][ok]
    Da, Db = Da[ok], Db[ok]
    pa = c[:2] + r_a[:, None] * u[0]
    pb = c[:2] + r_b[:, None] * u[1]
    za = c[2] + r_a * tan_e[0]
    zb = c[2] + r_b * tan_e[1]
    tza, tzb = Da[:, 2] - za, Db[:, 2] - zb
    level = np.abs(tza - tzb) <= height_tolerance_m
    seen, model = pb - pa, Db[:, :2] - Da[:, :2]
    yaw = np.arctan2(model[:, 1], model[:, 0]) - np.arctan2(seen[:, 1], seen[:, 0])
    R = rot_z(yaw)  # (N, 3, 3)
    t_xy = Da[:, :2] - np.einsum("nij,nj->ni", R[:, :2, :2], pa)
    T = np.tile(np.eye(4), (len(yaw), 1, 1))
    T[:, :3, :3] = R
    T[:, :2, 3] = t_xy
    T[:, 2, 3] = 0.5 * (tza + tzb)
    return T[level]


def resection_spread_m(camera_map: np.ndarray, centroids_map: np.ndarray, range_sigma_m: Callable[[float], float],
                       range_steps: int = 401) -> float:
    """How far the camera of a resection from two sightings (`resection_candidates`: camera `camera_map` (3,),
    centroids `centroids_map` (2, 3)) can move with their ranges, metres: the largest distance, in the frame of
    the two features, between the camera positions whose ranges keep the sightings their measured distance apart
    along their bearings and cost within 1 of the least (within one sigma, `range_sigma_m(range)`). Two doors a
    metre or two apart at 10 m pin the camera to a circle, and their ranges only coarsely to a place on it."""
    _, r_hat, u, _, sigma = _bearings(camera_map, centroids_map, range_sigma_m)
    P = np.asarray(centroids_map, float)
    d = float(np.linalg.norm(P[1, :2] - P[0, :2]))
    if d <= 0.0:
        return np.inf
    ra, rb, cost = _range_pairs(np.array([d]), r_hat, u, sigma, range_steps)
    ra, rb, cost = ra[:, None], rb[0], cost[0]  # (S, 1), (S, 2), (S, 2)
    if not np.isfinite(cost).any():
        return np.inf
    x = (ra**2 - rb**2 + d**2) / (2.0 * d)  # the camera with feature a at 0 and b at (d, 0)
    y = np.sqrt(np.clip(ra**2 - x**2, 0.0, None))
    near = cost <= cost.min() + 1.0
    xy = np.column_stack([x[near], y[near]])
    return float(np.max(np.linalg.norm(xy[:, None] - xy[None], axis=2)))


def _bearings(camera_map: np.ndarray, centroids_map: np.ndarray, range_sigma_m: Callable[[float], float]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two sightings from one camera: the camera (3,), their horizontal ranges (2,), unit bearings (2, 2), tangents
    of elevation (2,) and range sigmas (2,)."""
    c = np.asarray(camera_map, float)
    P = np.asarray(centroids_map, float)
    rel = P[:, :2] - c[:2]
    r_hat = np.linalg.norm(rel, axis=1)
    return c, r_hat, rel / r_hat[:, None], (P[:, 2] - c[2]) / r_hat, np.array([range_sigma_m(float(r)) for r in r_hat])


def _range_pairs(d: np.ndarray, r_hat: np.ndarray, u: np.ndarray, sigma: np.ndarray, range_steps: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For features `d` (N,) apart horizontally: the first range swept over +-3 sigmas (S,), the second range that
    puts the two that far apart along the bearings `u` (N, S, 2: both solutions), and the cost of each pair (the
    sum of the two squared normalised range errors; inf where no second range exists)."""
    cos_a = float(u[0] @ u[1])
    sin_a = float(abs(u[0, 0] * u[1, 1] - u[0, 1] * u[1, 0]))
    ra = np.linspace(max(0.3, r_hat[0] - 3 * sigma[0]), r_hat[0] + 3 * sigma[0], range_steps)  # (S,)
    disc = d[:, None] ** 2 - (ra[None] * sin_a) ** 2  # (N, S)
    root = np.sqrt(np.clip(disc, 0.0, None))
    rb = ra[None, :, None] * cos_a + np.stack([-root, root], axis=-1)  # (N, S, 2)
    cost = ((ra[None, :, None] - r_hat[0]) / sigma[0]) ** 2 + ((rb - r_hat[1]) / sigma[1]) ** 2
    return ra, rb, np.where((disc[..., None] >= 0) & (rb > 0.3), cost, np.inf)


def refined_by_bearings(T_cad_map: np.ndarray, cameras_map: np.ndarray, centroids_map: np.ndarray,
                        kinds: np.ndarray, features_cad: dict[str, np.ndarray], bearing_sigma_rad: float,
                        range_sigma_m: Callable[[np.ndarray], np.ndarray], bearing_tolerance_rad: float,
                        iterations: int = 5) -> tuple[np.ndarray, np.ndarray | None]:
    """T_cad_map (4, 4) moved and turned in the horizontal (its height and tilt kept) to fit the far sightings'
    horizontal bearings (`bearing_sigma_rad`) and, loosely, their ranges (`range_sigma_m(range)`): each sighting
    (camera `cameras_map` (K, 3), centroid `centroids_map` (K, 3), type `kinds` (K,)) taken as the same-type
    feature of `features_cad` nearest its bearing within `bearing_tolerance_rad` and 3 range sigmas, chosen
    again each of `iterations` Gauss-Newton steps. Sightings from several keyframes triangulate what one
    camera's pair (`resection_candidates`) left to its coarse ranges. With the pose, the sigmas of its horizontal
    position (along its worst direction) and heading, [m, rad] (None where fewer than 3 sightings are
    explained)."""
    T = np.asarray(T_cad_map, float).copy()
    for _ in range(iterations):
        cams = cameras_map @ T[:3, :3].T + T[:3, 3]
        rays = centroids_map @ T[:3, :3].T + T[:3, 3] - cams
        pivot = cams.mean(axis=0)
        rows, res = [], []
        for kind in np.unique(kinds):
            mine = np.flatnonzero(kinds == kind)
            F = features_cad.get(str(kind))
            if F is None or not len(F):
                continue
            to_f = F[None, :, :2] - cams[mine][:, None, :2]  # (k, F, 2)
            d = np.linalg.norm(to_f, axis=-1)
            r = np.linalg.norm(rays[mine, :2], axis=-1)
            b_seen = np.arctan2(rays[mine, 1], rays[mine, 0])
            off = (np.arctan2(to_f[..., 1], to_f[..., 0]) - b_seen[:, None] + np.pi) % (2 * np.pi) - np.pi
            sig_r = range_sigma_m(r)
            off = np.where((np.abs(off) <= bearing_tolerance_rad) & (np.abs(d - r[:, None]) <= 3 * sig_r[:, None]),
                           np.abs(off), np.inf)
            f = np.argmin(off, axis=1)
            ok = np.isfinite(off[np.arange(len(mine)), f])
            for k, fk in zip(np.flatnonzero(ok), f[ok], strict=True):
                c = cams[mine[k], :2]
                v = F[fk, :2] - c
                dist = float(np.linalg.norm(v))
                b_model = np.arctan2(v[1], v[0])
                e_b = (b_model - b_seen[k] + np.pi) % (2 * np.pi) - np.pi
                # the sighting's bearing as the pose moves by (dx, dy) and turns by dtheta about the pivot: the
                # camera moves with it, so the feature's bearing from it changes by the move across the line
                perp = np.array([-np.sin(b_model), np.cos(b_model)]) / dist
                lever = c - pivot[:2]
                dc_dtheta = np.array([-lever[1], lever[0]])
                # residual: model bearing - seen bearing; the seen one turns with dtheta, the model's moves with
                # the camera
                rows.append(np.r_[-perp, -perp @ dc_dtheta - 1.0] / bearing_sigma_rad)
                res.append(e_b / bearing_sigma_rad)
                u = v / dist
                rows.append(np.r_[-u, -u @ dc_dtheta] / sig_r[k])
                res.append((dist - r[k]) / sig_r[k])
        if len(res) < 6:
            return T, None
        J, e = np.array(rows), np.array(res)
        w = np.minimum(1.0, 2.0 / np.maximum(np.abs(e), 1e-12))  # Huber
        H = (J * w[:, None]).T @ J + 1e-9 * np.eye(3)
        step = -np.linalg.solve(H, (J * w[:, None]).T @ e)
        R = rot_z(step[2])
        delta = np.eye(4)
        delta[:3, :3] = R
        delta[:3, 3] = pivot - R @ pivot + np.r_[step[:2], 0.0]
        T = delta @ T
        if np.abs(step).max() < 1e-5:
            break
    cov = np.linalg.inv(H)
    return T, np.sqrt([np.linalg.eigvalsh(cov[:2, :2]).max(), cov[2, 2]])
