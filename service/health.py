"""What the running service measures about itself: dropped inputs by kind, rates and latencies."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque

import numpy as np

log = logging.getLogger(__name__)


class DropCounter:
    """Malformed or unusable inputs, counted by kind ("odometry/nan", "stereo/unknown_camera", ...).

    Each kind is logged once (the first time), so a flood of bad input cannot flood the log.
    """

    def __init__(self) -> None:
        self._counts: Counter[str] = Counter()
        self._lock = threading.Lock()

    def drop(self, kind: str, detail: str = "") -> None:
        with self._lock:
            self._counts[kind] += 1
            first = self._counts[kind] == 1
        if first:
            log.warning("dropping input: %s %s (logged once per kind; see diagnostics.dropped)", kind, detail)

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


class RateMeter:
    """Events per second over a sliding window of window_s seconds (monotonic clock)."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._times: deque[float] = deque(maxlen=4096)
        self._lock = threading.Lock()
        self.total = 0

    def tick(self) -> None:
        with self._lock:
            self._times.append(time.monotonic())
            self.total += 1

    def rate_hz(self) -> float:
        now = time.monotonic()
        with self._lock:
            recent = [t for t in self._times if now - t <= self.window_s]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)


class LatencyWindow:
    """The last n latencies in milliseconds; p50 and p99 of them."""

    def __init__(self, n: int = 1000) -> None:
        self._ms: deque[float] = deque(maxlen=n)
        self._lock = threading.Lock()

    def add_ms(self, ms: float) -> None:
        with self._lock:
            self._ms.append(ms)

    def percentiles(self) -> dict[str, float]:
        with self._lock:
            values = np.array(self._ms, float)
        if not len(values):
            return {}
        return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99))}
