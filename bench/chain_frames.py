"""Rendered stereo frames for the chain benchmark (bench.bench_chain): a stretch of a simulated flight with doors
or windows in view, cached as one .npz (rendering is the slow part).

    python -m bench.chain_frames [--building data/buildings/office_a.ifc] [--seed 1] [--frames 60]

The stretch is the `frames` consecutive frames (30 Hz) of a `duration`-s flight holding the most frames with a
door or window at least half visible and 150 px^2 or larger (consecutive: the visual odometry needs them).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path("/tmp/macroloc-chain-frames")


@dataclass(frozen=True)
class ChainFrames:
    """left/right: (N, H, W, 3) uint8 BGR; rig: (fx, fy, cx, cy, baseline_m, w, h); T_cad_cam: (N, 4, 4);
    boxes: per frame the true boxes ((type, (x0, y0, x1, y1)), ...) of the openings in view; corners_cam: per box its
    true corners (4, 3) in the camera frame (TL, TR, BR, BL in the image), None unless all 4 are in view."""

    left: np.ndarray
    right: np.ndarray
    rig: tuple[float, ...]
    T_cad_cam: np.ndarray
    boxes: list[list[tuple[str, tuple[float, float, float, float]]]]
    stamps_ns: np.ndarray
    corners_cam: list[list[np.ndarray | None]]


def _in_view(frame) -> list:  # type: ignore[no-untyped-def, type-arg]
    return [f for f in frame.features if f.visible_fraction >= 0.5
            and (f.box_xyxy[2] - f.box_xyxy[0]) * (f.box_xyxy[3] - f.box_xyxy[1]) >= 150]


def _boxes(frame) -> list[tuple[str, tuple[float, float, float, float]]]:  # type: ignore[no-untyped-def]
    return [(f.type, (float(f.box_xyxy[0]), float(f.box_xyxy[1]), float(f.box_xyxy[2]), float(f.box_xyxy[3])))
            for f in _in_view(frame)]


def _corners(frame) -> list[list[list[float]] | None]:  # type: ignore[no-untyped-def]
    from bench.eval_perception_sim import order_tl_tr_br_bl

    return [order_tl_tr_br_bl(f.corners_cam, f.corners_px).tolist() if np.all(f.corner_visible) else None
            for f in _in_view(frame)]


def render(building: Path, seed: int, frames: int, duration_s: float) -> Path:
    """The cached file for these arguments, rendered first where absent."""
    out = CACHE / f"{building.stem}-s{seed}-{frames}f-{int(duration_s)}s-v2.npz"
    if out.exists():
        return out
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.simulator import SimulationParams, Simulator

    sim = Simulator(building, SimulationParams(seed=seed, flight=FlightParams(duration_s=duration_s)))
    cam = sim.params.camera
    times = sim.frame_times_s
    step = 3  # a coarse look for the doors first: every third frame
    seen = np.zeros(len(times), bool)
    for i in range(0, len(times), step):
        seen[i:i + step] = bool(_in_view(sim.render_at(i, float(times[i]))))
    counts = np.convolve(seen, np.ones(frames), mode="valid")
    start = int(np.argmax(counts))
    rendered = [sim.render_at(i, float(times[i])) for i in range(start, start + frames)]
    sim.close()
    CACHE.mkdir(parents=True, exist_ok=True)
    boxes = np.array([repr(_boxes(f)) for f in rendered])
    corners = np.array([repr(_corners(f)) for f in rendered])
    np.savez_compressed(out, left=np.stack([f.left_bgr for f in rendered]),
                        right=np.stack([f.right_bgr for f in rendered]),
                        rig=np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m, cam.width, cam.height]),
                        T_cad_cam=np.stack([f.T_cad_body @ sim.T_body_cam for f in rendered]),
                        boxes=boxes, stamps_ns=np.array([f.stamp_ns for f in rendered]), corners=corners)
    return out


def load(path: Path) -> ChainFrames:
    import ast

    z = np.load(path)
    return ChainFrames(z["left"], z["right"], tuple(float(v) for v in z["rig"]), z["T_cad_cam"],
                       [ast.literal_eval(str(b)) for b in z["boxes"]], z["stamps_ns"],
                       [[None if c is None else np.array(c) for c in ast.literal_eval(str(f))] for f in z["corners"]])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--duration", type=float, default=30.0)
    args = ap.parse_args(argv)
    path = render(args.building, args.seed, args.frames, args.duration)
    frames = load(path)
    n_door = sum(bool(b) for b in frames.boxes)
    print(f"{path}: {len(frames.left)} frames, {n_door} with an opening in view")


if __name__ == "__main__":
    main()
