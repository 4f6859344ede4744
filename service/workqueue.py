"""The bounded queue between the service's intake threads and its single worker."""

from __future__ import annotations

import threading
from collections import deque
from typing import Any


class WorkQueue:
    """Events for the worker. Light events (odometry, IMU, observations, goals) keep their order; stereo
    frames are bounded: beyond `heavy_max` the oldest frame is dropped (counted)."""

    def __init__(self, heavy_max: int, light_max: int = 2048) -> None:
        self._items: deque[tuple[bool, Any]] = deque()
        self._heavy = 0
        self.heavy_max = heavy_max
        self.light_max = light_max
        self._cv = threading.Condition()
        self.dropped = 0

    def put(self, item: Any, heavy: bool) -> None:
        with self._cv:
            if heavy and self._heavy >= self.heavy_max:
                for k, (h, _) in enumerate(self._items):
                    if h:
                        del self._items[k]
                        self._heavy -= 1
                        self.dropped += 1
                        break
            elif not heavy and len(self._items) >= self.light_max:
                self._items.popleft()
                self.dropped += 1
            self._items.append((heavy, item))
            self._heavy += heavy
            self._cv.notify()

    def get(self, timeout_s: float) -> Any | None:
        with self._cv:
            if not self._items and not self._cv.wait_for(lambda: bool(self._items), timeout_s):
                return None
            heavy, item = self._items.popleft()
            self._heavy -= heavy
            return item

    def __len__(self) -> int:
        with self._cv:
            return len(self._items)
