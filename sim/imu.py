"""An IMU synthesized from a trajectory: accelerometer (specific force, gravity included) and gyroscope in the
body frame (x forward, y left, z up), with white noise and a random-walk bias, seeded.

Specific force f_body = R_cad_body^T (a_cad - g_cad) with g_cad = (0, 0, -9.81) m/s^2: at rest, level,
the accelerometer reads +9.81 on z. Angular rate: omega_body = vee(R_k^T R_{k+1}) / dt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.sim.flight import GRAVITY_MPS2, Trajectory


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time densities (a consumer-grade MEMS IMU): noise per sqrt(Hz), bias random walk per sqrt(s)."""

    accel_noise: float = 2.0e-3 * GRAVITY_MPS2  # m/s^2/sqrt(Hz)
    gyro_noise: float = 1.7e-4  # rad/s/sqrt(Hz)
    accel_bias_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    gyro_bias_walk: float = 2.0e-5  # rad/s^2/sqrt(Hz)
    accel_bias_init: float = 0.05  # m/s^2, standard deviation of the initial bias
    gyro_bias_init: float = 0.002  # rad/s


@dataclass
class ImuSamples:
    """stamps_s: (N,); accel_mps2, gyro_radps: (N, 3) measured (noise and bias included), body frame;
    accel_bias, gyro_bias: (N, 3) the true biases."""

    stamps_s: np.ndarray
    accel_mps2: np.ndarray
    gyro_radps: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray


def ideal_imu(traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (specific force (N, 3) m/s^2, angular rate (N, 3) rad/s) in the body frame."""
    t = traj.stamps_s
    dt = float(np.mean(np.diff(t)))
    acc_cad = np.gradient(np.gradient(traj.positions_cad, dt, axis=0), dt, axis=0)
    f_cad = acc_cad + np.array([0.0, 0.0, GRAVITY_MPS2])  # a - g, g = (0, 0, -9.81)
    f_body = np.einsum("nji,nj->ni", traj.R_cad_body, f_cad)  # R^T f
    rel = np.einsum("nji,njk->nik", traj.R_cad_body[:-1], traj.R_cad_body[1:])  # R_k^T R_{k+1}
    w = Rotation.from_matrix(rel).as_rotvec() / dt
    gyro = np.vstack([w[:1], 0.5 * (w[1:] + w[:-1]), w[-1:]])  # centred on the samples
    return f_body, gyro


def simulate_imu(traj: Trajectory, noise: ImuNoise, seed: int) -> ImuSamples:
    """Measured IMU samples at the trajectory's own rate."""
    rng = np.random.default_rng([seed, 0x1A])
    f, w = ideal_imu(traj)
    n = len(traj.stamps_s)
    dt = float(np.mean(np.diff(traj.stamps_s)))
    ba = rng.normal(0, noise.accel_bias_init, 3) + np.cumsum(rng.normal(0, noise.accel_bias_walk * np.sqrt(dt),
                                                                        (n, 3)), axis=0)
    bg = rng.normal(0, noise.gyro_bias_init, 3) + np.cumsum(rng.normal(0, noise.gyro_bias_walk * np.sqrt(dt),
                                                                       (n, 3)), axis=0)
    accel = f + ba + rng.normal(0, noise.accel_noise / np.sqrt(dt), (n, 3))  # discrete sigma = density / sqrt(dt)
    gyro = w + bg + rng.normal(0, noise.gyro_noise / np.sqrt(dt), (n, 3))
    return ImuSamples(traj.stamps_s.copy(), accel, gyro, ba, bg)
