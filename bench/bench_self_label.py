"""The self-labeller against the simulator's truth (issue 55, item 5): a simulated recording is labelled as
`macroloc adapt-detector --recording` labels a user's (service.offline.self_label.label_recording: the replay's
held poses, the generic detector by default), and every box is checked against the frame's ground truth.

A self-label is right when the simulator's truth has a door or window of its class in the frame (its instance mask
at least 30 pixels: sim.groundtruth) whose box (`GroundTruth.features_cam[k].box_xyxy`) it overlaps at IoU >= 0.5,
as a detection is matched (a label says "a door here", not which; `same_feature` counts those where it is also the
model's door the truth names).
Recall: of the truth labels in the labelled frames (visible fraction = mask pixels / the projected opening's area
>= the labeller's min_visible_fraction, box >= its min_box_px), the share that got a right self-label.
With --truth-out, the truth labels of the whole flight at the labeller's cadence (every_s) are written there too
(the truth-labelled adaptation to compare with).

    python -m bench.bench_self_label REC.mcap BUILDING.ifc --out DIR [--truth-out DIR] [--config C]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from macroloc.perception.trainset import YOLO_CLASSES, yolo_folder, yolo_line
from macroloc.proto.recording import decode_image, read_flight
from macroloc.service.config import load_config
from macroloc.service.offline.self_label import SelfLabelParams, clip_near, iou, label_recording
from macroloc.sim.scene import occluding_triangles


def truth_of_frame(frame, params: SelfLabelParams) -> dict[str, dict]:  # noqa: ANN001 - FlightFrame
    """{feature id: {type, box, fraction, pixels}} of a simulated frame's ground truth."""
    gt = frame.ground_truth
    mask = decode_image(frame.instances) if frame.instances is not None else None
    info = frame.stereo.info
    out = {}
    for k, f in enumerate(gt.features_cam):
        if f.type not in YOLO_CLASSES or len(f.box_xyxy) != 4:
            continue
        corners = np.array([[c.x, c.y, c.z] for c in f.corners])
        clipped = clip_near(corners, params.near_m)
        area = 0.0
        if len(clipped) >= 3:
            px = np.c_[info.fx * clipped[:, 0] / clipped[:, 2] + info.cx,
                       info.fy * clipped[:, 1] / clipped[:, 2] + info.cy].astype(np.float32)
            area = float(cv2.contourArea(px))
        pixels = int(np.count_nonzero(mask == k + 1)) if mask is not None else 0
        out[f.id] = {"type": f.type, "box": tuple(float(v) for v in f.box_xyxy), "pixels": pixels,
                     "fraction": pixels / area if area > 0 else 0.0}
    return out


def _is_truth_label(t: dict, params: SelfLabelParams) -> bool:
    x0, y0, x1, y1 = t["box"]
    return t["fraction"] >= params.min_visible_fraction and min(x1 - x0, y1 - y0) >= params.min_box_px


def write_yolo(out: Path, name: str, image: np.ndarray, boxes: list[tuple[str, tuple]], w: int, h: int) -> None:
    cv2.imwrite(str(out / "images" / f"{name}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 92])
    (out / "labels" / f"{name}.txt").write_text("".join(yolo_line(kind, box, w, h) + "\n" for kind, box in boxes))


def check_labels(recording: Path, labelled: Path, truth_out: Path | None = None,
                 params: SelfLabelParams | None = None, fix_s: float | None = None) -> dict:
    """The self-labels of `recording` under `labelled` against its truth (module doc); with `truth_out`, the truth
    labels of the whole flight at the labeller's cadence written there; with `fix_s` (the first fix, s of flight),
    the boxes of the frames before it (labelled back from it) counted apart too."""
    params = params or SelfLabelParams()
    labels: dict[str, list[dict]] = {}
    boxes_file = labelled / f"{recording.stem}.boxes.jsonl"
    for line in (boxes_file.read_text().splitlines() if boxes_file.is_file() else []):
        b = json.loads(line)
        labels.setdefault(b["frame"], []).append(b)
    labelled_frames = {p.stem for p in (labelled / "labels").glob(f"{recording.stem}_*.txt")}
    if truth_out:
        yolo_folder(truth_out)
    right, wrong, same_feature = 0, 0, 0
    why: Counter[str] = Counter()
    truth_in_labelled, found = 0, 0
    last_truth_ns = None
    truth_written: Counter[str] = Counter()
    before: Counter[str] = Counter()
    first_ns = None
    for frame in read_flight(recording):
        first_ns = frame.stamp_ns if first_ns is None else first_ns
        is_before = fix_s is not None and (frame.stamp_ns - first_ns) * 1e-9 < fix_s
        name = f"{recording.stem}_{frame.stamp_ns}"
        due = last_truth_ns is None or (frame.stamp_ns - last_truth_ns) * 1e-9 >= params.every_s
        if name not in labelled_frames and not (truth_out and due):
            continue
        truth = truth_of_frame(frame, params)
        if truth_out and due:
            last_truth_ns = frame.stamp_ns
            boxes = [(t["type"], t["box"]) for t in truth.values() if _is_truth_label(t, params)]
            write_yolo(truth_out, name, frame.images()[0], boxes, frame.stereo.left.width, frame.stereo.left.height)
            truth_written["images"] += 1
            truth_written.update(kind for kind, _ in boxes)
        if name not in labelled_frames:
            continue
        matched = set()
        for b in labels.get(name, []):
            best = max(((iou(tuple(b["box_xyxy"]), t["box"]), fid) for fid, t in truth.items()
                        if t["type"] == b["type"]), default=(0.0, ""))
            before.update(["boxes", "right" if best[0] >= 0.5 else "wrong"] if is_before else [])
            if best[0] >= 0.5:
                right += 1
                matched.add(best[1])
                same_feature += best[1] == b["feature_id"]
            else:
                wrong += 1
                why["no_truth_box" if best[0] == 0 else "iou_below_0.5"] += 1
        for fid, t in truth.items():
            if _is_truth_label(t, params):
                truth_in_labelled += 1
                found += fid in matched
    return {"precision": round(right / max(right + wrong, 1), 4), "right": right, "wrong": wrong,
            "same_feature": same_feature, "wrong_why": dict(why),
            "recall_in_labelled_frames": round(found / max(truth_in_labelled, 1), 4),
            "truth_labels_in_labelled_frames": truth_in_labelled, "truth_written": dict(truth_written),
            "before_fix": dict(before)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recording", type=Path)
    ap.add_argument("building", type=Path)
    ap.add_argument("--out", type=Path, required=True, help="the self-labelled frames")
    ap.add_argument("--truth-out", type=Path, help="the truth-labelled frames of the whole flight")
    ap.add_argument("--config", type=Path)
    args = ap.parse_args()
    t0 = time.perf_counter()
    report = label_recording(args.recording, args.building, load_config(args.config),
                             occluding_triangles(args.building), args.out)
    label_s = time.perf_counter() - t0
    out = {"recording": args.recording.name, "label_s": round(label_s, 1), "report": report,
           **check_labels(args.recording, args.out, args.truth_out, fix_s=report.get("localized_at_s"))}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
