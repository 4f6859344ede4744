"""Keyframe selection: a new keyframe after enough motion or time since the last one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.common.parameters import Parameters, param
from macroloc.graph.rigid import rotation_angle_rad


@dataclass(frozen=True)
class KeyframeRule(Parameters):
    """Which frames become keyframes, for every driver of the localizer (service.localizer_loop): a new keyframe after
    enough motion, turn or time since the last one, for every frame (measured in docs/measurements.md, "One keyframe
    rule for replay and service"), with two options the service used to add (`while_exploring`,
    `without_sightings_m`)."""

    translation_m: float = param(0.25, "a new keyframe after this much motion, m")
    rotation_rad: float = param(0.15, "... or this much rotation, rad")
    interval_s: float = param(0.34, "... or this much time, s")
    while_exploring: bool = param(
        False, "also every frame with sightings while not localized (slower to localize on 30 fps flights: "
        "docs/measurements.md, \"One keyframe rule for replay and service\")")
    without_sightings_m: float = param(
        0.0, "a frame without sightings is a keyframe only after this much motion, m (0: the translation, rotation and "
        "interval above decide for it too)")

    def is_keyframe(self, T_last: np.ndarray | None, T_now: np.ndarray, dt_s: float, has_sightings: bool,
                    localized: bool) -> bool:
        """T_last, T_now: 4x4 body poses in the odometry frame (T_last None: no keyframe yet); dt_s: seconds since
        the last keyframe (inf where unknown, e.g. after a clock reset)."""
        if T_last is None:
            return True
        if has_sightings and self.while_exploring and not localized:
            return True
        if not has_sightings and self.without_sightings_m:
            return bool(np.linalg.norm((np.linalg.inv(T_last) @ T_now)[:3, 3]) > self.without_sightings_m)
        d = np.linalg.inv(T_last) @ T_now
        return bool(np.linalg.norm(d[:3, 3]) > self.translation_m or rotation_angle_rad(d[:3, :3]) > self.rotation_rad
                    or dt_s >= self.interval_s)
