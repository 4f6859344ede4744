"""perception.gravity: up in the body frame from the specific force, the odometry's acceleration taken out."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from macroloc.perception.gravity import GravityEstimator

G_MPS2 = 9.81
RATE_HZ = 30.0
IMU_PER_FRAME = 7


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def _circling(t_s: float, radius_m: float, speed_mps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vehicle flying a level circle, nose along its velocity, slightly banked and wobbling: (R_world_body,
    position, acceleration), world z up."""
    w = speed_mps / radius_m
    p = np.array([radius_m * np.cos(w * t_s), radius_m * np.sin(w * t_s), 1.4 + 0.2 * np.sin(0.7 * t_s)])
    a = np.array([-radius_m * w**2 * np.cos(w * t_s), -radius_m * w**2 * np.sin(w * t_s),
                  -0.2 * 0.49 * np.sin(0.7 * t_s)])
    R = Rotation.from_euler("zyx", [w * t_s + np.pi / 2, 0.05 * np.sin(1.3 * t_s), 0.08]).as_matrix()
    return R, p, a


@settings(max_examples=10, deadline=None)
@given(radius=st.floats(1.5, 6.0), speed=st.floats(0.8, 2.0), odom_tilt_deg=st.floats(0.0, 3.0),
       odom_yaw=st.floats(-np.pi, np.pi), seed=st.integers(0, 1000))
def test_up_holds_through_a_turn(radius: float, speed: float, odom_tilt_deg: float, odom_yaw: float,
                                 seed: int) -> None:
    """In a steady turn the specific force leans by atan(v^2 / (r g)) (1-15 degrees here); the estimate stays
    within a tenth of that of true up (plus the noise of velocities from 3 mm position noise), in an odometry
    frame that is itself tilted and turned (as a drifted one is)."""
    rng = np.random.default_rng(seed)
    R_odom_world = Rotation.from_euler("zx", [odom_yaw, np.radians(odom_tilt_deg)]).as_matrix()
    est = GravityEstimator()
    raw_err, est_err = [], []
    for k in range(int(4 * RATE_HZ)):
        t_s = k / RATE_HZ
        forces = []
        for j in range(IMU_PER_FRAME):  # the samples since the previous frame
            R, _, a = _circling(t_s - j / (RATE_HZ * IMU_PER_FRAME), radius, speed)
            forces.append(R.T @ (a + [0.0, 0.0, G_MPS2]) + rng.normal(0, 0.02, 3))
        R, p, _ = _circling(t_s, radius, speed)
        T_odom_body = np.eye(4)
        T_odom_body[:3, :3], T_odom_body[:3, 3] = R_odom_world @ R, R_odom_world @ p + rng.normal(0, 0.003, 3)
        up = est.update(int(t_s * 1e9), T_odom_body, np.array(forces))
        true_up = R.T @ [0.0, 0.0, 1.0]
        if t_s >= 1.0:
            assert up is not None
            raw_err.append(_angle_deg(np.mean(forces, axis=0), true_up))
            est_err.append(_angle_deg(up, true_up))
    lean_deg = float(np.degrees(np.arctan(speed**2 / radius / G_MPS2)))
    assert np.median(raw_err) > 0.8 * lean_deg  # the specific force alone leans
    assert np.median(est_err) < 0.3 + 0.05 * lean_deg and max(est_err) < 0.8 + 0.1 * lean_deg


def test_no_samples_and_odometry_jumps_give_no_estimate() -> None:
    est = GravityEstimator()
    assert est.update(0, np.eye(4), np.zeros((0, 3))) is None
    still = np.array([[0.0, 0.0, G_MPS2]])
    for k in range(30):  # hovering: up is the body's z
        up = est.update(int(k * 1e9 / RATE_HZ), np.eye(4), still)
    assert up is not None and np.allclose(up, [0.0, 0.0, 1.0], atol=1e-6)
    T_jump = np.eye(4)
    T_jump[0, 3] = 2.0  # the odometry jumped 2 m in one frame: tens of m/s^2, not an acceleration to remove
    assert est.update(int(30 * 1e9 / RATE_HZ), T_jump, still) is None


def test_a_knock_or_a_free_fall_is_left_out() -> None:
    """Specific forces outside the params' bounds (a knock, a free fall) do not tilt up; with none inside, no
    estimate."""
    est = GravityEstimator()
    still = np.array([[0.0, 0.0, G_MPS2]])
    for k in range(30):
        est.update(int(k * 1e9 / RATE_HZ), np.eye(4), still)
    knock = np.array([[0.0, 0.0, G_MPS2], [30.0, 0.0, G_MPS2]])  # one sample of a 3 g knock sideways
    up = est.update(int(30 * 1e9 / RATE_HZ), np.eye(4), knock)
    assert up is not None and np.allclose(up, [0.0, 0.0, 1.0], atol=1e-6)
    assert est.update(int(31 * 1e9 / RATE_HZ), np.eye(4), np.array([[0.0, 0.0, 0.5]])) is None  # falling


def test_imu_gravity_holds_up_without_samples_and_forgets_it_after_samples_that_give_none() -> None:
    """ImuGravity's rule: samples then a pose give that pose's estimate; a pose with no sample since the last
    keeps the last up (nothing new was measured); a pose whose samples are all knocks gives None (unknown)."""
    from macroloc.perception.gravity import ImuGravity

    R = Rotation.from_euler("x", 10, degrees=True).as_matrix()  # body rolled 10 degrees, hovering
    T = np.eye(4)
    T[:3, :3] = R
    true_up_body = R.T @ [0.0, 0.0, 1.0]
    gravity = ImuGravity()
    assert gravity.odometry(0, T) is None  # nothing measured yet
    gravity.imu(np.tile(true_up_body * G_MPS2, (IMU_PER_FRAME, 1)))
    up = gravity.odometry(33_000_000, T)
    assert up is not None and _angle_deg(up, true_up_body) < 1e-6
    assert gravity.odometry(66_000_000, T) is up  # no sample since: the last up
    gravity.imu(true_up_body * 30.0)  # a knock (above max_specific_force_mps2): left out, none left
    assert gravity.odometry(99_000_000, T) is None and gravity.up_body is None


def test_imu_gravity_keeps_the_newest_samples_and_its_up_across_a_new_time_base() -> None:
    from macroloc.perception.gravity import ImuGravity

    gravity = ImuGravity(max_samples=4)
    for k in range(10):
        gravity.imu([0.0, 0.0, 9.0 + 0.1 * k])
    assert gravity._n_waiting == 4 and np.allclose(np.concatenate(gravity._accel_body)[:, 2], [9.6, 9.7, 9.8, 9.9])
    up = gravity.odometry(0, np.eye(4))
    assert up is not None and np.allclose(up, [0.0, 0.0, 1.0])
    gravity.new_time_base()
    assert gravity.up_body is up and gravity._estimator._history == type(gravity._estimator._history)()
