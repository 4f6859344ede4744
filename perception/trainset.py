"""Detector data: YOLO-labelled images, the class mapping, the fixed split, and augmentation (numpy/OpenCV).

Boxes are `boxes_xyxy` in the pixels of the image they belong to; classes are indices into
`perception.detector.CLASS_NAMES` (0 door, 1 window, 2 neither).

Facade photos (`../shared/data/images/facades`, labels `0 window, 1 cantilever, 2 arch, 3 signboard,
4 win_ad, 5 door`): 5 -> door, 0 and 4 -> window, 1/2/3 -> neither (the paper's third class, §2.2.1).
The held-out real test split is every `img_n.jpg` with n % 5 == 0 (the simulator's textures avoid it too);
the rest is split, seeded, into train and validation (the validation part sets the score threshold).

Indoor photos (`../shared/data/images/indoor_doors/<source>`, `perception.sources`; labels `0 door, 1 window`, an
empty label file is a negative image): each source split train/val/test by *source photo* (`source_stem`), seeded,
80/10/10 of the sources, so that the augmented copies of one photo (Roboflow's `NAME_ext.rf.HASH`) and the frames
of one video never sit in two parts.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from macroloc.perception.detector import PAD_VALUE

log = logging.getLogger(__name__)

FACADE_CLASS_MAP = {5: 0, 0: 1, 4: 1, 1: 2, 2: 2, 3: 2}
ROTATIONS_DEG = tuple(range(-20, 21, 5))  # paper §2.2.1: ±20° in 5° steps, eq. (1)
INDOOR_CLASS_MAP = {0: 0, 1: 1}
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
_SPLIT_PREFIX = re.compile(r"^(train|valid|test)_")  # the exporter's own split, not the source photo
_AUGMENTED_COPY = re.compile(r"_[A-Za-z]+\.rf\.[0-9a-fA-F]+$")  # Roboflow: SOURCE_png.rf.HASH (also jpg, JPG, jpeg)
_SECOND_DOWNLOAD = re.compile(r"-\d+-$")  # Door0007-1-: a second download of Door0007
_VIDEO_FRAME = re.compile(r"^(frame|v_test1_mp4-)\d+$")  # consecutive frames of one video are near copies


@dataclass
class Sample:
    """An image held in memory (BGR uint8, long side <= cache size) with its boxes (K,4) and classes (K,)."""

    name: str
    image_bgr: np.ndarray
    boxes_xyxy: np.ndarray
    classes: np.ndarray


YOLO_CLASSES = {"door": 0, "window": 1}  # the classes of the frames this project writes (rendered, self-labelled)


def yolo_line(kind: str, box_xyxy: tuple[float, float, float, float], width_px: int, height_px: int) -> str:
    """One YOLO label line `class cx cy w h` (normalised, the image spanning [0, 1]) of a box in pixels with pixel
    centres at integers (the image spanning [-0.5, W - 0.5])."""
    x0, y0, x1, y1 = box_xyxy
    cx, cy = ((x0 + x1) / 2 + 0.5) / width_px, ((y0 + y1) / 2 + 0.5) / height_px
    return f"{YOLO_CLASSES[kind]} {cx:.6f} {cy:.6f} {(x1 - x0) / width_px:.6f} {(y1 - y0) / height_px:.6f}"


def yolo_folder(out_dir: Path) -> None:
    """Make `out_dir` a YOLO folder of this project's classes: images/, labels/ and data.yaml."""
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "labels").mkdir(parents=True, exist_ok=True)
    names = "\n".join(f"  {v}: {k}" for k, v in YOLO_CLASSES.items())
    (out_dir / "data.yaml").write_text(f"path: .\ntrain: images\nval: images\nnames:\n{names}\n")


def read_yolo_labels(label_path: Path, width_px: int, height_px: int,
                     class_map: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """YOLO `class cx cy w h` (normalised) -> (boxes_xyxy in pixels (K,4), mapped classes (K,))."""
    boxes, classes = [], []
    if label_path.exists():
        for line in label_path.read_text().splitlines():
            parts = line.split()
            if len(parts) != 5 or int(parts[0]) not in class_map:
                continue
            cx, cy, w, h = (float(v) for v in parts[1:])
            boxes.append([(cx - w / 2) * width_px, (cy - h / 2) * height_px,
                          (cx + w / 2) * width_px, (cy + h / 2) * height_px])
            classes.append(class_map[int(parts[0])])
    return np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(classes, np.int64)


def facade_number(path: Path) -> int:
    match = re.search(r"(\d+)", path.stem)
    if match is None:
        raise ValueError(f"no image number in {path.name}")
    return int(match.group(1))


def is_real_test(path: Path) -> bool:
    """The held-out real test split: img_n.jpg with n % 5 == 0 (never trained on, never a sim texture)."""
    return facade_number(path) % 5 == 0


def split_facades(root: Path, seed: int = 0, val_fraction: float = 0.15) -> dict[str, list[Path]]:
    """Fixed split of the facade images: {"train", "val", "test"} lists of image paths."""
    images = sorted((root / "images").glob("*.jpg"), key=facade_number)
    test = [p for p in images if is_real_test(p)]
    rest = [p for p in images if not is_real_test(p)]
    order = np.random.default_rng(seed).permutation(len(rest))
    n_val = round(val_fraction * len(rest))
    val = sorted((rest[i] for i in order[:n_val]), key=facade_number)
    train = sorted((rest[i] for i in order[n_val:]), key=facade_number)
    return {"train": train, "val": val, "test": test}


def source_stem(path: Path) -> str:
    """The source photo an image file was made from: `train_Door0007-1-_png.rf.HASH.jpg` -> `Door0007`, the frames
    `frame224.jpg`, `frame225.jpg` of one video -> `frame`; an image that is its own source keeps its stem."""
    stem = _AUGMENTED_COPY.sub("", _SPLIT_PREFIX.sub("", path.stem))
    stem = _SECOND_DOWNLOAD.sub("", stem)
    video = _VIDEO_FRAME.match(stem)
    return video.group(1) if video else stem


def split_by_source(paths: list[Path], seed: int = 0,
                    fractions: tuple[float, float] = (0.8, 0.1)) -> dict[str, list[Path]]:
    """Seeded split of image files into {"train", "val", "test"} by source (`source_stem` within its folder):
    `fractions` (train, val) of the sources, the rest test; every copy of a source lands in the same part."""
    groups: dict[str, list[Path]] = {}
    for p in sorted(paths):
        groups.setdefault(f"{p.parent}/{source_stem(p)}", []).append(p)
    keys = sorted(groups)
    order = np.random.default_rng(seed).permutation(len(keys))
    n_train, n_val = round(fractions[0] * len(keys)), round(fractions[1] * len(keys))
    parts = {"train": order[:n_train], "val": order[n_train:n_train + n_val], "test": order[n_train + n_val:]}
    return {name: sorted(p for i in idx for p in groups[keys[i]]) for name, idx in parts.items()}


def load_sample(image_path: Path, label_path: Path, class_map: dict[int, int], max_side_px: int) -> Sample:
    """Read an image and its labels, downscaled so that its long side is at most `max_side_px`."""
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"cannot read image {image_path}")
    h, w = image.shape[:2]
    boxes, classes = read_yolo_labels(label_path, w, h, class_map)
    scale = min(1.0, max_side_px / max(h, w))
    if scale < 1.0:
        image = cv2.resize(image, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
        boxes = boxes * scale
    return Sample(image_path.stem, image, boxes, classes)


def facade_label_path(image_path: Path) -> Path:
    return image_path.parent.parent / "labels" / (image_path.stem + ".txt")


def _linear(s: float, rng: np.random.Generator, rotation_prob: float, aspect_range: tuple[float, float]) -> np.ndarray:
    """2x2 part of the map: scale `s`, an aspect change (x by sqrt(a), y by 1/sqrt(a)), an optional mirror, then
    the paper's rotation."""
    theta = np.deg2rad(rng.choice(ROTATIONS_DEG)) if rng.random() < rotation_prob else 0.0
    a = float(np.sqrt(np.exp(rng.uniform(np.log(aspect_range[0]), np.log(aspect_range[1])))))
    flip = -1.0 if rng.random() < 0.5 else 1.0
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])  # eq. (1) R_z(theta)
    return s * rot @ np.diag([flip * a, 1.0 / a])


def _affine(sample: Sample, out_wh: tuple[int, int], rng: np.random.Generator,
            scale_range: tuple[float, float], rotation_prob: float,
            aspect_range: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Forward 2x3 map source pixels -> output pixels: letterbox fit x random scale, aspect, rotation, shift, flip."""
    h, w = sample.image_bgr.shape[:2]
    w_out, h_out = out_wh
    fit = min(w_out / w, h_out / h)
    s = fit * float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1]))))
    A = _linear(s, rng, rotation_prob, aspect_range)
    # Where the image centre lands: anywhere that keeps some of the image in view.
    span_x, span_y = max(0.0, (w * s - w_out) / 2), max(0.0, (h * s - h_out) / 2)
    t_out = np.array([w_out / 2 + rng.uniform(-span_x - 0.15 * w_out, span_x + 0.15 * w_out),
                      h_out / 2 + rng.uniform(-span_y - 0.15 * h_out, span_y + 0.15 * h_out)])
    t = t_out - A @ np.array([w / 2, h / 2])
    return np.hstack([A, t[:, None]])


def _zoom_affine(box_xyxy: np.ndarray, out_wh: tuple[int, int], rng: np.random.Generator, rotation_prob: float,
                 aspect_range: tuple[float, float]) -> np.ndarray:
    """A map that zooms onto one box, as a drone flying up to a door sees it: the box fills 55-125 % of the
    output's height, its centre anywhere across the width, so it is often cut by the image border."""
    w_out, h_out = out_wh
    x0, y0, x1, y1 = box_xyxy
    s = float(rng.uniform(0.55, 1.25)) * h_out / max(y1 - y0, 1.0)
    A = _linear(s, rng, rotation_prob, aspect_range)
    t_out = np.array([rng.uniform(-0.05, 1.05) * w_out, rng.uniform(0.3, 0.7) * h_out])
    t = t_out - A @ np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    return np.hstack([A, t[:, None]])


def _photometric(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV).astype(np.float32)
    hsv[..., 0] = (hsv[..., 0] + rng.uniform(-6, 6)) % 180
    hsv[..., 1] *= rng.uniform(0.5, 1.4)
    hsv[..., 2] = hsv[..., 2] * rng.uniform(0.55, 1.45) + rng.uniform(-20, 20)
    out = cv2.cvtColor(np.clip(hsv, 0, 255).astype(np.uint8), cv2.COLOR_HSV2BGR)
    if rng.random() < 0.2:  # the right camera of a real rig is often grey
        out = cv2.cvtColor(cv2.cvtColor(out, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    if rng.random() < 0.2:
        out = cv2.GaussianBlur(out, (3, 3), rng.uniform(0.3, 1.2))
    if rng.random() < 0.3:
        noise = rng.normal(0, rng.uniform(2, 8), out.shape)
        out = np.clip(out.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    return out


def _camera(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """What a drone's camera adds to a photo, one effect each at a time: a white balance set for other light
    (per-channel gains), motion blur along a random direction (3-9 px), JPEG compression (quality 25-75)."""
    out: np.ndarray = image
    if rng.random() < 0.5:
        gains = np.exp(rng.uniform(-0.15, 0.15, 3))
        out = np.clip(out.astype(np.float32) * gains, 0, 255).astype(np.uint8)
    if rng.random() < 0.25:
        n = int(rng.integers(3, 10))
        line = np.zeros((n, n), np.float32)
        line[n // 2] = 1.0 / n
        rot = cv2.getRotationMatrix2D(((n - 1) / 2, (n - 1) / 2), float(rng.uniform(0, 180)), 1.0)
        kernel = np.asarray(cv2.warpAffine(line, rot, (n, n)), np.float32)
        out = cv2.filter2D(out, -1, kernel / max(float(kernel.sum()), 1e-6))
    if rng.random() < 0.3:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(25, 76))])
        decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR) if ok else None
        out = out if decoded is None else np.asarray(decoded)
    return out


def lens_distort(image: np.ndarray, boxes_xyxy: np.ndarray, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """A wide-angle (k1 > 0: barrel, straight lines bow outwards) or a pincushion (k1 < 0) lens of one radial term
    about the image centre: the output pixel at normalised radius r (1 at the half-diagonal) samples the input at
    r * (1 + k1 r^2), so with k1 > 0 more of the scene is squeezed towards the border. Boxes follow
    their sides' points through the inverse map (fixed-point iterations) and are bounded; returns both."""
    h, w = image.shape[:2]
    c, half_diag = np.array([(w - 1) / 2, (h - 1) / 2]), float(np.hypot(w, h) / 2)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    u, v = (xs - c[0]) / half_diag, (ys - c[1]) / half_diag
    f = 1 + k1 * (u * u + v * v)
    warped = cv2.remap(image, (c[0] + u * f * half_diag).astype(np.float32),
                       (c[1] + v * f * half_diag).astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=(PAD_VALUE,) * 3)
    if len(boxes_xyxy) == 0:
        return warped, boxes_xyxy.reshape(0, 4)
    t = np.linspace(0, 1, 9)
    out = []
    for x0, y0, x1, y1 in boxes_xyxy:
        edge = np.concatenate([np.stack([x0 + t * (x1 - x0), np.full(9, y0)], 1),
                               np.stack([x0 + t * (x1 - x0), np.full(9, y1)], 1),
                               np.stack([np.full(9, x0), y0 + t * (y1 - y0)], 1),
                               np.stack([np.full(9, x1), y0 + t * (y1 - y0)], 1)])
        src = (edge - c) / half_diag
        dst = src.copy()
        for _ in range(8):  # solve src = dst * (1 + k1 |dst|^2) for dst
            dst = src / (1 + k1 * (dst ** 2).sum(1, keepdims=True))
        p = dst * half_diag + c
        out.append([p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()])
    boxes = np.asarray(out, np.float64)
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, w)
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, h)
    return warped, boxes


def augment(sample: Sample, out_wh: tuple[int, int], rng: np.random.Generator,
            scale_range: tuple[float, float] = (0.6, 2.5), rotation_prob: float = 0.6,
            min_visible: float = 0.45, zoom_prob: float = 0.0,
            aspect_range: tuple[float, float] = (1.0, 1.0), camera_prob: float = 0.0,
            lens_prob: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One augmented training image (H,W,3 uint8) with its boxes (K,4, output pixels) and classes (K,).

    The geometric part is one affine map applied by inverse warping (every output pixel samples the
    source at M^-1 p, so no holes: paper §2.2.1); box corners go through the forward map and are bounded.
    With probability `zoom_prob` the map zooms onto one box at least 15 % of the image tall (`_zoom_affine`);
    with `lens_prob` a radial lens distortion follows (`lens_distort`), with `camera_prob` a camera's white balance,
    motion blur or JPEG (`_camera`) after the photometric changes.
    """
    h = sample.image_bgr.shape[0]
    tall = sample.boxes_xyxy[sample.boxes_xyxy[:, 3] - sample.boxes_xyxy[:, 1] >= 0.15 * h]
    if len(tall) and rng.random() < zoom_prob:
        M = _zoom_affine(tall[rng.integers(len(tall))], out_wh, rng, rotation_prob, aspect_range)
    else:
        M = _affine(sample, out_wh, rng, scale_range, rotation_prob, aspect_range)
    M_inv = cv2.invertAffineTransform(M)
    image = cv2.warpAffine(sample.image_bgr, M_inv, out_wh, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=(PAD_VALUE,) * 3)
    boxes, classes = transform_boxes(sample.boxes_xyxy, sample.classes, M, out_wh, min_visible)
    if rng.random() < lens_prob:  # wide-angle (barrel, most drones' cameras) or a little pincushion
        image, boxes = lens_distort(image, boxes, float(rng.uniform(-0.08, 0.35)))
        big = (boxes[:, 2] - boxes[:, 0] >= 3) & (boxes[:, 3] - boxes[:, 1] >= 3)
        boxes, classes = boxes[big], classes[big]
    image = _photometric(image, rng)
    return (_camera(image, rng) if rng.random() < camera_prob else image), boxes, classes


Augmented = tuple[np.ndarray, np.ndarray, np.ndarray]  # image (H, W, 3) uint8, boxes_xyxy (K, 4), classes (K,)


def mosaic(samples: list[Sample], out_wh: tuple[int, int], rng: np.random.Generator,
           tile: Callable[[Sample, tuple[int, int], np.random.Generator], Augmented] = augment) -> Augmented:
    """Four samples, each augmented into one quadrant of the output (the split point drawn within the middle
    30 % of each axis), so that their openings appear at half the size or less, with real surroundings, not
    padding: what a far door, or a facade's window, looks like to the network. `tile(sample, (w, h), rng)` makes
    each quadrant (e.g. `augment` with the training's settings); boxes cut by a quadrant's edge follow its
    `min_visible` rule."""
    w, h = out_wh
    cx, cy = round(rng.uniform(0.35, 0.65) * w), round(rng.uniform(0.35, 0.65) * h)
    canvas = np.full((h, w, 3), PAD_VALUE, np.uint8)
    boxes, classes = [], []
    for sample, (x0, y0, x1, y1) in zip(samples, [(0, 0, cx, cy), (cx, 0, w, cy), (0, cy, cx, h), (cx, cy, w, h)],
                                        strict=True):
        image, b, c = tile(sample, (x1 - x0, y1 - y0), rng)
        canvas[y0:y1, x0:x1] = image
        boxes.append(b + np.array([x0, y0, x0, y0], dtype=np.float64))
        classes.append(c)
    return canvas, np.concatenate(boxes).reshape(-1, 4), np.concatenate(classes)


def transform_boxes(boxes_xyxy: np.ndarray, classes: np.ndarray, M: np.ndarray, out_wh: tuple[int, int],
                    min_visible: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes through a 2x3 affine map: bounds of the mapped corners, clipped; mostly hidden ones dropped."""
    if len(boxes_xyxy) == 0:
        return boxes_xyxy.reshape(0, 4), classes[:0]
    x0, y0, x1, y1 = boxes_xyxy.T
    corners = np.stack([np.stack([x0, y0], -1), np.stack([x1, y0], -1),
                        np.stack([x1, y1], -1), np.stack([x0, y1], -1)], 1)  # (K, 4, 2)
    mapped = corners @ M[:, :2].T + M[:, 2]
    full = np.concatenate([mapped.min(1), mapped.max(1)], 1)
    clipped = full.copy()
    clipped[:, [0, 2]] = np.clip(full[:, [0, 2]], 0, out_wh[0])
    clipped[:, [1, 3]] = np.clip(full[:, [1, 3]], 0, out_wh[1])
    area = lambda b: np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)  # noqa: E731
    keep = (area(clipped) >= min_visible * np.maximum(area(full), 1e-9)) & \
           (clipped[:, 2] - clipped[:, 0] >= 3) & (clipped[:, 3] - clipped[:, 1] >= 3)
    return clipped[keep], classes[keep]
