"""The building labels its own doors (service.offline.self_label): occlusion by the model's own geometry, the
held-pose rule, and a rendered flight's labels against the simulator's truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.bench_self_label import truth_of_frame
from macroloc.graph.features import MacroFeature
from macroloc.graph.localizer import Estimate
from macroloc.graph.posegraph import PoseGraph
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



def _anchored_graph(T_map_bodies: list[np.ndarray], T_cad_map: np.ndarray, held_sigma_m: float = 0.01) -> PoseGraph:
    """A pose graph of keyframes at `T_map_bodies` (their odometry exact, 1 cm and 0.1 deg a step), anchored by the
    newest keyframe's CAD pose measured to `held_sigma_m` (T_cad_map of the truth)."""
    graph = PoseGraph()
    graph.add_first_keyframe(T_map_bodies[0])
    for prev, curr in zip(T_map_bodies[:-1], T_map_bodies[1:], strict=True):
        graph.add_keyframe(np.linalg.inv(prev) @ curr, np.r_[np.full(3, np.radians(0.1)), np.full(3, 0.01)], curr)
    graph.add_anchor(np.linalg.inv(T_cad_map))
    i = graph.n_keyframes - 1
    sigmas = np.r_[np.full(3, np.radians(0.2)), np.full(3, held_sigma_m)]
    graph.add_cad_pose(i, T_cad_map @ T_map_bodies[-1], np.diag(sigmas**-2.0))
    graph.update(extra_iterations=2)
    return graph


def test_frames_before_the_fix_are_labelled_from_their_keyframes_in_the_anchored_graph(
        tmp_path: Path, rendered_office_flight: Path, office_path: Path, office_model) -> None:  # noqa: ANN001
    """Frames while the pose is not held are kept, and labelled when it is: each from its keyframe as the pose
    graph then holds it (anchored), carried to the frame by the odometry. Here the map frame is the CAD frame turned
    30 deg and moved, a keyframe every 10 frames, the pose held from 5 s on: every box from before agrees with the
    simulator's truth, as the held frames' do."""
    params = SelfLabelParams(every_s=0.5)
    labeller = SelfLabeller(office_model.features, ModelDepth(occluding_triangles(office_path)), tmp_path, "b",
                            params)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    T_cad_map = np.array([[c, -s, 0, 5.0], [s, c, 0, -3.0], [0, 0, 1, 0.2], [0, 0, 0, 1]])
    frames = list(read_flight(rendered_office_flight))
    held_from = next(k for k, f in enumerate(frames) if (f.stamp_ns - frames[0].stamp_ns) * 1e-9 >= 5.0)
    T_map_bodies = [np.linalg.inv(T_cad_map) @ matrix_from_pose(f.ground_truth.T_cad_body) for f in frames]
    graph = _anchored_graph(T_map_bodies[: held_from + 1: 10], T_cad_map)
    truths = {}
    for k, frame in enumerate(frames):
        T_map_body = T_map_bodies[k]
        if k >= held_from:
            estimate = _estimate(sigma_m=0.01, sigma_deg=0.1, T_cad_body=T_cad_map @ T_map_body)
            estimate.T_map_body = T_map_body
        else:
            estimate = Estimate(frame.stamp_ns, "exploring", T_map_body, keyframe=k // 10)
        labeller.frame(frame, FrameSeen(stereo_T_body_cam(frame.stereo), [], graph), estimate)
        truths[f"b_{frame.stamp_ns}"] = truth_of_frame(frame, params)
    labeller.finish(None)  # type: ignore[arg-type]
    frames_by = labeller.report.frames
    assert frames_by["labelled_before_fix"] >= 9 and frames_by["labelled"] >= 3  # 0-5 s every 0.5 s; 5-7 s
    before = [b for b in labeller.report.labels if int(b.frame[2:]) - frames[0].stamp_ns < 5e9]
    assert len(before) >= 3
    for box in before:
        best = max(iou(box.box_xyxy, t["box"]) for t in truths[box.frame].values() if t["type"] == box.type)
        assert best >= 0.5, f"{box.feature_id} labelled at {box.box_xyxy} in {box.frame}"
    assert len(list((tmp_path / "labels").glob("b_*.txt"))) == frames_by["labelled"] + frames_by["labelled_before_fix"]


def test_the_drift_from_a_keyframe_leaves_its_doors_uncertain_and_older_frames_are_let_go(
        tmp_path: Path, rendered_office_flight: Path) -> None:
    """A frame kept 30 m of odometry after its keyframe carries the drift the pose graph assumes (0.03 m/m: 0.9 m,
    3 sigma 2.7 m): no door 6 m ahead can be boxed from it; 0 m after it, the door is boxed. Without the graph, or
    with its keyframe no longer in it, nothing is labelled. Frames more than `before_fix_s` before the newest are
    let go."""
    frame = next(iter(read_flight(rendered_office_flight)))
    seen = FrameSeen(T_BODY_CAM, [])
    T_body = np.eye(4)
    T_body[2, 3] = 1.0
    graph = _anchored_graph([T_body], np.eye(4))
    for path_m, target, expected in ((0.0, graph, {"labelled": 1}), (30.0, graph, {"uncertain": 1}),
                                     (0.0, None, {})):
        labeller = _labeller(tmp_path / f"p{path_m}{target is None}", [_door(6.0)], np.zeros((0, 3, 3)))
        labeller._keyframes[0] = (T_body, -path_m)  # the keyframe path_m of odometry before the frame
        labeller.frame(frame, seen, Estimate(frame.stamp_ns, "exploring", T_body, keyframe=0))
        labeller._label_waiting(target)
        assert labeller.report.boxes == expected
        assert labeller.report.frames == ({"labelled_before_fix": 1} if target else {"not_localized": 1})
    labeller = _labeller(tmp_path / "old", [_door(6.0)], np.zeros((0, 3, 3)))
    labeller.params = SelfLabelParams(before_fix_s=1.0, every_s=0.0)
    for k in range(3):
        frame.stamp_ns = k * 1_000_000_000
        labeller.frame(frame, seen, Estimate(frame.stamp_ns, "exploring", T_body, keyframe=0))
    assert len(labeller._waiting) == 2 and labeller.report.frames == {"not_localized": 1}
