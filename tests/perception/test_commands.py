"""`macroloc detect` and `macroloc perceive`: the contract's JSON, and one clean line + exit 2 for bad input."""

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from macroloc.cli.main import main
from tests.conftest import shared_data
from tests.perception.helpers import png_bomb


def _run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_detect_json_and_plot(capsys, tmp_path: Path):
    image = shared_data("images/facades/images/img_10.jpg")
    code, out, _ = _run(capsys, ["detect", str(image), str(image), "--json", "--plot", str(tmp_path)])
    assert code == 0
    doc = json.loads(out)
    assert [im["path"] for im in doc["images"]] == [str(image)] * 2
    h, w = cv2.imread(str(image)).shape[:2]
    for d in doc["images"][0]["detections"]:
        assert set(d) == {"type", "score", "box_xyxy", "truncated"} and d["type"] in ("door", "window")
        x0, y0, x1, y1 = d["box_xyxy"]
        assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h
    assert (tmp_path / "img_10_detect.jpg").exists()


def _bmp_header(width: int, height: int) -> bytes:
    """A BMP's file and info headers (8-bit) without its pixels: Pillow sizes it from these alone."""
    return b"BM" + struct.pack("<IHHI", 54, 0, 0, 54) + struct.pack("<IiiHHIIiiII", 40, width, height, 1, 8, 0, 0,
                                                                     0, 0, 0, 0)


@pytest.mark.parametrize("make", ["missing", "not_an_image", "png_bomb", "bmp_bomb"])
def test_detect_bad_input_is_one_line_and_exit_2(capsys, tmp_path: Path, make: str):
    """A bomb (a 390 KB PNG of 20000 x 20000 pixels, a BMP header declaring as many) is refused from its
    header before anything is decoded."""
    path = tmp_path / "x.jpg"
    if make == "not_an_image":
        path.write_text("hello")
    elif make == "png_bomb":
        path.write_bytes(png_bomb(20000, 20000))
    elif make == "bmp_bomb":
        path.write_bytes(_bmp_header(20000, 20000))
    code, out, err = _run(capsys, ["detect", str(path), "--json"])
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    if "bomb" in make:
        assert "refused before decoding" in err, err


def _pair_args(folder: Path, frame: str = "50"):
    return ["perceive", "--left", str(folder / "left" / f"{frame}.jpg"),
            "--right", str(folder / "right" / f"{frame}.jpg"),
            "--calib-left", str(folder / "stereo_left.yaml"), "--calib-right", str(folder / "stereo_right.yaml")]


def test_perceive_json_contract_on_the_real_pair(capsys, tmp_path: Path):
    folder = shared_data("stereo/rtabmap_stereo_rect")
    code, out, _ = _run(capsys, [*_pair_args(folder), "--json", "--plot", str(tmp_path / "p.png")])
    assert code == 0
    doc = json.loads(out)
    for f in doc["features"]:
        assert {"type", "score", "box_xyxy", "corners_cam"} <= set(f)
        assert np.asarray(f["corners_cam"]).shape == (4, 3) and np.all(np.asarray(f["corners_cam"])[:, 2] > 0)
    assert (tmp_path / "p.png").exists()


@pytest.mark.parametrize("problem", ["missing_calib", "bad_gravity", "size_mismatch", "bomb", "bad_config"])
def test_perceive_bad_input_is_one_line_and_exit_2(capsys, tmp_path: Path, problem: str):
    folder = shared_data("stereo/rtabmap_stereo_rect")
    args = _pair_args(folder)
    if problem == "missing_calib":
        args[args.index("--calib-left") + 1] = str(tmp_path / "none.yaml")
    elif problem == "bad_gravity":
        args += ["--gravity", "0,nan,1"]
    elif problem == "bad_config":
        (tmp_path / "c.toml").write_text("[perception.proposals]\nmax_proposals = -1\n")
        args += ["--config", str(tmp_path / "c.toml")]
    elif problem == "bomb":
        bomb = tmp_path / "bomb.png"
        bomb.write_bytes(png_bomb(20000, 20000))
        args[args.index("--right") + 1] = str(bomb)
    else:
        small = tmp_path / "small.png"
        cv2.imwrite(str(small), np.zeros((10, 10), np.uint8))
        args[args.index("--left") + 1] = str(small)
    code, out, err = _run(capsys, [*args, "--json"])
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, err


def test_perceive_reports_each_features_source_and_size_check(capsys, tmp_path: Path):
    """Without a building every feature is `unchecked` and from the detector; with one (Office_A's sizes stand in
    for the real building's), each is confirmed or unchecked with the model size it fits, or rejected for its
    size with the reason."""
    folder = shared_data("stereo/rtabmap_stereo_rect")
    code, out, _ = _run(capsys, [*_pair_args(folder, "60"), "--json"])
    assert code == 0
    plain = json.loads(out)["features"]
    assert all(f["size_check"] == "unchecked" and f["source"] == "cnn" for f in plain)
    code, out, _ = _run(capsys, [*_pair_args(folder, "60"), "--json", "--building",
                                 str(Path(__file__).parents[2] / "data" / "buildings" / "office_a.ifc")])
    assert code == 0
    doc = json.loads(out)
    for f in doc["features"]:
        assert f["source"] in ("cnn", "geometry", "fused") and f["size_check"] in ("confirmed", "unchecked")
        assert f["size_check"] == "unchecked" or len(f["model_size_m"]) == 2
    assert all(not r["reason"].startswith("size:") or "fits no model" in r["reason"] for r in doc["rejected"])


def test_perceive_with_a_missing_building_is_one_line_and_exit_2(capsys, tmp_path: Path):
    folder = shared_data("stereo/rtabmap_stereo_rect")
    code, out, err = _run(capsys, [*_pair_args(folder), "--json", "--building", str(tmp_path / "none.ifc")])
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, err
