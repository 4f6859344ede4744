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


def levelled_about(T: np.ndarray, point_child: np.ndarray) -> np.ndarray:
    """T_parent_child (4x4, both frames z up) with its tilt removed as `levelled` removes it, turned about
    `point_child` (3,) instead of the child's origin: that point stays where T put it. Between a building's frame and
    a flight's, a tilt of a degree about an origin 30 m away moves the vehicle half a metre; about the vehicle it
    moves it not at all."""
    out = levelled(T)
    p = np.asarray(point_child, float)
    out[:3, 3] += (T[:3, :3] - out[:3, :3]) @ p
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


def yaw_rigid_fits(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`yaw_rigid_fit` of K point sets at once: src, dst (K, M, 3), weights (K, M) (0 drops a point; each set
    needs a positive total) -> (K, 4, 4)."""
    w = np.asarray(weights, dtype=float)
    w_sum = w.sum(axis=1)[:, None]
    a_bar = (w[..., None] * src).sum(axis=1) / w_sum
    b_bar = (w[..., None] * dst).sum(axis=1) / w_sum
    x, y = src[..., :2] - a_bar[:, None, :2], dst[..., :2] - b_bar[:, None, :2]
    s_cos = (w * (x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1])).sum(axis=1)
    s_sin = (w * (x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0])).sum(axis=1)
    return _stack_T(rot_z(np.arctan2(s_sin, s_cos)), a_bar, b_bar)


def weighted_rigid_fits(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`weighted_rigid_fit` (eqs. 11-17) of K point sets at once: src, dst (K, M, 3), weights (K, M) (0 drops a
    point; each set needs a positive total and 3 points not collinear) -> (K, 4, 4)."""
    w = np.asarray(weights, dtype=float)
    w_sum = w.sum(axis=1)[:, None]
    a_bar = (w[..., None] * src).sum(axis=1) / w_sum  # eq. (12)
    b_bar = (w[..., None] * dst).sum(axis=1) / w_sum
    x, y = src - a_bar[:, None], dst - b_bar[:, None]  # eq. (13)
    S = np.einsum("km,kmi,kmj->kij", w, x, y)  # eq. (14)
    U, _, Vt = np.linalg.svd(S)  # eq. (15)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    sign = np.sign(np.linalg.det(V @ Ut))
    D = np.broadcast_to(np.eye(3), S.shape).copy()
    D[:, 2, 2] = np.where(sign == 0, 1.0, sign)
    return _stack_T(V @ D @ Ut, a_bar, b_bar)  # eqs. (16), (17)


def _stack_T(R: np.ndarray, a_bar: np.ndarray, b_bar: np.ndarray) -> np.ndarray:
    """(K, 4, 4) transforms with rotations R (K, 3, 3) that take the centroids a_bar onto b_bar (K, 3)."""
    T = np.broadcast_to(np.eye(4), (len(R), 4, 4)).copy()
    T[:, :3, :3] = R
    T[:, :3, 3] = b_bar - np.einsum("kij,kj->ki", R, a_bar)
    return T
