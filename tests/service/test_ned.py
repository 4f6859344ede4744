"""ENU/FLU <-> NED/FRD and the covariance order (service.ned): round trips and known cases on random poses."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from macroloc.service.ned import (
    R_ned_frd_from_R_enu_flu,
    T_enu_flu_from_T_ned_frd,
    T_ned_frd_from_T_enu_flu,
    cov_ros_from_gtsam,
    enu_from_ned,
    matrix_from_quat_wxyz,
    ned_from_enu,
    quat_wxyz_from_matrix,
    yaw_ned_from_yaw_enu,
)

finite = st.floats(-100, 100, allow_nan=False)
quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1)


def _T(q: list[float], t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = t
    return T


@settings(max_examples=200, deadline=None)
@given(quats, st.lists(finite, min_size=3, max_size=3))
def test_round_trips_and_rigidity(q: list[float], t: list[float]) -> None:
    T_enu_flu = _T(q, t)
    T_ned_frd = T_ned_frd_from_T_enu_flu(T_enu_flu)
    assert np.allclose(T_enu_flu_from_T_ned_frd(T_ned_frd), T_enu_flu, atol=1e-12)
    R = T_ned_frd[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(enu_from_ned(ned_from_enu(np.array(t))), t)
    # a point in the body: FLU (x, y, z) is FRD (x, -y, -z); the same world point either way
    p_flu = np.array([0.3, -1.2, 0.7])
    p_enu = T_enu_flu[:3, :3] @ p_flu + T_enu_flu[:3, 3]
    p_ned = T_ned_frd[:3, :3] @ (p_flu * [1, -1, -1]) + T_ned_frd[:3, 3]
    assert np.allclose(p_ned, ned_from_enu(p_enu), atol=1e-9)
    q_wxyz = quat_wxyz_from_matrix(R)
    assert q_wxyz[0] >= 0 and np.allclose(matrix_from_quat_wxyz(q_wxyz), R, atol=1e-9)


def test_known_yaw_and_axes() -> None:
    """Facing east in ENU (yaw 0) is yaw +90 deg in NED; facing north (ENU yaw 90 deg) is NED yaw 0; level flight
    keeps the body's down axis along NED's down."""
    assert np.isclose(yaw_ned_from_yaw_enu(0.0), np.pi / 2)
    assert np.isclose(yaw_ned_from_yaw_enu(np.pi / 2), 0.0)
    assert np.isclose(yaw_ned_from_yaw_enu(np.pi), -np.pi / 2)
    for yaw_enu in np.linspace(-3, 3, 13):
        c, s = np.cos(yaw_enu), np.sin(yaw_enu)
        R_ned_frd = R_ned_frd_from_R_enu_flu(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]))
        yaw_ned = np.arctan2(R_ned_frd[1, 0], R_ned_frd[0, 0])
        assert np.isclose(np.angle(np.exp(1j * (yaw_ned - yaw_ned_from_yaw_enu(yaw_enu)))), 0.0, atol=1e-12)
        assert np.allclose(R_ned_frd[:, 2], [0, 0, 1])  # body down = world down
    assert np.allclose(ned_from_enu(np.array([1.0, 2.0, 3.0])), [2.0, 1.0, -3.0])


@settings(max_examples=50, deadline=None)
@given(quats)
def test_covariance_order(q: list[float]) -> None:
    """GTSAM [rot; trans] (body tangent) -> ROS [x y z; rot] (world): a translation-only variance along body x lands
    in the position block along the body's x axis in the world; a rotation-only one in the rotation block."""
    R = Rotation.from_quat(q).as_matrix()
    cov = np.zeros((6, 6))
    cov[3, 3] = 4.0  # translation along body x, m^2
    cov[2, 2] = 0.01  # rotation about body z, rad^2
    ros = cov_ros_from_gtsam(cov, R)
    assert np.allclose(ros[:3, :3], 4.0 * np.outer(R[:, 0], R[:, 0]))
    assert np.allclose(ros[3:, 3:], 0.01 * np.outer(R[:, 2], R[:, 2]))
    assert np.allclose(ros[:3, 3:], 0.0)
    assert np.isclose(np.trace(ros), 4.01)
