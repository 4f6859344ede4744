"""The real rectified pairs of rtabmap_stereo_rect: the double doors come out as a plausible door in 3D."""

import cv2
import numpy as np
import pytest

from perception.calib import read_stereo_rig
from perception.pipeline import Perception, StereoPair
from tests.conftest import shared_data

DOUBLE_DOOR_PX = {"50": (105.0, 140.0, 220.0, 295.0), "60": (170.0, 110.0, 290.0, 255.0)}  # by eye, for matching


def _centre_inside(box, region) -> bool:
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    return region[0] <= cx <= region[2] and region[1] <= cy <= region[3]


@pytest.mark.parametrize("frame", ["50", "60"])
def test_double_doors_are_detected_and_reconstructed(frame):
    folder = shared_data("stereo/rtabmap_stereo_rect")
    rig = read_stereo_rig(folder / "stereo_left.yaml", folder / "stereo_right.yaml")
    pair = StereoPair(cv2.imread(str(folder / "left" / f"{frame}.jpg")),
                      cv2.imread(str(folder / "right" / f"{frame}.jpg"), cv2.IMREAD_GRAYSCALE), rig)
    result = Perception.create().process(pair)
    doors = [f for f in result.features if f.type == "door" and _centre_inside(f.box_xyxy, DOUBLE_DOOR_PX[frame])]
    assert doors, f"no door reconstructed at the double doors; detections {result.detections}, {result.rejected}"
    best = max(doors, key=lambda f: f.score)
    assert 1.3 <= best.width_m <= 2.4 and 1.8 <= best.height_m <= 2.8, best.to_json()
    assert best.tilt_deg < 10.0
    assert 5.0 < float(np.mean(best.corners_cam[:, 2])) < 10.0
