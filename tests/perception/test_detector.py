import json

import cv2
import numpy as np
import pytest

from macroloc.perception.detector import DEFAULT_MODEL, Detection, Detector, DetectorSpec, decode, letterbox, nms
from macroloc.perception.evaluate import GroundTruth, average_precision, best_f1_threshold, pr_curve
from tests.conftest import shared_data


def test_shipped_model_is_small_and_described():
    assert DEFAULT_MODEL.exists() and DEFAULT_MODEL.stat().st_size < 10 * 2**20
    doc = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    assert doc["classes"] == ["door", "window", "neither"]
    spec = DetectorSpec.load(DEFAULT_MODEL.with_suffix(".json"))
    assert 0 < spec.score_threshold < 1 and len(spec.anchors_px) >= 1
    assert (DEFAULT_MODEL.parent / "detector_pr.png").exists()


def test_letterbox_maps_back_to_image_pixels():
    image = np.zeros((540, 960, 3), np.uint8)
    net, box = letterbox(image, (320, 240))
    assert net.shape == (240, 320, 3)
    # the image's corners land on the letterboxed content's corners and come back
    corners_net = np.array([box.offset_px[0], box.offset_px[1], box.offset_px[0] + 960 * box.scale,
                            box.offset_px[1] + 540 * box.scale])
    assert np.allclose(box.to_image(corners_net), [0, 0, 960, 540], atol=1e-6)


def test_decode_places_a_box_from_a_known_raw_map():
    spec = DetectorSpec(anchors_px=((20.0, 40.0),), input_wh=(64, 48), stride_px=16)
    raw = np.full((8, 3, 4), -10.0)
    raw[:, 1, 2] = [0.0, 0.0, np.log(2.0), 0.0, 10.0, 8.0, 0.0, 0.0]  # cell (row 1, col 2), class door
    boxes, scores, cls = decode(raw, spec)
    i = int(np.argmax(scores))
    assert cls[i] == 0 and scores[i] > 0.99
    assert np.allclose(boxes[i], [2.5 * 16 - 20, 1.5 * 16 - 20, 2.5 * 16 + 20, 1.5 * 16 + 20])


def test_nms_keeps_the_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60]], float)
    assert nms(boxes, np.array([0.5, 0.9, 0.3]), 0.45).tolist() == [1, 2]


def test_ap_and_threshold_on_known_cases():
    gts = [[GroundTruth("door", (0, 0, 10, 10)), GroundTruth("door", (20, 20, 30, 30))]]
    perfect = [[Detection("door", 0.9, (0, 0, 10, 10)), Detection("door", 0.8, (20, 20, 30, 30))]]
    assert pr_curve("door", perfect, gts).ap == pytest.approx(1.0)
    half = [[Detection("door", 0.9, (0, 0, 10, 10)), Detection("door", 0.8, (100, 100, 110, 110))]]
    curve = pr_curve("door", half, gts)
    assert curve.ap == pytest.approx(0.5)
    assert curve.at(0.85) == (1.0, 0.5)
    assert best_f1_threshold([curve]) <= 0.9
    assert average_precision(np.array([0.5, 1.0]), np.array([1.0, 0.5])) == pytest.approx(0.75)


def test_detects_on_a_held_out_real_photo_in_its_own_pixels():
    root = shared_data("images/facades")
    path = root / "images" / "img_5.jpg"  # n % 5 == 0: the held-out real test split
    image = cv2.imread(str(path))
    dets = Detector().detect(image, score_threshold=0.05)
    assert dets, "nothing detected on a facade photo"
    h, w = image.shape[:2]
    for d in dets:
        x0, y0, x1, y1 = d.box_xyxy
        assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h
        assert d.type in ("door", "window") and 0.05 <= d.score <= 1
    grey = Detector().detect(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), score_threshold=0.05)
    assert grey  # grey frames (a stereo rig's right camera) are accepted too


def test_a_box_at_the_image_border_is_marked_truncated_and_says_so_in_json():
    from macroloc.perception.detector import Letterbox, at_border, postprocess

    spec = DetectorSpec(anchors_px=((20.0, 40.0),), input_wh=(64, 48), stride_px=16)
    raw = np.full((8, 3, 4), -10.0)
    raw[:, 1, 0] = [0.0, 0.0, 0.0, 0.0, 10.0, 8.0, 0.0, 0.0]  # centre (8, 24): 20 px wide, cut at x = 0
    raw[:, 1, 2] = [0.0, 0.0, -1.0, -1.0, 10.0, 8.0, 0.0, 0.0]  # centre (40, 24), well inside
    dets = postprocess(raw, Letterbox(1.0, (0.0, 0.0)), spec, 0.5, 64, 48)
    by_x = sorted(dets, key=lambda d: d.box_xyxy[0])
    assert [d.truncated for d in by_x] == [True, False]
    assert by_x[0].to_json()["truncated"] is True and by_x[1].to_json()["truncated"] is False
    assert at_border((3.0, 10.0, 60.0, 46.5), 64, 48) and not at_border((3.0, 3.0, 61.0, 45.0), 64, 48)
