"""Rendered frames with their ground truth, saved once for `bench.bench_size_check` (rendering is the slow part).

    python -m bench.size_check_frames [--building data/buildings/office_a.ifc] [--seeds 1 2] [--every 6]

Writes `<out>/<building>_s<seed>_<index>.npz`: left, right (BGR uint8), the truth's boxes, types, corners in the
camera frame (TL, TR, BR, BL in the image), which corners are visible, visible fraction, and the model's
width/height of each, plus the camera.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def render(building: Path, seeds: list[int], every: int, duration_s: float, out: Path) -> int:
    from bench.eval_perception_sim import order_tl_tr_br_bl
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.simulator import SimulationParams, Simulator

    out.mkdir(parents=True, exist_ok=True)
    n = 0
    for seed in seeds:
        sim = Simulator(building, SimulationParams(seed=seed, flight=FlightParams(duration_s=duration_s)))
        cam = sim.params.camera
        size = {f.id: (f.width_m, f.height_m) for f in sim.features}
        times = sim.frame_times_s
        for i in range(0, len(times), every):
            frame = sim.render_at(i, float(times[i]))
            truths = [t for t in frame.features if (t.box_xyxy[2] - t.box_xyxy[0]) * (t.box_xyxy[3] - t.box_xyxy[1])
                      >= 150]
            corners = [order_tl_tr_br_bl(t.corners_cam, t.corners_px) if (t.corners_cam[:, 2] > 0).all()
                       else t.corners_cam for t in truths]
            np.savez_compressed(
                out / f"{building.stem}_s{seed}_{i:05d}.npz", left=frame.left_bgr, right=frame.right_bgr,
                boxes=np.array([t.box_xyxy for t in truths], float).reshape(-1, 4),
                types=np.array([t.type for t in truths], str), corners_cam=np.array(corners, float).reshape(-1, 4, 3),
                corner_visible=np.array([t.corner_visible for t in truths], bool).reshape(-1, 4),
                visible_fraction=np.array([t.visible_fraction for t in truths], float),
                size_m=np.array([size[t.id] for t in truths], float).reshape(-1, 2),
                camera=np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m, cam.width, cam.height], float))
            n += 1
        sim.close()
    return n


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--every", type=int, default=6)
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "size_check" / "frames")
    args = ap.parse_args(argv)
    print(render(args.building, args.seeds, args.every, args.duration, args.out), "frames")


if __name__ == "__main__":
    main()
