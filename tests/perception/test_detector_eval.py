"""The detector's figures by door size and for doors cut by the border, on constructed detections."""

import numpy as np
import pytest

from macroloc.perception.detector import Detection
from macroloc.perception.detector_eval import figures
from macroloc.perception.evaluate import GroundTruth, pr_curve
from macroloc.perception.trainset import Sample


def _sample(boxes: list[list[float]]) -> Sample:
    return Sample("s", np.zeros((100, 200, 3), np.uint8), np.array(boxes, float).reshape(-1, 4),
                  np.zeros(len(boxes), np.int64))


def test_subsets_count_their_own_doors_and_ignore_the_others():
    tall_cut = [0.0, 5.0, 40.0, 95.0]  # 0.9 of the height, at the left border
    small = [100.0, 40.0, 110.0, 60.0]  # 0.2 of the height, inside
    middle = [150.0, 20.0, 180.0, 70.0]  # 0.5, inside
    samples = [_sample([tall_cut, small, middle])]
    truths = [[GroundTruth("door", tuple(b)) for b in (tall_cut, small, middle)]]  # type: ignore[misc]
    dets = [[Detection("door", 0.9, tuple(tall_cut), True),  # type: ignore[arg-type]
             Detection("door", 0.8, tuple(middle)),  # type: ignore[arg-type]
             Detection("door", 0.7, (60.0, 10.0, 70.0, 30.0))]]  # a small false one
    fig = figures(samples, dets, truths, 0.5)
    sizes = fig["door_by_height_fraction"]
    assert [sizes[k]["n_truth"] for k in ("lt_0.25", "0.25_0.75", "gt_0.75")] == [1, 1, 1]
    assert sizes["gt_0.75"]["ap50"] == pytest.approx(1.0) and sizes["0.25_0.75"]["ap50"] == pytest.approx(1.0)
    assert sizes["lt_0.25"]["ap50"] == 0.0  # only the false small box falls in it
    assert fig["door_truncated"]["n_truth"] == 1 and fig["door_truncated"]["ap50"] == pytest.approx(1.0)
    assert fig["door"]["recall_at_threshold"] == pytest.approx(2 / 3, abs=1e-4)  # rounded to 4 digits


def test_pr_curve_without_a_subset_is_unchanged():
    gts = [[GroundTruth("door", (0, 0, 10, 10))]]
    dets = [[Detection("door", 0.9, (0, 0, 10, 10)), Detection("door", 0.5, (50, 50, 60, 60))]]
    assert pr_curve("door", dets, gts).ap == pytest.approx(1.0)
    assert pr_curve("door", dets, gts, within=[lambda b: b[0] > 20]).n_truth == 0
