"""Door proposals from geometry: two long vertical lines as far apart as a model door is wide, on a wall."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.perception.door_proposals import propose_doors
from macroloc.perception.evaluate import iou_xyxy
from macroloc.perception.size_check import OpeningSizes
from macroloc.perception.stereo import SgbmMatcher, depth_from_disparity


@pytest.fixture(scope="module")
def close_up():  # noqa: ANN201 - (left, right, rig, truth box, door width/height)
    """The test room's 1.0 x 2.1 m door seen from 2.2 m, 10 deg off its normal, the camera 1.4 m above the floor:
    the door runs off the image's bottom (rendered: the look the detector was blind to)."""
    from macroloc.perception.calib import StereoRig
    from macroloc.sim.groundtruth import feature_half_depths, features_in_view
    from macroloc.sim.materials import dress_scene
    from macroloc.sim.render import CameraModel, Lighting, StereoRenderer
    from macroloc.sim.textures import make_texture_layers
    from tests.sim.room import look_at, room_scene

    scene, features = room_scene()
    cam = CameraModel()
    renderer = StereoRenderer(dress_scene(scene, features, seed=2), make_texture_layers(2), cam)
    lighting = Lighting(positions_cad=np.array([[2.0, 2.0, 2.7], [6.0, 4.0, 2.7]]), colours=np.ones((2, 3)),
                        noise_sigma=0.01)
    eye = np.array([3.5 - 2.2 * np.sin(np.radians(10)), 6.0 - 2.2 * np.cos(np.radians(10)), 1.4])
    T = look_at(eye, [3.5, 6.0, 1.3])
    try:
        left, right = renderer.render_stereo(T, lighting, 0.0)
    finally:
        renderer.release()
    truth = [f for f in features_in_view(features, feature_half_depths(scene, features), T, cam, left.depth_m,
                                         left.instance) if f.type == "door"]
    rig = StereoRig(cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m, cam.width, cam.height)
    return left.image_bgr, right, rig, tuple(float(v) for v in truth[0].box_xyxy)


def test_a_rendered_close_up_door_is_found_without_the_detector(close_up):
    """The detector's box withheld: the chain on the geometry proposal alone gives a door of the model's size,
    flagged `geometry`."""
    from macroloc.perception.model_check import ModelCheckedPerception
    from macroloc.perception.pipeline import Perception, StereoPair

    left, right, rig, box = close_up
    sizes = OpeningSizes.of([("door", 1.0, 2.1), ("window", 1.5, 1.2)])
    result = ModelCheckedPerception(Perception.create(), sizes).process_detections(StereoPair(left, right, rig), [])
    doors = [f for f in result.features if iou_xyxy(np.array([f.feature.box_xyxy]), np.array([box]))[0, 0] >= 0.5]
    assert len(doors) == 1, (result.proposals, result.rejected)
    assert doors[0].source == "geometry" and doors[0].size.status == "confirmed"
    assert doors[0].size.matched_wh_m == (1.0, 2.1) and abs(doors[0].feature.width_m - 1.0) < 0.15


def test_perceive_s_chain_takes_the_proposals_and_size_check_from_the_config(close_up):
    """`macroloc perceive --config`: [perception.proposals] max_proposals = 0 leaves the close-up door the
    detector does not see unfound; a size check with no tolerance cannot confirm it."""
    from macroloc.cli.commands.perceive import model_checked_chain
    from macroloc.perception.pipeline import StereoPair
    from macroloc.service.config import PerceptionConfig

    left, right, rig, box = close_up
    sizes = OpeningSizes.of([("door", 1.0, 2.1), ("window", 1.5, 1.2)])

    def doors(table: dict) -> list:
        chain = model_checked_chain(PerceptionConfig.model_validate(table), None, sizes)
        result = chain.process_detections(StereoPair(left, right, rig), [])
        return [f for f in result.features if iou_xyxy(np.array([f.feature.box_xyxy]), np.array([box]))[0, 0] >= 0.5]

    assert [d.size.status for d in doors({})] == ["confirmed"]
    assert doors({"proposals": {"max_proposals": 0}}) == []
    assert all(d.size.status != "confirmed" for d in doors({"size_check": {"floor_m": 0.0, "per_m": 0.0}}))


def _proposals(close_up, sizes: OpeningSizes) -> list:  # noqa: ANN001
    left, right, rig, _ = close_up
    return propose_doors(left, depth_from_disparity(SgbmMatcher().disparity_px(left, right), rig), rig, sizes)


def test_the_close_up_door_is_proposed_with_its_width_and_model_size(close_up):
    box = close_up[3]
    props = _proposals(close_up, OpeningSizes.of([("door", 1.0, 2.1), ("window", 1.5, 1.2)]))
    hits = [p for p in props if iou_xyxy(np.array([p.box_xyxy]), np.array([box]))[0, 0] >= 0.5]
    assert len(hits) == 1 and hits[0].model_wh_m == (1.0, 2.1) and abs(hits[0].width_m - 1.0) < 0.15
    assert hits[0].cut_vertically  # it runs off the image's bottom


@pytest.mark.parametrize("door_widths_m", [(1.5,), (1.4, 1.98)])
def test_two_vertical_sides_spaced_like_no_model_door_are_not_proposed(close_up, door_widths_m):
    """The same door, whose sides stand 1.0 m apart, in models whose doors (all 2.1 m tall) are 1.5 m, or 1.4 and
    1.98 m wide."""
    box = close_up[3]
    props = _proposals(close_up, OpeningSizes.of([("door", w, 2.1) for w in door_widths_m]))
    assert not [p for p in props if iou_xyxy(np.array([p.box_xyxy]), np.array([box]))[0, 0] >= 0.5]
