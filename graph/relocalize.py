"""Aligning observed rectangle landmarks to known rectangles in the CAD frame (gravity-aware, 4 DOF).

One matched vertical door or window fixes T_cad_map up to the flip of its normal (both frames are
gravity-aligned), so every (observed, known, flip) triple of the same type is a hypothesis; each is scored
by how many observed centroids land within `inlier_m` of a known centroid of the same type with a
compatible wall normal. A second, clearly different hypothesis with nearly as much support makes the answer
`ambiguous` (a symmetric building), never a guess.

This is what re-localizes a new flight into a saved map (its known rectangles are the landmarks that
flight linked to the model), and a stand-in registration against a whole model while
`graph.registration` is absent.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from macroloc.graph.landmarks import FLIP_ABOUT_UP
from macroloc.graph.rigid import rotation_angle_rad

NORMAL_COS_MIN = np.cos(np.radians(35.0))  # |n_obs . n_known| above this: same wall direction
CHUNK = 256  # hypotheses scored at once (memory: CHUNK x observed x known x 3 floats)


@dataclass(frozen=True)
class KnownRect:
    """A rectangle known in the CAD frame: id, type, T_cad_rect (4x4)."""

    id: str
    type: str
    T_cad_rect: np.ndarray


@dataclass(frozen=True)
class ObservedRect:
    """A landmark of this flight: its key j, type, T_map_rect (4x4), and whether every sighting of it was cut by
    the image border (sideways, vertically): its size along such an axis is then only a lower bound."""

    key: int
    type: str
    T_map_rect: np.ndarray
    cut: tuple[bool, bool] = (False, False)


@dataclass
class Alignment:
    status: str  # "localized" | "ambiguous" | "not_localized"
    T_cad_map: np.ndarray | None
    matches: list[tuple[int, str]] = field(default_factory=list)  # (landmark key, known id)
    inliers: int = 0
    # distinct poses that explain the landmarks (T_cad_map, landmarks explained), best first; the localizer's
    # surface check chooses among them (graph.surfaces)
    candidates: list[tuple[np.ndarray, int]] = field(default_factory=list)
    # where the surface check confirms none of the candidates: the next registrar's answer, asked only then
    # (graph.registrar.FirstOfRegistrar: a saved map's few candidates first, the whole model's after)
    fallback: Callable[[], Alignment] | None = None
    # the fallback's candidates would hold these (it cannot tell apart what these leave apart)
    fallback_holds_these: bool = False


def align_rectangles(observed: list[ObservedRect], known: list[KnownRect], inlier_m: float = 0.35,
                     min_inliers: int = 3, ambiguity_ratio: float = 0.8, max_seeds: int = 12,
                     candidates_from: int | None = None, max_candidates: int = 64) -> Alignment:
    """Best gravity-aligned T_cad_map explaining `observed` by `known`, with its matches; see module doc.
    `candidates_from` (<= min_inliers; None: min_inliers): from this many observed rectangles on, an answer
    short of 'localized' carries as candidates every distinct hypothesis explaining as many of them as the
    best (at most `max_candidates`), for other evidence (the walls) to choose among."""
    fewest = min_inliers if candidates_from is None else min(candidates_from, min_inliers)
    if len(observed) < fewest or not known:
        return Alignment("not_localized", None)
    known_xyz = np.array([k.T_cad_rect[:3, 3] for k in known])
    known_n = np.array([k.T_cad_rect[:3, 1] for k in known])
    known_type = np.array([k.type for k in known])
    obs_T = np.array([o.T_map_rect for o in observed])
    obs_type = np.array([o.type for o in observed])
    same_type = obs_type[:, None] == known_type[None, :]  # (O, K)
    hyps = []
    for o in range(min(max_seeds, len(observed))):
        for k in np.flatnonzero(same_type[o]):
            for flip in (np.eye(4), FLIP_ABOUT_UP):
                hyps.append(known[k].T_cad_rect @ flip @ np.linalg.inv(obs_T[o]))
    if not hyps:
        return Alignment("not_localized", None)
    H = np.array(hyps)  # (N, 4, 4) candidate T_cad_map
    best_k = np.zeros((len(H), len(observed)), dtype=int)
    hit = np.zeros((len(H), len(observed)), dtype=bool)
    for lo in range(0, len(H), CHUNK):
        best_k[lo:lo + CHUNK], hit[lo:lo + CHUNK] = _nearest_known(H[lo:lo + CHUNK], obs_T, same_type, known_xyz,
                                                                  known_n, inlier_m)
    support = np.array([len(set(best_k[n][hit[n]].tolist())) for n in range(len(H))])
    order = np.argsort(-support, kind="stable")
    best = int(order[0])
    if support[best] < fewest:
        return Alignment("not_localized", None, inliers=int(support[best]))
    candidates = [] if candidates_from is None else distinct_poses(H, order[support[order] == support[best]],
                                                                   max_candidates)
    if support[best] < min_inliers:
        return Alignment("ambiguous" if candidates else "not_localized", None, inliers=int(support[best]),
                         candidates=[(T, int(support[best])) for T in candidates])
    matches = [(observed[o].key, known[int(best_k[best, o])].id) for o in np.flatnonzero(hit[best])]
    for n in order[1:]:
        if support[n] < ambiguity_ratio * support[best]:
            break
        if _differs(H[n], H[best]):
            return Alignment("ambiguous", H[best], matches, int(support[best]),
                             [(T, int(support[best])) for T in candidates])
    return Alignment("localized", H[best], matches, int(support[best]))


def _nearest_known(H: np.ndarray, obs_T: np.ndarray, same_type: np.ndarray, known_xyz: np.ndarray,
                   known_n: np.ndarray, inlier_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For hypotheses H (N, 4, 4): index of the compatible known rectangle nearest to each observed one
    (N, O), and whether it lies within `inlier_m` (N, O)."""
    xyz = np.einsum("nij,oj->noi", H[:, :3, :3], obs_T[:, :3, 3]) + H[:, None, :3, 3]  # (N, O, 3) in cad
    nrm = np.einsum("nij,oj->noi", H[:, :3, :3], obs_T[:, :3, 1])
    dist = np.linalg.norm(xyz[:, :, None, :] - known_xyz[None, None], axis=3)  # (N, O, K)
    ok = (dist < inlier_m) & same_type[None] & (np.abs(nrm @ known_n.T) > NORMAL_COS_MIN)
    dist = np.where(ok, dist, np.inf)
    return dist.argmin(axis=2), np.isfinite(dist.min(axis=2))


def distinct_poses(H: np.ndarray, order: Sequence[int] | np.ndarray, limit: int | None = None, trans_m: float = 1.0,
                   angle_rad: float = np.radians(15.0)) -> list[np.ndarray]:
    """The poses H[order] (N, 4, 4), best first, less those that do not differ from one kept before by `trans_m`
    or `angle_rad` (`_differs`); at most `limit` of them."""
    kept: list[np.ndarray] = []
    for n in order:
        if limit is not None and len(kept) >= limit:
            break
        if all(_differs(H[n], T, trans_m, angle_rad) for T in kept):
            kept.append(H[n])
    return kept


def _differs(T_a: np.ndarray, T_b: np.ndarray, trans_m: float = 1.0, angle_rad: float = np.radians(15.0)) -> bool:
    D = np.linalg.inv(T_a) @ T_b
    angle = rotation_angle_rad(D[:3, :3])
    return bool(np.linalg.norm(D[:3, 3]) > trans_m or angle > angle_rad)
