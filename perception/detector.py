"""Door/window detector at run time: the exported ONNX network through onnxruntime (no torch).

Pixels: boxes are `box_xyxy` = (x0, y0, x1, y1) in the *input image's* pixels (x right, y down).
The network sees the image letterboxed into its input size (`DetectorSpec.input_wh`), BGR in [0, 1].
Decoding follows YOLOv2: centre = (cell + sigmoid(t_xy)) * stride, size = anchor * exp(t_wh),
score = sigmoid(t_obj) * softmax(class logits); the third class ("neither", paper §2.2.1) is dropped.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from macroloc.common.errors import UserInputError

log = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_MODEL = MODELS_DIR / "detector.onnx"
CLASS_NAMES = ("door", "window", "neither")
REPORTED_TYPES = ("door", "window")
PAD_VALUE = 114
MAX_INPUT_SIDE_PX = 4096  # a sidecar asking for a larger network input is refused (DetectorSpec.load)
MAX_DETECTIONS = 32  # per image, best first: bounds the per-box work downstream
TRUNCATION_MARGIN_PX = 2.0  # a box this close to the image border may be cut by it


@dataclass(frozen=True)
class Detection:
    """One detected macro-feature: `type` (door|window), `score` in [0, 1], `box_xyxy` in image pixels;
    `truncated` where the box reaches within `TRUNCATION_MARGIN_PX` of the image border (the opening may be cut by
    it: a door seen from close up)."""

    type: str
    score: float
    box_xyxy: tuple[float, float, float, float]
    truncated: bool = False

    def to_json(self) -> dict[str, object]:
        return {"type": self.type, "score": round(self.score, 4), "box_xyxy": [round(v, 1) for v in self.box_xyxy],
                "truncated": self.truncated}


def at_border(box_xyxy: tuple[float, float, float, float], width_px: int, height_px: int,
              margin_px: float = TRUNCATION_MARGIN_PX) -> bool:
    """Whether a box (image pixels) reaches within `margin_px` of the border of a `width_px` x `height_px` image."""
    x0, y0, x1, y1 = box_xyxy
    return x0 <= margin_px or y0 <= margin_px or x1 >= width_px - margin_px or y1 >= height_px - margin_px


@dataclass(frozen=True)
class DetectorSpec:
    """What the network expects and how to decode it (the JSON sidecar beside the ONNX file)."""

    classes: tuple[str, ...] = CLASS_NAMES
    input_wh: tuple[int, int] = (320, 240)
    stride_px: int = 16
    anchors_px: tuple[tuple[float, float], ...] = ((16.0, 32.0),)
    score_threshold: float = 0.3
    nms_iou: float = 0.45
    extra: dict[str, object] = field(default_factory=dict)

    @staticmethod
    def load(path: Path) -> DetectorSpec:
        """The sidecar's spec; UserInputError where its input size (each side 1-4096 px, the tensor onnxruntime is
        given) or stride (1-256 px) is out of range."""
        doc = json.loads(path.read_text())
        w, h, stride = int(doc["input_wh"][0]), int(doc["input_wh"][1]), int(doc["stride_px"])
        if not (0 < w <= MAX_INPUT_SIDE_PX and 0 < h <= MAX_INPUT_SIDE_PX and 0 < stride <= 256):
            raise UserInputError(f"detector sidecar {path}: input_wh {w}x{h} or stride_px {stride} out of range")
        return DetectorSpec(
            classes=tuple(doc["classes"]),
            input_wh=(w, h),
            stride_px=stride,
            anchors_px=tuple((float(w), float(h)) for w, h in doc["anchors_px"]),
            score_threshold=float(doc["score_threshold"]),
            nms_iou=float(doc.get("nms_iou", 0.45)),
            extra={k: v for k, v in doc.items() if k not in {"classes", "input_wh", "stride_px", "anchors_px",
                                                             "score_threshold", "nms_iou"}},
        )

    def to_json(self) -> dict[str, object]:
        return {"classes": list(self.classes), "input_wh": list(self.input_wh), "stride_px": self.stride_px,
                "anchors_px": [list(a) for a in self.anchors_px], "score_threshold": self.score_threshold,
                "nms_iou": self.nms_iou, **self.extra}


@dataclass(frozen=True)
class Letterbox:
    """Image pixels -> network input pixels: `p_net = p_img * scale + offset_px`."""

    scale: float
    offset_px: tuple[float, float]

    def to_image(self, boxes_xyxy_net: np.ndarray) -> np.ndarray:
        off = np.array(self.offset_px * 2, dtype=np.float64)
        return (boxes_xyxy_net - off) / self.scale


def letterbox(image_bgr: np.ndarray, input_wh: tuple[int, int]) -> tuple[np.ndarray, Letterbox]:
    """Resize keeping the aspect ratio and pad (grey) to `input_wh`; returns (uint8 HxWx3, mapping)."""
    w_net, h_net = input_wh
    h, w = image_bgr.shape[:2]
    scale = min(w_net / w, h_net / h)
    w_new, h_new = max(1, round(w * scale)), max(1, round(h * scale))
    ox, oy = (w_net - w_new) // 2, (h_net - h_new) // 2
    canvas = np.full((h_net, w_net, 3), PAD_VALUE, np.uint8)
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    canvas[oy:oy + h_new, ox:ox + w_new] = cv2.resize(image_bgr, (w_new, h_new), interpolation=interp)
    return canvas, Letterbox(scale, (float(ox), float(oy)))


def to_bgr(image: np.ndarray) -> np.ndarray:
    """Grey (HxW or HxWx1) or BGR image -> BGR uint8."""
    if image.ndim == 2 or image.shape[2] == 1:
        return cv2.cvtColor(image.reshape(image.shape[:2]), cv2.COLOR_GRAY2BGR)
    return image[:, :, :3]


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def decode(raw: np.ndarray, spec: DetectorSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw map (A*(5+C), Hg, Wg) -> boxes_xyxy_net (K,4), scores (K,), class index (K,), all anchors/cells."""
    n_a, n_c = len(spec.anchors_px), len(spec.classes)
    _, h_g, w_g = raw.shape
    r = raw.reshape(n_a, 5 + n_c, h_g, w_g).astype(np.float64)
    gy, gx = np.mgrid[0:h_g, 0:w_g]
    anchors = np.asarray(spec.anchors_px, np.float64)[:, :, None, None]  # (A, 2, 1, 1)
    cx = (gx[None] + _sigmoid(r[:, 0])) * spec.stride_px
    cy = (gy[None] + _sigmoid(r[:, 1])) * spec.stride_px
    bw = anchors[:, 0] * np.exp(np.clip(r[:, 2], -8, 8))
    bh = anchors[:, 1] * np.exp(np.clip(r[:, 3], -8, 8))
    obj = _sigmoid(r[:, 4])
    logits = r[:, 5:]
    prob = np.exp(logits - logits.max(axis=1, keepdims=True))
    prob /= prob.sum(axis=1, keepdims=True)
    cls = prob.argmax(axis=1)
    score = obj * prob.max(axis=1)
    boxes = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], axis=-1)
    return boxes.reshape(-1, 4), score.reshape(-1), cls.reshape(-1)


def nms(boxes_xyxy: np.ndarray, scores: np.ndarray, iou_max: float) -> np.ndarray:
    """Greedy non-maximum suppression; returns kept indices, best first."""
    order = np.argsort(-scores)
    keep: list[int] = []
    areas = np.prod(np.clip(boxes_xyxy[:, 2:] - boxes_xyxy[:, :2], 0, None), axis=1)
    while order.size:
        i = int(order[0])
        keep.append(i)
        rest = order[1:]
        lt = np.maximum(boxes_xyxy[i, :2], boxes_xyxy[rest, :2])
        rb = np.minimum(boxes_xyxy[i, 2:], boxes_xyxy[rest, 2:])
        inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
        iou = inter / np.maximum(areas[i] + areas[rest] - inter, 1e-9)
        order = rest[iou <= iou_max]
    return np.asarray(keep, dtype=np.int64)


class Detector:
    """ONNX detector. `detect(image)` -> detections of doors and windows in the image's pixels."""

    def __init__(self, model_path: Path = DEFAULT_MODEL, spec: DetectorSpec | None = None, threads: int = 2) -> None:
        import onnxruntime as ort

        self.model_path = Path(model_path)
        self.spec = spec or DetectorSpec.load(self.model_path.with_suffix(".json"))
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        # No busy-waiting after a run: on 2 cores the spinning threads would steal the CPU from SGBM next.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self._session = ort.InferenceSession(str(self.model_path), options, providers=["CPUExecutionProvider"])
        self._input = self._session.get_inputs()[0].name

    def raw(self, image: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        """The network's raw output map for one image (grey or BGR uint8), and the letterbox used."""
        net_img, box = letterbox(to_bgr(image), self.spec.input_wh)
        blob = (net_img.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
        return self._session.run(None, {self._input: blob})[0][0], box

    def detect(self, image: np.ndarray, score_threshold: float | None = None) -> list[Detection]:
        """Doors and windows with score >= threshold (default: the sidecar's PR-chosen one), after NMS."""
        threshold = self.spec.score_threshold if score_threshold is None else score_threshold
        raw, box = self.raw(image)
        return postprocess(raw, box, self.spec, threshold, image.shape[1], image.shape[0])


def postprocess(raw: np.ndarray, box: Letterbox, spec: DetectorSpec, threshold: float,
                width_px: int, height_px: int) -> list[Detection]:
    """Decode, threshold, drop "neither", per-class NMS, map back to image pixels (clipped)."""
    boxes_net, scores, cls = decode(raw, spec)
    out: list[Detection] = []
    for c, name in enumerate(spec.classes):
        if name not in REPORTED_TYPES:
            continue
        sel = (cls == c) & (scores >= threshold)
        if not sel.any():
            continue
        b, s = boxes_net[sel], scores[sel]
        for i in nms(b, s, spec.nms_iou):
            x0, y0, x1, y1 = box.to_image(b[i])
            x0, x1 = float(np.clip(x0, 0, width_px)), float(np.clip(x1, 0, width_px))
            y0, y1 = float(np.clip(y0, 0, height_px)), float(np.clip(y1, 0, height_px))
            if x1 - x0 >= 2 and y1 - y0 >= 2:
                out.append(Detection(name, float(s[i]), (x0, y0, x1, y1), at_border((x0, y0, x1, y1), width_px,
                                                                                    height_px)))
    out.sort(key=lambda d: -d.score)
    return out[:MAX_DETECTIONS]
