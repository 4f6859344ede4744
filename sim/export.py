"""Detector training data from simulated flights: left images and YOLO labels (classes 0 door, 1 window).

Layout (the usual YOLO one; several flights, of several buildings, may share one folder):
    OUT/images/<prefix>_<frame>.jpg
    OUT/labels/<prefix>_<frame>.txt     one line per door/window: "class cx cy w h", normalised to [0, 1]
    OUT/data.yaml                       names of the classes
A feature gets a label when at least `min_visible_fraction` of its opening is visible (occlusion and image
edges) and its box is at least `min_box_px` on each side.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from macroloc.perception.trainset import YOLO_CLASSES, yolo_folder, yolo_line
from macroloc.sim.flight import FlightParams
from macroloc.sim.groundtruth import FeatureInView
from macroloc.sim.simulator import SimulationParams, Simulator

log = logging.getLogger(__name__)

def yolo_lines(features: list[FeatureInView], width: int, height: int, min_visible_fraction: float = 0.25,
               min_box_px: float = 6.0) -> list[str]:
    """YOLO label lines of one image. Boxes are in pixels with pixel centres at integers (the image spans
    [-0.5, W - 0.5]); YOLO's are normalised with the image spanning [0, 1]."""
    lines = []
    for f in features:
        if f.type not in YOLO_CLASSES or f.visible_fraction < min_visible_fraction:
            continue
        x0, y0, x1, y1 = (float(v) for v in f.box_xyxy)
        if x1 - x0 < min_box_px or y1 - y0 < min_box_px:
            continue
        lines.append(yolo_line(f.type, (x0, y0, x1, y1), width, height))
    return lines


@dataclass
class YoloExporter:
    """Writes every `every_n`-th frame given to `add` (see the module docstring)."""

    out_dir: Path
    prefix: str
    every_n: int = 10
    jpeg_quality: int = 92
    min_visible_fraction: float = 0.25
    counts: dict[str, int] = field(default_factory=lambda: {"images": 0, "door": 0, "window": 0})

    def __post_init__(self) -> None:
        yolo_folder(self.out_dir)

    def add(self, index: int, left_bgr: np.ndarray, features: list[FeatureInView]) -> bool:
        """Write frame `index` when it is one of every `every_n`; returns whether it was written."""
        if index % self.every_n:
            return False
        h, w = left_bgr.shape[:2]
        name = f"{self.prefix}_{index:06d}"
        lines = yolo_lines(features, w, h, self.min_visible_fraction)
        cv2.imwrite(str(self.out_dir / "images" / f"{name}.jpg"), left_bgr,
                    [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        (self.out_dir / "labels" / f"{name}.txt").write_text("".join(line + "\n" for line in lines))
        self.counts["images"] += 1
        for line in lines:
            self.counts["door" if line.startswith("0 ") else "window"] += 1
        return True


def render_training_frames(building: Path, out_dir: Path, seeds: tuple[int, ...], duration_s: float = 40.0,
                           every: int = 6, prefix: str | None = None) -> dict[str, int]:
    """Seeded flights through `building`, every `every`-th frame written to `out_dir` as a left image with YOLO
    labels; only those frames are rendered. Returns the counts {"images", "door", "window"}."""
    totals = {"images": 0, "door": 0, "window": 0}
    for seed in seeds:
        t0 = time.time()
        sim = Simulator(building, SimulationParams(seed=seed, flight=FlightParams(duration_s=duration_s)))
        try:
            exporter = YoloExporter(out_dir, f"{prefix or building.stem}_s{seed}", every_n=1)
            times = sim.frame_times_s
            for i in range(0, len(times), every):
                frame = sim.render_at(i, float(times[i]))
                exporter.add(i, frame.left_bgr, frame.features)
        finally:
            sim.close()
        for k in totals:
            totals[k] += exporter.counts[k]
        log.info("%s seed %d: %s in %.0f s", building.name, seed, exporter.counts, time.time() - t0)
    return totals
