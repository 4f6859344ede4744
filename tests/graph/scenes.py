"""Fake-data factories for the pose-graph tests: a corridor of doors and a drone flying along it.

Frames: cad (z up), body (x forward, y left, z up). Everything in metres.
"""

from __future__ import annotations

import numpy as np

from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.landmarks import frame_from_normal


def rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def door(fid: str, centre_xy: tuple[float, float], normal_xy: tuple[float, float], kind: str = "door",
         width: float = 0.9, height: float = 2.1, bottom: float = 0.0) -> MacroFeature:
    n = np.array([normal_xy[0], normal_xy[1], 0.0])
    n /= np.linalg.norm(n)
    u = np.cross([0.0, 0.0, 1.0], n)
    c = np.array([centre_xy[0], centre_xy[1], bottom + height / 2])
    corners = np.array([c + sx * width / 2 * u + sz * height / 2 * np.array([0, 0, 1.0])
                        for sx, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return MacroFeature(fid, kind, "L1", corners, c, n, width, height)  # type: ignore[arg-type]


def corridor_model(n_doors: int = 12, spacing_m: float = 3.0, seed: int = 0) -> BuildingModel:
    """Doors on both walls of a corridor along +x (walls at y = +-1.5), irregularly spaced, and windows."""
    rng = np.random.default_rng(seed)
    feats = []
    for k in range(n_doors):
        x = k * spacing_m + rng.uniform(-0.8, 0.8)
        side = 1.0 if k % 2 == 0 else -1.0
        kind = "window" if k % 3 == 2 else "door"
        feats.append(door(f"F{k:02d}", (x, 1.5 * side), (0.0, side), kind=kind,
                          width=rng.uniform(0.8, 1.4), bottom=0.9 if kind == "window" else 0.0,
                          height=1.2 if kind == "window" else 2.1))
    return BuildingModel(source="corridor", sha256="corridor" + str(seed), features=feats, storeys=["L1"])


def straight_flight(n: int, step_m: float = 0.3, z: float = 1.4, yaw_wobble: float = 0.2) -> list[np.ndarray]:
    """T_cad_body along the corridor, yaw wobbling so both walls come into view."""
    return [make_T(rot_z(yaw_wobble * np.sin(0.3 * i)), np.array([i * step_m, 0.1 * np.sin(0.2 * i), z]))
            for i in range(n)]


def sightings_from(model: BuildingModel, T_cad_body: np.ndarray, max_range_m: float = 6.0,
                   rng: np.random.Generator | None = None, sigma_m: float = 0.0) -> list:
    """Sightings (body-frame corners) of every feature in front of the body within range."""
    from macroloc.graph.localizer import Sighting

    out = []
    T_body_cad = np.linalg.inv(T_cad_body)
    for f in model.features:
        corners = (T_body_cad[:3, :3] @ f.corners_cad.T).T + T_body_cad[:3, 3]
        c = corners.mean(axis=0)
        if c[0] < 0.5 or np.linalg.norm(c) > max_range_m or abs(np.arctan2(c[1], c[0])) > np.radians(50):
            continue
        if rng is not None and sigma_m > 0:
            corners = corners + rng.normal(0, sigma_m, corners.shape)
        out.append(Sighting(f.type, corners, truth_id=f.id))
    return out


def drifting_odometry(poses: list[np.ndarray], yaw_per_step: float = 0.004, scale: float = 1.02) -> list[np.ndarray]:
    """T_odom_body with a yaw bias and a scale error accumulating: a known drift."""
    out = [poses[0].copy()]
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        d = np.linalg.inv(a) @ b
        d[:3, 3] *= scale
        d[:3, :3] = d[:3, :3] @ rot_z(yaw_per_step)
        out.append(out[-1] @ d)
    return out


def feature_frames(model: BuildingModel) -> dict[str, np.ndarray]:
    return {f.id: frame_from_normal(f.centroid_cad, f.normal_cad) for f in model.features}
