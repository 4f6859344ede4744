"""A building's near-self-maps: yaw + translation maps of the CAD frame that put many doors/windows onto alike ones.

A pose T_cad_map and S @ T_cad_map explain the same observations whenever S maps the features those
observations sit on onto features of the same type: a storey turned 180° onto itself, storeys that repeat,
a regular row of windows. Such S are the rivals that the registration must always score (`graph.robust`).

Candidates come from ordered pairs (a, b), a != b, of same-type features with a horizontal wall normal (a among
at most `max_sources` of its type): the yaw
that turns a's normal onto b's (and that + 180°, the normal's sign being a convention) and the translation that
puts a's centroid onto b's. Candidates are pooled in bins of `yaw_bin_deg` x `shift_bin_m`; a bin's vote count
is how many feature pairs it maps (within the bin), and the self-maps kept are the bins with at least
`min_votes`, the identity excluded. Frames: CAD, metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.graph.rigid import rot_z

SELF_MAPS_VERSION = 2  # bump when the computation changes: the disk cache is keyed by it


@dataclass(frozen=True)
class SelfMapParams:
    yaw_bin_deg: float = 3.0  # candidates pooled per bin: an alike feature's normal is known to a degree or so
    shift_bin_m: float = 0.25  # ... and its centroid to centimetres; a bin this wide catches one self-map
    min_votes: int = 2  # a self-map mapping a single pair maps every pair of alike features: no information
    max_maps: int = 4000  # the most voted kept (the table below is maps x features)
    max_sources: int = 400  # per type, at most this many features (evenly drawn) map onto all the others: a
    # self-map of a large building moves many features, so a subset still votes for it (memory stays bounded)
    landing_m: float = 0.30  # a feature is mapped onto an alike one when it lands this close to it
    max_horizontal_normal_z: float = 0.5  # |normal_z| below this: a wall feature (skylights generate nothing)


@dataclass(frozen=True)
class SelfMaps:
    """M self-maps: rotation about +z by yaw_rad (M,), then shift_m (M, 3); votes (M,), most voted first;
    lands (M, N) bool: self-map m puts feature n within landing_m of a feature of the same type."""

    yaw_rad: np.ndarray
    shift_m: np.ndarray
    votes: np.ndarray
    lands: np.ndarray

    def transforms(self) -> np.ndarray:
        """(M, 4, 4) T_cad_cad."""
        T = np.zeros((len(self.yaw_rad), 4, 4))
        T[:, :3, :3] = rot_z(self.yaw_rad)
        T[:, 3, 3] = 1.0
        T[:, :3, 3] = self.shift_m
        return T


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def building_self_maps(centroids_cad: np.ndarray, normals_cad: np.ndarray, type_codes: np.ndarray,
                       params: SelfMapParams | None = None) -> SelfMaps:
    """The self-maps of features with centroids (N, 3), unit normals (N, 3) and integer types (N,) (see module doc)."""
    params = params or SelfMapParams()
    wall = np.abs(normals_cad[:, 2]) < params.max_horizontal_normal_z
    heading = np.arctan2(normals_cad[:, 1], normals_cad[:, 0])
    a_all, b_all = [], []
    for code in np.unique(type_codes[wall]):
        idx = np.flatnonzero(wall & (type_codes == code))
        sources = idx[:: max(1, int(np.ceil(len(idx) / params.max_sources)))]
        a, b = np.meshgrid(sources, idx, indexing="ij")
        off = a != b
        a_all.append(a[off])
        b_all.append(b[off])
    empty = SelfMaps(np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=int), np.zeros((0, len(centroids_cad)), bool))
    if not a_all or not sum(len(a) for a in a_all):
        return empty
    a, b = np.concatenate(a_all), np.concatenate(b_all)
    base = heading[b] - heading[a]
    yaw = _wrap(np.concatenate([base, base + np.pi]))
    a, b = np.concatenate([a, a]), np.concatenate([b, b])
    c, s = np.cos(yaw), np.sin(yaw)
    ca, cb = centroids_cad[a], centroids_cad[b]
    shift = np.stack([cb[:, 0] - (c * ca[:, 0] - s * ca[:, 1]), cb[:, 1] - (s * ca[:, 0] + c * ca[:, 1]),
                      cb[:, 2] - ca[:, 2]], axis=1)
    yaw_bins = int(round(360.0 / params.yaw_bin_deg))
    keys = np.column_stack([np.round(yaw / (2.0 * np.pi) * yaw_bins).astype(np.int64) % yaw_bins,
                            np.round(shift / params.shift_bin_m).astype(np.int64)])
    _, inverse, votes = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    keep = np.flatnonzero(votes >= params.min_votes)
    if not len(keep):
        return empty
    # the bin's mean (yaw averaged on the circle)
    n = votes[keep].astype(float)
    where = np.isin(inverse, keep)
    slot = np.searchsorted(keep, inverse[where])
    sum_c = np.bincount(slot, np.cos(yaw[where]), len(keep))
    sum_s = np.bincount(slot, np.sin(yaw[where]), len(keep))
    mean_shift = np.stack([np.bincount(slot, shift[where, k], len(keep)) for k in range(3)], axis=1) / n[:, None]
    mean_yaw = np.arctan2(sum_s, sum_c)
    identity = (np.abs(np.degrees(mean_yaw)) < params.yaw_bin_deg) & (np.linalg.norm(mean_shift, axis=1)
                                                                      < params.shift_bin_m)
    order = np.argsort(-votes[keep], kind="stable")
    order = order[~identity[order]][: params.max_maps]
    yaw_m, shift_m = mean_yaw[order], mean_shift[order]
    return SelfMaps(yaw_m, shift_m, votes[keep][order], _landings(yaw_m, shift_m, centroids_cad, type_codes, params))


def _landings(yaw: np.ndarray, shift: np.ndarray, centroids: np.ndarray, type_codes: np.ndarray,
              params: SelfMapParams) -> np.ndarray:
    """(M, N) bool: self-map m puts feature n within landing_m of a feature of its type."""
    from scipy.spatial import cKDTree

    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    moved = np.stack([c * centroids[:, 0] - s * centroids[:, 1] + shift[:, 0:1],
                      s * centroids[:, 0] + c * centroids[:, 1] + shift[:, 1:2],
                      centroids[:, 2] + shift[:, 2:3]], axis=-1)  # (M, N, 3)
    lands = np.zeros(moved.shape[:2], dtype=bool)
    for code in np.unique(type_codes):
        cols = np.flatnonzero(type_codes == code)
        d, _ = cKDTree(centroids[cols]).query(moved[:, cols].reshape(-1, 3), distance_upper_bound=params.landing_m)
        lands[:, cols] = np.isfinite(d).reshape(len(yaw), len(cols))
    return lands
