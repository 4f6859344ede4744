"""The real photo sources: splits by source and by source photo, and the leave-one-source-out evaluation."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from macroloc.perception import detector_eval, sources
from macroloc.perception.detector import Detection
from macroloc.perception.trainset import source_stem
from tests.conftest import shared_data


@pytest.mark.parametrize("name", [n for n, s in sources.REAL_SOURCES.items() if s.indoor])
def test_each_indoor_source_splits_by_source_photo(name: str) -> None:
    root = shared_data("images")
    src = sources.REAL_SOURCES[name]
    split = sources.split_source(root, src)
    assert split == sources.split_source(root, src)  # seeded: fixed
    every = sources.source_images(root, src)
    assert sorted(p for part in split.values() for p in part) == every
    stems = {part: {source_stem(p) for p in paths} for part, paths in split.items()}
    assert not stems["train"] & stems["val"] and not stems["train"] & stems["test"] and not stems["val"] & stems["test"]
    assert all(split.values())


def test_fisheye_copies_of_one_photo_share_their_stem() -> None:
    root = shared_data("images")
    stems = {source_stem(p) for p in sources.source_images(root, sources.source("fisheye_robot"))}
    assert len(stems) == 244  # the README's count of source photos (584 exported images)


def test_unknown_source_is_named() -> None:
    with pytest.raises(ValueError, match="fisheye_robot"):
        sources.source("nope")


def _fixture(root: Path) -> Path:
    """Two tiny sources: indoor_objects (a door and a window per image, one image without any) and facades."""
    rng = np.random.default_rng(0)
    for folder, labels in (("indoor_doors/indoor_objects", ["0 0.3 0.5 0.2 0.8\n1 0.75 0.3 0.2 0.2\n", ""]),
                           ("facades", ["5 0.5 0.5 0.2 0.15\n0 0.2 0.2 0.1 0.1\n"])):
        (root / folder / "images").mkdir(parents=True)
        (root / folder / "labels").mkdir()
        for i, text in enumerate(labels * 3):
            cv2.imwrite(str(root / folder / "images" / f"img_{i + 1}.jpg"), rng.integers(0, 255, (100, 200, 3),
                                                                                          np.uint8))
            (root / folder / "labels" / f"img_{i + 1}.txt").write_text(text)
    return root


def _oracle(root: Path, shift_px: float):  # type: ignore[no-untyped-def]
    """A 'detector' that returns each image's true boxes moved by `shift_px` (found by the image's pixels)."""
    table = {}
    for src in sources.REAL_SOURCES.values():
        for s in sources.load_all(root, src):
            table[s.image_bgr.tobytes()] = [
                Detection(("door", "window", "neither")[int(c)], 0.9, tuple(float(v) + shift_px for v in b))
                for b, c in zip(s.boxes_xyxy, s.classes, strict=True) if int(c) < 2]
    return lambda image: table[image.tobytes()]


def test_leave_one_source_out_scores_each_source_with_its_model(tmp_path: Path) -> None:
    root = _fixture(tmp_path)
    exact, blind = _oracle(root, 0.0), (lambda image: [])
    report = detector_eval.leave_one_source_out({"indoor_objects": exact, "facades": blind}, root, {"facades": 0.5})
    assert set(report) == {"indoor_objects", "facades"}
    indoor = report["indoor_objects"]
    assert indoor["n_images"] == 6 and indoor["door"]["n_truth"] == 3 and indoor["window"]["n_truth"] == 3
    assert indoor["door"]["ap50"] == pytest.approx(1.0) and indoor["window"]["ap50"] == pytest.approx(1.0)
    assert indoor["door_tall"]["n_truth"] == 3 and indoor["door_tall"]["ap50"] == pytest.approx(1.0)  # 0.8 tall
    facades = report["facades"]
    assert facades["door"]["n_truth"] == 3 and facades["door"]["ap50"] == 0.0  # nothing found: AP 0
    assert facades["door_tall"]["n_truth"] == 0  # the facade doors are 0.15 of the image tall
    assert facades["window"]["recall_at_threshold"] == 0.0


def test_a_box_off_by_more_than_iou_half_counts_at_ap30_not_ap50(tmp_path: Path) -> None:
    root = _fixture(tmp_path)
    shifted = _oracle(root, 12.0)  # the door box is 40 x 80 px: a 12 px shift in x and y -> IoU ~0.4
    report = detector_eval.leave_one_source_out({"indoor_objects": shifted}, root)
    door = report["indoor_objects"]["door"]
    assert door["ap50"] == 0.0 and door["ap30"] == pytest.approx(1.0)


def test_absent_source_is_skipped(tmp_path: Path) -> None:
    assert detector_eval.leave_one_source_out({"fisheye_robot": lambda image: []}, tmp_path) == {}
