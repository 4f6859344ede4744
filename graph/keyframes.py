"""Keyframe selection: a new keyframe after enough motion or time since the last one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.graph.rigid import rotation_angle_rad


@dataclass(frozen=True)
class KeyframePolicy:
    """A new keyframe after this much motion (metres, radians) or time (seconds) since the last one."""

    min_translation_m: float = 0.25
    min_rotation_rad: float = 0.15
    max_interval_s: float = 0.34

    def is_keyframe(self, T_last: np.ndarray | None, T_now: np.ndarray, dt_s: float) -> bool:
        """T_last, T_now: 4x4 poses of the body in one frame (map/odometry); dt_s: time since the last keyframe."""
        if T_last is None:
            return True
        d = np.linalg.inv(T_last) @ T_now
        angle = rotation_angle_rad(d[:3, :3])
        return bool(np.linalg.norm(d[:3, 3]) > self.min_translation_m or angle > self.min_rotation_rad
                    or dt_s >= self.max_interval_s)
