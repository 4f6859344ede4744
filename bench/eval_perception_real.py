"""The real stereo pairs (../shared/data/stereo/rtabmap_stereo_rect, frames 50 and 60): the double doors detected
and reconstructed; width, height and tilt from vertical, and a picture.

    python -m bench.eval_perception_real [--out out/perception]

A real double door is about 1.6-1.9 m wide and 2.0-2.4 m tall. No gravity is given (the pairs have no IMU), so
tilt is measured against the camera's y axis: it includes the camera's own roll and pitch.
Besides the whole chain, the chain after the detector runs on a box drawn by hand around the double doors
(`HAND_BOX_PX`), so the reconstruction is measured even where the detector misses them.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HAND_BOX_PX = {"50": (110.0, 143.0, 212.0, 290.0), "60": (178.0, 114.0, 280.0, 252.0)}  # by eye: the double doors
PAIR = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "stereo" / "rtabmap_stereo_rect"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "perception")
    args = ap.parse_args(argv)
    from macroloc.perception.calib import read_stereo_rig
    from macroloc.perception.detector import Detection
    from macroloc.perception.draw import draw_features
    from macroloc.perception.pipeline import Perception, StereoPair

    rig = read_stereo_rig(PAIR / "stereo_left.yaml", PAIR / "stereo_right.yaml")
    chain = Perception.create()
    args.out.mkdir(parents=True, exist_ok=True)
    report: dict[str, object] = {}
    tiles = []
    for frame in ("50", "60"):
        left = cv2.imread(str(PAIR / "left" / f"{frame}.jpg"))
        right = cv2.imread(str(PAIR / "right" / f"{frame}.jpg"), cv2.IMREAD_GRAYSCALE)
        pair = StereoPair(left, right, rig)
        result = chain.process(pair)
        hand = chain.process_boxes(pair, [Detection("door", 1.0, HAND_BOX_PX[frame])])
        report[frame] = {
            "hand_box": {"box_xyxy": list(HAND_BOX_PX[frame]),
                         "features": [{**f.to_json(), "sides_from_lines": list(f.sides_from_lines)}
                                      for f in hand.features],
                         "rejected": [r.reason for r in hand.rejected]},
            "detections": [d.to_json() for d in result.detections],
            "features": [{**f.to_json(), "sides_from_lines": list(f.sides_from_lines)} for f in result.features],
            "rejected": [{**r.detection.to_json(), "reason": r.reason} for r in result.rejected],
            "timings_ms": {k: round(v, 2) for k, v in result.timings_ms.items()},
        }
        tiles.append(draw_features(left, result.features, result.rejected))
        tiles.append(draw_features(left, hand.features, hand.rejected))
    picture = args.out / "real_double_doors.png"
    cv2.imwrite(str(picture), np.vstack([np.hstack(tiles[0::2]), np.hstack(tiles[1::2])]))  # rows: detector, hand
    (args.out / "real_double_doors.json").write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report, indent=1))
    print(f"picture: {picture}")


if __name__ == "__main__":
    main()
