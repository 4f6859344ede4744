"""Train the door/window detector and export it: `python -m macroloc.perception.train` reproduces the shipped weights.

Data: the real facade photos (`../shared/data/images/facades`, fixed split: test = img_n with n % 5 == 0,
never trained on; validation = a seeded 15 % of the rest, which sets the score threshold from its PR curve),
optionally plus rendered frames of the simulator (`--sim out/sim_yolo`, YOLO labels 0 door, 1 window, rendered
by `python -m bench.sim_trainset` on first use from the duplex and FZK-Haus; Office_A is held out), which then
fill `--sim-fraction` of each batch. The shipped model uses the defaults: real photos only (the variant with
rendered frames scored lower on the real validation split and no better on rendered Office_A frames).
Writes `perception/models/detector.onnx`, its JSON sidecar (classes, input size, anchors, threshold,
figures) and `detector_pr.png`; the detailed figures go to `out/detector/`.
Needs the `train` extra (torch); runs on the CPU with 2 threads by default.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from macroloc.perception.detector import CLASS_NAMES, REPORTED_TYPES, Detection, Detector, DetectorSpec
from macroloc.perception.evaluate import GroundTruth, PRCurve, best_f1_threshold, plot_pr, pr_curve
from macroloc.perception.trainset import (
    FACADE_CLASS_MAP,
    Sample,
    augment,
    facade_label_path,
    load_sample,
    split_facades,
)

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
INPUT_WH = (320, 240)
N_ANCHORS = 5
SIM_CLASS_MAP = {0: 0, 1: 1}
DEFAULT_SIM_DIR = ROOT / "out" / "sim_yolo"


def kmeans_anchors(wh: np.ndarray, k: int, rng: np.random.Generator, iters: int = 60) -> np.ndarray:
    """k-means on box sizes with 1 - IoU as the distance (YOLOv2); returns (k, 2) sorted by area."""
    centres = wh[rng.choice(len(wh), k, replace=False)].copy()
    for _ in range(iters):
        inter = np.minimum(wh[:, None, 0], centres[None, :, 0]) * np.minimum(wh[:, None, 1], centres[None, :, 1])
        iou = inter / (wh[:, None].prod(-1) + centres[None].prod(-1) - inter)
        assign = iou.argmax(1)
        for j in range(k):
            if np.any(assign == j):
                centres[j] = np.median(wh[assign == j], axis=0)
    return centres[np.argsort(centres.prod(1))]


def build_targets(boxes: list[np.ndarray], classes: list[np.ndarray], anchors: np.ndarray,
                  grid_hw: tuple[int, int], stride: int) -> dict[str, np.ndarray]:
    """YOLOv2 targets: each truth to the cell of its centre and the anchor of best shape IoU."""
    n, a = len(boxes), len(anchors)
    h_g, w_g = grid_hw
    pos = np.zeros((n, a, h_g, w_g), bool)
    txy = np.zeros((n, a, 2, h_g, w_g), np.float32)
    twh = np.zeros((n, a, 2, h_g, w_g), np.float32)
    tcls = np.zeros((n, a, h_g, w_g), np.int64)
    weight = np.zeros((n, a, h_g, w_g), np.float32)
    area_in = INPUT_WH[0] * INPUT_WH[1]
    for i, (b, c) in enumerate(zip(boxes, classes, strict=True)):
        for (x0, y0, x1, y1), k in zip(b, c, strict=True):
            w, h = x1 - x0, y1 - y0
            cx, cy = (x0 + x1) / 2 / stride, (y0 + y1) / 2 / stride
            gx, gy = min(int(cx), w_g - 1), min(int(cy), h_g - 1)
            inter = np.minimum(w, anchors[:, 0]) * np.minimum(h, anchors[:, 1])
            j = int(np.argmax(inter / (w * h + anchors.prod(1) - inter)))
            pos[i, j, gy, gx] = True
            txy[i, j, :, gy, gx] = (cx - gx, cy - gy)
            twh[i, j, :, gy, gx] = (np.log(w / anchors[j, 0]), np.log(h / anchors[j, 1]))
            tcls[i, j, gy, gx] = k
            weight[i, j, gy, gx] = 2.0 - w * h / area_in
    return {"pos": pos, "txy": txy, "twh": twh, "tcls": tcls, "weight": weight}


def yolo_loss(raw, targets, gt_boxes, anchors, stride):  # type: ignore[no-untyped-def]
    """Sum over the batch (divided by its size) of box, objectness (with YOLOv2's ignore rule) and class terms."""
    import torch
    import torch.nn.functional as F  # noqa: N812

    n, _, h_g, w_g = raw.shape
    a = len(anchors)
    p = raw.view(n, a, -1, h_g, w_g)
    t = {k: torch.from_numpy(v) for k, v in targets.items()}
    pos = t["pos"]
    # Objectness: negatives are every non-assigned slot whose predicted box overlaps no truth by > 0.5.
    with torch.no_grad():
        gy, gx = torch.meshgrid(torch.arange(h_g), torch.arange(w_g), indexing="ij")
        anc = torch.from_numpy(anchors).float()
        cx = (gx + torch.sigmoid(p[:, :, 0])) * stride
        cy = (gy + torch.sigmoid(p[:, :, 1])) * stride
        bw = anc[None, :, 0, None, None] * torch.exp(p[:, :, 2].clamp(-8, 8))
        bh = anc[None, :, 1, None, None] * torch.exp(p[:, :, 3].clamp(-8, 8))
        pred = torch.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], -1)  # (n, a, h, w, 4)
        ignore = torch.zeros_like(pos)
        for i, g in enumerate(gt_boxes):
            if len(g) == 0:
                continue
            gt = torch.from_numpy(g).float()
            pb = pred[i].reshape(-1, 4)
            lt = torch.maximum(pb[:, None, :2], gt[None, :, :2])
            rb = torch.minimum(pb[:, None, 2:], gt[None, :, 2:])
            inter = (rb - lt).clamp(min=0).prod(-1)
            union = (pb[:, 2:] - pb[:, :2]).prod(-1)[:, None] + (gt[:, 2:] - gt[:, :2]).prod(-1)[None] - inter
            ignore[i] = ((inter / union.clamp(min=1e-9)).max(1).values > 0.5).view(a, h_g, w_g)
    obj_target = pos.float()
    obj_mask = pos | ~ignore
    l_obj = F.binary_cross_entropy_with_logits(p[:, :, 4], obj_target, reduction="none")[obj_mask].sum()
    if pos.any():
        w = t["weight"][pos]
        pxy = p[:, :, 0:2].permute(0, 1, 3, 4, 2)[pos]
        pwh = p[:, :, 2:4].permute(0, 1, 3, 4, 2)[pos]
        txy = t["txy"].permute(0, 1, 3, 4, 2)[pos]
        twh = t["twh"].permute(0, 1, 3, 4, 2)[pos]
        l_xy = (F.binary_cross_entropy_with_logits(pxy, txy, reduction="none").sum(1) * w).sum()
        l_wh = (((pwh - twh) ** 2).sum(1) * w).sum()
        logits = p[:, :, 5:].permute(0, 1, 3, 4, 2)[pos]
        l_cls = F.cross_entropy(logits, t["tcls"][pos], reduction="sum")
    else:
        l_xy = l_wh = l_cls = raw.sum() * 0.0
    return (2.0 * l_xy + 2.0 * l_wh + l_obj + l_cls) / n


def load_facades(root: Path, seed: int) -> dict[str, list[Sample]]:
    split = split_facades(root, seed=seed)
    return {name: [load_sample(p, facade_label_path(p), FACADE_CLASS_MAP, 480) for p in paths]
            for name, paths in split.items()}


def load_sim(dirs: list[Path]) -> list[Sample]:
    """Rendered frames exported by the simulator: DIR/images/*.png|jpg with DIR/labels/*.txt (0 door, 1 window)."""
    out = []
    for d in dirs:
        for img in sorted((d / "images").glob("*")):
            if img.suffix.lower() in {".png", ".jpg", ".jpeg"}:
                out.append(load_sample(img, d / "labels" / (img.stem + ".txt"), SIM_CLASS_MAP, 480))
    return out


class _Shuffled:
    """Endless epochs over a list of samples, reshuffled each time (seeded)."""

    def __init__(self, samples: list[Sample], rng: np.random.Generator) -> None:
        self.samples, self.rng, self.order = samples, rng, []  # type: ignore[var-annotated]

    def take(self, n: int) -> list[Sample]:
        while len(self.order) < n:
            self.order += self.rng.permutation(len(self.samples)).tolist()
        idx, self.order = self.order[:n], self.order[n:]
        return [self.samples[i] for i in idx]


def ensure_sim_frames(dirs: list[Path]) -> list[Path]:
    """The default rendered-frames folder is made on first use by `python -m bench.sim_trainset` (a separate
    process: perception does not import the simulator)."""
    for d in dirs:
        if d == DEFAULT_SIM_DIR and not (d / "images").exists():
            log.info("rendering training frames into %s (python -m bench.sim_trainset)", d)
            subprocess.run([sys.executable, "-m", "bench.sim_trainset", "--out", str(d)], cwd=ROOT, check=True)
    return dirs


def evaluate_onnx(detector: Detector, samples: list[Sample]) -> dict[str, PRCurve]:
    """PR curves (door, window) of the exported model on in-memory samples (threshold 0.01)."""
    dets: list[list[Detection]] = []
    truths: list[list[GroundTruth]] = []
    for s in samples:
        dets.append(detector.detect(s.image_bgr, score_threshold=0.01))
        truths.append([GroundTruth(CLASS_NAMES[int(c)], tuple(float(v) for v in b))  # type: ignore[arg-type]
                       for b, c in zip(s.boxes_xyxy, s.classes, strict=True) if CLASS_NAMES[int(c)] in REPORTED_TYPES])
    return {k: pr_curve(k, dets, truths) for k in REPORTED_TYPES}


def train(args: argparse.Namespace) -> None:
    import torch

    from macroloc.perception.model import STRIDE_PX, TinyYolo

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    data = load_facades(args.facades, args.seed)
    sim = load_sim(ensure_sim_frames(args.sim))
    real = data["train"]
    log.info("train: %d real, %d rendered; val %d, test %d", len(real), len(sim), len(data["val"]), len(data["test"]))
    wh = np.concatenate([b[:, 2:] - b[:, :2] for _ in range(2) for s in real + sim
                         for b in [augment(s, INPUT_WH, rng)[1]] if len(b)])
    anchors = kmeans_anchors(wh, N_ANCHORS, rng)
    log.info("anchors (px): %s", np.round(anchors, 1).tolist())
    model = TinyYolo(N_ANCHORS, len(CLASS_NAMES))
    ema = TinyYolo(N_ANCHORS, len(CLASS_NAMES))
    ema.load_state_dict(model.state_dict())
    ema.eval()
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=5e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=args.steps, pct_start=0.05)
    grid_hw = (INPUT_WH[1] // STRIDE_PX, INPUT_WH[0] // STRIDE_PX)
    pools = [_Shuffled(real, rng), _Shuffled(sim, rng)] if sim else [_Shuffled(real, rng)]
    n_sim = round(args.sim_fraction * args.batch) if sim else 0
    t0 = time.time()
    for step in range(args.steps):
        picked = pools[0].take(args.batch - n_sim) + (pools[1].take(n_sim) if n_sim else [])
        batch = [augment(s, INPUT_WH, rng) for s in picked]
        x = torch.from_numpy(np.stack([b[0] for b in batch]).astype(np.float32) / 255.0).permute(0, 3, 1, 2)
        targets = build_targets([b[1] for b in batch], [b[2] for b in batch], anchors, grid_hw, STRIDE_PX)
        model.train()
        loss = yolo_loss(model(x), targets, [b[1] for b in batch], anchors, STRIDE_PX)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        sched.step()
        decay = 0.998 * (1 - np.exp(-(step + 1) / 200))
        with torch.no_grad():
            for pe, pm in zip(ema.state_dict().values(), model.state_dict().values(), strict=True):
                if pe.dtype.is_floating_point:
                    pe.mul_(decay).add_(pm.detach(), alpha=1 - decay)
                else:
                    pe.copy_(pm)
        if step % 100 == 0 or step == args.steps - 1:
            log.info("step %d/%d loss %.3f (%.0f s)", step, args.steps, float(loss.detach()), time.time() - t0)
    export(ema, anchors, args, data, sim, time.time() - t0)


def rendered_sources(sim: list[Sample]) -> list[str]:
    """The buildings and seeds rendered frames came from, by their exported names (BUILDING_sSEED_FRAME)."""
    return sorted({m.group(1) for s in sim if (m := re.match(r"(.+_s\d+)_\d+$", s.name))})


def export(model, anchors: np.ndarray, args: argparse.Namespace, data: dict[str, list[Sample]],  # type: ignore[no-untyped-def]
           sim: list[Sample], train_s: float) -> None:
    import torch

    from macroloc.perception.model import STRIDE_PX

    args.out.mkdir(parents=True, exist_ok=True)
    args.report.mkdir(parents=True, exist_ok=True)
    onnx_path = args.out / "detector.onnx"
    model.eval()
    dummy = torch.zeros(1, 3, INPUT_WH[1], INPUT_WH[0])
    torch.onnx.export(model, (dummy,), str(onnx_path), input_names=["image"], output_names=["raw"],
                      opset_version=13, dynamo=False)
    spec = DetectorSpec(CLASS_NAMES, INPUT_WH, STRIDE_PX, tuple((float(w), float(h)) for w, h in anchors), 0.5)
    detector = Detector(onnx_path, spec)
    val = evaluate_onnx(detector, data["val"])
    threshold = best_f1_threshold(list(val.values()))
    test = evaluate_onnx(detector, data["test"])
    figures = {
        split: {k: {"ap50": round(c.ap, 4), "n_truth": c.n_truth,
                    "precision_at_threshold": round(c.at(threshold)[0], 4),
                    "recall_at_threshold": round(c.at(threshold)[1], 4)} for k, c in curves.items()}
        for split, curves in (("val", val), ("test_real", test))
    }
    extra: dict[str, object] = {
        "threshold_rule": "max mean F1 (door, window) on the validation split's PR curves",
        "trained_on": {"real_facade_photos": len(data["train"]), "rendered_frames": len(sim)},
        "split": "facades: test = img_n with n % 5 == 0 (never trained on); val = seeded 15 % of the rest",
        "training": {"steps": args.steps, "batch": args.batch, "lr": args.lr, "seed": args.seed,
                     "sim_fraction": args.sim_fraction, "rendered_flights": rendered_sources(sim),
                     "seconds": round(train_s)},
        "figures": figures,
        "reproduce": "python -m macroloc.perception.train",
    }
    spec = DetectorSpec(CLASS_NAMES, INPUT_WH, STRIDE_PX, spec.anchors_px, threshold, spec.nms_iou, extra)
    onnx_path.with_suffix(".json").write_text(json.dumps(spec.to_json(), indent=1) + "\n")
    plot_pr(list(val.values()), threshold, str(args.out / "detector_pr.png"),
            f"validation split (real photos, {len(data['val'])} images)")
    plot_pr(list(test.values()), threshold, str(args.report / "pr_test_real.png"),
            f"held-out real test photos ({len(data['test'])} images)")
    (args.report / "metrics.json").write_text(json.dumps({"threshold": threshold, **figures}, indent=1) + "\n")
    log.info("threshold %.2f; figures %s", threshold, json.dumps(figures))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m macroloc.perception.train", description=__doc__.splitlines()[0])
    ap.add_argument("--facades", type=Path, default=SHARED_DATA / "images" / "facades")
    ap.add_argument("--sim", type=Path, nargs="*", default=[],
                    help="folders of rendered frames with YOLO labels; out/sim_yolo is made by bench.sim_trainset "
                         "on first use (default: none, the shipped model is trained on real photos only)")
    ap.add_argument("--sim-fraction", type=float, default=0.5, help="share of each batch drawn from rendered frames")
    ap.add_argument("--steps", type=int, default=3600)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "perception" / "models")
    ap.add_argument("--report", type=Path, default=ROOT / "out" / "detector")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    train(parse_args(argv))


if __name__ == "__main__":
    main()
