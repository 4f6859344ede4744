"""What a registration answers, and the helpers both methods share (graph.registration's paper method and
graph.robust): the result type, the corner pairs a refinement fits, the storey most matches lie on."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from macroloc.graph.model_index import ModelIndex
from macroloc.graph.observations import Observation


@dataclass
class RegistrationResult:
    """status: 'localized' | 'ambiguous' | 'not_localized'; T_cad_map maps map-frame points into the CAD frame.

    For 'ambiguous', T_cad_map is the best of the competing poses, `alternatives` holds the others, and `matches`
    is empty (no observation can be tied to one CAD feature).
    """

    status: str
    T_cad_map: np.ndarray | None
    matches: list[tuple[int, str]]
    inliers: int
    storey: str | None
    elapsed_ms: float = 0.0  # the registration alone: no import, file reading or per-building pre-processing
    total_ms: float | None = None  # the whole command (imports, reading files, pre-processing), where one measured
    alternatives: list[np.ndarray] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    candidates: list[tuple[np.ndarray, int]] = field(default_factory=list)  # distinct poses, inliers; best first
    posterior: dict | None = None  # graph.posterior's over the poses found (`Posterior.to_json`), where computed

    def to_json(self) -> dict:
        return {
            "status": self.status,
            "T_cad_map": None if self.T_cad_map is None else np.round(self.T_cad_map, 6).tolist(),
            "matches": [{"observation": i, "feature": fid} for i, fid in self.matches],
            "inliers": self.inliers,
            "storey": self.storey,
            "elapsed_ms": round(self.elapsed_ms, 3),
            **({} if self.total_ms is None else {"total_ms": round(self.total_ms, 3)}),
            "alternatives": [np.round(T, 6).tolist() for T in self.alternatives],
            "diagnostics": self.diagnostics,
            **({} if self.posterior is None else {"posterior": self.posterior}),
        }


def majority_storey(index: ModelIndex, feature_indices: list[int]) -> str | None:
    if not feature_indices:
        return None
    values, counts = np.unique(index.storeys[feature_indices], return_counts=True)
    return str(values[int(np.argmax(counts))])


def corner_correspondences(T: np.ndarray, obs: list[Observation], pairs: list[tuple[int, int]],
                           index: ModelIndex) -> tuple[np.ndarray, np.ndarray]:
    """Point pairs (map, CAD) for a refinement: each observed corner with the nearest corner of its matched CAD
    feature under T (corners come unordered); centroids for centroid-only observations."""
    with_c = [(i, j) for i, j in pairs if obs[i].corners_map is not None]
    without = [(i, j) for i, j in pairs if obs[i].corners_map is None]
    src = [np.array([obs[i].centroid_map for i, _ in without], dtype=float).reshape(-1, 3)]
    dst = [index.centroids[[j for _, j in without]].reshape(-1, 3)]
    if with_c:
        oc = np.stack([np.asarray(obs[i].corners_map) for i, _ in with_c])  # (P, 4, 3) map
        cc = index.corners[[j for _, j in with_c]]  # (P, 4, 3) CAD
        moved = oc @ T[:3, :3].T + T[:3, 3]
        nearest = np.argmin(np.linalg.norm(moved[:, :, None, :] - cc[:, None, :, :], axis=3), axis=2)
        src.append(oc.reshape(-1, 3))
        dst.append(np.take_along_axis(cc, nearest[:, :, None], axis=1).reshape(-1, 3))
    return np.concatenate(src), np.concatenate(dst)
