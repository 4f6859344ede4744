"""Frame conventions at the vehicle's edge: ROS's ENU/FLU (REP-103) and PX4's NED/FRD, and GTSAM's covariance order.

World frames: ENU (x east, y north, z up) and NED (x north, y east, z down); `p_ned = R_NED_ENU @ p_enu`.
Body frames: FLU (x forward, y left, z up: macroloc's `body`, REP-103's `base_link`) and FRD (x forward, y right,
z down: PX4's body); `v_flu = R_FLU_FRD @ v_frd`. Both swaps are their own inverses. Orientations are rotation
matrices `R_world_body` or unit quaternions `quat_wxyz` (Hamilton, body to world, w >= 0 on output).

Covariance: GTSAM's Pose3 covariance is [rot(3); trans(3)] in the body's tangent space (a perturbation
T * Exp(xi)); ROS's PoseWithCovariance is [x, y, z, rot x, rot y, rot z] about the axes of the header's (world)
frame, m^2 and rad^2. To first order, a body perturbation (w_b, v_b) moves the position by R v_b and turns the
attitude by R w_b in the world frame, so cov_ros = J cov_gtsam J^T with J = [[0, R], [R, 0]].
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

R_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # swap x/y, flip z
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])  # flip y and z


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (3, 3) (Shepperd's method: from the largest of
    w, x, y, z; plain numpy, ~10x faster than scipy's per single rotation)."""
    m = np.asarray(R, float)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    k = int(np.argmax([trace, m[0, 0], m[1, 1], m[2, 2]]))
    if k == 0:
        r = np.sqrt(1.0 + trace) * 2.0  # 4 w
        q = np.array([0.25 * r, (m[2, 1] - m[1, 2]) / r, (m[0, 2] - m[2, 0]) / r, (m[1, 0] - m[0, 1]) / r])
    elif k == 1:
        r = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0  # 4 x
        q = np.array([(m[2, 1] - m[1, 2]) / r, 0.25 * r, (m[0, 1] + m[1, 0]) / r, (m[0, 2] + m[2, 0]) / r])
    elif k == 2:
        r = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0  # 4 y
        q = np.array([(m[0, 2] - m[2, 0]) / r, (m[0, 1] + m[1, 0]) / r, 0.25 * r, (m[1, 2] + m[2, 1]) / r])
    else:
        r = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0  # 4 z
        q = np.array([(m[1, 0] - m[0, 1]) / r, (m[0, 2] + m[2, 0]) / r, (m[1, 2] + m[2, 1]) / r, 0.25 * r])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def matrix_from_quat_wxyz(quat_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(quat_wxyz, float)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def ned_from_enu(p_enu: np.ndarray) -> np.ndarray:
    """Points (..., 3) from ENU to NED (and back: the swap is its own inverse), metres."""
    return np.asarray(p_enu, float) @ R_NED_ENU.T


enu_from_ned = ned_from_enu


def R_ned_frd_from_R_enu_flu(R_enu_flu: np.ndarray) -> np.ndarray:
    """An attitude (body FLU in world ENU) as PX4's (body FRD in world NED)."""
    return R_NED_ENU @ np.asarray(R_enu_flu, float) @ R_FLU_FRD


def R_enu_flu_from_R_ned_frd(R_ned_frd: np.ndarray) -> np.ndarray:
    return R_NED_ENU.T @ np.asarray(R_ned_frd, float) @ R_FLU_FRD.T


def T_ned_frd_from_T_enu_flu(T_enu_flu: np.ndarray) -> np.ndarray:
    """A 4x4 pose T_enu_flu as T_ned_frd (position in NED, metres; attitude FRD in NED)."""
    T = np.eye(4)
    T[:3, :3] = R_ned_frd_from_R_enu_flu(T_enu_flu[:3, :3])
    T[:3, 3] = ned_from_enu(T_enu_flu[:3, 3])
    return T


def T_enu_flu_from_T_ned_frd(T_ned_frd: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R_enu_flu_from_R_ned_frd(T_ned_frd[:3, :3])
    T[:3, 3] = enu_from_ned(T_ned_frd[:3, 3])
    return T


def yaw_ned_from_yaw_enu(yaw_enu_rad: float) -> float:
    """A heading about ENU's +z from east (counter-clockwise) as PX4's yaw about NED's +z (down) from north
    (clockwise), wrapped to (-pi, pi]: yaw_ned = pi/2 - yaw_enu."""
    return float(np.angle(np.exp(1j * (np.pi / 2 - yaw_enu_rad))))


def cov_ros_from_gtsam(cov_rot_trans_body: np.ndarray, R_world_body: np.ndarray) -> np.ndarray:
    """6x6 covariance from GTSAM's [rot; trans] body tangent order to ROS's [x y z; rot x y z] in the world frame
    (module doc), m^2 / rad^2."""
    R = np.asarray(R_world_body, float)
    J = np.zeros((6, 6))
    J[:3, 3:] = R  # position <- body translation
    J[3:, :3] = R  # world rotation <- body rotation
    return J @ np.asarray(cov_rot_trans_body, float) @ J.T

