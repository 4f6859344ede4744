"""Fake-data factories for the perception tests: synthetic rectified pairs and door images with known answers."""

from __future__ import annotations

import struct
import zlib

import numpy as np

from macroloc.perception.calib import StereoRig

RIG = StereoRig(fx_px=480.0, fy_px=480.0, cx_px=320.0, cy_px=240.0, baseline_m=0.12, width_px=640, height_px=480)


def texture(height: int, width: int, seed: int = 0, blob_px: int = 4, fine_sigma: float = 12.0) -> np.ndarray:
    """Random blotchy grey texture (uint8) that block matching can lock onto."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, (height // blob_px + 1, width // blob_px + 1)).astype(np.float32)
    big = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
    fine = rng.normal(0, fine_sigma, (height, width))
    return np.clip(big + fine, 0, 255).astype(np.uint8)


def fronto_parallel_pair(depth_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Left/right images of a textured plane at `depth_m`: the right image is the left shifted by the disparity."""
    import cv2

    disparity_px = RIG.fx_px * RIG.baseline_m / depth_m
    left = texture(RIG.height_px, RIG.width_px + 64, seed)
    M = np.array([[1.0, 0.0, disparity_px], [0.0, 1.0, 0.0]])  # right(u) = left(u + d)
    right = cv2.warpAffine(left, M, (left.shape[1], left.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return left[:, : RIG.width_px].copy(), right[:, : RIG.width_px].copy()


def door_image(box_xyxy: tuple[int, int, int, int], gaps: bool = True, seed: int = 0) -> np.ndarray:
    """A light wall with a dark door leaf in `box_xyxy` whose vertical edges are broken by small gaps."""
    rng = np.random.default_rng(seed)
    img = np.full((RIG.height_px, RIG.width_px), 200, np.uint8)
    x0, y0, x1, y1 = box_xyxy
    img[y0:y1, x0:x1] = 90
    if gaps:  # wall-coloured notches that break the sides into pieces a few px apart
        for v in range(y0 + 30, y1 - 10, 45):
            img[v:v + 4, x0:x0 + 3] = 200
            img[v + 10:v + 14, x1 - 3:x1] = 200
    return np.clip(img.astype(np.int16) + rng.integers(-4, 5, img.shape), 0, 255).astype(np.uint8)


def door_pair(depth_m: float, door_wh_m: tuple[float, float] = (0.9, 2.0), seed: int = 0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float, float]]:
    """A textured fronto-parallel wall at `depth_m` with a darker door (centred on the optical axis, its centre
    0.1 m below it). Returns left, right (grey uint8), the door's true corners (4,3, camera frame, TL TR BR BL)
    and its box in pixels."""
    import cv2

    w_m, h_m = door_wh_m
    x0, x1, y0, y1 = -w_m / 2, w_m / 2, 0.1 - h_m / 2, 0.1 + h_m / 2
    corners = np.array([[x0, y0, depth_m], [x1, y0, depth_m], [x1, y1, depth_m], [x0, y1, depth_m]])
    u = corners[:, 0] / depth_m * RIG.fx_px + RIG.cx_px
    v = corners[:, 1] / depth_m * RIG.fy_px + RIG.cy_px
    disparity_px = RIG.fx_px * RIG.baseline_m / depth_m
    wide = texture(RIG.height_px, RIG.width_px + 64, seed, blob_px=6, fine_sigma=3.0).astype(np.float32)
    door = np.zeros_like(wide, bool)
    door[int(round(v[0])):int(round(v[2])), int(round(u[0])):int(round(u[1]))] = True
    wide = np.where(door, 10 + 0.35 * wide, 110 + 0.55 * wide)  # a dark leaf on a light wall, both textured
    wide = wide.astype(np.uint8)
    M = np.array([[1.0, 0.0, disparity_px], [0.0, 1.0, 0.0]])  # right(u) = left(u + d)
    right = cv2.warpAffine(wide, M, (wide.shape[1], wide.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    box = (float(u[0]) - 6, float(v[0]) - 5, float(u[1]) + 5, float(v[2]) + 6)
    return wide[:, : RIG.width_px].copy(), right[:, : RIG.width_px].copy(), corners, box


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bomb(width: int, height: int, rows_per_block: int = 100) -> bytes:
    """A valid mono 8-bit PNG of width x height zero pixels, crafted without compressing them all: one block of
    rows is deflated once with a full flush (which makes the next identical block compress to identical bytes)
    and repeated; the zlib trailer's Adler-32 of n zero bytes is (n mod 65521) << 16 | 1. 20000 x 20000 gives
    ~390 KB in ~20 ms (decoded: 400 MB)."""
    assert height % rows_per_block == 0
    block = bytes((width + 1) * rows_per_block)  # each row: filter byte 0, then the pixels
    deflate = zlib.compressobj(9)
    first = deflate.compress(block) + deflate.flush(zlib.Z_FULL_FLUSH)
    again = deflate.compress(block) + deflate.flush(zlib.Z_FULL_FLUSH)
    assert first[2:] == again  # after the 2-byte zlib header, every block deflates alike
    n = (width + 1) * height
    idat = first[:2] + again * (height // rows_per_block) + b"\x03\x00" + struct.pack(">I", (n % 65521) << 16 | 1)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)  # 8 bits, greyscale, deflate, no filter, no interlace
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")
