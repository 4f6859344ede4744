"""Perception on simulated flights, against ground truth: detection AP on rendered frames, and 3D corner errors.

    python -m bench.eval_perception_sim [--building data/buildings/office_a.ifc] [--seeds 1 2] [--every 6]

For every `--every`-th frame: the whole chain (detector -> LSD sides -> SGBM -> 3D corners), and the same chain
fed the ground-truth boxes (`oracle boxes`: it measures sides + depth + 3D fit alone). A reconstructed feature
is matched to the ground-truth feature of the same type with the best box IoU (>= 0.5); its corners are
compared in the camera frame, the ground truth's ordered like ours (TL, TR, BR, BL in the image), only for
features with all 4 corners visible. Errors are binned by the ground truth's mean corner depth (z, m), for all
views and for views within 45 deg of head-on (corridor doors are often seen almost edge-on).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BINS_M = ((2.0, 4.0), (4.0, 8.0))
FRONTAL_DEG = 45.0


def view_angle_deg(corners_cam: np.ndarray) -> float:
    """Angle between the feature's normal and the line of sight to its centre (0 = seen head-on)."""
    normal = np.cross(corners_cam[1] - corners_cam[0], corners_cam[3] - corners_cam[0])
    sight = corners_cam.mean(axis=0)
    c = abs(normal @ sight) / (np.linalg.norm(normal) * np.linalg.norm(sight))
    return float(np.degrees(np.arccos(np.clip(c, 0.0, 1.0))))


def order_tl_tr_br_bl(corners_cam: np.ndarray, corners_px: np.ndarray) -> np.ndarray:
    """Reorder 4 corners (and their pixels) to top-left, top-right, bottom-right, bottom-left in the image."""
    by_v = np.argsort(corners_px[:, 1])
    top, bottom = by_v[:2], by_v[2:]
    tl, tr = top[np.argsort(corners_px[top, 0])]
    bl, br = bottom[np.argsort(corners_px[bottom, 0])]
    return corners_cam[[tl, tr, br, bl]]


def _iou(a, b) -> float:  # type: ignore[no-untyped-def]
    from macroloc.perception.evaluate import iou_xyxy

    return float(iou_xyxy(np.asarray([a], float), np.asarray([b], float))[0, 0])


def run(building: Path, seeds: list[int], every: int, duration_s: float,
        model: Path | None = None) -> dict[str, object]:
    from macroloc.perception.calib import StereoRig
    from macroloc.perception.detector import Detection
    from macroloc.perception.evaluate import GroundTruth, pr_curve
    from macroloc.perception.pipeline import Perception, StereoPair
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.simulator import SimulationParams, Simulator

    chain = Perception.create(model)
    errors: dict[str, dict[str, list[float]]] = {"detector": {}, "oracle_boxes": {}}
    counts = {"frames": 0, "truth_4_visible": 0}
    dets_all: list[list[Detection]] = []
    truths_all: list[list[GroundTruth]] = []
    for seed in seeds:
        sim = Simulator(building, SimulationParams(seed=seed, flight=FlightParams(duration_s=duration_s)))
        cam = sim.params.camera
        rig = StereoRig(cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m, cam.width, cam.height)
        times = sim.frame_times_s
        for i in range(0, len(times), every):
            frame = sim.render_at(i, float(times[i]))
            counts["frames"] += 1
            pair = StereoPair(frame.left_bgr, frame.right_bgr, rig)
            truths = [f for f in frame.features if f.visible_fraction >= 0.5 and
                      (f.box_xyxy[2] - f.box_xyxy[0]) * (f.box_xyxy[3] - f.box_xyxy[1]) >= 150]
            result = chain.process(pair)
            dets_all.append(chain.detector.detect(pair.left, score_threshold=0.01))
            truths_all.append([GroundTruth(t.type, tuple(float(v) for v in t.box_xyxy)) for t in truths])  # type: ignore[misc]
            oracle = chain.process_boxes(pair, [Detection(t.type, 1.0, tuple(float(v) for v in t.box_xyxy))  # type: ignore[arg-type]
                                                for t in truths])
            for name, feats in (("detector", result.features), ("oracle_boxes", oracle.features)):
                for t in truths:
                    if not np.all(t.corner_visible):
                        continue
                    if name == "detector":
                        counts["truth_4_visible"] += 1
                    cands = [f for f in feats if f.type == t.type and _iou(f.box_xyxy, t.box_xyxy) >= 0.5]
                    if not cands:
                        continue
                    best = max(cands, key=lambda f: _iou(f.box_xyxy, t.box_xyxy))  # noqa: B023
                    gt = order_tl_tr_br_bl(t.corners_cam, t.corners_px)
                    z = float(gt[:, 2].mean())
                    err = np.linalg.norm(best.corners_cam - gt, axis=1)
                    for lo, hi in BINS_M:
                        if lo <= z < hi:
                            errors[name].setdefault(f"{lo:g}-{hi:g} m, all views", []).extend(err)
                            if view_angle_deg(gt) <= FRONTAL_DEG:
                                errors[name].setdefault(f"{lo:g}-{hi:g} m, view <= {FRONTAL_DEG:g} deg", []).extend(err)
        sim.close()
    out: dict[str, object] = {"building": building.name, "seeds": seeds, **counts}
    for name, per_bin in errors.items():
        out[name] = {k: {"corners": len(v), "median_m": round(float(np.median(v)), 3),
                         "p90_m": round(float(np.percentile(v, 90)), 3)} for k, v in sorted(per_bin.items())}
    threshold = chain.detector.spec.score_threshold
    out["detection_ap50"] = {k: {"ap50": round(c.ap, 4), "n_truth": c.n_truth,
                                 "precision_recall_at_threshold": [round(v, 3) for v in c.at(threshold)]}
                             for k in ("door", "window") for c in [pr_curve(k, dets_all, truths_all)]}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--every", type=int, default=6)
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "perception" / "sim_eval.json")
    ap.add_argument("--model", type=Path, default=None, help="detector ONNX (default: the shipped one)")
    args = ap.parse_args(argv)
    figures = run(args.building, args.seeds, args.every, args.duration, args.model)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(figures, indent=1) + "\n")
    print(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
