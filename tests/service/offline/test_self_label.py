"""The building labels its own doors (service.offline.self_label): occlusion by the model's own geometry, the
held-pose rule, and a rendered flight's labels against the simulator's truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.bench_self_label import truth_of_frame
from macroloc.graph.features import MacroFeature
from macroloc.graph.localizer import Estimate
from macroloc.proto.recording import matrix_from_pose, read_flight
from macroloc.service.frames import stereo_T_body_cam
from macroloc.service.offline.replay import FrameSeen
from macroloc.service.offline.self_label import ModelDepth, SelfLabeller, SelfLabelParams, iou
from macroloc.sim.scene import occluding_triangles

# the camera (OpenCV: x right, y down, z forward) on a body whose x is forward: z up
T_BODY_CAM = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)
FX, W, H = 300.0, 640, 480


def _quad(x: float, half_y: float, z0: float, z1: float) -> np.ndarray:
    """Two triangles of a wall at x, spanning y in [-half_y, half_y] and z in [z0, z1]."""
    a, b, c, d = [x, -half_y, z0], [x, half_y, z0], [x, half_y, z1], [x, -half_y, z1]
    return np.array([[a, b, c], [a, c, d]], float)


def _door(x: float, y: float = 0.0, kind: str = "door") -> MacroFeature:
    corners = np.array([[x, y + 0.45, 0.0], [x, y - 0.45, 0.0], [x, y - 0.45, 2.0], [x, y + 0.45, 2.0]])
    return MacroFeature(f"{kind}@{x},{y}", kind, None, corners, corners.mean(axis=0), np.array([-1.0, 0, 0]),  # type: ignore[arg-type]
                        0.9, 2.0)


def _estimate(status: str = "localized", sigma_m: float = 0.02, sigma_deg: float = 0.3,
              T_cad_body: np.ndarray | None = None) -> Estimate:
    T = np.eye(4) if T_cad_body is None else T_cad_body
    T = T.copy()
    if T_cad_body is None:
        T[2, 3] = 1.0  # the camera 1 m above the floor
    cov = np.diag([np.radians(sigma_deg) ** 2] * 3 + [sigma_m**2] * 3)
    return Estimate(0, status, T, T_cad_body=T, covariance=cov)


def _labeller(tmp_path: Path, features: list[MacroFeature], occluders: np.ndarray) -> SelfLabeller:
    return SelfLabeller(features, ModelDepth(occluders), tmp_path, "t")


def test_model_depth_hides_a_point_behind_a_surface_and_not_one_before_it() -> None:
    depth = ModelDepth(_quad(3.0, 2.0, -1.0, 3.0))
    origin = np.array([0.0, 0.0, 1.0])
    points = np.array([[5.0, 0.0, 1.0], [2.0, 0.0, 1.0], [5.0, 0.0, 6.0], [3.1, 0.0, 1.0], [5.0, 5.0, 1.0]])
    # behind; before; over the wall's top; behind it by less than the tolerance; beside it
    assert depth.hidden(origin, points, tol_m=0.25).tolist() == [True, False, False, False, False]


def test_a_door_behind_a_wall_is_never_labelled_and_one_in_view_is(tmp_path: Path) -> None:
    door = _door(6.0)
    seen = _labeller(tmp_path / "a", [door], np.zeros((0, 3, 3))).boxes(_estimate(), T_BODY_CAM, FX, FX, 319.5,
                                                                       239.5, W, H)
    assert [b.feature_id for b in seen] == [door.id] and not seen[0].cut and seen[0].visible_fraction == 1.0
    wall = _quad(3.0, 2.0, -1.0, 3.0)  # a wall between the camera and the door
    labeller = _labeller(tmp_path / "b", [door], wall)
    assert labeller.boxes(_estimate(), T_BODY_CAM, FX, FX, 319.5, 239.5, W, H) == []
    assert labeller.report.boxes == {"hidden": 1}
    half = _labeller(tmp_path / "c", [door], _quad(3.0, 0.1, -1.0, 3.0) + np.array([0, 0.15, 0]))
    (box,) = half.boxes(_estimate(), T_BODY_CAM, FX, FX, 319.5, 239.5, W, H)  # a post hides a part of it
    assert 0.25 <= box.visible_fraction < 1.0


def test_a_door_cut_by_the_border_is_flagged_and_one_behind_the_camera_is_not_labelled(tmp_path: Path) -> None:
    beside, behind = _door(2.0, y=2.05), _door(-4.0)
    labeller = _labeller(tmp_path, [beside, behind], np.zeros((0, 3, 3)))
    (box,) = labeller.boxes(_estimate(), T_BODY_CAM, FX, FX, 319.5, 239.5, W, H)
    assert box.feature_id == beside.id and box.cut and box.box_xyxy[0] == -0.5
    assert labeller.report.boxes == {"labelled": 1, "behind": 1}


@pytest.mark.parametrize(("estimate", "why"), [
    (_estimate(status="exploring"), "not_localized"), (_estimate(status="degraded"), "not_localized"),
    (Estimate(0, "localized", np.eye(4), T_cad_body=np.eye(4), covariance=None), "not_localized")])
def test_nothing_is_labelled_where_the_pose_is_not_held(tmp_path: Path, rendered_office_flight: Path,
                                                         estimate: Estimate, why: str) -> None:
    labeller = _labeller(tmp_path, [_door(6.0)], np.zeros((0, 3, 3)))
    frame = next(iter(read_flight(rendered_office_flight)))
    labeller.frame(frame, FrameSeen(stereo_T_body_cam(frame.stereo), []), estimate)
    labeller.finish(None)  # type: ignore[arg-type]
    assert labeller.report.frames == {why: 1}
    assert not list((tmp_path / "images").iterdir()) and not list((tmp_path / "labels").iterdir())


def test_a_pose_too_uncertain_to_box_the_door_labels_it_not(tmp_path: Path) -> None:
    labeller = _labeller(tmp_path, [_door(6.0)], np.zeros((0, 3, 3)))
    # at 3 sigma the pose turns 6 deg (31 px at 300 px focal length) or moves 0.9 m aside (45 px at 6 m): the
    # 45 px wide box overlaps itself at IoU 0.18-0
    assert labeller.boxes(_estimate(sigma_m=0.3, sigma_deg=2.0), T_BODY_CAM, FX, FX, 319.5, 239.5, W, H) == []
    assert labeller.report.boxes == {"uncertain": 1}


def test_a_rendered_flight_labelled_from_its_true_poses_agrees_with_the_simulators_truth(
        tmp_path: Path, rendered_office_flight: Path, office_path: Path, office_model) -> None:  # noqa: ANN001
    """Every box the labeller writes from the true pose is a door the simulator's instance mask shows, at IoU >= 0.5
    with its truth box (never one hidden behind a wall or a closed door), and the flight has doors in the camera's
    view that the model hides (so that the occlusion test is exercised)."""
    params = SelfLabelParams(every_s=0.5)
    labeller = SelfLabeller(office_model.features, ModelDepth(occluding_triangles(office_path)), tmp_path, "r",
                            params)
    checked = 0
    for frame in read_flight(rendered_office_flight):
        before = len(labeller.report.labels)
        T_cad_body = matrix_from_pose(frame.ground_truth.T_cad_body)
        labeller.frame(frame, FrameSeen(stereo_T_body_cam(frame.stereo), []),
                       _estimate(sigma_m=0.01, sigma_deg=0.1, T_cad_body=T_cad_body))
        truth = truth_of_frame(frame, params)
        for box in labeller.report.labels[before:]:  # the truth lists what its mask shows (>= 30 pixels)
            best = max(iou(box.box_xyxy, t["box"]) for t in truth.values() if t["type"] == box.type)
            assert best >= 0.5, f"{box.feature_id} labelled at {box.box_xyxy} in {box.frame}: hidden, or not there"
            checked += 1
    labeller.finish(None)  # type: ignore[arg-type]
    assert checked >= 5 and labeller.report.boxes["hidden"] >= 5
    assert len(list((tmp_path / "labels").glob("*.txt"))) == labeller.report.frames["labelled"] >= 10
    assert (tmp_path / "r.labels.png").is_file()  # the contact sheet


def test_an_opening_there_but_not_labelled_is_greyed_out_and_a_labelled_one_spared(tmp_path: Path) -> None:
    """A door too uncertain to box is still a door: greyed out (its sigma points' boxes), so that a detector
    trained on the frame is not taught that it is background; a labelled box inside the region keeps its pixels."""
    from macroloc.service.offline.self_label import grey_out

    near, far = _door(4.0), _door(12.0, y=0.2)
    labeller = _labeller(tmp_path, [near, far], np.zeros((0, 3, 3)))
    # 3 sigma of 1 deg turns the view by 16 px: the near door's 68 px wide box keeps IoU 0.62, the far one's 23 px
    # wide box drops to 0.18
    labels = labeller.boxes(_estimate(sigma_m=0.02, sigma_deg=1.0), T_BODY_CAM, FX, FX, 319.5, 239.5, W, H)
    assert [b.feature_id for b in labels] == [near.id] and labeller.report.boxes == {"labelled": 1, "uncertain": 1}
    (region,) = labeller.greyed
    far_box = (319.5 - FX * 0.65 / 12, 239.5 - FX * 1.0 / 12, 319.5 - FX * -0.25 / 12, 239.5 + FX * 1.0 / 12)
    assert region[0] < far_box[0] and region[2] > far_box[2]  # wider than its own box: where it could be
    image = np.random.default_rng(0).integers(0, 255, (H, W, 3), np.uint8)
    out = grey_out(image, [(100.0, 100.0, 200.0, 200.0)], [(150.0, 150.0, 300.0, 300.0)])
    assert (out[100:150, 100:201] == out[100, 100]).all() and (out[151:200, 151:200] == image[151:200, 151:200]).all()
    assert (out[:100] == image[:100]).all() and (out[201:] == image[201:]).all()
