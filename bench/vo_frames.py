"""Whole rendered flights for the odometry benchmark (bench.bench_odometry): every frame's grey stereo pair and
true camera pose, cached under /tmp/macroloc-vo-frames as .npy files read by memory map (rendering is the slow
part, ~0.2 s of CPU a frame).

    python -m bench.vo_frames --building data/buildings/office_a.ifc --seed 5 [--duration 60]

The frames are written as they are rendered (`count` says how many are done), so a flight cut short can be
benchmarked as far as it got. Grey, not BGR: the odometry converts to grey first (perception.stereo.to_gray).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

CACHE = Path("/tmp/macroloc-vo-frames")


@dataclass(frozen=True)
class Flight:
    """left/right: (N, H, W) uint8 grey (memory-mapped); T_cad_cam: (N, 4, 4) the true left camera poses;
    rig: (fx, fy, cx, cy, baseline_m, w, h)."""

    name: str
    left: np.ndarray
    right: np.ndarray
    T_cad_cam: np.ndarray
    rig: tuple[float, ...]


def folder(building: Path, seed: int, duration_s: float) -> Path:
    return CACHE / f"{building.stem}-s{seed}-{int(duration_s)}s"


def render(building: Path, seed: int, duration_s: float) -> Path:
    """The flight's folder, rendered first where absent, or on from where it stopped where unfinished (one
    process at a time: two rendering the same flight write the same files)."""
    out = folder(building, seed, duration_s)
    meta = out / "meta.json"
    done = json.loads(meta.read_text())["count"] if meta.exists() else 0
    if meta.exists() and done == json.loads(meta.read_text())["frames"]:
        return out
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.simulator import SimulationParams, Simulator

    sim = Simulator(building, SimulationParams(seed=seed, flight=FlightParams(duration_s=duration_s)))
    cam = sim.params.camera
    times = sim.frame_times_s
    n = len(times)
    out.mkdir(parents=True, exist_ok=True)
    shape = (n, int(cam.height), int(cam.width))
    mode = "r+" if done else "w+"
    left = np.lib.format.open_memmap(out / "left.npy", mode, np.uint8, shape)
    right = np.lib.format.open_memmap(out / "right.npy", mode, np.uint8, shape)
    T = np.stack([sim.trajectory.T_cad_body(float(t)) @ sim.T_body_cam for t in times])
    np.save(out / "T_cad_cam.npy", T)
    info = {"frames": n, "count": done,
            "rig": [cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m, cam.width, cam.height]}
    try:
        for i, t in enumerate(times):
            if i < done:
                continue
            f = sim.render_at(i, float(t))
            left[i] = cv2.cvtColor(f.left_bgr, cv2.COLOR_BGR2GRAY)
            right[i] = cv2.cvtColor(f.right_bgr, cv2.COLOR_BGR2GRAY)
            if i % 30 == 29 or i == n - 1:
                left.flush()
                right.flush()
                info["count"] = i + 1
                meta.write_text(json.dumps(info))
    finally:
        sim.close()
    return out


def cached(building: Path, seed: int, duration_s: float) -> Path:
    """The flight's folder as it is where there is one (perhaps still rendering elsewhere), else rendered."""
    out = folder(building, seed, duration_s)
    return out if (out / "meta.json").exists() else render(building, seed, duration_s)


def load(path: Path, frames: int | None = None) -> Flight:
    """The rendered frames so far (at most `frames`)."""
    info = json.loads((path / "meta.json").read_text())
    n = info["count"] if frames is None else min(frames, info["count"])
    return Flight(path.name, np.load(path / "left.npy", mmap_mode="r")[:n],
                  np.load(path / "right.npy", mmap_mode="r")[:n], np.load(path / "T_cad_cam.npy")[:n],
                  tuple(float(v) for v in info["rig"]))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--building", type=Path, required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--duration", type=float, default=60.0)
    args = ap.parse_args(argv)
    path = render(args.building, args.seed, args.duration)
    print(path, load(path).left.shape)


if __name__ == "__main__":
    main()
