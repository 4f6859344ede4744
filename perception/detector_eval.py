"""The detector's figures on labelled images: AP at IoU 0.5 and 0.3, precision/recall at the threshold, and doors by
size (fraction of the image height) and cut by the image border. No torch: scores any exported ONNX model.

Boxes are in each image's own pixels. A truth is "truncated" where its box reaches within `TRUNCATION_MARGIN_PX` of
the border (`perception.detector.at_border`), the same rule as `Detection.truncated`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from macroloc.perception import sources
from macroloc.perception.detector import CLASS_NAMES, REPORTED_TYPES, Detection, Detector, at_border
from macroloc.perception.evaluate import BoxFilter, GroundTruth, PRCurve, pr_curve
from macroloc.perception.trainset import Sample

SIZE_BINS = (("lt_0.25", 0.0, 0.25), ("0.25_0.75", 0.25, 0.75), ("gt_0.75", 0.75, float("inf")))
TALL_FRACTION = 0.25  # a door at least this fraction of the image tall: one a drone's camera sees within ~6 m
DetectFn = Callable[[np.ndarray], list[Detection]]


def detect_all(detector: Detector | DetectFn, samples: Sequence[Sample],
               threshold: float = 0.01) -> tuple[list[list[Detection]], list[list[GroundTruth]]]:
    """Detections (score >= threshold) and truths (door, window) of every sample, aligned by image. `detector` is
    a `Detector` or any function of an image that returns its detections (already thresholded)."""
    dets: list[list[Detection]] = []
    truths: list[list[GroundTruth]] = []
    for s in samples:
        dets.append(detector.detect(s.image_bgr, score_threshold=threshold) if isinstance(detector, Detector)
                    else detector(s.image_bgr))
        truths.append([GroundTruth(CLASS_NAMES[int(c)], (float(b[0]), float(b[1]), float(b[2]), float(b[3])))
                       for b, c in zip(s.boxes_xyxy, s.classes, strict=True) if CLASS_NAMES[int(c)] in REPORTED_TYPES])
    return dets, truths


def _size_filter(height_px: int, lo: float, hi: float) -> BoxFilter:
    return lambda b: lo <= (b[3] - b[1]) / height_px < hi


def _border_filter(width_px: int, height_px: int) -> BoxFilter:
    return lambda b: at_border(b, width_px, height_px)


def _figures(curve: PRCurve, curve30: PRCurve | None, threshold: float) -> dict[str, object]:
    p, r = curve.at(threshold)
    out: dict[str, object] = {"ap50": round(curve.ap, 4), "n_truth": curve.n_truth,
                              "precision_at_threshold": round(p, 4), "recall_at_threshold": round(r, 4)}
    if curve30 is not None:
        out["ap30"] = round(curve30.ap, 4)
    return out


def figures(samples: Sequence[Sample], dets: Sequence[Sequence[Detection]], truths: Sequence[Sequence[GroundTruth]],
            threshold: float, kinds: Sequence[str] = REPORTED_TYPES, subsets: bool = True) -> dict[str, object]:
    """Per kind: AP50, AP30, P/R at `threshold`; with `subsets`, the doors by size and cut by the border too."""
    out: dict[str, object] = {"n_images": len(samples)}
    for kind in kinds:
        out[kind] = _figures(pr_curve(kind, dets, truths), pr_curve(kind, dets, truths, iou_min=0.3), threshold)
    if subsets and "door" in kinds:
        hw = [s.image_bgr.shape[:2] for s in samples]
        by_size = {}
        for name, lo, hi in SIZE_BINS:
            within = [_size_filter(h, lo, hi) for h, _ in hw]
            by_size[name] = _figures(pr_curve("door", dets, truths, within=within),
                                     pr_curve("door", dets, truths, 0.3, within), threshold)
        out["door_by_height_fraction"] = by_size
        tall = [_size_filter(h, TALL_FRACTION, float("inf")) for h, _ in hw]
        out["door_tall"] = _figures(pr_curve("door", dets, truths, within=tall),
                                    pr_curve("door", dets, truths, 0.3, tall), threshold)
        within = [_border_filter(w, h) for h, w in hw]
        out["door_truncated"] = _figures(pr_curve("door", dets, truths, within=within),
                                         pr_curve("door", dets, truths, 0.3, within), threshold)
    return out


def curves(dets: Sequence[Sequence[Detection]], truths: Sequence[Sequence[GroundTruth]],
           kinds: Sequence[str] = REPORTED_TYPES) -> list[PRCurve]:
    """AP50 PR curves, one per kind."""
    return [pr_curve(k, dets, truths) for k in kinds]


def leave_one_source_out(models: Mapping[str, Detector | DetectFn], images_root: Path,
                         thresholds: Mapping[str, float] | None = None) -> dict[str, dict[str, object]]:
    """Each source scored, all of it, by the model trained without it: `models` maps a source name
    (`perception.sources.REAL_SOURCES`) to that model. Per source: door AP50 / AP30 for all doors and for doors at
    least `TALL_FRACTION` of the image tall (`door_tall`), window AP50 where the source has windows, precision and
    recall at the model's threshold (`thresholds[source]`, else the Detector's own). Sources absent under
    `images_root` are skipped."""
    out: dict[str, dict[str, object]] = {}
    for name, model in models.items():
        src = sources.source(name)
        samples = sources.load_all(images_root, src)
        if not samples:
            continue
        t = (thresholds or {}).get(name, model.spec.score_threshold if isinstance(model, Detector) else 0.5)
        dets, truths = detect_all(model, samples)
        out[name] = figures(samples, dets, truths, t)
    return out
