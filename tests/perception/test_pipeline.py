import subprocess
import sys

import numpy as np
import pytest

from macroloc.perception.detector import Detection
from macroloc.perception.pipeline import ObservedFeature, Perception, Rejected, StereoPair
from tests.perception.helpers import RIG, door_pair


@pytest.mark.parametrize("depth_m", [2.5, 5.0])
def test_chain_after_the_detector_recovers_a_door_on_a_wall(depth_m):
    left, right, corners, box = door_pair(depth_m)
    chain = Perception.create()
    result = chain.process_boxes(StereoPair(left, right, RIG), [Detection("door", 0.9, box)])
    assert not result.rejected, result.rejected
    (f,) = result.features
    u_true = corners[:, 0] / depth_m * RIG.fx_px + RIG.cx_px
    assert abs(f.sides_px[0][:, 0].mean() - u_true[0]) < 1.5 and abs(f.sides_px[1][:, 0].mean() - u_true[1]) < 1.5
    # SGBM's sub-pixel disparity is biased towards whole pixels by up to ~0.4 px on this texture: dz = z^2/(f b) dd
    tol = 0.02 + 0.4 * depth_m**2 / (RIG.fx_px * RIG.baseline_m)
    assert np.abs(f.corners_cam - corners).max() < tol
    assert f.width_m == pytest.approx(0.9, abs=tol) and f.height_m == pytest.approx(2.0, abs=tol)
    assert set(result.timings_ms) == {"stereo", "lines", "reconstruct"}
    # at 2.5 m the door's box ends 23 px above the image's bottom: within BORDER_MARGIN_FRACTION, so its
    # bottom is taken as possibly cut; at 5 m it is well inside the image
    assert f.truncated == (False, depth_m < 3.0)
    assert f.to_json()["truncated"] == {"sideways": False, "vertically": depth_m < 3.0}  # perceive --json says so


@pytest.mark.parametrize(("box", "expected"), [
    ((100.0, 50.0, 200.0, 400.0), (False, False)),
    ((0.0, 50.0, 200.0, 400.0), (True, False)),
    ((100.0, 50.0, 639.5, 400.0), (True, False)),
    ((100.0, 0.0, 200.0, 400.0), (False, True)),
    ((100.0, 50.0, 200.0, 480.0), (False, True)),
    ((100.0, 50.0, 200.0, 460.0), (False, True)),  # a window running on below the image: the box stops short
    ((620.0, 50.0, 630.0, 400.0), (True, False)),
])
def test_a_box_at_the_image_border_is_truncated_on_that_axis(box, expected):
    from macroloc.perception.pipeline import ObservedFeature

    assert ObservedFeature.truncation(box, 640, 480) == expected


def test_corners_projected_past_the_border_truncate_a_box_that_stops_short():
    from macroloc.perception.pipeline import ObservedFeature

    box = (200.0, 100.0, 300.0, 400.0)
    inside = np.array([[200.0, 100.0], [300.0, 100.0], [300.0, 400.0], [200.0, 400.0]])
    assert ObservedFeature.truncation(box, 640, 480, inside) == (False, False)
    below = inside + np.array([[0, 0], [0, 0], [0, 70.0], [0, 70.0]])  # the bottom corners at 470 px
    assert ObservedFeature.truncation(box, 640, 480, below) == (False, True)
    assert RIG.project(np.array([[0.0, 0.0, 2.0], [1.0, -0.5, 2.0]])) == pytest.approx(
        np.array([[RIG.cx_px, RIG.cy_px], [RIG.cx_px + RIG.fx_px / 2, RIG.cy_px - RIG.fy_px / 4]]))


def test_implausible_shapes_are_rejected_with_a_reason():
    left, right, _, box = door_pair(3.0, door_wh_m=(0.9, 0.8))  # far too short for a door
    result = Perception.create().process_boxes(StereoPair(left, right, RIG), [Detection("door", 0.9, box)])
    assert not result.features and "height" in result.rejected[0].reason


def test_runtime_needs_neither_torch_nor_the_service():
    code = ("import sys, macroloc.perception.pipeline, macroloc.perception.detector, macroloc.perception.calib, "
            "macroloc.perception.evaluate, macroloc.perception.train, macroloc.perception.trainset, "
            "macroloc.perception.draw, macroloc.perception.detector_eval; "
            "bad = [m for m in ('torch', 'zenoh', 'macroloc.service', 'typer') if m in sys.modules]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_doorway_is_placed_on_its_wall_not_in_the_room_seen_through_it():
    """The chain reads the doorway's depth from the wall beside it; with that switched off (`wall=None`), from
    inside its sides, where the camera sees the room 3 m behind: there the doorway would be 3.5 m tall, and is
    rejected."""
    from tests.perception.test_reconstruct import _doorway_on_a_wall

    depth, sides, corners, _ = _doorway_on_a_wall(20.0, np.array([0.1, 0.1, 4.0]), 3.0, 0.0, 0)
    grey = np.zeros((RIG.height_px, RIG.width_px), np.uint8)
    pair = StereoPair(grey, grey, RIG, gravity_cam=np.array([0.0, 1.0, 0.0]))
    box = (float(sides.left_px[:, 0].min()), float(sides.left_px[:, 1].min()), float(sides.right_px[:, 0].max()),
           float(sides.right_px[:, 1].max()))
    chain = Perception.create()
    on_wall = chain._reconstruct(Detection("door", 0.9, box), sides, depth, pair)
    chain.wall = None
    inside = chain._reconstruct(Detection("door", 0.9, box), sides, depth, pair)
    assert isinstance(on_wall, ObservedFeature) and np.abs(on_wall.corners_cam - corners).max() < 0.02
    assert isinstance(inside, Rejected) and "height" in inside.reason
