"""Issue 5's figure: iSAM2 update time per keyframe at 100 and 1000 keyframes (target <= 5 ms).

    python -m bench.bench_posegraph [--keyframes 1100]
    python -m bench.bench_posegraph --long [--keyframes 10000] [--window W] [--chunk K] [--wall-fits]  # issue 37
    python -m bench.bench_posegraph --long --loop 10 5 --windowed-only   # a small loop: its doors mapped by 100

A drone flies laps of a 40 m x 20 m loop corridor lined with doors and windows (0.3 m per keyframe, every
door re-observed on each lap: loop closures), localized in the model after a few metres, so the graph holds
keyframes, landmarks, the CAD anchor and its robust links. The update time is iSAM2's alone (new factors
only); the whole `Localizer.add_keyframe` (association, registration, links) is printed beside it.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from bench.common import row, time_ms
from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.localizer import Localizer, Sighting
from macroloc.graph.posegraph import IsamSettings
from macroloc.graph.registrar import SavedMapRegistrar
from macroloc.graph.relocalize import KnownRect
from macroloc.service.localizer_loop import make_localizer

LOOP_X_M, LOOP_Y_M, STEP_M = 40.0, 20.0, 0.3
WALL_FIT_INFORMATION = np.diag(np.r_[np.full(3, 0.02**-2), np.full(3, 0.03**-2)])  # [rot; trans] a wall fit's


def loop_building(seed: int = 0, size_m: tuple[float, float] = (LOOP_X_M, LOOP_Y_M)) -> BuildingModel:
    """Doors/windows on the outer and inner walls of a rectangular loop corridor (2.4 m wide), `size_m` (x, y) its
    centre line's sides."""
    rng = np.random.default_rng(seed)
    feats = []
    for k, s in enumerate(np.arange(0.0, 2 * sum(size_m), 2.7)):
        p, t = _loop_point(s + rng.uniform(-0.6, 0.6), size_m)
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


def _loop_point(s: float, size_m: tuple[float, float] = (LOOP_X_M, LOOP_Y_M)) -> tuple[np.ndarray, np.ndarray]:
    """Point (3,) at arc length s along the loop's centre line (z = 1.4 m) and its unit tangent."""
    x_m, y_m = size_m
    s %= 2 * (x_m + y_m)
    legs = [(np.array([0.0, 0.0]), np.array([1.0, 0.0]), x_m), (np.array([x_m, 0.0]), np.array([0.0, 1.0]), y_m),
            (np.array([x_m, y_m]), np.array([-1.0, 0.0]), x_m), (np.array([0.0, y_m]), np.array([0.0, -1.0]), y_m)]
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


def run(n_keyframes: int, settings: IsamSettings | None = None, step_cpu_ms: np.ndarray | None = None,
        reeliminated: np.ndarray | None = None, error_m: np.ndarray | None = None,
        wall_fits: bool = False, size_m: tuple[float, float] = (LOOP_X_M, LOOP_Y_M)
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Localizer]:
    """Wall and CPU ms of each keyframe's iSAM2 update, wall ms of each whole add_keyframe, the localizer; the
    CPU ms of each whole add_keyframe into `step_cpu_ms`, the variables iSAM2 re-eliminated in its last update
    into `reeliminated` and the newest keyframe's position error in the model (NaN before localized) into
    `error_m`, where given. `wall_fits`: once localized, every keyframe also gets a T_cad_body measurement and a
    second update, as the localizer's fit of its depth to the walls gives one (`SurfaceFitter.fit_newest`, not
    run here: the bench has no depth): a factor between the anchor and every keyframe."""
    model = loop_building(size_m=size_m)
    known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features]
    loc = make_localizer(model, isam=settings, registrar=SavedMapRegistrar(known))  # the session's factory
    rng = np.random.default_rng(1)
    update_ms, step_ms, cpu_ms = np.zeros(n_keyframes), np.zeros(n_keyframes), np.zeros(n_keyframes)
    T_odom_cad = np.eye(4)
    T_odom_cad[:3, 3] = (5.0, -3.0, 0.0)
    drift = np.eye(4)
    for i in range(n_keyframes):
        p, t = _loop_point(i * STEP_M, size_m)
        yaw = np.arctan2(t[1], t[0]) + 0.25 * np.sin(0.2 * i)
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        T[:3, 3] = p
        drift[:3, 3] += rng.normal(0, 0.003, 3) * [1, 1, 0]
        seen = sightings(model, T, rng)
        start, start_cpu = time.perf_counter(), time.process_time()
        loc.add_keyframe(i * 300_000_000, T_odom_cad @ drift @ T, seen, np.array([0, 0, 1.0]))
        update_ms[i], cpu_ms[i] = loc.graph.last_update_ms, loc.graph.last_update_cpu_ms
        if wall_fits and loc.graph.has_anchor:
            T_fit = T.copy()
            T_fit[:3, 3] += rng.normal(0, 0.03, 3)
            loc.graph.add_cad_pose(i, T_fit, WALL_FIT_INFORMATION)
            loc.graph.update()
            update_ms[i] += loc.graph.last_update_ms  # with the keyframe's own update, as the localizer's fit
            cpu_ms[i] += loc.graph.last_update_cpu_ms
        step_ms[i] = (time.perf_counter() - start) * 1e3
        if step_cpu_ms is not None:
            step_cpu_ms[i] = (time.process_time() - start_cpu) * 1e3
        if reeliminated is not None:
            reeliminated[i] = loc.graph.last_reeliminated
        if error_m is not None:
            T_cad_map = loc.graph.T_cad_map()
            error_m[i] = np.nan if T_cad_map is None else \
                float(np.linalg.norm((T_cad_map @ loc.graph.T_map_body(i))[:3, 3] - T[:3, 3]))
    return update_ms, cpu_ms, step_ms, loc


def long_mission(n_keyframes: int, window: int, chunk: int, wall_fits: bool,
                 size_m: tuple[float, float] = (LOOP_X_M, LOOP_Y_M), all_kept: bool = True) -> None:
    """Issue 37's table: CPU ms per keyframe (iSAM2's update, the whole add_keyframe), mean over the last 100
    keyframes before 100 / 1,000 / 10,000 (those reached), without a window (all keyframes kept, unless not
    `all_kept`), with one keeping every door mapped, and with one marginalising the doors out of sight (the
    default), on a loop of `size_m`."""
    at = [n for n in (100, 1000, 3000, 10000) if n <= n_keyframes]
    results = {}
    windowed = IsamSettings(window_keyframes=window, marginalise_every=chunk)
    lap = 2 * sum(size_m) / STEP_M
    print(f"loop {size_m[0]:g} x {size_m[1]:g} m: {len(loop_building(size_m=size_m).features)} doors and windows, "
          f"{lap:.0f} keyframes a lap")
    runs = ((("all kept", IsamSettings(window_keyframes=0)),) if all_kept else ()) + \
        ((f"window {window}/{chunk}, doors kept", replace(windowed, marginalise_landmarks=False)),
         (f"window {window}/{chunk}", windowed))
    for name, settings in runs:
        step_cpu, reelim, error_m = np.zeros(n_keyframes), np.zeros(n_keyframes), np.zeros(n_keyframes)
        _, cpu_ms, step_wall, loc = run(n_keyframes, settings, step_cpu, reelim, error_m, wall_fits, size_m)
        results[name] = (cpu_ms, step_cpu, step_wall, reelim, 1e3 * error_m)
        last = loc.graph.n_keyframes - 1
        cov_ms = float(np.median(time_ms(lambda: loc.graph.covariance_cad_body(last), repeat=5)))  # noqa: B023
        print(f"{name}: {loc.graph.n_keyframes} keyframes, {len(loc.landmarks)} landmarks, {len(loc.links)} CAD links, "
              f"status {loc.status}, live keyframes {last + 1 - loc.graph.live_from}, live landmarks "
              f"{len(loc.landmarks) - len(loc.graph.marginalised_landmarks)}, covariance of the newest "
              f"T_cad_body (the service's, each keyframe) {cov_ms:.2f} ms wall")
    print(f"{'CPU ms, mean of the 100 keyframes before':60s}" + "".join(f"{n:>10d}" for n in at)
          + f"{'ratio ' + str(at[-1]) + '/100':>16s}  target <= 2")
    for name, (cpu_ms, step_cpu, step_wall, reelim, error_mm) in results.items():
        ratios = {}
        for what, values in (("iSAM2 update", cpu_ms), ("whole add_keyframe", step_cpu),
                             ("whole add_keyframe, wall ms", step_wall),
                             ("variables re-eliminated (count)", reelim), ("newest keyframe's error, mm", error_mm)):
            means = [float(np.nanmean(values[n - 100:n])) for n in at]
            ratios[what] = means[-1] / means[0]
            print(f"{name + ', ' + what:60s}" + "".join(f"{m:10.2f}" for m in means) + f"{ratios[what]:16.2f}")
        step = ratios["whole add_keyframe"]
        print(row(f"{name}: whole add_keyframe CPU, {at[-1]} / 100 keyframes", f"{step:.2f}", "<= 2", step <= 2.0))
    print("threads: 1 (this GTSAM wheel links no TBB or OpenMP; the localizer's numpy works on small matrices)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=1100)
    parser.add_argument("--long", action="store_true", help="issue 37's table: old (all kept) vs windowed")
    parser.add_argument("--window", type=int, default=IsamSettings().window_keyframes or 100,
                        help="keyframes kept behind the newest (--long)")
    parser.add_argument("--chunk", type=int, default=IsamSettings().marginalise_every,
                        help="keyframes marginalised at a time (--long)")
    parser.add_argument("--wall-fits", action="store_true", help="a T_cad_body factor on every keyframe (--long)")
    parser.add_argument("--loop", type=float, nargs=2, default=(LOOP_X_M, LOOP_Y_M), metavar=("X", "Y"),
                        help="the loop corridor's sides, m (--long; a lap is 2 (X + Y) / 0.3 keyframes)")
    parser.add_argument("--windowed-only", action="store_true", help="skip the all-kept run (--long)")
    args = parser.parse_args()
    if args.long:
        long_mission(args.keyframes, args.window, args.chunk, args.wall_fits, tuple(args.loop),
                     not args.windowed_only)
        return
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
