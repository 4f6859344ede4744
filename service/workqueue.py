"""The bounded queue between the service's intake threads and its single worker."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterator
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


class CountingRing:
    """A subscriber's handler keeping the latest `size` samples, as Zenoh's RingChannel does, but counting the
    samples it pushes out (`on_overflow` is called for each): a stream faster than its intake loses samples
    visibly, in the diagnostics, not silently. Iterating blocks for the next sample until `close()`."""

    def __init__(self, size: int, on_overflow: Callable[[], None]) -> None:
        self._items: deque[Any] = deque()
        self.size = size
        self.on_overflow = on_overflow
        self._cv = threading.Condition()
        self._closed = False

    def __call__(self, sample: Any) -> None:  # Zenoh's callback thread: append only
        overflow = False
        with self._cv:
            if len(self._items) >= self.size:
                self._items.popleft()
                overflow = True
            self._items.append(sample)
            self._cv.notify()
        if overflow:
            self.on_overflow()

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    def __iter__(self) -> Iterator[Any]:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._items) or self._closed)
                if not self._items:
                    return
                sample = self._items.popleft()
            yield sample
