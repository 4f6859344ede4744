"""Issue 3's figures: stereo rendering rate at 640 x 480 and the time to simulate (and record) 60 s of flight.

    python -m bench.bench_render [--building data/buildings/office_a.ifc] [--frames 60] [--flight-s 60]

Rendering is Mesa llvmpipe on the CPU through EGL: it shares the cores with everything else running, so the
load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import row

ROOT = Path(__file__).resolve().parents[1]
TARGET_FPS = 60.0


def bench_render(building: Path, n_frames: int) -> list[str]:
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.simulator import SimulationParams, Simulator

    t0 = time.perf_counter()
    sim = Simulator(building, SimulationParams(seed=1, flight=FlightParams(duration_s=60.0)))
    setup_s = time.perf_counter() - t0
    times = np.linspace(0.0, sim.trajectory.duration_s, n_frames)
    poses = [sim.trajectory.T_cad_body(float(t)) @ sim.T_body_cam for t in times]
    sim.renderer.render_stereo(poses[0], sim.lighting)  # warm-up: shader compilation
    t0, c0 = time.perf_counter(), time.process_time()
    for i, T in enumerate(poses):
        sim.renderer.render_stereo(T, sim.lighting, float(i))
    render_fps = n_frames / (time.perf_counter() - t0)
    cpu_ms = (time.process_time() - c0) / n_frames * 1000.0  # all threads (llvmpipe uses one per core)
    t0 = time.perf_counter()
    for i, t in enumerate(times):
        sim.render_at(i, float(t))
    frame_fps = n_frames / (time.perf_counter() - t0)
    cam = sim.params.camera
    tris = len(sim.scene.triangles_cad)
    sim.close()
    return [
        row(f"scene set-up ({building.name}, {tris} triangles)", f"{setup_s:.1f} s", ""),
        row(f"stereo pairs rendered, {cam.width}x{cam.height} (+depth, ids)", f"{render_fps:.1f} pairs/s",
            f">= {TARGET_FPS:.0f} pairs/s", render_fps >= TARGET_FPS),
        row("  CPU time per pair (all threads; load-independent)", f"{cpu_ms:.0f} ms", ""),
        row(f"  => on {os.cpu_count()} idle cores, at best", f"{1000.0 * (os.cpu_count() or 1) / cpu_ms:.0f} pairs/s",
            f">= {TARGET_FPS:.0f} pairs/s"),
        row("  with ground truth per frame", f"{frame_fps:.1f} frames/s", ""),
    ]


def bench_flight(building: Path, flight_s: float) -> list[str]:
    from macroloc.cli.simulated_flight import simulate_to_mcap
    from macroloc.service.config import load_config

    cfg = load_config(None)
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": flight_s})})
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "flight.mcap"
        t0 = time.perf_counter()
        summary = simulate_to_mcap(building, out, cfg, seed=1)
        wall = time.perf_counter() - t0
        size_mb = out.stat().st_size / 1e6
    ratio = wall / flight_s
    return [row(f"simulate + record {flight_s:.0f} s of flight ({building.name})", f"{wall:.0f} s ({ratio:.1f}x real)",
                "a few times real time", ratio <= 5.0),
            row("  frames, recording size", f"{summary['frames']}, {size_mb:.0f} MB", "")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--frames", type=int, default=60, help="stereo pairs to time")
    ap.add_argument("--flight-s", type=float, default=60.0, help="flight to simulate and record (0: skip)")
    args = ap.parse_args()
    print(f"# bench_render on {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    for line in bench_render(args.building, args.frames):
        print(line, flush=True)
    if args.flight_s > 0:
        for line in bench_flight(args.building, args.flight_s):
            print(line, flush=True)
    print(f"# load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
