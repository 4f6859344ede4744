from functools import partial
from pathlib import Path

import numpy as np
import pytest

from macroloc.perception.detector import PAD_VALUE
from macroloc.perception.trainset import (
    ROTATIONS_DEG,
    Sample,
    _affine,
    augment,
    is_real_test,
    mosaic,
    read_yolo_labels,
    split_facades,
    transform_boxes,
)
from tests.conftest import shared_data


def test_split_keeps_the_real_test_part_out_and_is_fixed():
    root = shared_data("images/facades")
    a, b = split_facades(root, seed=0), split_facades(root, seed=0)
    assert a == b
    assert all(is_real_test(p) for p in a["test"]) and len(a["test"]) > 100
    assert not any(is_real_test(p) for p in a["train"] + a["val"])
    assert not set(a["train"]) & set(a["val"])


def test_yolo_labels_map_to_door_window_neither(tmp_path: Path):
    label = tmp_path / "x.txt"
    label.write_text("5 0.5 0.5 0.2 0.4\n0 0.25 0.25 0.1 0.1\n4 0.1 0.1 0.1 0.1\n"
                     "3 0.7 0.7 0.2 0.2\n9 0.5 0.5 0.1 0.1\n")
    from macroloc.perception.trainset import FACADE_CLASS_MAP

    boxes, classes = read_yolo_labels(label, 200, 100, FACADE_CLASS_MAP)
    assert classes.tolist() == [0, 1, 1, 2]
    assert np.allclose(boxes[0], [80, 30, 120, 70])


def _sample() -> Sample:
    img = np.zeros((120, 160, 3), np.uint8)
    img[40:80, 60:100] = 255
    return Sample("s", img, np.array([[60.0, 40.0, 100.0, 80.0]]), np.array([0]))


def test_augmented_boxes_enclose_the_object():
    rng = np.random.default_rng(3)
    for _ in range(30):
        image, boxes, _ = augment(_sample(), (320, 240), rng, rotation_prob=1.0)
        assert image.shape == (240, 320, 3)
        for x0, y0, x1, y1 in boxes.astype(int):
            inside = image[max(0, y0 + 2):y1 - 2, max(0, x0 + 2):x1 - 2].astype(int).sum(axis=2)
            assert inside.size == 0 or inside.max() > 300  # the white object is within its box


def test_mosaic_puts_four_samples_in_quadrants_with_their_boxes_on_their_objects():
    """Each quadrant holds one sample's object, smaller than the sample alone, and its box encloses it."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        image, boxes, classes = mosaic([_sample()] * 4, (320, 240), rng,
                                       partial(augment, scale_range=(0.8, 1.2), rotation_prob=0.0))
        assert image.shape == (240, 320, 3) and len(boxes) == len(classes) <= 4
        assert len(boxes) >= 1 and (boxes[:, 3] - boxes[:, 1]).max() < 0.5 * 240
        for x0, y0, x1, y1 in boxes.astype(int):
            inside = image[y0 + 2:y1 - 2, x0 + 2:x1 - 2].astype(int).sum(axis=2)
            assert inside.size == 0 or inside.max() > 300


def test_rotations_are_the_papers_and_inverse_warping_leaves_no_holes():
    assert ROTATIONS_DEG == (-20, -15, -10, -5, 0, 5, 10, 15, 20)
    rng = np.random.default_rng(0)
    img = np.full((240, 320, 3), 7, np.uint8)
    s = Sample("flat", img, np.zeros((0, 4)), np.zeros(0, np.int64))
    angles = set()
    for _ in range(40):
        M = _affine(s, (320, 240), rng, (2.0, 2.0), rotation_prob=1.0)
        angles.add(round(float(np.degrees(np.arctan2(M[1, 0], abs(M[0, 0])))) ))
        import cv2

        out = cv2.warpAffine(img, cv2.invertAffineTransform(M), (320, 240),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=(PAD_VALUE,) * 3)
        centre = out[100:140, 140:180]
        assert np.all(centre == 7)  # every output pixel painted from the source: no holes
    assert angles <= {abs(a) * s for a in ROTATIONS_DEG for s in (-1, 1)} and len(angles) >= 5


def test_mostly_hidden_boxes_are_dropped():
    M = np.array([[1.0, 0.0, -90.0], [0.0, 1.0, 0.0]])
    boxes, classes = transform_boxes(np.array([[60.0, 0, 100, 50], [0, 0, 40, 40]]), np.array([1, 2]), M,
                                     (320, 240), 0.45)
    assert classes.tolist() == []
    boxes, classes = transform_boxes(np.array([[100.0, 0, 200, 50]]), np.array([1]), M, (320, 240), 0.45)
    assert classes.tolist() == [1] and np.allclose(boxes, [[10, 0, 110, 50]])


@pytest.mark.parametrize("n", [0, 5, 10, 105])
def test_test_split_rule(n: int):
    assert is_real_test(Path(f"img_{n}.jpg"))


def test_a_trained_model_names_the_flights_its_rendered_frames_came_from():
    from macroloc.perception.train import rendered_sources

    def sample(name: str) -> Sample:
        return Sample(name, np.zeros((4, 4, 3), np.uint8), np.zeros((0, 4)), np.zeros(0, int))

    sim = [sample(n) for n in ("office_a_s11_000000", "office_a_s11_000006", "duplex_s2_000012", "photo_17")]
    assert rendered_sources(sim) == ["duplex_s2", "office_a_s11"]


def test_rendered_frames_folder_missing_is_one_line_naming_how_to_make_it(tmp_path: Path):
    from macroloc.perception.train import ensure_sim_frames

    made = tmp_path / "frames"
    (made / "images").mkdir(parents=True)
    assert ensure_sim_frames([made]) == [made]
    with pytest.raises(SystemExit, match="bench.sim_trainset --out .*elsewhere"):
        ensure_sim_frames([tmp_path / "elsewhere"])


def test_source_stem_joins_augmented_copies_second_downloads_and_video_frames():
    from macroloc.perception.trainset import source_stem

    names = {"train_Door0007-1-_png.rf.26753ed80f77fd6a21db4f738dbad705.jpg": "Door0007",
             "valid_Door0007_png.rf.051d31e59f7f6723f27763dc767e58ee.jpg": "Door0007",
             "test_IMG_0113_JPG.rf.202cf85bc7825df6c8103955d143597a.jpg": "IMG_0113",
             "train_aradoor_jpeg.rf.220ef0ec4d4b170948f2a50b21db2001.jpg": "aradoor",
             "train_frame224_jpg.rf.0a1b2c3d.jpg": "frame", "train_v_test1_mp4-17_jpg.rf.ff00.jpg": "v_test1_mp4-",
             "test_1043.png": "1043"}
    assert {n: source_stem(Path(n)) for n in names} == names


def _parts_by_stem(split: dict[str, list[Path]]) -> dict[str, set[str]]:
    from macroloc.perception.trainset import source_stem

    parts: dict[str, set[str]] = {}
    for name, paths in split.items():
        for p in paths:
            parts.setdefault(f"{p.parent}/{source_stem(p)}", set()).add(name)
    return parts


def test_split_by_source_keeps_every_copy_of_a_photo_in_one_part():
    from macroloc.perception.trainset import split_by_source

    folder = Path("robot_door_detection/images")
    paths = [folder / f"{prefix}_Door{n:04d}_png.rf.{h:08x}.jpg"
             for n in range(40) for prefix, h in (("train", 3 * n), ("train", 3 * n + 1), ("valid", 3 * n + 2))]
    split = split_by_source(paths, seed=4)
    assert split == split_by_source(paths, seed=4)
    assert sorted(p for part in split.values() for p in part) == sorted(paths)
    assert all(len(parts) == 1 for parts in _parts_by_stem(split).values())
    assert [len(split[k]) // 3 for k in ("train", "val", "test")] == [32, 4, 4]  # 80/10/10 of the 40 sources


def test_anchors_follow_the_input_size_and_old_runs_were_320_by_240():
    from macroloc.perception.train import anchors_for_input, init_input_wh

    anchors = np.array([[18.0, 27.0], [220.0, 235.0]])
    scaled = anchors_for_input(anchors, (320, 240), (448, 336))
    np.testing.assert_allclose(scaled / [448, 336], anchors / [320, 240])  # the same fraction of the image
    assert init_input_wh({"settings": {"steps": 1500}}) == (320, 240)
    assert init_input_wh({"settings": {"input_wh": [448, 336]}}) == (448, 336)
