"""The building checks the detector (issue 32): precision and recall of the detector alone, the detector with the
size check, geometry proposals alone, and both fused, on rendered frames with known truth; the chain's size error
(`--measure`, where `perception.size_check.SizeTolerance` comes from); the real stereo pairs.

    python -m bench.size_check_frames --seeds 1 2 3          # render once: out/size_check/frames
    python -m bench.bench_size_check [--frames out/size_check/frames] [--measure] [--real]

A feature is right when its box overlaps a truth's by IoU >= 0.5 (each truth taken once, best score first);
"openings" ignores the type, "doors" counts door features against door truths. Truths: at least half visible,
150 px or more, mean corner depth 0.5-12 m (the chain's plausible range). "close-up": truths (and, for
false positives, features) nearer than 3.5 m.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODES = ("cnn", "cnn+size", "geometry", "fused")
CLOSE_M = 3.5


def _rig(camera: np.ndarray):  # type: ignore[no-untyped-def]
    from macroloc.perception.calib import StereoRig

    c = camera
    return StereoRig(float(c[0]), float(c[1]), float(c[2]), float(c[3]), float(c[4]), int(c[5]), int(c[6]))


def building_sizes(path: Path):  # type: ignore[no-untyped-def]
    from macroloc.graph.bim import load_building
    from macroloc.perception.size_check import OpeningSizes

    return OpeningSizes.of((f.type, f.width_m, f.height_m) for f in load_building(path).features)


def _truths(d: dict) -> np.ndarray:  # type: ignore[type-arg]
    """Indices of the frame's truths that count."""
    z = d["corners_cam"][:, :, 2].mean(axis=1) if len(d["boxes"]) else np.zeros(0)
    return np.flatnonzero((d["visible_fraction"] >= 0.5) & (z > 0.5) & (z < 12.0))


def _match(boxes: list, scores: list, truth_boxes: np.ndarray) -> list[int]:  # type: ignore[type-arg]
    """For each feature (best score first) the truth index it takes, or -1."""
    from macroloc.perception.evaluate import iou_xyxy

    out = [-1] * len(boxes)
    if not boxes or not len(truth_boxes):
        return out
    iou = iou_xyxy(np.asarray(boxes, float), truth_boxes)
    taken: set[int] = set()
    for k in np.argsort(-np.asarray(scores)):
        for t in np.argsort(-iou[k]):
            if iou[k, t] < 0.5:
                break
            if int(t) not in taken:
                taken.add(int(t))
                out[k] = int(t)
                break
    return out


def evaluate(frames: list[Path], sizes) -> dict[str, object]:  # type: ignore[no-untyped-def]
    from macroloc.perception.model_check import ModelCheckedPerception
    from macroloc.perception.pipeline import Perception, StereoPair

    chain = Perception.create()
    runners = {"cnn": ModelCheckedPerception(chain, None), "cnn+size": ModelCheckedPerception(chain, sizes,
                                                                                             proposals=None),
               "geometry": ModelCheckedPerception(chain, sizes), "fused": ModelCheckedPerception(chain, sizes)}
    keys = [(m, c, s) for m in MODES for c in ("openings", "doors") for s in ("all", "close-up")]
    tally = {k: {"tp": 0, "fp": 0, "truths": 0} for k in keys}
    statuses: dict[str, dict[str, int]] = {m: {} for m in MODES}
    ms: dict[str, list[float]] = {"propose": [], "size_check": []}
    for path in frames:
        d = dict(np.load(path))
        pair = StereoPair(d["left"], d["right"], _rig(d["camera"]))
        dets = chain.detector.detect(pair.left)
        keep = _truths(d)
        tb, tt = d["boxes"][keep], d["types"][keep]
        tz = d["corners_cam"][keep][:, :, 2].mean(axis=1) if len(keep) else np.zeros(0)
        for mode in MODES:
            res = runners[mode].process_detections(pair, [] if mode == "geometry" else dets)
            if mode == "fused":
                for lap in ms:
                    ms[lap].append(res.timings_ms[lap])
            for f in res.features:
                statuses[mode][f"{f.source}/{f.size.status}"] = statuses[mode].get(f"{f.source}/{f.size.status}", 0) + 1
            for cat in ("openings", "doors"):
                feats = [f for f in res.features if cat == "openings" or f.feature.type == "door"]
                tsel = np.array([cat == "openings" or kind == "door" for kind in tt], bool)
                idx = np.flatnonzero(tsel)
                m = _match([f.feature.box_xyxy for f in feats], [f.feature.score for f in feats], tb[idx])
                for scope in ("all", "close-up"):
                    near = tz[idx] < CLOSE_M if scope == "close-up" else np.ones(len(idx), bool)
                    t = tally[(mode, cat, scope)]
                    t["truths"] += int(near.sum())
                    for f, ti in zip(feats, m, strict=True):
                        if ti >= 0 and near[ti]:
                            t["tp"] += 1
                        elif ti < 0 and (scope == "all" or float(f.feature.corners_cam[:, 2].mean()) < CLOSE_M):
                            t["fp"] += 1  # a wrong box has no truth's depth: its own
    out: dict[str, object] = {"frames": len(frames), "statuses": statuses,
                              "ms_median": {k: round(float(np.median(v)), 1) for k, v in ms.items() if v}}
    for (mode, cat, scope), t in tally.items():
        n_feat = t["tp"] + t["fp"]
        out[f"{mode} {cat} {scope}"] = {**t, "precision": round(t["tp"] / n_feat, 3) if n_feat else None,
                                        "recall": round(t["tp"] / t["truths"], 3) if t["truths"] else None}
    return out


def measure(frames: list[Path]) -> dict[str, object]:
    """Width and height errors (measured - the model's) of the chain's features matched to a truth (any type),
    dimensions not cut by the border, by depth: the figure `SizeTolerance` is drawn from."""
    from macroloc.perception.pipeline import Perception, StereoPair

    chain = Perception.create()
    err, depth = [], []
    for path in frames:
        d = dict(np.load(path))
        res = chain.process(StereoPair(d["left"], d["right"], _rig(d["camera"])))
        keep = _truths(d)
        m = _match([f.box_xyxy for f in res.features], [f.score for f in res.features], d["boxes"][keep])
        for f, k in zip(res.features, m, strict=True):
            if k < 0:
                continue
            tw, th = d["size_m"][keep[k]]
            for cut, e in zip(f.truncated, (f.width_m - tw, f.height_m - th), strict=True):
                if not cut:
                    err.append(abs(e))
                    depth.append(float(f.corners_cam[:, 2].mean()))
    e, z = np.array(err), np.array(depth)
    out: dict[str, object] = {"dimensions": len(e)}
    for lo, hi in ((0, 3), (3, 5), (5, 7), (7, 9), (9, 12)):
        s = (z >= lo) & (z < hi)
        if s.any():
            out[f"{lo}-{hi} m"] = {"n": int(s.sum()), "p50": round(float(np.median(e[s])), 3),
                                   "p95": round(float(np.percentile(e[s], 95)), 3), "max": round(float(e[s].max()), 3)}
    from macroloc.perception.size_check import SizeTolerance

    tol = SizeTolerance()
    out["within_tolerance"] = round(float(np.mean(e <= tol.floor_m + tol.per_m * z)), 3)
    return out


def real(sizes) -> dict[str, object]:  # type: ignore[no-untyped-def]
    """The rtabmap pairs (no BIM of that building: `sizes` is a stand-in model's)."""
    import cv2

    from bench.eval_perception_real import HAND_BOX_PX, PAIR
    from macroloc.perception.calib import read_stereo_rig
    from macroloc.perception.detector import Detection
    from macroloc.perception.model_check import ModelCheckedPerception
    from macroloc.perception.pipeline import Perception, StereoPair

    rig = read_stereo_rig(PAIR / "stereo_left.yaml", PAIR / "stereo_right.yaml")
    chain = Perception.create()
    out: dict[str, object] = {}
    for frame in ("50", "60"):
        left, right = cv2.imread(str(PAIR / "left" / f"{frame}.jpg")), cv2.imread(str(PAIR / "right" / f"{frame}.jpg"))
        assert left is not None and right is not None, f"the real pair {frame} is missing under {PAIR}"
        pair = StereoPair(left, right, rig)
        dets = chain.detector.detect(pair.left)
        per: dict[str, object] = {"detections": [d.to_json() for d in dets]}
        hand = [Detection("door", 1.0, HAND_BOX_PX[frame])]
        for mode, runner, given in (("cnn+size", ModelCheckedPerception(chain, sizes, proposals=None), dets),
                                    ("geometry", ModelCheckedPerception(chain, sizes), []),
                                    ("fused", ModelCheckedPerception(chain, sizes), dets),
                                    ("hand box+size", ModelCheckedPerception(chain, sizes, proposals=None), hand)):
            res = runner.process_detections(pair, given)
            per[mode] = {"features": [{k: v for k, v in f.to_json().items() if k != "corners_cam"}
                                      for f in res.features],
                         "proposals": [{"box_xyxy": [round(v) for v in p.box_xyxy], "width_m": round(p.width_m, 2),
                                        "height_m": round(p.height_m, 2), "depth_m": round(p.depth_m, 2)}
                                       for p in res.proposals],
                         "rejected": [f"{r.detection.type} {[round(v) for v in r.detection.box_xyxy]}: {r.reason}"
                                      for r in res.rejected]}
        out[frame] = per
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=Path, default=ROOT / "out" / "size_check" / "frames")
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--measure", action="store_true", help="the chain's size error instead")
    ap.add_argument("--real", action="store_true", help="the real stereo pairs instead (the building's sizes)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "size_check" / "bench.json")
    args = ap.parse_args(argv)
    frames = sorted(args.frames.glob(f"{args.building.stem}_s*.npz"))
    if args.measure:
        figures = measure(frames)
    elif args.real:
        figures = real(building_sizes(args.building))
    else:
        figures = evaluate(frames, building_sizes(args.building))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(figures, indent=1) + "\n")
    print(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
