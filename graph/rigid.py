"""Rigid transforms: the paper's weighted SVD fit (eqs. 11–17), a gravity-constrained (yaw) fit, helpers.

Convention: `T_a_b` (4x4) maps points from frame b into frame a: p_a = R p_b + t.
"""

from __future__ import annotations

import numpy as np

from macroloc.common.geometry import rotation_angle_rad  # noqa: F401 - re-exported

Z_UP = np.array([0.0, 0.0, 1.0])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Transform (..., 3) points by the 4x4 T."""
    return np.asarray(points) @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(rotation_angle_rad(R)))


def weighted_rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """T_dst_src minimising sum_i w_i |R a_i + t - b_i|^2 (eq. 11) by weighted SVD.

    eq. (12): weighted centroids; eq. (13): centred vectors; eq. (14): S = X W Y^T; eq. (15): S = U s V^T;
    eq. (16): R = V U^T — with the reflection case handled (R = V diag(1, 1, det(V U^T)) U^T, Umeyama);
    eq. (17): t = b_bar - R a_bar.  src, dst: (N, 3), N >= 3 and not collinear.
    """
    a = np.asarray(src, dtype=float).reshape(-1, 3)
    b = np.asarray(dst, dtype=float).reshape(-1, 3)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    w_sum = w.sum()
    a_bar = (w[:, None] * a).sum(axis=0) / w_sum  # eq. (12)
    b_bar = (w[:, None] * b).sum(axis=0) / w_sum
    X = (a - a_bar).T  # eq. (13), 3 x N
    Y = (b - b_bar).T
    S = X @ np.diag(w) @ Y.T  # eq. (14)
    U, _, Vt = np.linalg.svd(S)  # eq. (15)
    V = Vt.T
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(V @ U.T)) or 1.0])
    R = V @ D @ U.T  # eq. (16), reflection-safe
    return make_T(R, b_bar - R @ a_bar)  # eq. (17)


def yaw_rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """T_dst_src restricted to a rotation about +z and a translation (both frames gravity-aligned, 4 DoF)."""
    a = np.asarray(src, dtype=float).reshape(-1, 3)
    b = np.asarray(dst, dtype=float).reshape(-1, 3)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    a_bar = (w[:, None] * a).sum(axis=0) / w.sum()
    b_bar = (w[:, None] * b).sum(axis=0) / w.sum()
    x, y = a[:, :2] - a_bar[:2], b[:, :2] - b_bar[:2]
    s_cos = float((w * (x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1])).sum())
    s_sin = float((w * (x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0])).sum())
    R = rot_z(np.arctan2(s_sin, s_cos))
    return make_T(R, b_bar - R @ a_bar)


def rot_z(yaw: float | np.ndarray) -> np.ndarray:
    """The rotation about z by `yaw` (rad): (3, 3), or (..., 3, 3) for an array of angles."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((*np.shape(yaw), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def levelled(T: np.ndarray, up_child: np.ndarray | None = None) -> np.ndarray:
    """T_parent_child (4x4, the parent z up) turned by the smallest rotation that takes the child's up
    (`up_child`, unit or not; default its z axis) to z, keeping its heading and its translation: between two
    z-up frames, its tilt removed; with a measured up (gravity), the child's attitude made that up's."""
    out = np.array(T, dtype=float)
    up = out[:3, 2] if up_child is None else out[:3, :3] @ np.asarray(up_child, float)
    out[:3, :3] = rotation_aligning(up, np.array([0.0, 0.0, 1.0])) @ out[:3, :3]
    return out


def rotation_aligning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R a_hat = b_hat (Rodrigues), for unit or non-unit 3-vectors."""
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)
    b = np.asarray(b, dtype=float) / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = float(np.linalg.norm(v)), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0])  # opposite: turn by pi about any axis perpendicular to a
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = v / s  # axis-angle form (Rodrigues), well conditioned also near pi, unlike I + K + K^2 / (1 + c)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)
