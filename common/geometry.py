"""Rotation angles, for both libraries."""

from __future__ import annotations

import numpy as np


def rotation_angle_rad(R: np.ndarray) -> float:
    """The angle of the 3x3 rotation R (radians, in [0, pi])."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
