"""A contact sheet: sampled left frames in a grid with their ground-truth boxes and visible corners drawn."""

from __future__ import annotations

import cv2
import numpy as np

from macroloc.perception.draw import contact_sheet  # noqa: F401 - the grid, shared with the self-labeller's sheet
from macroloc.sim.groundtruth import FeatureInView

COLOURS_BGR = {"door": (40, 200, 40), "window": (230, 140, 30)}


def annotate(image_bgr: np.ndarray, features: list[FeatureInView], label: str = "") -> np.ndarray:
    """A copy of the image with each feature's box (green door, blue window), id prefix and corners
    (filled = visible, hollow = occluded or outside)."""
    out = image_bgr.copy()
    for f in features:
        colour = COLOURS_BGR.get(f.type, (0, 0, 255))
        x0, y0, x1, y1 = (int(round(v)) for v in f.box_xyxy)
        cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), colour, 2)
        cv2.putText(out, f"{f.type} {f.id[:6]}", (x0 + 3, max(12, y0 + 14)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    colour, 1, cv2.LINE_AA)
        for (u, v), vis in zip(f.corners_px, f.corner_visible, strict=True):
            if np.isfinite(u) and np.isfinite(v) and abs(u) < 1e5 and abs(v) < 1e5:
                cv2.circle(out, (int(round(u)), int(round(v))), 5, (0, 0, 255), -1 if vis else 1)
    if label:
        cv2.putText(out, label, (6, out.shape[0] - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out
