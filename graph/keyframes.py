"""Keyframe selection: a new keyframe after enough motion or time since the last one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from macroloc.graph.rigid import rotation_angle_rad


@dataclass(frozen=True)
class KeyframePolicy:
    """A new keyframe after this much motion (metres, radians) or time (seconds) since the last one."""

    translation_m: float = 0.25
    rotation_rad: float = 0.15
    interval_s: float = 0.34

    def is_keyframe(self, T_last: np.ndarray | None, T_now: np.ndarray, dt_s: float) -> bool:
        """T_last, T_now: 4x4 poses of the body in one frame (map/odometry); dt_s: time since the last keyframe."""
        if T_last is None:
            return True
        d = np.linalg.inv(T_last) @ T_now
        angle = rotation_angle_rad(d[:3, :3])
        return bool(np.linalg.norm(d[:3, 3]) > self.translation_m or angle > self.rotation_rad
                    or dt_s >= self.interval_s)


@dataclass(frozen=True)
class KeyframeRule:
    """Which frames become keyframes, for every driver of the localizer (service.session).

    `policy`: motion, turn or time since the last keyframe, for every frame (the default, measured in
    docs/measurements.md, "One keyframe rule for replay and service"). Two options the service used to add:
    `while_exploring`: every frame with sightings is a keyframe while the localizer is not localized;
    `without_sightings_m`: a frame without sightings is a keyframe only after this much motion (m) since the last
    one (0: the policy decides for it too)."""

    policy: KeyframePolicy = KeyframePolicy()
    while_exploring: bool = False
    without_sightings_m: float = 0.0

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
        return self.policy.is_keyframe(T_last, T_now, dt_s)
