from pathlib import Path

import numpy as np
import pytest

from macroloc.graph.errors import UserInputError
from macroloc.perception.calib import read_camera_info, read_stereo_rig
from tests.conftest import shared_data

ROS_YAML = """image_width: 640
image_height: 480
camera_name: narrow_stereo/{side}
camera_matrix:
  rows: 3
  cols: 3
  data: [500.0, 0.0, 320.5, 0.0, 500.0, 240.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.0, 0.0, 0.0, 0.0, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [500.0, 0.0, 320.5, {tx}, 0.0, 500.0, 240.5, 0.0, 0.0, 0.0, 1.0, 0.0]
"""


def test_reads_the_shared_rtabmap_calibration():
    folder = shared_data("stereo/rtabmap_stereo_rect")
    rig = read_stereo_rig(folder / "stereo_left.yaml", folder / "stereo_right.yaml")
    assert rig.fx_px == pytest.approx(487.6087, abs=1e-3)
    assert (rig.cx_px, rig.cy_px) == pytest.approx((318.116, 249.444), abs=1e-3)
    assert rig.baseline_m == pytest.approx(58.3627 / 487.6087, rel=1e-4)
    assert (rig.width_px, rig.height_px) == (640, 480)


def test_reads_plain_ros_camera_info(tmp_path: Path):
    (tmp_path / "l.yaml").write_text(ROS_YAML.format(side="left", tx=0.0))
    (tmp_path / "r.yaml").write_text(ROS_YAML.format(side="right", tx=-60.0))
    info = read_camera_info(tmp_path / "l.yaml")
    assert np.allclose(info.K, [[500, 0, 320.5], [0, 500, 240.5], [0, 0, 1]])
    rig = read_stereo_rig(tmp_path / "l.yaml", tmp_path / "r.yaml")
    assert rig.baseline_m == pytest.approx(0.12)


@pytest.mark.parametrize("text", ["not: [a yaml", "image_width: 640\nimage_height: 480\n", "\x00\x01"])
def test_malformed_calibration_is_a_user_error(tmp_path: Path, text: str):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(UserInputError):
        read_camera_info(path)


def test_wrong_baseline_sign_is_a_user_error(tmp_path: Path):
    (tmp_path / "l.yaml").write_text(ROS_YAML.format(side="left", tx=0.0))
    (tmp_path / "r.yaml").write_text(ROS_YAML.format(side="right", tx=60.0))
    with pytest.raises(UserInputError, match="baseline"):
        read_stereo_rig(tmp_path / "l.yaml", tmp_path / "r.yaml")
