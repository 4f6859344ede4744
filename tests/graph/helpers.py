"""Fake-data factories for the graph tests (random rigid motions, synthetic buildings)."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.graph.features import MacroFeature
from macroloc.graph.params import LocalizerParams
from macroloc.graph.rectangle import opening_rectangle
from macroloc.graph.rigid import make_T


def random_T(rng: np.random.Generator, max_translation_m: float = 20.0, yaw_only: bool = False) -> np.ndarray:
    R = (Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)).as_matrix() if yaw_only
         else Rotation.random(random_state=rng).as_matrix())
    return make_T(R, rng.uniform(-max_translation_m, max_translation_m, 3))


def box_vertices(centre, normal_xy, width_m: float, height_m: float, depth_m: float = 0.1) -> np.ndarray:
    n = np.array([normal_xy[0], normal_xy[1], 0.0]) / np.linalg.norm(normal_xy)
    u = np.cross([0.0, 0.0, 1.0], n)
    z = np.array([0.0, 0.0, 1.0])
    return np.array([np.asarray(centre) + a * width_m / 2 * u + b * depth_m / 2 * n + c * height_m / 2 * z
                     for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])


def random_building(rng: np.random.Generator, n: int = 40, size_m: float = 40.0) -> list[MacroFeature]:
    """Doors and windows at random places on axis-aligned walls of one storey (an asymmetric building)."""
    out = []
    for i in range(n):
        kind = "door" if rng.random() < 0.5 else "window"
        w, h = (0.9, 2.1) if kind == "door" else (rng.choice([0.8, 1.2, 1.6]), 1.2)
        z = h / 2 if kind == "door" else 0.9 + h / 2
        normal = [(1, 0), (0, 1), (-1, 0), (0, -1)][rng.integers(4)]
        centre = np.array([*rng.uniform(0, size_m, 2), z])
        r = opening_rectangle(box_vertices(centre, normal, w, h))
        out.append(MacroFeature(f"F{i:03d}", kind, "L1", r.corners, r.centroid, r.normal, r.width_m, r.height_m))
    return out


def localizer_params(base: LocalizerParams | None = None, **changes: object) -> LocalizerParams:
    """`base` (None: the defaults) with fields of its parts changed by their names (`surface_min_points=100` is
    `DepthWindowParams.surface_min_points`): a test's shorthand for the nested `LocalizerParams`."""
    base = base or LocalizerParams()
    parts = {part.name: getattr(base, part.name) for part in fields(base)}
    for name, value in changes.items():
        owners = [k for k, part in parts.items() if name in {f.name for f in fields(part)}]
        assert len(owners) == 1, f"{name} is no field of one part of LocalizerParams"
        parts[owners[0]] = replace(parts[owners[0]], **{name: value})
    return LocalizerParams(**parts)  # type: ignore[arg-type]
