"""The detector's figures on the held-out real test photos (never trained on), new beside old, from one run.

    python -m bench.eval_detector [--old /tmp/old/detector.onnx] [--rendered DIR ...] [--json out/detector/compare.json]

Indoor test split: `perception.trainset.split_indoor` (seed 0, by source photo); facade test split: img_n with
n % 5 == 0. Per model: door AP50 / AP30 and precision/recall at the model's own threshold, doors by height fraction
and doors cut by the border (indoor), windows and doors on the facades. The old model defaults to the shipped one
before issue 32 (from git). `--rendered DIR ...` adds rendered frames with YOLO labels (0 door, 1 window) of a building
never trained on, e.g. Office_A exported by `sim.export.render_training_frames`. A benchmark: it prints figures, it
asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

from bench.bench_detector import old_from_git
from macroloc.perception.detector import Detector

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "images"
TARGET_AP50 = 0.85


def score(model: Path, threads: int, rendered: list[Path]) -> dict[str, object]:
    from macroloc.perception import detector_eval
    from macroloc.perception.train import load_facades, load_indoor, load_sim

    detector = Detector(model, threads=threads)
    t = detector.spec.score_threshold
    out: dict[str, object] = {"threshold": t}
    parts = [("indoor_test", load_indoor(SHARED / "indoor_doors", 0)["test"]),
             ("facade_test", load_facades(SHARED / "facades", 0)["test"])]
    parts += [(f"rendered_{folder.name}", load_sim([folder])) for folder in rendered]
    for name, samples in parts:
        dets, truths = detector_eval.detect_all(detector, samples)
        out[name] = detector_eval.figures(samples, dets, truths, t, subsets=name == "indoor_test")
    out["real_double_door"] = real_double_door(detector)
    return out


def real_double_door(detector: Detector) -> dict[str, dict[str, float]]:
    """The real stereo pairs' double doors (rtabmap_stereo_rect, frames 50 and 60): the best score of a door box at
    IoU >= 0.5 with the hand-drawn box (`bench.eval_perception_real.HAND_BOX_PX`), and that IoU."""
    import cv2
    import numpy as np

    from bench.eval_perception_real import HAND_BOX_PX, PAIR
    from macroloc.perception.evaluate import iou_xyxy

    out = {}
    for frame, hand in HAND_BOX_PX.items():
        image = cv2.imread(str(PAIR / "left" / f"{frame}.jpg"))
        if image is None:
            continue
        doors = [d for d in detector.detect(image, score_threshold=0.01) if d.type == "door"]
        overlap = iou_xyxy(np.array([d.box_xyxy for d in doors]).reshape(-1, 4), np.array([hand]))[:, 0]
        score = np.array([d.score for d in doors])
        found = np.flatnonzero(overlap >= 0.5)
        k = found[np.argmax(score[found])] if len(found) else None
        out[frame] = {"door_score": 0.0 if k is None else round(float(score[k]), 3),
                      "iou": 0.0 if k is None else round(float(overlap[k]), 2)}
    return out


def _pr(v: dict) -> str:  # type: ignore[type-arg]
    return (f"AP50 {v['ap50']:.3f}  AP30 {v['ap30']:.3f}  P {v['precision_at_threshold']:.3f}  "
            f"R {v['recall_at_threshold']:.3f}  (n={v['n_truth']})")


def lines(name: str, fig: dict) -> list[str]:  # type: ignore[type-arg]
    ind, fac = fig["indoor_test"], fig["facade_test"]
    d = ind["door"]
    rows = [f"{name}: threshold {fig['threshold']:.2f}",
            f"  indoor door  AP50 {d['ap50']:.3f}  AP30 {d['ap30']:.3f}  P {d['precision_at_threshold']:.3f}  "
            f"R {d['recall_at_threshold']:.3f}  (n={d['n_truth']}; target AP50 >= {TARGET_AP50})"]
    for k, v in list(ind["door_by_height_fraction"].items()) + [("truncated", ind["door_truncated"])]:
        rows.append(f"    door {k:<10} {_pr(v)}")
    for k in ("window", "door"):
        rows.append(f"  facade {k:<6} {_pr(fac[k])}")
    rows.append("  real double door (rtabmap), best door box at IoU >= 0.5: " + ", ".join(
        f"frame {k} score {v['door_score']:.3f} (IoU {v['iou']:.2f})" for k, v in fig["real_double_door"].items()))
    for part in (p for p in fig if p.startswith("rendered_")):
        for k in ("door", "window"):
            rows.append(f"  {part} {k:<6} {_pr(fig[part][k])}")
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--new", type=Path, default=None, help="ONNX model (default: the shipped one)")
    ap.add_argument("--old", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rendered", type=Path, nargs="*", default=[],
                    help="folders of rendered frames (images/, labels/) of buildings never trained on, one part each")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    from macroloc.perception.detector import DEFAULT_MODEL

    report = {}
    with tempfile.TemporaryDirectory() as tmp:
        old = args.old or old_from_git(Path(tmp))
        for name, path in [("new", args.new or DEFAULT_MODEL)] + ([("old", old)] if old else []):
            report[name] = score(path, args.threads, args.rendered)
            print("\n".join(lines(name, report[name])), flush=True)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
