"""The depth points of the recent keyframes, which check candidate poses against the walls (graph.judge) and fit
the newest keyframe to them once localized.

Each keyframe keeps its points at the camera's height (the floor and the ceiling fit any pose on a storey) and,
apart, those below it (the floor, for the height), in its body frame; they are taken into the map frame at the
keyframes' current estimates whenever they are used.

Frames: body (x forward, y left, z up), map (the flight's odometry frame, z up). Metres.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator

import numpy as np

from macroloc.graph.rigid import apply


class DepthWindow:
    """The points of the newest `keyframes` keyframes: (keyframe, points at the camera's height, points below
    it), body frame."""

    def __init__(self, keyframes: int, viewer_body: np.ndarray, T_map_body: Callable[[int], np.ndarray]) -> None:
        """`viewer_body` (3,): the camera's position in the body frame; `T_map_body(i)`: keyframe i's current
        estimate (the pose graph's)."""
        self._window: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=keyframes)
        self._viewer_body = viewer_body
        self._T_map_body = T_map_body

    def add(self, i: int, band_body: np.ndarray, floor_body: np.ndarray) -> None:
        self._window.append((i, band_body, floor_body))

    def __len__(self) -> int:
        return len(self._window)

    def __iter__(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        return iter(self._window)

    @property
    def newest(self) -> tuple[int, np.ndarray, np.ndarray]:
        return self._window[-1]

    @property
    def n_points(self) -> int:
        """Points at the camera's height in the window."""
        return sum(len(p) for _, p, _ in self._window)

    def points_map(self, at_most: int = 2000, since: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The window's points at the camera's height (N, 3) in the map frame, at the keyframes' current
        estimates, and the camera each was seen from (N, 3); `at_most` of them, evenly drawn (a support known to
        ~1 % is enough, and each point costs a k-d tree query and a line of sight); of keyframes from `since` on."""
        points, origins = [np.zeros((0, 3))], [np.zeros((0, 3))]
        for i, p, _ in self._window:
            if len(p) and i >= since:
                T_map_body = self._T_map_body(i)
                points.append(apply(T_map_body, p))
                origins.append(np.repeat(apply(T_map_body, self._viewer_body[None]), len(p), axis=0))
        every = max(1, int(np.ceil(sum(len(p) for p in points) / at_most)))
        return np.vstack(points)[::every], np.vstack(origins)[::every]
