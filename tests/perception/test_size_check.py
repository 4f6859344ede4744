"""The size check: a reconstruction must have the size of one of the model's doors or windows."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.perception.size_check import OpeningSizes, SizeTolerance, check_size, fitting

SIZES = OpeningSizes.of([("door", 1.067, 2.21), ("door", 0.81, 1.52), ("door", 1.98, 2.16), ("window", 1.2, 1.5),
                         ("window", 1.0, 1.0)])


def test_sizes_are_distinct_and_rounded():
    sizes = OpeningSizes.of([("door", 1.0671, 2.2102), ("door", 1.0669, 2.2098), ("window", 1.2, 1.5)])
    assert sizes.sizes == (("door", 1.07, 2.21), ("window", 1.2, 1.5))
    assert sizes.wh_m("door").shape == (1, 2) and sizes.wh_m("stair").shape == (0, 2)


def test_a_door_whose_width_fits_no_model_door_is_rejected():
    verdict = check_size("door", 1.55, 2.2, 4.0, (False, False), SIZES)
    assert verdict.status == "rejected" and "fits no model" in verdict.reason


def test_a_door_that_fits_a_model_door_is_confirmed_with_that_size():
    verdict = check_size("door", 1.12, 2.15, 4.0, (False, False), SIZES)
    assert verdict.status == "confirmed" and verdict.kind == "door" and verdict.matched_wh_m == (1.07, 2.21)


def test_a_door_sized_window_is_retyped_a_door():
    verdict = check_size("window", 1.05, 2.18, 6.0, (False, False), SIZES)
    assert verdict.status == "confirmed" and verdict.kind == "door" and verdict.retyped_from == "window"


def test_the_tolerance_grows_with_depth():
    tol = SizeTolerance()
    assert check_size("door", 1.07 + tol.at(3.0) + 0.02, 2.21, 3.0, (False, False), SIZES).status == "rejected"
    assert check_size("door", 1.07 + tol.at(3.0) + 0.02, 2.21, 8.0, (False, False), SIZES).status == "confirmed"


@pytest.mark.parametrize(("width_m", "status"), [(0.6, "confirmed"), (1.5, "confirmed"), (2.6, "rejected")])
def test_a_box_cut_sideways_is_checked_on_its_height_and_bounded_by_its_visible_width(width_m, status):
    """The visible part of a cut opening is never wider than the opening: only a width above every model
    width (plus the tolerance) rejects it; the whole height is compared both ways."""
    verdict = check_size("door", width_m, 2.2, 4.0, (True, False), SIZES)
    assert verdict.status == status
    assert verdict.whole == (False, True)


def test_a_box_cut_both_ways_is_unchecked_unless_too_big():
    assert check_size("door", 0.7, 1.2, 2.0, (True, True), SIZES).status == "unchecked"
    assert check_size("door", 2.6, 3.0, 2.0, (True, True), SIZES).status == "rejected"


def test_without_the_model_everything_is_unchecked():
    assert check_size("door", 9.0, 9.0, 4.0, (False, False), None).status == "unchecked"
    assert check_size("door", 9.0, 9.0, 4.0, (False, False), OpeningSizes(())).status == "unchecked"


def test_fitting_broadcasts_over_many_measurements():
    wh = SIZES.wh_m("door")
    ok = fitting(wh, np.array([1.07, 1.5]), np.array([2.2, 2.2]), np.array([0.2, 0.2]),
                 np.array([[False, False], [False, False]]))
    assert ok.shape == (2, len(wh)) and ok[0].any() and not ok[1].any()


@pytest.mark.parametrize(("model_door_m", "status"), [((0.9, 2.0), "confirmed"), ((1.5, 2.0), "rejected")])
def test_the_chain_checks_a_reconstructed_door_against_the_model(model_door_m, status):
    """A 0.9 x 2.0 m door 3 m away on a textured wall, through the chain after the detector: confirmed where the
    model has a door of that size, rejected (with the reason) where its only door is 1.5 m wide."""
    from macroloc.perception.detector import Detection
    from macroloc.perception.model_check import ModelCheckedPerception
    from macroloc.perception.pipeline import Perception, StereoPair
    from tests.perception.helpers import RIG, door_pair

    left, right, _, box = door_pair(3.0, (0.9, 2.0))
    sizes = OpeningSizes.of([("door", *model_door_m), ("window", 1.2, 1.5)])
    checked = ModelCheckedPerception(Perception.create(), sizes, proposals=None)
    result = checked.process_detections(StereoPair(left, right, RIG), [Detection("door", 0.9, box)])
    if status == "confirmed":
        assert [f.size.status for f in result.features] == ["confirmed"]
        assert result.features[0].source == "cnn" and result.features[0].size.matched_wh_m == model_door_m
    else:
        assert not result.features and any(r.reason.startswith("size:") for r in result.rejected)


def test_the_model_check_takes_the_models_sizes_as_plain_data():
    """perception/ gains no import of graph/: the sizes come in as OpeningSizes, built by the caller."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "perception"
    imported = []
    for name in ("size_check.py", "door_proposals.py", "model_check.py"):
        for node in ast.walk(ast.parse((root / name).read_text())):
            if isinstance(node, ast.ImportFrom):
                imported.append(node.module or "")
            elif isinstance(node, ast.Import):
                imported += [a.name for a in node.names]
    assert not [m for m in imported if m.split(".")[0] in ("graph", "service", "sim")]
