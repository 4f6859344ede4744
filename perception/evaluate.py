"""Detection scoring: average precision at IoU 0.5 per class (VOC all-point interpolation), PR curves,
and the choice of the score threshold from the precision-recall curve (paper §2.2.1).

Boxes are `box_xyxy` in image pixels; a ground truth is matched at most once, greedily by score.
A subset of the truths (doors of a size, doors cut by the border) is scored COCO-style: truths outside the subset
and detections matched to them are ignored, an unmatched detection counts as false only if it falls in the subset.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from macroloc.perception.detector import Detection


@dataclass(frozen=True)
class GroundTruth:
    type: str
    box_xyxy: tuple[float, float, float, float]


@dataclass(frozen=True)
class PRCurve:
    """Per class: scores (descending), precision and recall after each detection, AP, number of truths."""

    type: str
    scores: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    ap: float
    n_truth: int

    def at(self, threshold: float) -> tuple[float, float]:
        """(precision, recall) keeping detections with score >= threshold."""
        k = int(np.searchsorted(-self.scores, -threshold, side="right"))
        if k == 0:
            return 1.0, 0.0
        return float(self.precision[k - 1]), float(self.recall[k - 1])


def iou_xyxy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix of boxes a (N,4) and b (M,4) -> (N,M)."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-12)


def average_precision(recall: np.ndarray, precision: np.ndarray) -> float:
    """Area under the monotone precision envelope (VOC 2010+ all-point interpolation)."""
    r = np.concatenate([[0.0], recall, [1.0]])
    p = np.concatenate([[0.0], precision, [0.0]])
    p = np.maximum.accumulate(p[::-1])[::-1]
    idx = np.nonzero(r[1:] != r[:-1])[0]
    return float(np.sum((r[idx + 1] - r[idx]) * p[idx + 1]))


BoxFilter = Callable[[tuple[float, float, float, float]], bool]


def pr_curve(kind: str, detections: Sequence[Sequence[Detection]], truths: Sequence[Sequence[GroundTruth]],
             iou_min: float = 0.5, within: Sequence[BoxFilter] | None = None) -> PRCurve:
    """PR curve and AP of one class over a set of images (lists aligned by image); `within` (one filter per image,
    on boxes in that image's pixels) restricts it to a subset of the truths."""
    records: list[tuple[float, bool]] = []
    n_truth = 0
    for k, (dets, gts) in enumerate(zip(detections, truths, strict=True)):
        keep = within[k] if within is not None else None
        mine = [g.box_xyxy for g in gts if g.type == kind]
        gt = np.array(mine, np.float64).reshape(-1, 4)
        counted = np.array([keep is None or keep(b) for b in mine], bool)
        n_truth += int(counted.sum())
        ds = sorted((d for d in dets if d.type == kind), key=lambda d: -d.score)
        used = np.zeros(len(gt), bool)
        if ds and len(gt):
            ious = iou_xyxy(np.array([d.box_xyxy for d in ds], np.float64), gt)
        for i, d in enumerate(ds):
            j = -1
            if len(gt):
                cand = np.where(used, -1.0, ious[i])
                j = int(np.argmax(cand)) if cand.max() >= iou_min else -1
            if j >= 0:
                used[j] = True
                if counted[j]:
                    records.append((d.score, True))
            elif keep is None or keep(d.box_xyxy):
                records.append((d.score, False))
    records.sort(key=lambda r: -r[0])
    scores = np.array([r[0] for r in records])
    tp = np.cumsum([r[1] for r in records]).astype(np.float64)
    fp = np.cumsum([not r[1] for r in records]).astype(np.float64)
    recall = tp / max(n_truth, 1)
    precision = tp / np.maximum(tp + fp, 1e-12)
    ap = average_precision(recall, precision) if len(records) else 0.0
    return PRCurve(kind, scores, precision, recall, ap, n_truth)


def best_f1_threshold(curves: Sequence[PRCurve], candidates: np.ndarray | None = None) -> float:
    """The score threshold that maximises the mean F1 over the classes' PR curves."""
    grid = np.round(np.arange(0.05, 0.951, 0.01), 2) if candidates is None else candidates
    best, best_t = -1.0, 0.5
    for t in grid:
        f1s = []
        for c in curves:
            p, r = c.at(float(t))
            f1s.append(2 * p * r / max(p + r, 1e-12))
        if np.mean(f1s) > best:
            best, best_t = float(np.mean(f1s)), float(t)
    return best_t


def plot_pr(curves: Sequence[PRCurve], threshold: float, path: str, title: str) -> None:
    """Save the PR curves with the chosen threshold's operating point marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4.2), dpi=110)
    for c in curves:
        line = ax.plot(c.recall, c.precision, label=f"{c.type} AP50={c.ap:.3f} (n={c.n_truth})")[0]
        p, r = c.at(threshold)
        ax.plot([r], [p], "o", color=line.get_color())
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title(f"{title}\n(dots: score threshold {threshold:.2f})", fontsize=9)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
