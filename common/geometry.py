"""Rotation angles, for both libraries."""

from __future__ import annotations

import numpy as np


def rotation_angle_rad(R: np.ndarray) -> float:
    """The angle of the 3x3 rotation R (radians, in [0, pi])."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def forward_stereo_T_body_cam(baseline_m: float = 0.12, forward_m: float = 0.10) -> np.ndarray:
    """T_body_cam (4x4) of the left camera of a forward-looking stereo pair, the default mounting (the simulator's,
    and the service's for a camera that does not say its own): cam z = body x, cam x = -body y, cam y = -body z;
    the pair's centre `forward_m` ahead of the body origin, the left camera `baseline_m` / 2 to the left (+y)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: cam x, y, z in body
    T[:3, 3] = (forward_m, baseline_m / 2, 0.0)
    return T
