"""Issue 5's figure: iSAM2 update time per keyframe at 100 and 1000 keyframes (target <= 5 ms).

    python -m bench.bench_posegraph [--keyframes 1100]

A drone flies laps of a 40 m x 20 m loop corridor lined with doors and windows (0.3 m per keyframe, every
door re-observed on each lap: loop closures), localized in the model after a few metres, so the graph holds
keyframes, landmarks, the CAD anchor and its robust links. The update time is iSAM2's alone (new factors
only); the whole `Localizer.add_keyframe` (association, registration, links) is printed beside it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.common import row, time_ms
from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.localizer import Localizer, Sighting
from macroloc.graph.registrar import StoredMapRegistrar
from macroloc.graph.relocalize import KnownRect
from macroloc.service.session import make_localizer

LOOP_X_M, LOOP_Y_M, STEP_M = 40.0, 20.0, 0.3


def loop_building(seed: int = 0) -> BuildingModel:
    """Doors/windows on the outer and inner walls of a rectangular loop corridor (2.4 m wide)."""
    rng = np.random.default_rng(seed)
    feats = []
    for k, s in enumerate(np.arange(0.0, 2 * (LOOP_X_M + LOOP_Y_M), 2.7)):
        p, t = _loop_point(s + rng.uniform(-0.6, 0.6))
        outward = np.array([t[1], -t[0], 0.0])  # right of the direction of travel: the outer wall
        side = 1.0 if k % 2 == 0 else -1.0
        kind = "window" if k % 3 == 2 else "door"
        n = side * outward
        centre = p + 1.2 * n + np.array([0.0, 0.0, 1.05 if kind == "door" else 1.5])
        w, h = rng.uniform(0.8, 1.3), (2.1 if kind == "door" else 1.2)
        u = np.cross(n, [0.0, 0.0, 1.0])
        corners = np.array([centre + a * w / 2 * u + b * h / 2 * np.array([0, 0, 1.0])
                            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        feats.append(MacroFeature(f"F{k:03d}", kind, "L1", corners, centre, n, w, h))  # type: ignore[arg-type]
    return BuildingModel("loop", "loop-bench", feats, storeys=["L1"])


def _loop_point(s: float) -> tuple[np.ndarray, np.ndarray]:
    """Point (3,) at arc length s along the loop's centre line (z = 1.4 m) and its unit tangent."""
    s %= 2 * (LOOP_X_M + LOOP_Y_M)
    legs = [(np.array([0.0, 0.0]), np.array([1.0, 0.0]), LOOP_X_M), (np.array([LOOP_X_M, 0.0]), np.array([0.0, 1.0]),
            LOOP_Y_M), (np.array([LOOP_X_M, LOOP_Y_M]), np.array([-1.0, 0.0]), LOOP_X_M),
            (np.array([0.0, LOOP_Y_M]), np.array([0.0, -1.0]), LOOP_Y_M)]
    for start, d, length in legs:
        if s <= length:
            xy = start + s * d
            return np.array([xy[0], xy[1], 1.4]), np.array([d[0], d[1], 0.0])
        s -= length
    raise AssertionError("unreachable")


def sightings(model: BuildingModel, T_cad_body: np.ndarray, rng: np.random.Generator) -> list[Sighting]:
    T_body_cad = np.linalg.inv(T_cad_body)
    out = []
    for f in model.features:
        corners = (T_body_cad[:3, :3] @ f.corners_cad.T).T + T_body_cad[:3, 3]
        c = corners.mean(axis=0)
        if 0.5 < c[0] < 6.0 and abs(np.arctan2(c[1], c[0])) < np.radians(50):
            out.append(Sighting(f.type, corners + rng.normal(0, 0.02, corners.shape)))
    return out


def run(n_keyframes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, Localizer]:
    """Wall and CPU ms of each keyframe's iSAM2 update, wall ms of each whole add_keyframe, the localizer."""
    model = loop_building()
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features]
    loc = make_localizer(model, registrar=StoredMapRegistrar(known))  # the session's factory, this registrar
    rng = np.random.default_rng(1)
    update_ms, step_ms, cpu_ms = np.zeros(n_keyframes), np.zeros(n_keyframes), np.zeros(n_keyframes)
    T_odom_cad = np.eye(4)
    T_odom_cad[:3, 3] = (5.0, -3.0, 0.0)
    drift = np.eye(4)
    for i in range(n_keyframes):
        p, t = _loop_point(i * STEP_M)
        yaw = np.arctan2(t[1], t[0]) + 0.25 * np.sin(0.2 * i)
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        T[:3, 3] = p
        drift[:3, 3] += rng.normal(0, 0.003, 3) * [1, 1, 0]
        start = time.perf_counter()
        loc.add_keyframe(i * 300_000_000, T_odom_cad @ drift @ T, sightings(model, T, rng), np.array([0, 0, 1.0]))
        step_ms[i] = (time.perf_counter() - start) * 1e3
        update_ms[i] = loc.graph.last_update_ms
        cpu_ms[i] = loc.graph.last_update_cpu_ms
    return update_ms, cpu_ms, step_ms, loc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=1100)
    args = parser.parse_args()
    update_ms, cpu_ms, step_ms, loc = run(args.keyframes)
    print(f"loop corridor: {len(loc.model.features)} features, {loc.graph.n_keyframes} keyframes, "
          f"{len(loc.landmarks)} landmarks, {len(loc.links)} CAD links, status {loc.status}")
    for at in (100, 1000):
        if at + 25 > args.keyframes:
            continue
        window = slice(at - 25, at + 25)
        med, p95 = float(np.median(update_ms[window])), float(np.percentile(update_ms[window], 95))
        cpu_med, cpu_p95 = float(np.median(cpu_ms[window])), float(np.percentile(cpu_ms[window], 95))
        print(row(f"iSAM2 update per keyframe at {at} keyframes (wall)", f"{med:.2f} ms (p95 {p95:.2f})",
                  "<= 5 ms", med <= 5.0))
        print(row(f"iSAM2 update per keyframe at {at} keyframes (CPU)", f"{cpu_med:.2f} ms (p95 {cpu_p95:.2f})",
                  "<= 5 ms", cpu_p95 <= 5.0))
        print(row(f"whole add_keyframe at {at} keyframes", f"{float(np.median(step_ms[window])):.2f} ms", "-"))
    last = loc.graph.n_keyframes - 1
    cov_ms = time_ms(lambda: loc.graph.covariance_cad_body(last), repeat=20)
    print(row(f"covariance of T_cad_body (marginals), {last + 1} keyframes", f"{float(np.median(cov_ms)):.2f} ms",
              "-"))


if __name__ == "__main__":
    main()
