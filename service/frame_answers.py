"""The vehicle's odometry kept by stamp (the worker's, for sightings; the intake's, for stereo frames answered on
arrival).

A frame's pose goes out as soon as the frame arrives, from its intake thread: the odometry at its stamp
(`OdometryBuffer`) moved by the newest keyframe's estimate (`service.localizer_loop.PoseSnapshot`): what the session
gives any frame between keyframes, without waiting for the worker, which perceives the frame and updates the
pose graph meanwhile (a frame's perception and a keyframe's registration take longer than a camera period on two
cores). In lock-step the worker answers each frame itself, after perceiving it (service.node).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

ODOMETRY_MATCH_NS = 60_000_000  # a stamp takes the odometry sample within 60 ms of it


class OdometryBuffer:
    """The newest odometry poses by stamp; thread-safe (the front end keeps one, the intake threads another)."""

    def __init__(self, size: int = 512, match_ns: int = ODOMETRY_MATCH_NS) -> None:
        self._poses: OrderedDict[int, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.size, self.match_ns = size, match_ns

    def add(self, stamp_ns: int, T_odom_body: np.ndarray) -> None:
        with self._lock:
            self._poses[stamp_ns] = T_odom_body
            while len(self._poses) > self.size:
                self._poses.popitem(last=False)

    def __contains__(self, stamp_ns: int) -> bool:
        with self._lock:
            return stamp_ns in self._poses

    def clear(self) -> None:
        with self._lock:
            self._poses.clear()

    def at(self, stamp_ns: int, newest_if_later: bool = False) -> np.ndarray | None:
        """The pose nearest in time to stamp_ns within `match_ns`; where stamp_ns is newer than all (its odometry is
        on its way), the newest if `newest_if_later`, else None; None without any."""
        with self._lock:
            if not self._poses:
                return None
            if stamp_ns in self._poses:
                return self._poses[stamp_ns]
            newest = next(reversed(self._poses))
            if stamp_ns > newest:
                return self._poses[newest] if newest_if_later else None
            stamps = np.fromiter(self._poses.keys(), np.int64)
            k = int(np.argmin(np.abs(stamps - stamp_ns)))
            return self._poses[int(stamps[k])] if abs(int(stamps[k]) - stamp_ns) <= self.match_ns else None
