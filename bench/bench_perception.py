"""Per-frame time of the perception chain at 640 x 480, stage by stage, beside the 30 frames/s budget.

    python -m bench.bench_perception [--frames 60] [--json]

Uses the real rectified pair in ../shared/data/stereo/rtabmap_stereo_rect (a synthetic textured pair when
absent). A benchmark: it prints figures, it asserts nothing. onnxruntime and OpenCV get 2 threads (2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PAIR = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "stereo" / "rtabmap_stereo_rect"
BUDGET_MS = 1000.0 / 30.0


def load_pair():  # type: ignore[no-untyped-def]
    from macroloc.perception.calib import StereoRig, read_stereo_rig
    from macroloc.perception.pipeline import StereoPair

    if PAIR.exists():
        rig = read_stereo_rig(PAIR / "stereo_left.yaml", PAIR / "stereo_right.yaml")
        return StereoPair(cv2.imread(str(PAIR / "left" / "50.jpg")), cv2.imread(str(PAIR / "right" / "50.jpg"), 0),
                          rig), "rtabmap_stereo_rect/50"
    rng = np.random.default_rng(0)
    left = cv2.resize(rng.uniform(0, 255, (120, 176)).astype(np.uint8), (704, 480))
    rig = StereoRig(480.0, 480.0, 319.5, 239.5, 0.12, 640, 480)
    return StereoPair(left[:, 20:660].copy(), left[:, 4:644].copy(), rig), "synthetic textured pair"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cv2.setNumThreads(2)
    from macroloc.perception.pipeline import Perception

    chain = Perception.create(threads=2)
    pair, source = load_pair()
    for _ in range(5):
        chain.process(pair)  # warm-up
    laps: dict[str, list[float]] = {}
    totals = []
    for _ in range(args.frames):
        t0 = time.perf_counter()
        result = chain.process(pair)
        totals.append((time.perf_counter() - t0) * 1e3)
        for k, v in result.timings_ms.items():
            laps.setdefault(k, []).append(v)
    # A frame with one door: the hand-drawn double-door box of bench.eval_perception_real (the detector misses it).
    from bench.eval_perception_real import HAND_BOX_PX
    from macroloc.perception.detector import Detection

    door = [Detection("door", 1.0, HAND_BOX_PX["50"])]
    laps_door: dict[str, list[float]] = {}
    for _ in range(args.frames):
        t0 = time.perf_counter()
        r_door = chain.process_boxes(pair, door)
        r_door.timings_ms["detect"] = float(np.median(laps["detect"]))  # the detector runs on every frame alike
        for k, v in r_door.timings_ms.items():
            laps_door.setdefault(k, []).append(v)
    # The same two independent stages overlapped: detector and SGBM in two threads (both release the GIL).
    overlapped = []
    with ThreadPoolExecutor(2) as pool:
        for _ in range(args.frames):
            t0 = time.perf_counter()
            f_det = pool.submit(chain.detector.detect, pair.left)
            f_disp = pool.submit(chain.matcher.disparity_px, pair.left, pair.right)
            f_det.result(), f_disp.result()
            overlapped.append((time.perf_counter() - t0) * 1e3)
    figures = {
        "source": source, "frames": args.frames, "detections": len(result.detections),
        "features": len(result.features),
        "stage_median_ms": {k: round(float(np.median(v)), 2) for k, v in laps.items()},
        "total_median_ms": round(float(np.median(totals)), 2),
        "total_p90_ms": round(float(np.percentile(totals, 90)), 2),
        "detect_and_stereo_overlapped_median_ms": round(float(np.median(overlapped)), 2),
        "with_one_door_stage_median_ms": {k: round(float(np.median(v)), 2) for k, v in laps_door.items()},
        "with_one_door_total_median_ms": round(float(np.median([sum(x) for x in zip(*laps_door.values(),
                                                                                     strict=True)])), 2),
        "budget_ms_at_30fps": round(BUDGET_MS, 2),
    }
    figures["fps_serial"] = round(1000.0 / figures["total_median_ms"], 1)  # type: ignore[operator]
    if args.json:
        print(json.dumps(figures))
        return
    print(f"perception chain at 640x480 on {source} ({args.frames} frames, 2 threads)")
    for k, v in figures["stage_median_ms"].items():  # type: ignore[union-attr]
        print(f"  {k:12s} {v:7.2f} ms")
    print(f"  {'total':12s} {figures['total_median_ms']:7.2f} ms median, {figures['total_p90_ms']:.2f} ms p90 "
          f"-> {figures['fps_serial']} frames/s (target >= 30, budget {BUDGET_MS:.1f} ms)")
    print(f"  detect || full-frame stereo in two threads: {figures['detect_and_stereo_overlapped_median_ms']:.2f} ms")
    print("with one door box in view (stereo on the rows the box spans):")
    for k, v in figures["with_one_door_stage_median_ms"].items():  # type: ignore[union-attr]
        print(f"  {k:12s} {v:7.2f} ms")
    total = figures["with_one_door_total_median_ms"]
    print(f"  {'total':12s} {total:7.2f} ms -> {1000.0 / total:.1f} frames/s")  # type: ignore[operator]


if __name__ == "__main__":
    main()
