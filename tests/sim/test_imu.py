"""The synthesized IMU: gravity in the accelerometer, rates in the gyroscope, and it integrates back."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.sim.flight import GRAVITY_MPS2, Trajectory
from macroloc.sim.imu import ImuNoise, ideal_imu, simulate_imu

RATE_HZ = 200.0


def _trajectory(duration_s: float = 4.0) -> Trajectory:
    """A smooth test trajectory: a horizontal circle of radius 2 m at 1.2 m, yaw along the tangent, slight roll."""
    t = np.arange(0.0, duration_s, 1 / RATE_HZ)
    w = 0.5  # rad/s
    pos = np.column_stack([2 * np.cos(w * t), 2 * np.sin(w * t), 1.2 + 0.1 * np.sin(t)])
    yaw = w * t + np.pi / 2
    roll = 0.05 * np.sin(2 * t)
    R = Rotation.from_euler("ZYX", np.column_stack([yaw, np.zeros_like(t), roll])).as_matrix()
    return Trajectory(t, pos, R)


def test_level_hover_reads_gravity_up() -> None:
    t = np.arange(0.0, 1.0, 1 / RATE_HZ)
    traj = Trajectory(t, np.tile([1.0, 2.0, 1.5], (len(t), 1)), np.tile(np.eye(3), (len(t), 1, 1)))
    f, w = ideal_imu(traj)
    assert np.allclose(f, [0.0, 0.0, GRAVITY_MPS2], atol=1e-9) and np.allclose(w, 0.0, atol=1e-12)


def test_gyro_reads_the_yaw_rate() -> None:
    traj = _trajectory()
    _, w = ideal_imu(traj)
    # body z is tilted only by the small roll, so the yaw rate shows on body z and y
    assert np.median(np.linalg.norm(w, axis=1)) > 0.45


def test_noise_free_imu_integrates_back_to_the_trajectory() -> None:
    traj = _trajectory()
    f, w = ideal_imu(traj)
    dt = 1 / RATE_HZ
    k0 = 2  # skip the one-sided differences at the ends
    R = traj.R_cad_body[k0].copy()
    v = (traj.positions_cad[k0 + 1] - traj.positions_cad[k0 - 1]) / (2 * dt)
    p = traj.positions_cad[k0].copy()
    g = np.array([0.0, 0.0, -GRAVITY_MPS2])
    for k in range(k0, len(traj.stamps_s) - 3):
        a = R @ f[k] + g
        p = p + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        R = R @ Rotation.from_rotvec(0.5 * (w[k] + w[k + 1]) * dt).as_matrix()
    end = len(traj.stamps_s) - 3
    assert np.linalg.norm(p - traj.positions_cad[end]) < 0.05  # metres after ~4 s of dead reckoning
    assert np.degrees(Rotation.from_matrix(R.T @ traj.R_cad_body[end]).magnitude()) < 0.5


def test_noise_and_bias_are_seeded() -> None:
    traj = _trajectory(1.0)
    a, b = simulate_imu(traj, ImuNoise(), seed=3), simulate_imu(traj, ImuNoise(), seed=3)
    c = simulate_imu(traj, ImuNoise(), seed=4)
    assert np.array_equal(a.accel_mps2, b.accel_mps2) and not np.array_equal(a.accel_mps2, c.accel_mps2)
    f, _ = ideal_imu(traj)
    resid = a.accel_mps2 - f - a.accel_bias
    expected = ImuNoise().accel_noise * np.sqrt(RATE_HZ)
    assert 0.8 * expected < resid.std() < 1.2 * expected
