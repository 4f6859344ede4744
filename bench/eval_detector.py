"""The detector's figures on the held-out real test photos (never trained on), new beside old, from one run.

    python -m bench.eval_detector [--old /tmp/old/detector.onnx] [--rendered DIR] [--json out/detector/compare.json]

Indoor test split: `perception.trainset.split_indoor` (seed 0, by source photo); facade test split: img_n with
n % 5 == 0. Per model: door AP50 / AP30 and precision/recall at the model's own threshold, doors by height fraction
and doors cut by the border (indoor), windows and doors on the facades. The old model defaults to the shipped one
before issue 32 (from git). `--rendered DIR` adds rendered frames with YOLO labels (0 door, 1 window) of a building
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

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "images"
TARGET_AP50 = 0.85


def score(model: Path, threads: int, rendered: Path | None) -> dict[str, object]:
    from macroloc.perception import detector_eval
    from macroloc.perception.detector import Detector
    from macroloc.perception.train import load_facades, load_indoor, load_sim

    detector = Detector(model, threads=threads)
    t = detector.spec.score_threshold
    out: dict[str, object] = {"threshold": t}
    parts = [("indoor_test", load_indoor(SHARED / "indoor_doors", 0)["test"]),
             ("facade_test", load_facades(SHARED / "facades", 0)["test"])]
    if rendered is not None:
        parts.append(("rendered", load_sim([rendered])))
    for name, samples in parts:
        dets, truths = detector_eval.detect_all(detector, samples)
        out[name] = detector_eval.figures(samples, dets, truths, t, subsets=name == "indoor_test")
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
    for k in ("door", "window") if "rendered" in fig else ():
        rows.append(f"  rendered {k:<6} {_pr(fig['rendered'][k])}")
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--new", type=Path, default=None, help="ONNX model (default: the shipped one)")
    ap.add_argument("--old", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rendered", type=Path, default=None, help="folder of rendered frames (images/, labels/)")
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
