"""The perception chain's code as it was before issue 37, kept only for bench.bench_chain to time and compare
against: the pure-Python segment joiner (perception.lines before vectorising)."""

from __future__ import annotations

import numpy as np

from perception.lines import LineConfig, _merge, _orient
from perception.odometry import OdometryConfig


def _angle_deg(seg: np.ndarray) -> float:
    d = seg[1] - seg[0]
    return float(np.degrees(np.arctan2(d[1], d[0])) % 180.0)


def _angle_diff_deg(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def _joinable(a: np.ndarray, b: np.ndarray, cfg: LineConfig) -> bool:
    if _angle_diff_deg(_angle_deg(a), _angle_deg(b)) > cfg.join_angle_deg:
        return False
    gap = min(np.linalg.norm(p - q) for p in a for q in b)
    if gap > cfg.join_gap_px:
        return False
    d = (a[1] - a[0]) / max(np.linalg.norm(a[1] - a[0]), 1e-9)
    normal = np.array([-d[1], d[0]])
    return bool(np.max(np.abs((b - a[0]) @ normal)) <= cfg.join_offset_px)


def join_segments_python(segments: list[np.ndarray], cfg: LineConfig | None = None) -> list[np.ndarray]:
    """perception.lines.join_segments before issue 37: pair by pair in Python, restarting after each merge."""
    cfg = cfg or LineConfig()
    segs = [_orient(np.asarray(s, np.float64).reshape(2, 2)) for s in segments]
    merged = True
    while merged:
        merged = False
        for i in range(len(segs)):
            for j in range(i + 1, len(segs)):
                if _joinable(segs[i], segs[j], cfg):
                    segs[i] = _merge(segs[i], segs[j])
                    del segs[j]
                    merged = True
                    break
            if merged:
                break
    return segs


# The odometry's settings before issue 37 (perception.odometry.OdometryConfig's defaults then).
OLD_ODOMETRY = OdometryConfig(n_features=2000)
