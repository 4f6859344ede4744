"""Place recognition at keyframes, for the replay and the service: views kept for the map this flight saves, and
keyframes placed in a stored map's views (perception.place) while the localizer is not localized.

Both cost image work at keyframes only: a view to keep is ORB and SGBM on the stereo pair (~40 ms here); placing a
keyframe is ORB and a match against every stored view (tried while the status is anything but `localized`, at
most every `every_s` of flight: 1 s, ~40 ms each while the new flight is where the map has no view).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from graph.mapstore import KeyframeView, StoredMap
from graph.rigid import rotation_angle_deg
from perception.calib import StereoRig
from perception.place import PlaceConfig, PlaceRecognizer

log = logging.getLogger(__name__)


@dataclass
class Placed:
    T_cad_body: np.ndarray | None  # the keyframe's pose in the CAD frame, where it was placed
    view: KeyframeView | None  # its view, where views are kept


class KeyframePlaces:
    """See module doc. `stored`: the map to place keyframes in (only one with views and a T_cad_map can);
    `keep_views`: keep views of the keyframes (every `view_every_m` / `view_every_deg`) for the map this flight
    will save."""

    def __init__(self, stored: StoredMap | None, keep_views: bool, config: PlaceConfig | None = None,
                 every_s: float = 1.0, view_every_m: float = 0.5, view_every_deg: float = 15.0) -> None:
        """`every_s`: placing is tried at most this often (flight time); a view is kept for a keyframe this far
        (`view_every_m` or `view_every_deg`, by the odometry) from the last keyframe that kept one."""
        self.stored = stored if stored is not None and stored.placed_views() and stored.T_cad_map is not None \
            else None
        self.keep_views = keep_views
        self.config = config
        self.every_s = every_s
        self.view_every_m, self.view_every_deg = view_every_m, view_every_deg
        self.min_view_points = 20
        self._T_odom_viewed: np.ndarray | None = None
        self.tries = 0
        self.placed = 0
        self._recognizer: PlaceRecognizer | None = None
        self._last_try_ns: int | None = None

    @property
    def active(self) -> bool:
        return self.stored is not None or self.keep_views

    def at_keyframe(self, stamp_ns: int, T_odom_body: np.ndarray, left: np.ndarray, right: np.ndarray,
                    rig: StereoRig, T_body_cam: np.ndarray, up_body: np.ndarray | None, status: str) -> Placed:
        """This keyframe's place in the stored map (while not localized) and its view (when kept)."""
        if self._recognizer is None:
            self._recognizer = PlaceRecognizer(rig, T_body_cam, self.config)
            if self.stored is not None:
                self._recognizer.use(self.stored.placed_views())
                log.info("place recognition: %d stored views", len(self.stored.placed_views()))
        T_cad_body = None
        due = self._last_try_ns is None or (stamp_ns - self._last_try_ns) * 1e-9 >= self.every_s
        if self.stored is not None and status != "localized" and due:
            self._last_try_ns = stamp_ns
            self.tries += 1
            match = self._recognizer.place(left, up_body)
            if match is not None:
                assert self.stored.T_cad_map is not None
                T_cad_body = self.stored.T_cad_map @ match.T_map_body
                self.placed += 1
                log.info("keyframe placed in the stored map: %d inliers (stored view %d)", match.inliers, match.view)
        view = None
        if self.keep_views and self._view_due(T_odom_body):
            view = self._recognizer.describe(left, right)
            self._T_odom_viewed = T_odom_body
            if len(view.descriptors) < self.min_view_points:  # a blank wall, a dark frame: nothing to place by
                view = None
        return Placed(T_cad_body, view)

    def _view_due(self, T_odom_body: np.ndarray) -> bool:
        if self._T_odom_viewed is None:
            return True
        step = np.linalg.inv(self._T_odom_viewed) @ T_odom_body
        return bool(np.linalg.norm(step[:3, 3]) >= self.view_every_m
                    or rotation_angle_deg(step[:3, :3]) >= self.view_every_deg)
