"""Place recognition at keyframes, for the replay and the service: views kept for the map this flight saves, and
keyframes placed in a saved map's views (service.saved_map, perception.place) while the localizer is not localized.

Both cost image work at keyframes only: a view to keep is ORB and SGBM on the stereo pair; placing a keyframe is ORB
and a match against every stored view (tried while the status is anything but `localized`, at most every `every_s`
of flight; faiss votes, several times faster than OpenCV's brute-force matcher: perception.place). Their costs:
docs/measurements.md, "Place recognition's cost".
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from macroloc.graph.mapstore import VIEW_SPACING_DEG, VIEW_SPACING_M, KeyframeView
from macroloc.graph.rigid import rotation_angle_deg
from macroloc.perception.place import PlaceParams, PlaceRecognizer
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame
from macroloc.service.frames import calibrated, stereo_rig

if TYPE_CHECKING:
    from macroloc.service.saved_map import SavedMap

log = logging.getLogger(__name__)


@dataclass
class Placed:
    T_cad_body: np.ndarray | None  # the keyframe's pose in the CAD frame, where it was placed
    view: KeyframeView | None  # its view, where views are kept


class KeyframePlaces:
    """See module doc. `stored`: the saved map to place keyframes in (only one with views and a T_cad_map can);
    `keep_views`: keep views of the keyframes (every `view_every_m` / `view_every_deg`) for the map this flight
    will save."""

    MIN_VIEW_POINTS = 20  # a view with fewer (a blank wall, a dark frame) has nothing to place by: not kept

    def __init__(self, stored: SavedMap | None, keep_views: bool, config: PlaceParams | None = None,
                 every_s: float = 1.0, view_every_m: float = VIEW_SPACING_M,
                 view_every_deg: float = VIEW_SPACING_DEG) -> None:
        """`every_s`: placing is tried at most this often (flight time); a view is kept for a keyframe this far
        (`view_every_m` or `view_every_deg`, by the odometry) from the last keyframe that kept one."""
        self.stored = stored if stored is not None and stored.placed_views() and stored.T_cad_map is not None \
            else None
        self.keep_views = keep_views
        self.config = config
        self.every_s = every_s
        self.view_every_m, self.view_every_deg = view_every_m, view_every_deg
        self._T_odom_viewed: np.ndarray | None = None
        self._recognizer: PlaceRecognizer | None = None
        self._last_try_ns: int | None = None

    @property
    def active(self) -> bool:
        return self.stored is not None or self.keep_views

    def at_frame(self, frame: FlightFrame, T_odom_body: np.ndarray, T_body_cam: np.ndarray,
                 up_body: np.ndarray | None, status: str) -> Placed:
        """A keyframe's stereo frame: its place in the saved map (while not localized, at most every `every_s`)
        and its view (when kept and due). The frame's images are decoded only where that work needs them (once:
        `FlightFrame.images`): none after localizing between views. Nothing from a frame without images or
        calibration (a ground-truth flight's)."""
        stereo, stamp_ns = frame.stereo, frame.stamp_ns
        if not self.active or not calibrated(stereo):
            return Placed(None, None)
        place = self.stored is not None and status != "localized" and \
            (self._last_try_ns is None or (stamp_ns - self._last_try_ns) * 1e-9 >= self.every_s)
        describe = self.keep_views and self._view_due(T_odom_body)
        if not place and not describe:
            return Placed(None, None)
        recognizer = self._recognizer_for(stereo, T_body_cam)
        left, right = frame.images()
        T_cad_body = None
        if place:
            assert self.stored is not None and self.stored.T_cad_map is not None
            self._last_try_ns = stamp_ns
            match = recognizer.place(left, up_body)
            if match is not None:
                T_cad_body = self.stored.T_cad_map @ match.T_map_body
                log.info("keyframe placed in the saved map: %d inliers (stored view %d)", match.inliers, match.view)
        view = None
        if describe:
            view = recognizer.describe(left, right)
            self._T_odom_viewed = T_odom_body
            if len(view.descriptors) < self.MIN_VIEW_POINTS:
                view = None
        return Placed(T_cad_body, view)

    def _recognizer_for(self, frame: pb.StereoFrame, T_body_cam: np.ndarray) -> PlaceRecognizer:
        """The recognizer, made for the first frame's camera (the stored views loaded into it)."""
        if self._recognizer is None:
            self._recognizer = PlaceRecognizer(stereo_rig(frame), T_body_cam, self.config)
            if self.stored is not None:
                self._recognizer.use(self.stored.placed_views())
                log.info("place recognition: %d stored views", len(self.stored.placed_views()))
        return self._recognizer

    def _view_due(self, T_odom_body: np.ndarray) -> bool:
        if self._T_odom_viewed is None:
            return True
        step = np.linalg.inv(self._T_odom_viewed) @ T_odom_body
        return bool(np.linalg.norm(step[:3, 3]) >= self.view_every_m
                    or rotation_angle_deg(step[:3, :3]) >= self.view_every_deg)
