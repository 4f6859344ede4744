"""Trajectory errors with evo's definitions (Grupp, evo: APE and RPE, translation part, no alignment).

APE_i = || trans( P_ref,i^-1 P_est,i ) ||          (evo `ape --pose_relation trans_part`; unaligned here on
                                                      purpose: both trajectories are in the CAD frame)
RPE_ij = || trans( (P_ref,i^-1 P_ref,j)^-1 (P_est,i^-1 P_est,j) ) ||   for pairs j = i + delta
Poses are (N, 4, 4) T_cad_body with matching stamps; results in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ErrorStats:
    rmse: float
    mean: float
    median: float
    max: float
    n: int

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, float)
        if e.size == 0:
            return cls(float("nan"), float("nan"), float("nan"), float("nan"), 0)
        return cls(float(np.sqrt(np.mean(e**2))), float(e.mean()), float(np.median(e)), float(e.max()), int(e.size))


def _relative(P_a: np.ndarray, P_b: np.ndarray) -> np.ndarray:
    """(N, 4, 4) P_a^-1 P_b for rigid transforms."""
    R_t = np.transpose(P_a[:, :3, :3], (0, 2, 1))
    out = np.tile(np.eye(4), (len(P_a), 1, 1))
    out[:, :3, :3] = R_t @ P_b[:, :3, :3]
    out[:, :3, 3] = np.einsum("nij,nj->ni", R_t, P_b[:, :3, 3] - P_a[:, :3, 3])
    return out


def ape_translation(P_ref: np.ndarray, P_est: np.ndarray) -> np.ndarray:
    """(N,) APE translation part per pose, metres (equals the distance between the two positions)."""
    return np.linalg.norm(_relative(P_ref, P_est)[:, :3, 3], axis=1)


def rpe_translation(P_ref: np.ndarray, P_est: np.ndarray, delta: int = 1) -> np.ndarray:
    """(N - delta,) RPE translation part for pose pairs `delta` apart, metres."""
    if len(P_ref) <= delta:
        return np.zeros(0)
    rel_ref = _relative(P_ref[:-delta], P_ref[delta:])
    rel_est = _relative(P_est[:-delta], P_est[delta:])
    return np.linalg.norm(_relative(rel_ref, rel_est)[:, :3, 3], axis=1)
