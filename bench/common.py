"""Small timing helpers shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


def time_ms(fn: Callable[[], object], repeat: int = 50, warmup: int = 3) -> np.ndarray:
    """Wall times of `fn` in milliseconds over `repeat` calls (after `warmup` calls)."""
    for _ in range(warmup):
        fn()
    out = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t0) * 1000.0
    return out


def row(what: str, value: str, target: str, verdict: bool | None = None) -> str:
    mark = "" if verdict is None else ("  ok" if verdict else "  MISSED")
    return f"{what:<52} {value:>22}   target {target}{mark}"
