"""Train the door/window detector and export it; `make train` reproduces the shipped weights in three runs.

The shipped weights: a run from scratch with the defaults (`--out out/detector/base --report out/detector/base`,
4,200 steps, 60 % indoor photos), a fine-tune of its weights with a larger facade share
(`--init out/detector/base/checkpoint.pt --indoor-fraction 0.35 --lr 5e-4 --steps 2000`), then a fine-tune of those
with rendered frames of the duplex and FZK-Haus in a quarter of each batch (`--sim out/sim_yolo --sim-fraction 0.25
--steps 1500`); the sidecar's `training` (with `init`) and `reproduce` say so.
`--init` takes a run's `checkpoint.pt` or the `detector.pt` written beside
every exported ONNX (the same weights before the batch norms are folded) and keeps their anchors;
`macroloc adapt-detector` fine-tunes the shipped `perception/models/detector.pt` on renders of one building.

Data: every real labelled source (`perception.sources.REAL_SOURCES`: the indoor sources under `--indoor`, the
facades at `--facades`), each split 80/10/10 by source photo, seeded (the facades: test = img_n with n % 5 == 0);
`--leave-out SOURCE...` keeps sources out entirely, so that a model can be scored on a camera it never saw
(`bench.eval_detector`). `--indoor-fraction` of each batch's real photos come from the indoor sources, shared by the
square root of their sizes, the rest from the facades; optionally rendered frames of the simulator (`--sim
out/sim_yolo`, YOLO labels 0 door, 1 window, rendered by `python -m bench.sim_trainset` on first use from the
duplex and FZK-Haus; Office_A is held out) fill `--sim-fraction`. The validation parts set the score threshold
from their PR curves.
`--arch shufflenet` starts from pretrained features (`perception.backbone.ShuffleYolo`, `--pretrained`, optionally
`--freeze` its first stages) instead of TinyYolo from scratch.
Augmentation is what a drone sees: the paper's rotations, zoom-in crops onto a door (filling 55-125 % of the
frame's height, often cut by the border), aspect changes (the indoor photos were stretched to squares), brightness
and exposure, random greyscale, mirror, mosaics; with `--camera P` a wide-angle lens distortion and a camera's white
balance, motion blur or JPEG.
A run saves its whole state every `--save-every` steps; `--stop-at STEP` stops it there and `--resume` goes on to
the same weights as one run in one go (a long training in parts).
Writes `perception/models/detector.onnx`, its JSON sidecar (classes, input size, anchors, threshold,
figures) and `detector_pr.png`; the detailed figures and the EMA weights (`checkpoint.pt`, for `--export-only`)
go to `out/detector/`. Needs the `train` extra (torch); runs on the CPU.
"""

from __future__ import annotations

import argparse
import copy
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

from macroloc.perception import detector_eval, sources
from macroloc.perception.detector import CLASS_NAMES, Detector, DetectorSpec
from macroloc.perception.evaluate import best_f1_threshold, plot_pr
from macroloc.perception.sources import REAL_SOURCES, RealSource
from macroloc.perception.trainset import Sample, augment, load_sample, mosaic

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data"))
INPUT_WH = (320, 240)
N_ANCHORS = 5
SIM_CLASS_MAP = {0: 0, 1: 1}
DEFAULT_SIM_DIR = ROOT / "out" / "sim_yolo"
SHIPPED_WEIGHTS = ROOT / "perception" / "models" / "detector.pt"
PRETRAINED = SHARED_DATA.parent / "weights" / "fastestdet_coco" / "fastestdet_coco.pth"


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
    area_in = w_g * stride * h_g * stride
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
    dev = raw.device
    t = {k: torch.from_numpy(v).to(dev) for k, v in targets.items()}
    pos = t["pos"]
    # Objectness: negatives are every non-assigned slot whose predicted box overlaps no truth by > 0.5.
    with torch.no_grad():
        gy, gx = torch.meshgrid(torch.arange(h_g, device=dev), torch.arange(w_g, device=dev), indexing="ij")
        anc = torch.from_numpy(anchors).float().to(dev)
        cx = (gx + torch.sigmoid(p[:, :, 0])) * stride
        cy = (gy + torch.sigmoid(p[:, :, 1])) * stride
        bw = anc[None, :, 0, None, None] * torch.exp(p[:, :, 2].clamp(-8, 8))
        bh = anc[None, :, 1, None, None] * torch.exp(p[:, :, 3].clamp(-8, 8))
        pred = torch.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], -1)  # (n, a, h, w, 4)
        ignore = torch.zeros_like(pos)
        for i, g in enumerate(gt_boxes):
            if len(g) == 0:
                continue
            gt = torch.from_numpy(g).float().to(dev)
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


def _augment(sample: Sample, out_wh: tuple[int, int], rng: np.random.Generator, camera: float = 0.0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The training augmentation (see the module docstring) into `out_wh`; boxes at least 30 % visible are kept
    (cut doors); `camera` is the probability of a lens distortion and, apart, of a camera's effects."""
    return augment(sample, out_wh, rng, scale_range=(0.7, 2.5), rotation_prob=0.5, min_visible=0.3, zoom_prob=0.35,
                   aspect_range=(0.7, 1.45), camera_prob=camera, lens_prob=camera)


def augment_for_training(sample: Sample, rng: np.random.Generator, out_wh: tuple[int, int] = INPUT_WH,
                         camera: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One training image (`out_wh`, the network's input size) from one sample."""
    return _augment(sample, out_wh, rng, camera)


def mosaic_for_training(samples: list[Sample], rng: np.random.Generator, out_wh: tuple[int, int] = INPUT_WH,
                        camera: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four samples in the quadrants of one training image (`perception.trainset.mosaic`), each with the
    training augmentation."""
    return mosaic(samples, out_wh, rng, lambda s, wh, r: _augment(s, wh, r, camera))


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
    process: perception does not import the simulator), however it is spelt (`out/sim_yolo` from the project's
    root, as the Makefile does, or absolute); any other folder must exist."""
    for d in dirs:
        if (d / "images").exists():
            continue
        if d.resolve() == DEFAULT_SIM_DIR.resolve():
            log.info("rendering training frames into %s (python -m bench.sim_trainset)", d)
            subprocess.run([sys.executable, "-m", "bench.sim_trainset", "--out", str(d.resolve())], cwd=ROOT,
                           check=True)
        else:
            raise SystemExit(f"error: {d} has no images/ folder of rendered frames (make one with "
                             f"`python -m bench.sim_trainset --out {d}`)")
    return dirs


def load_init(path: Path):  # type: ignore[no-untyped-def]
    """The weights `--init` starts from: a `checkpoint.pt` of a run ({"ema", "anchors", "width", ...}) or the
    shipped `detector.pt` (same keys; `arch` says the network, TinyYolo where absent). Returns (the network in eval
    mode, anchors (k, 2) px, the file's settings)."""
    import torch

    ckpt = torch.load(path, weights_only=False, map_location="cpu")
    if "ema" not in ckpt or "anchors" not in ckpt:
        raise ValueError(f"{path}: not a detector checkpoint (needs 'ema' weights and 'anchors')")
    model = build_model(str(ckpt.get("arch", "tiny")), int(ckpt.get("width", 1)), None)
    model.load_state_dict(ckpt["ema"])
    model.eval()
    return model, np.asarray(ckpt["anchors"], dtype=np.float64), {k: v for k, v in ckpt.items()
                                                                   if k not in ("ema", "anchors")}


def init_input_wh(init_info: dict[str, object]) -> tuple[int, int]:
    """The input size the init's weights were trained at (runs before `--input-wh` were 320 x 240)."""
    settings = init_info.get("settings")
    wh = settings.get("input_wh") if isinstance(settings, dict) else None
    return (int(wh[0]), int(wh[1])) if wh else INPUT_WH


def input_size(args: argparse.Namespace) -> tuple[int, int]:
    """The network's input size (w, h) px of a run (`--input-wh`)."""
    return int(args.input_wh[0]), int(args.input_wh[1])


def anchors_for_input(anchors_px: np.ndarray, from_wh: tuple[int, int], to_wh: tuple[int, int]) -> np.ndarray:
    """Anchors (k, 2) px learned at input size `from_wh`, for the same openings at `to_wh` (the image is scaled
    to the input: an anchor covers the same fraction of it)."""
    return np.asarray(anchors_px, float) * (np.asarray(to_wh, float) / np.asarray(from_wh, float))


def source_folder(args: argparse.Namespace, src: RealSource) -> Path:
    """Where a source's images/ and labels/ are: the indoor sources under `--indoor`, the facades at `--facades`."""
    return args.indoor / Path(src.folder).name if src.indoor else args.facades


def load_real(args: argparse.Namespace) -> dict[str, dict[str, list[Sample]]]:
    """Every registered real source present, minus `--leave-out`, split (train/val/test) and loaded."""
    out = {}
    for name, src in REAL_SOURCES.items():
        if name in args.leave_out:
            continue
        parts = sources.split_folder(source_folder(args, src), src, args.seed)
        if any(parts.values()):
            out[name] = {part: sources.load(paths, src) for part, paths in parts.items()}
    return out


def batch_shares(n: int, weights: dict[str, float]) -> dict[str, int]:
    """`n` batch slots shared in proportion to `weights` (largest remainders; every slot given)."""
    total = sum(weights.values())
    exact = {k: n * w / total for k, w in weights.items()}
    out = {k: int(v) for k, v in exact.items()}
    for k in sorted(exact, key=lambda k: out[k] - exact[k])[: n - sum(out.values())]:
        out[k] += 1
    return out


def source_weights(real: dict[str, dict[str, list[Sample]]], indoor_fraction: float) -> dict[str, float]:
    """Each real source's share of a batch: `indoor_fraction` to the indoor sources, shared in proportion to the
    square root of their training images (a big source leads, a small one is not drowned: the network should learn
    doors, not one photographer), the rest to the facades; a kind that is absent leaves its share to the other."""
    n = {k: len(v["train"]) for k, v in real.items() if v["train"]}
    indoor = {k: np.sqrt(c) for k, c in n.items() if REAL_SOURCES[k].indoor}
    outdoor = {k: np.sqrt(c) for k, c in n.items() if not REAL_SOURCES[k].indoor}
    f_in = indoor_fraction if indoor and outdoor else float(bool(indoor))
    out = {k: f_in * v / sum(indoor.values()) for k, v in indoor.items()}
    out.update({k: (1 - f_in) * v / sum(outdoor.values()) for k, v in outdoor.items()})
    return out


def build_model(arch: str, width: int, pretrained: Path | None):  # type: ignore[no-untyped-def]
    """The network of `--arch`: `tiny` (TinyYolo from scratch) or `shufflenet` (ShuffleYolo, its backbone and neck
    from `pretrained` where given)."""
    if arch == "tiny":
        from macroloc.perception.model import TinyYolo

        return TinyYolo(N_ANCHORS, len(CLASS_NAMES), width)
    from macroloc.perception.backbone import ShuffleYolo

    model = ShuffleYolo(N_ANCHORS, len(CLASS_NAMES))
    if pretrained is not None:
        log.info("pretrained: %d tensors from %s", len(model.load_pretrained(pretrained)), pretrained)
    return model


def freeze(model, parts: list[str]) -> int:  # type: ignore[no-untyped-def]
    """Keep the weights of these backbone parts (e.g. `first_conv stage2`: the pretrained edge and texture
    filters, which any camera's doors share) as they are; returns the count of tensors frozen. Their batch-norm
    statistics still follow the training images."""
    backbone = getattr(model, "backbone", None)
    if not parts or backbone is None:
        return 0
    frozen = [p for n, p in backbone.named_parameters() if n.split(".")[0] in parts]
    for p in frozen:
        p.requires_grad_(False)
    return len(frozen)


def train(args: argparse.Namespace) -> None:
    import torch

    from macroloc.perception.model import STRIDE_PX

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    state = load_state(args) if args.resume else None
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    real = load_real(args)
    sim = load_sim(ensure_sim_frames(args.sim))
    log.info("train: %s, %d rendered; left out: %s", ", ".join(f"{len(v['train'])} {k}" for k, v in real.items()),
             len(sim), ", ".join(args.leave_out) or "none")
    input_wh = input_size(args)
    if input_wh[0] % STRIDE_PX or input_wh[1] % STRIDE_PX:
        raise SystemExit(f"error: --input-wh {input_wh[0]} {input_wh[1]}: both must be multiples of {STRIDE_PX}")
    train_sets = {k: v["train"] for k, v in real.items() if v["train"]}
    if args.init is not None:  # fine-tune: the init's weights, anchors (the head is tied to them) and width
        model, anchors, init_info = load_init(args.init)
        args.width, args.init_info = int(init_info.get("width", 1)), init_info
        args.arch = str(init_info.get("arch", "tiny"))
        anchors = anchors_for_input(anchors, init_input_wh(init_info), input_wh)
        log.info("init from %s (%s steps); anchors (px at %dx%d): %s", args.init, init_info.get("steps"),
                 *input_wh, np.round(anchors, 1).tolist())
    else:
        wh = np.concatenate([b[:, 2:] - b[:, :2] for _ in range(2) for s in [*sum(train_sets.values(), []), *sim]
                             for b in [augment_for_training(s, rng, input_wh)[1]] if len(b)])
        anchors = kmeans_anchors(wh, N_ANCHORS, rng)
        log.info("anchors (px): %s", np.round(anchors, 1).tolist())
        model = build_model(args.arch, args.width, args.pretrained if args.arch == "shufflenet" else None)
    model.to(args.device)
    ema = copy.deepcopy(model)
    ema.eval()
    if args.freeze:
        log.info("frozen: %d tensors of %s", freeze(model, args.freeze), " ".join(args.freeze))
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=args.lr, weight_decay=5e-4)
    sched = (torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=args.steps, pct_start=0.05)
             if args.steps > 0 else None)  # --steps 0: export the init as it is
    grid_hw = (input_wh[1] // STRIDE_PX, input_wh[0] // STRIDE_PX)
    n_sim = round(args.sim_fraction * args.batch) if sim else 0
    shares = batch_shares(args.batch - n_sim, source_weights(real, args.indoor_fraction)) if train_sets else {}
    pools = {k: _Shuffled(train_sets[k], rng) for k in shares}
    if n_sim:
        pools["rendered"], shares["rendered"] = _Shuffled(sim, rng), n_sim
    log.info("batch of %d: %s", args.batch, shares)
    first_step, spent_s = 0, 0.0
    if state is not None:  # the run goes on exactly where its last state was saved
        first_step, spent_s = restore_state(state, model, ema, opt, sched, rng, pools)
        anchors = np.asarray(state["anchors"])
        log.info("resumed at step %d of %d (%s)", first_step, args.steps, args.report / STATE_FILE)
    t0 = time.time() - spent_s
    last = args.steps if args.stop_at is None else min(args.steps, args.stop_at)
    for step in range(first_step, last):
        picked = [(s, pools[k]) for k, n in shares.items() for s in pools[k].take(n)]
        batch = [mosaic_for_training([s, *pool.take(3)], rng, input_wh, args.camera)
                 if args.mosaic > 0 and rng.random() < args.mosaic
                 else augment_for_training(s, rng, input_wh, args.camera)
                 for s, pool in picked]
        x = torch.from_numpy(np.stack([b[0] for b in batch]).astype(np.float32) / 255.0).permute(0, 3, 1, 2)
        x = x.to(args.device)
        targets = build_targets([b[1] for b in batch], [b[2] for b in batch], anchors, grid_hw, STRIDE_PX)
        model.train()
        loss = yolo_loss(model(x), targets, [b[1] for b in batch], anchors, STRIDE_PX)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        if sched is not None:
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
        done = step + 1
        if done % args.save_every == 0 or done == last:  # EMA weights so far: `--export-only` scores them
            save_checkpoint(ema, anchors, args, done, time.time() - t0)
            save_state(args, done, time.time() - t0, model, ema, opt, sched, rng, pools, anchors)
    if last < args.steps:
        log.info("stopped at step %d of %d: go on with --resume --report %s", last, args.steps, args.report)
        return
    train_s = time.time() - t0
    export(ema, anchors, args, real, sim, train_s)


STATE_FILE = "state.pt"
RESUMED_SETTINGS = ("steps", "batch", "lr", "seed", "width", "arch", "indoor_fraction", "sim_fraction", "mosaic",
                    "camera", "freeze", "input_wh", "leave_out", "pretrained", "init", "sim", "indoor", "facades")


def save_state(args: argparse.Namespace, step: int, spent_s: float, model, ema, opt, sched,  # type: ignore[no-untyped-def]
               rng: np.random.Generator, pools: dict[str, _Shuffled], anchors: np.ndarray) -> None:
    """Everything a stopped run needs to go on to the same result (`--resume`): weights, optimiser, schedule,
    the random generators, where each data pool is in its epoch, and the run's settings. Written atomically."""
    import torch

    settings = {k: getattr(args, k) for k in RESUMED_SETTINGS if hasattr(args, k)}
    state = {"step": step, "spent_s": spent_s, "model": model.state_dict(), "ema": ema.state_dict(),
             "opt": opt.state_dict(), "sched": None if sched is None else sched.state_dict(),
             "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
             "pools": {k: list(p.order) for k, p in pools.items()}, "anchors": np.asarray(anchors),
             "settings": settings, "init_info": getattr(args, "init_info", None)}
    tmp = args.report / (STATE_FILE + ".tmp")
    torch.save(state, tmp)
    tmp.replace(args.report / STATE_FILE)


def load_state(args: argparse.Namespace) -> dict:  # type: ignore[type-arg]
    """The saved state of the run in `--report`, its settings put back into `args` (those of the command line are
    the run's own: a resumed run is the same run)."""
    import torch

    path = args.report / STATE_FILE
    if not path.exists():
        raise SystemExit(f"error: --resume: no saved run state at {path} (a run saves it every --save-every steps)")
    state = torch.load(path, weights_only=False, map_location="cpu")
    for k, v in state["settings"].items():
        setattr(args, k, v)
    if state.get("init_info") is not None:
        args.init_info = state["init_info"]
    return state


def restore_state(state: dict, model, ema, opt, sched, rng: np.random.Generator,  # type: ignore[no-untyped-def, type-arg]
                  pools: dict[str, _Shuffled]) -> tuple[int, float]:
    import torch

    model.load_state_dict(state["model"])
    ema.load_state_dict(state["ema"])
    opt.load_state_dict(state["opt"])
    if sched is not None and state["sched"] is not None:
        sched.load_state_dict(state["sched"])
    rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    for k, order in state["pools"].items():
        pools[k].order = list(order)
    return int(state["step"]), float(state["spent_s"])


def save_checkpoint(ema, anchors: np.ndarray, args: argparse.Namespace, steps: int,  # type: ignore[no-untyped-def]
                    train_s: float) -> None:
    import torch

    args.report.mkdir(parents=True, exist_ok=True)
    torch.save({"ema": ema.state_dict(), "anchors": anchors, "width": args.width, "arch": args.arch,
                "train_s": train_s, "steps": steps, "settings": training_settings(args)}, args.report / "checkpoint.pt")


def training_settings(args: argparse.Namespace) -> dict[str, object]:
    """The settings of this run, and of the run it started from (`--init`), for the sidecar and checkpoint."""
    out: dict[str, object] = {"steps": args.steps, "batch": args.batch, "lr": args.lr, "seed": args.seed,
                              "width": args.width, "indoor_fraction": args.indoor_fraction,
                              "sim_fraction": args.sim_fraction, "mosaic": args.mosaic,
                              "input_wh": list(args.input_wh), "arch": args.arch, "camera": args.camera,
                              "freeze": list(args.freeze), "leave_out": list(args.leave_out),
                              "pretrained": None if args.arch != "shufflenet" or args.pretrained is None
                              else Path(args.pretrained).name}
    init = getattr(args, "init", None)
    if init is not None:
        info = getattr(args, "init_info", {})
        out["init"] = {"path": str(init), "steps": info.get("steps"), "settings": info.get("settings")}
    return out


def export_only(args: argparse.Namespace) -> None:
    """Export and score the EMA weights a finished run saved (`--export-only CHECKPOINT`)."""
    import torch

    ckpt = torch.load(args.export_only, weights_only=False)
    model = build_model(str(ckpt.get("arch", "tiny")), int(ckpt["width"]), None)
    model.load_state_dict(ckpt["ema"])
    args.width, args.steps, args.arch = int(ckpt["width"]), int(ckpt["steps"]), str(ckpt.get("arch", "tiny"))
    settings = ckpt.get("settings") or {}
    for k in ("batch", "lr", "seed", "indoor_fraction", "sim_fraction", "input_wh", "camera", "leave_out"):
        if k in settings:
            setattr(args, k, settings[k])
    if isinstance(settings.get("init"), dict):
        args.init, args.init_info = settings["init"]["path"], {"steps": settings["init"].get("steps"),
                                                               "settings": settings["init"].get("settings")}
    export(model, np.asarray(ckpt["anchors"]), args, load_real(args), [], float(ckpt["train_s"]))


def reproduce_command(args: argparse.Namespace) -> str:
    """The command line(s) that make these weights: with `--init`, the run that made the init first (`make train`)."""
    cmd = "python -m macroloc.perception.train"
    init = getattr(args, "init", None)
    if init is None:
        return cmd
    sims = "".join(f" --sim {d}" for d in getattr(args, "sim", []))
    tail = (f" --indoor-fraction {args.indoor_fraction} --lr {args.lr} --steps {args.steps} --batch {args.batch} "
            f"--seed {args.seed}{sims}" + (f" --sim-fraction {args.sim_fraction}" if sims else "")
            + (f" --mosaic {args.mosaic}" if args.mosaic else "")
            + (" --input-wh {} {}".format(*input_size(args)) if input_size(args) != INPUT_WH else ""))
    base = (getattr(args, "init_info", None) or {}).get("settings") or {}
    if not base or "init" in base or sims or Path(init).resolve() == SHIPPED_WEIGHTS.resolve():
        shown = "perception/models/detector.pt" if Path(init).resolve() == SHIPPED_WEIGHTS.resolve() else init
        return f"{cmd} --init {shown}{tail}"
    mine = f"{cmd} --init out/detector/base/checkpoint.pt{tail}"
    first = (f"{cmd} --steps {base.get('steps')} --batch {base.get('batch')} --lr {base.get('lr')} "
             f"--seed {base.get('seed')} --width {base.get('width')} --indoor-fraction {base.get('indoor_fraction')} "
             "--out out/detector/base --report out/detector/base")
    return f"{first} && {mine}"


def rendered_sources(sim: list[Sample]) -> list[str]:
    """The buildings and seeds rendered frames came from, by their exported names (BUILDING_sSEED_FRAME)."""
    return sorted({m.group(1) for s in sim if (m := re.match(r"(.+_s\d+)_\d+$", s.name))})


def export(model, anchors: np.ndarray, args: argparse.Namespace, data: dict[str, dict[str, list[Sample]]],  # type: ignore[no-untyped-def]
           sim: list[Sample], train_s: float) -> None:
    import torch

    from macroloc.perception.model import STRIDE_PX

    args.out.mkdir(parents=True, exist_ok=True)
    args.report.mkdir(parents=True, exist_ok=True)
    onnx_path = args.out / "detector.onnx"
    model = model.cpu().eval()
    input_wh = input_size(args)
    dummy = torch.zeros(1, 3, input_wh[1], input_wh[0])
    torch.onnx.export(model, (dummy,), str(onnx_path), input_names=["image"], output_names=["raw"],
                      opset_version=13, dynamo=False)
    # The weights themselves beside the ONNX (which folds the batch norms): `--init` fine-tunes from them.
    torch.save({"ema": model.state_dict(), "anchors": np.asarray(anchors), "width": args.width, "arch": args.arch,
                "steps": args.steps, "settings": training_settings(args)}, onnx_path.with_suffix(".pt"))
    spec = DetectorSpec(CLASS_NAMES, input_wh, STRIDE_PX, tuple((float(w), float(h)) for w, h in anchors), 0.5)
    detector = Detector(onnx_path, spec, threads=args.threads)
    val_samples = [x for d in data.values() for x in d["val"]]
    val_dets, val_truths = detector_eval.detect_all(detector, val_samples)
    val_curves = detector_eval.curves(val_dets, val_truths)
    threshold = best_f1_threshold([c for c in val_curves if c.n_truth])
    figures = {}
    for src, d in data.items():
        for part in ("test", "val"):
            dets, truths = detector_eval.detect_all(detector, d[part])
            figures[f"{src}_{part}"] = detector_eval.figures(d[part], dets, truths, threshold,
                                                              subsets=REAL_SOURCES[src].indoor)
    counts = {f"{src}_{part}": len(v) for src, d in data.items() for part, v in d.items()}
    extra: dict[str, object] = {
        "threshold_rule": "max mean F1 (door, window) on the PR curves of the validation parts of the sources trained "
                          "on",
        "trained_on": {**{f"{src}_photos": len(d["train"]) for src, d in data.items()}, "rendered_frames": len(sim)},
        "left_out_sources": list(args.leave_out),
        "data_counts_images": counts,
        "split": "each source 80/10/10 by source photo, seeded (perception.trainset.split_by_source: augmented "
                 "copies and frames of one video stay in one part); facades: test = img_n with n % 5 == 0 (never "
                 "trained on), val = seeded 15 % of the rest. In-source test figures measure memory of a source; "
                 "the left-out figures are in docs/measurements.md (bench.eval_detector --loso)",
        "training": {**training_settings(args), "rendered_flights": rendered_sources(sim), "threads": args.threads,
                     "seconds": round(train_s), "machine": f"{os.cpu_count()} CPU cores (shared)"},
        "figures": figures,
        "reproduce": reproduce_command(args),
    }
    spec = DetectorSpec(CLASS_NAMES, input_wh, STRIDE_PX, spec.anchors_px, threshold, spec.nms_iou, extra)
    onnx_path.with_suffix(".json").write_text(json.dumps(spec.to_json(), indent=1) + "\n")
    plot_pr(val_curves, threshold, str(args.out / "detector_pr.png"),
            f"validation parts ({', '.join(data)}: {len(val_samples)} images)")
    (args.report / "metrics.json").write_text(json.dumps({"threshold": threshold, **figures}, indent=1) + "\n")
    log.info("threshold %.2f; figures %s", threshold, json.dumps(figures))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m macroloc.perception.train", description=__doc__.splitlines()[0])
    ap.add_argument("--facades", type=Path, default=SHARED_DATA / "images" / "facades")
    ap.add_argument("--indoor", type=Path, default=SHARED_DATA / "images" / "indoor_doors")
    ap.add_argument("--indoor-fraction", type=float, default=0.6,
                    help="share of each batch's real photos drawn from the indoor photos (the rest: facades)")
    ap.add_argument("--width", type=int, default=1, help="channel multiplier of the TinyYolo network")
    ap.add_argument("--arch", choices=("tiny", "shufflenet"), default="tiny",
                    help="tiny: TinyYolo from scratch; shufflenet: ShuffleNetV2-0.5x features from --pretrained under "
                         "a door/window head (perception.backbone)")
    ap.add_argument("--pretrained", type=Path, default=PRETRAINED,
                    help="pretrained ShuffleNetV2-0.5x weights for --arch shufflenet (FastestDet's COCO network, or "
                         "the ImageNet backbone alone)")
    ap.add_argument("--freeze", nargs="*", default=[], metavar="PART",
                    help="backbone parts whose pretrained weights stay fixed (shufflenet: first_conv stage2 stage3)")
    ap.add_argument("--leave-out", nargs="*", default=[], choices=tuple(REAL_SOURCES), metavar="SOURCE",
                    help=f"real photo sources kept out of training entirely ({', '.join(REAL_SOURCES)}): a model "
                         "that is then scored on them shows what a camera it never saw gets")
    ap.add_argument("--camera", type=float, default=0.0,
                    help="probability of a lens distortion (wide-angle) and, apart, of a camera's white balance, "
                         "motion blur or JPEG on a training image")
    ap.add_argument("--sim", type=Path, nargs="*", default=[],
                    help="folders of rendered frames with YOLO labels; out/sim_yolo is made by bench.sim_trainset "
                         "on first use (default: none, the shipped model is trained on real photos only)")
    ap.add_argument("--sim-fraction", type=float, default=0.5, help="share of each batch drawn from rendered frames")
    ap.add_argument("--mosaic", type=float, default=0.0,
                    help="share of training images made of four samples in quadrants (smaller, far openings)")
    ap.add_argument("--input-wh", type=int, nargs=2, default=list(INPUT_WH), metavar=("W", "H"),
                    help="the network's input size in px (a multiple of the stride, 16); with --init at another "
                         "size the init's anchors are scaled to it")
    ap.add_argument("--steps", type=int, default=4200, help="training steps (0 with --init: export the init)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu",
                    help="torch device of the training (cpu, the tested one; cuda on a machine with a GPU)")
    ap.add_argument("--save-every", type=int, default=250,
                    help="steps between saves of the EMA weights and of the run's whole state (for --resume)")
    ap.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                    help="save the run's state at this step and stop (a long training in parts: --resume goes on)")
    ap.add_argument("--resume", action="store_true",
                    help="go on with the run whose state is in --report, with its own settings, to the same result "
                         "as if it had not stopped")
    ap.add_argument("--out", type=Path, default=ROOT / "perception" / "models")
    ap.add_argument("--report", type=Path, default=ROOT / "out" / "detector")
    ap.add_argument("--export-only", type=Path, default=None, help="export and score a finished run's checkpoint.pt")
    ap.add_argument("--init", type=Path, default=None,
                    help="start from these weights (a run's checkpoint.pt or a shipped detector.pt) and keep their "
                         "anchors: fine-tuning (default: none, from scratch)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    args = parse_args(argv)
    if args.export_only is not None:
        export_only(args)
    else:
        train(args)


if __name__ == "__main__":
    main()
