"""The chain checked by the building (issue 32): geometry proposals where the detector is blind, and every
reconstruction's size against the model's doors and windows.

detect (CNN) + propose doors (LSD lines, stereo depth, the model's door sizes) -> the chain after the detector on
both -> size check. A proposal whose box overlaps a detection (IoU >= 0.5, the evaluation's match criterion) leaves
the decision to the detection (its box, score and type) and marks it `fused`; one that overlaps none goes on alone
as `geometry`. The model's sizes come in as `OpeningSizes` (plain data); without them nothing is proposed and every
feature is `unchecked`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from macroloc.perception.detector import Detection
from macroloc.perception.door_proposals import DoorProposal, ProposalParams, propose_doors
from macroloc.perception.evaluate import iou_xyxy
from macroloc.perception.pipeline import ObservedFeature, Perception, PerceptionResult, Rejected, StereoPair
from macroloc.perception.size_check import OpeningSizes, SizeTolerance, SizeVerdict, check_size
from macroloc.perception.stereo import depth_from_disparity

log = logging.getLogger(__name__)

Source = Literal["cnn", "geometry", "fused"]
OVERLAP_IOU = 0.5  # a proposal and a detection are the same opening: the match criterion of detection AP


@dataclass(frozen=True)
class CheckedFeature:
    """A feature, where its box came from, and the size check's verdict."""

    feature: ObservedFeature
    source: Source
    size: SizeVerdict

    def to_json(self) -> dict[str, object]:
        return {**self.feature.to_json(), "source": self.source, **self.size.to_json()}


@dataclass
class CheckedResult:
    features: list[CheckedFeature]
    rejected: list[Rejected]
    detections: list[Detection]
    proposals: list[DoorProposal]
    timings_ms: dict[str, float] = field(default_factory=dict)


class ModelCheckedPerception:
    """`process(pair)`: the chain's features, each with its source and size verdict.

    `use_detector=False` runs geometry alone, `proposals=None` the detector alone (both for the benchmark)."""

    def __init__(self, chain: Perception, sizes: OpeningSizes | None, tol: SizeTolerance | None = None,
                 proposals: ProposalParams | None = ProposalParams(), use_detector: bool = True) -> None:
        self.chain = chain
        self.sizes = sizes if sizes is not None and sizes.sizes else None
        self.tol = tol or SizeTolerance()
        self.proposals = proposals if self.sizes is not None else None
        self.use_detector = use_detector

    def process(self, pair: StereoPair) -> CheckedResult:
        t0 = time.perf_counter()
        detections = self.chain.detector.detect(pair.left) if self.use_detector else []
        result = self.process_detections(pair, detections)
        result.timings_ms = {"detect": (time.perf_counter() - t0) * 1e3 - sum(result.timings_ms.values()),
                             **result.timings_ms}
        return result

    def process_detections(self, pair: StereoPair, detections: list[Detection]) -> CheckedResult:
        """The steps after the detector: propose, reconstruct both, check sizes."""
        laps: dict[str, float] = {}
        t = time.perf_counter()
        depth_m, proposals = None, []
        if self.proposals is not None and self.sizes is not None:
            depth_m = depth_from_disparity(self.chain.matcher.disparity_px(pair.left, pair.right), pair.rig)
            proposals = propose_doors(pair.left, depth_m, pair.rig, self.sizes, self.tol, self.proposals,
                                      pair.gravity_cam, self.chain.wall)
        laps["propose"] = (time.perf_counter() - t) * 1e3
        source, extra = _sources(detections, proposals)
        result = self.chain.process_boxes(pair, detections + extra, depth_m=depth_m)
        t = time.perf_counter()
        checked, rejected = self._check_sizes(result, source)
        laps["size_check"] = (time.perf_counter() - t) * 1e3
        return CheckedResult(checked, result.rejected + rejected, detections, proposals,
                             {**laps, **{k: v for k, v in result.timings_ms.items() if k != "detect"}})

    def _check_sizes(self, result: PerceptionResult, source: dict[tuple[float, ...], Source]
                     ) -> tuple[list[CheckedFeature], list[Rejected]]:
        checked: list[CheckedFeature] = []
        rejected: list[Rejected] = []
        for f in result.features:
            verdict = check_size(f.type, f.width_m, f.height_m, float(f.corners_cam[:, 2].mean()), f.truncated,
                                 self.sizes, self.tol)
            src = source.get(tuple(f.box_xyxy), "cnn")
            if verdict.status == "rejected":
                rejected.append(Rejected(Detection(f.type, f.score, f.box_xyxy), f"size: {verdict.reason}"))
                continue
            if verdict.retyped_from is not None:
                f = dataclasses.replace(f, type=verdict.kind)
            checked.append(CheckedFeature(f, src, verdict))
        return checked, rejected


def _sources(detections: list[Detection], proposals: list[DoorProposal]
             ) -> tuple[dict[tuple[float, ...], Source], list[Detection]]:
    """Each box's source, and the proposals that overlap no detection as door detections (score: their fit)."""
    source: dict[tuple[float, ...], Source] = {tuple(d.box_xyxy): "cnn" for d in detections}
    extra: list[Detection] = []
    det_boxes = np.array([d.box_xyxy for d in detections], float).reshape(-1, 4)
    for p in proposals:
        iou = _iou(np.array(p.box_xyxy), det_boxes)
        if len(iou) and iou.max() >= OVERLAP_IOU:
            source[tuple(detections[int(np.argmax(iou))].box_xyxy)] = "fused"
        else:
            extra.append(Detection("door", p.fit, p.box_xyxy))
            source[tuple(p.box_xyxy)] = "geometry"
    return source, extra


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    return np.asarray(iou_xyxy(box[None], boxes)[0]) if len(boxes) else np.zeros(0)
