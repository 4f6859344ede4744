"""Pictures for people: detections, refined sides and reconstructed sizes drawn on an image (BGR, pixels)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from macroloc.perception.detector import Detection, to_bgr

COLOURS_BGR = {"door": (40, 180, 255), "window": (255, 160, 40)}


def draw_detections(image: np.ndarray, detections: Sequence[Detection]) -> np.ndarray:
    out = to_bgr(image).copy()
    for d in detections:
        x0, y0, x1, y1 = (int(round(v)) for v in d.box_xyxy)
        colour = COLOURS_BGR.get(d.type, (200, 200, 200))
        cv2.rectangle(out, (x0, y0), (x1, y1), colour, 2)
        cv2.putText(out, f"{d.type} {d.score:.2f}", (x0, max(12, y0 - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1,
                    cv2.LINE_AA)
    return out


def draw_features(image: np.ndarray, features: Sequence, rejected: Sequence = ()) -> np.ndarray:  # type: ignore[type-arg]
    """Features (`perception.pipeline.ObservedFeature`): box, the two refined sides, size and tilt; rejected
    detections as thin grey boxes with their reason."""
    out = to_bgr(image).copy()
    for r in rejected:
        x0, y0, x1, y1 = (int(round(v)) for v in r.detection.box_xyxy)
        cv2.rectangle(out, (x0, y0), (x1, y1), (150, 150, 150), 1)
        cv2.putText(out, r.reason[:40], (x0, min(out.shape[0] - 4, y1 + 12)), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (150, 150, 150), 1, cv2.LINE_AA)
    for f in features:
        colour = COLOURS_BGR.get(f.type, (200, 200, 200))
        x0, y0, x1, y1 = (int(round(v)) for v in f.box_xyxy)
        cv2.rectangle(out, (x0, y0), (x1, y1), colour, 1)
        for side, from_lines in zip(f.sides_px, f.sides_from_lines, strict=True):
            p0, p1 = (tuple(int(round(v)) for v in p) for p in side)
            cv2.line(out, p0, p1, (0, 255, 0) if from_lines else (0, 0, 255), 3)
        z_m = float(f.corners_cam[:, 2].mean())
        text = f"{f.type} {f.width_m:.2f} x {f.height_m:.2f} m, tilt {f.tilt_deg:.1f} deg, z {z_m:.2f} m"
        cv2.putText(out, text, (x0, max(12, y0 - 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, text, (x0, max(12, y0 - 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return out


def contact_sheet(tiles_bgr: list[np.ndarray], columns: int = 4, tile_width: int = 320) -> np.ndarray:
    """(rows * h, columns * tile_width, 3) uint8 grid of the tiles, each resized to `tile_width`."""
    if not tiles_bgr:
        return np.zeros((10, 10, 3), np.uint8)
    h0, w0 = tiles_bgr[0].shape[:2]
    th = int(round(h0 * tile_width / w0))
    rows = (len(tiles_bgr) + columns - 1) // columns
    sheet = np.zeros((rows * th, columns * tile_width, 3), np.uint8)
    for i, tile in enumerate(tiles_bgr):
        r, c = divmod(i, columns)
        sheet[r * th:(r + 1) * th, c * tile_width:(c + 1) * tile_width] = cv2.resize(
            tile, (tile_width, th), interpolation=cv2.INTER_AREA)
    return sheet
