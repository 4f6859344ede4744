"""Procedural surface textures (seeded) for walls, floors, ceilings, doors and the outside.

Each texture is a (S, S, 3) uint8 RGB tile covering 1 m x 1 m of surface; the renderer stacks them into one
texture array and maps world coordinates onto it (planar projection along the face's dominant axis). The
point is texture for stereo matching and visual odometry plus variety for the detector, not photo-realism.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

TEXTURE_SIZE_PX = 256
# layer indices of `make_texture_layers`
PLASTER, CONCRETE, BRICK, WOOD_FLOOR, TILES, CARPET, CEILING, WOOD_GRAIN, PAINTED, METAL, GRASS, ASPHALT = range(12)
WALL_LAYERS = (PLASTER, PLASTER, CONCRETE, BRICK)
FLOOR_LAYERS = (WOOD_FLOOR, TILES, CARPET, CONCRETE)
DOOR_LAYERS = (WOOD_GRAIN, PAINTED, WOOD_GRAIN, METAL)


def value_noise(rng: np.random.Generator, size: int, cells: int, aspect: float = 1.0) -> np.ndarray:
    """(size, size) float32 smooth noise in [-1, 1] from a random (cells x cells*aspect) grid, bicubic, tileable."""
    ny, nx = max(2, cells), max(2, int(round(cells * aspect)))
    grid = rng.uniform(-1, 1, (ny, nx)).astype(np.float32)
    grid = np.pad(grid, 2, mode="wrap")  # wrap so the tile repeats without a seam
    big = cv2.resize(grid, (size * (nx + 4) // nx, size * (ny + 4) // ny), interpolation=cv2.INTER_CUBIC)
    oy, ox = 2 * size // ny, 2 * size // nx
    return np.clip(big[oy:oy + size, ox:ox + size], -1, 1)


def fractal_noise(rng: np.random.Generator, size: int, base_cells: int = 4, octaves: int = 5) -> np.ndarray:
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        out += amp * value_noise(rng, size, min(size // 2, base_cells * 2**o))
        total += amp
        amp *= 0.55
    return out / total


def _rgb(grey: np.ndarray, colour: tuple[float, float, float]) -> np.ndarray:
    return np.clip(grey[..., None] * np.array(colour, np.float32)[None, None, :], 0, 1)


def make_texture_layers(seed: int, size: int = TEXTURE_SIZE_PX) -> np.ndarray:
    """(L, size, size, 3) uint8 RGB layers, in the order of the layer constants above (mostly grey-ish: the
    renderer multiplies them by a per-element tint)."""
    rng = np.random.default_rng(seed)
    s = size
    yy, xx = np.mgrid[0:s, 0:s].astype(np.float32) / s
    layers: list[np.ndarray] = []
    # plaster: soft blotches + fine speckle
    layers.append(_rgb(0.82 + 0.10 * fractal_noise(rng, s, 3) + 0.05 * rng.standard_normal((s, s)), (1, 1, 1)))
    # concrete: stronger blotches and pores
    pores = (rng.random((s, s)) < 0.01).astype(np.float32)
    layers.append(_rgb(0.7 + 0.18 * fractal_noise(rng, s, 4) - 0.3 * pores, (1, 1, 1)))
    # brick: 4 courses of 0.25 m, half-bond, per-brick tint, mortar lines
    row = np.floor(yy * 4)
    col = np.floor(xx * 2 + 0.5 * (row % 2))
    tint = rng.uniform(0.75, 1.0, (8, 8))[row.astype(int) % 8, col.astype(int) % 8]
    mortar = ((yy * 4) % 1 < 0.06) | ((xx * 2 + 0.5 * (row % 2)) % 1 < 0.03)
    brick = np.where(mortar, 0.85, tint * (0.9 + 0.1 * fractal_noise(rng, s, 8)))
    layers.append(np.clip(brick[..., None] * np.array([1.0, 0.6, 0.45]), 0, 1))
    # wood floor: planks 0.2 m wide, grain along x
    plank = np.floor(yy * 5)
    grain = value_noise(rng, s, 4, aspect=0.25)[:, ::1] * 0.5 + 0.5 * value_noise(rng, s, 32, aspect=0.1)
    ptint = rng.uniform(0.75, 1.05, 8)[plank.astype(int) % 8]
    seam = ((yy * 5) % 1 < 0.03) | (((xx + 0.37 * plank) % 1) < 0.01)
    wood = np.where(seam, 0.35, ptint * (0.8 + 0.15 * grain))
    layers.append(np.clip(wood[..., None] * np.array([0.85, 0.62, 0.40]), 0, 1))
    # tiles: 0.5 m grid, per-tile tint, grout
    tile = rng.uniform(0.85, 1.0, (4, 4))[(yy * 2).astype(int) % 4, (xx * 2).astype(int) % 4]
    grout = ((yy * 2) % 1 < 0.02) | ((xx * 2) % 1 < 0.02)
    tiles = np.where(grout, 0.45, tile * (0.92 + 0.06 * fractal_noise(rng, s, 6)))
    layers.append(_rgb(tiles, (0.95, 0.93, 0.88)))
    # carpet: high-frequency fibre noise
    layers.append(_rgb(0.6 + 0.12 * value_noise(rng, s, 64) + 0.1 * rng.standard_normal((s, s)), (0.55, 0.6, 0.7)))
    # ceiling tiles: 0.6 m grid with perforation speckle
    grid = ((yy / 0.6) % 1 < 0.015) | ((xx / 0.6) % 1 < 0.015)
    layers.append(_rgb(np.where(grid, 0.6, 0.9 + 0.06 * rng.standard_normal((s, s))), (1, 1, 1)))
    # wood grain (doors): long vertical grain
    g = 0.5 * value_noise(rng, s, 48, aspect=1 / 16) + 0.3 * value_noise(rng, s, 12, aspect=1 / 8)
    layers.append(np.clip((0.75 + 0.2 * g)[..., None] * np.array([0.78, 0.55, 0.35]), 0, 1))
    # painted (doors): nearly flat with slight brush noise
    layers.append(_rgb(0.9 + 0.04 * value_noise(rng, s, 32, aspect=1 / 4), (1, 1, 1)))
    # brushed metal
    layers.append(_rgb(0.75 + 0.1 * value_noise(rng, s, 128, aspect=1 / 32), (0.9, 0.92, 0.95)))
    # grass and asphalt outside
    layers.append(np.clip((0.55 + 0.25 * fractal_noise(rng, s, 8))[..., None] * np.array([0.35, 0.55, 0.25]), 0, 1))
    layers.append(_rgb(0.4 + 0.1 * fractal_noise(rng, s, 16) + 0.06 * rng.standard_normal((s, s)), (1, 1, 1)))
    # surface grain on every layer: centimetre-scale detail that stereo matching and odometry can hold on to
    grains = [1.0 + 0.12 * value_noise(rng, s, 32) + 0.10 * value_noise(rng, s, 96) for _ in layers]
    out = np.stack([np.clip(layer * g[..., None], 0, 1) for layer, g in zip(layers, grains, strict=True)])
    return (out * 255).astype(np.uint8)


# --- door and window textures cut from real photos -----------------------------------------------------------

FACADE_DOOR_CLASS, FACADE_WINDOW_CLASS = 5, 0  # classes of the facade data set's YOLO labels
HELD_OUT_EVERY = 5  # photos whose number n has n % 5 == 0 are the detector's held-out test split: never used


def facade_photo_number(path: Path) -> int | None:
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else None


def facade_crops(folder: Path, seed: int, n_doors: int = 8, n_windows: int = 8,
                 size: int = TEXTURE_SIZE_PX) -> tuple[np.ndarray, np.ndarray]:
    """(doors (D, size, size, 3), windows (W, size, size, 3)) uint8 RGB crops along the labelled boxes of the
    facade photos in `folder` (images/, labels/ in YOLO format), train split only (n % 5 != 0), seeded.
    A crop is stretched to the square tile; the renderer maps it across the opening, so it gets its shape back."""
    rng = np.random.default_rng([seed, 0xFACE])
    images = sorted(p for p in (folder / "images").glob("*.jpg")
                    if (n := facade_photo_number(p)) is not None and n % HELD_OUT_EVERY != 0)
    rng.shuffle(images)  # type: ignore[arg-type]
    out: dict[int, list[np.ndarray]] = {FACADE_DOOR_CLASS: [], FACADE_WINDOW_CLASS: []}
    want = {FACADE_DOOR_CLASS: n_doors, FACADE_WINDOW_CLASS: n_windows}
    for img_path in images:
        if all(len(out[c]) >= want[c] for c in out):
            break
        label = folder / "labels" / f"{img_path.stem}.txt"
        if not label.exists():
            continue
        rows = [r.split() for r in label.read_text().splitlines() if len(r.split()) == 5]
        boxes = [(int(r[0]), *map(float, r[1:])) for r in rows if int(r[0]) in out]
        if not boxes:
            continue
        img = cv2.imread(str(img_path))
        if img is None:
            continue
        h, w = img.shape[:2]
        pick = boxes[int(rng.integers(len(boxes)))]
        cls, (cx, cy, bw, bh) = int(pick[0]), pick[1:]
        if len(out[cls]) >= want[cls] or bw * w < 40 or bh * h < 60:
            continue
        x0, x1 = int(max(0, (cx - bw / 2) * w)), int(min(w, (cx + bw / 2) * w))
        y0, y1 = int(max(0, (cy - bh / 2) * h)), int(min(h, (cy + bh / 2) * h))
        crop = cv2.resize(img[y0:y1, x0:x1], (size, size), interpolation=cv2.INTER_AREA)
        out[cls].append(crop[:, :, ::-1])  # BGR -> RGB like the procedural layers
    empty = np.zeros((0, size, size, 3), np.uint8)
    return (np.stack(out[FACADE_DOOR_CLASS]) if out[FACADE_DOOR_CLASS] else empty,
            np.stack(out[FACADE_WINDOW_CLASS]) if out[FACADE_WINDOW_CLASS] else empty)
