"""`macroloc replay` on a ground-truth flight through the bundled FZK-Haus: the JSON contract, the report,
save -> load -> re-localize, and clean errors for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from macroloc.cli.main import main

KEYS = {"frames", "processing_fps", "localized", "time_to_localize_s", "ape_rmse_m", "ape_max_m",
        "wrong_localizations", "wrong_while_localized_s", "status_final"}


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory, fzk_path: Path) -> Path:
    from macroloc.sim.truth_flight import write_truth_flight

    return write_truth_flight(fzk_path, tmp_path_factory.mktemp("flight") / "fzk.mcap", seed=0, duration_s=14.0)


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, dict | None, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, (json.loads(out) if rc == 0 and out.strip() else None), err


def test_the_truth_flight_holds_what_the_contract_says(flight: Path) -> None:
    from macroloc.proto.recording import matrix_from_pose, read_flight, read_metadata

    frames = list(read_flight(flight))
    assert len(frames) == 14 * 30
    assert read_metadata(flight).storey
    seen = [f for f in frames if f.ground_truth.features_cam]
    assert seen
    gt = seen[0].ground_truth
    assert len(gt.corner_visible) == 4 * len(gt.features_cam)
    assert all(len(f.corners) == 4 and f.id for f in gt.features_cam)
    assert all(c.z > 0 for f in gt.features_cam for c, v in zip(f.corners, gt.corner_visible, strict=False) if v)
    T = matrix_from_pose(gt.T_cad_body)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_replay_prints_the_contract_writes_a_report_and_a_map(flight: Path, fzk_path: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib.axes

    drawn: list = []  # the top-down picture is a floor plan: the walls, cut at the flight's height, under the rest
    add_collection = matplotlib.axes.Axes.add_collection
    monkeypatch.setattr(matplotlib.axes.Axes, "add_collection",
                        lambda self, c, *a, **k: (drawn.append(c), add_collection(self, c, *a, **k))[1])
    rc, doc, err = run(["replay", str(flight), "--building", str(fzk_path), "--json", "--report",
                        str(tmp_path / "report"), "--save-map", str(tmp_path / "map.pb")], capsys)
    assert rc == 0, err
    assert doc is not None and set(doc) >= KEYS
    assert doc["frames"] == 14 * 30
    assert doc["localized"] and doc["wrong_localizations"] == 0
    assert doc["ape_rmse_m"] < 0.15
    for name in ("topdown.png", "frames.png", "result.json"):
        assert (tmp_path / "report" / name).stat().st_size > 0
    walls = [c for c in drawn if c.get_label() == "walls"]
    assert len(walls) == 1 and len(walls[0].get_segments()) >= 20  # FZK-Haus: its outer and inner walls
    from macroloc.service.state import SavedMapFile

    assert any(lm.id for lm in SavedMapFile.at(tmp_path / "map.pb").read().landmarks_map)
    report = tmp_path / "report"
    assert json.loads((report / "config.json").read_text())["graph"]  # the resolved configuration of the run
    assert _evo_ape_rmse_m(report / "truth_tum.txt", report / "estimate_tum.txt") == \
        pytest.approx(doc["ape_rmse_m"], abs=0.001)


def _evo_ape_rmse_m(truth: Path, estimate: Path) -> float:
    """evo's own APE (its command line: TUM files, no alignment, translation part): the RMSE it prints."""
    import re
    import subprocess
    import sys

    evo_ape = Path(sys.executable).parent / "evo_ape"
    out = subprocess.run([str(evo_ape), "tum", str(truth), str(estimate), "--no_warnings"], check=True,
                         capture_output=True, text=True, timeout=120).stdout
    match = re.search(r"^\s*rmse\s+([0-9.eE+-]+)", out, re.MULTILINE)
    assert match is not None, out
    return float(match.group(1))


def test_a_second_flight_relocalizes_into_the_saved_map(flight: Path, fzk_path: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    map_path = tmp_path / "map.pb"
    assert run(["replay", str(flight), "--building", str(fzk_path), "--json", "--save-map", str(map_path)],
               capsys)[0] == 0
    rc, doc, err = run(["replay", str(flight), "--building", str(fzk_path), "--json", "--map", str(map_path),
                        "--seed", "7"], capsys)
    assert rc == 0, err
    assert doc is not None and doc["localized"] and doc["wrong_localizations"] == 0


@pytest.mark.parametrize("argv_tail, message", [
    (["--observations", "sonar"], "--observations"),
    (["--map", "/nonexistent/map.pb"], "saved map not found"),
    (["--storey", "Level 9"], "storey 'Level 9' has no doors or windows"),
])
def test_bad_input_is_one_line_and_exit_2(flight: Path, fzk_path: Path, argv_tail: list[str], message: str,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = run(["replay", str(flight), "--building", str(fzk_path), "--json", *argv_tail], capsys)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and message in err


def test_an_old_json_map_is_one_line_and_exit_2(flight: Path, fzk_path: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A map `replay --save-map` wrote before issue 56 (JSON) is refused, in one line that says to save it again."""
    old = tmp_path / "map.json"
    old.write_text(json.dumps({"version": 2, "building_sha256": "sha", "T_cad_map": None, "keyframes": [],
                               "landmarks": []}))
    rc, _, err = run(["replay", str(flight), "--building", str(fzk_path), "--json", "--map", str(old)], capsys)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and "JSON map of an earlier macroloc; save the map again" in err


def test_a_missing_recording_is_exit_2(fzk_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = run(["replay", str(tmp_path / "none.mcap"), "--building", str(fzk_path), "--json"], capsys)
    assert rc == 2 and "recording not found" in err


def test_a_correct_entry_that_drifts_away_counts_as_wrong_while_localized() -> None:
    from macroloc.service.offline.replay import ReplayTrace, _wrong_localizations, _wrong_while_localized_s

    trace = ReplayTrace()
    for k in range(40):  # 10 Hz; localized from 1 s; the estimate drifts 0.1 m per frame from 1 s on
        T_true = np.eye(4)
        T_true[0, 3] = 0.2 * k
        T_est = T_true.copy()
        T_est[1, 3] = 0.1 * max(0, k - 10)
        trace.t_s.append(0.1 * k)
        trace.status.append("exploring" if k < 10 else "localized")
        trace.T_true.append(T_true)
        trace.T_est.append(T_est if k >= 10 else None)  # type: ignore[arg-type]
    assert _wrong_localizations(trace) == 0  # the entry at 1 s was right
    # more than 1 m off from k = 21 (1.1 m) to k = 39: 19 frames of 0.1 s
    assert _wrong_while_localized_s(trace) == pytest.approx(1.9)


def test_a_truth_flight_s_depth_camera_image_gives_the_service_points_on_a_grid() -> None:
    """`--observations truth`: the vehicle sends the recording's true depth image with its stereo frame (a depth
    camera's), and the service reads points on a grid of it in the body frame (service.frames.depth_points_body):
    what the surface check of registrations reads (graph.surfaces)."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import FlightFrame, encode_image, pose_from_matrix
    from macroloc.service.frames import depth_points_body
    from macroloc.service.offline.vehicle import RecordedVehicle

    info = pb.CameraInfo(width=640, height=480, fx=480.0, fy=480.0, cx=319.5, cy=239.5, baseline_m=0.1,
                         T_body_cam=pose_from_matrix(np.eye(4)))
    gt = pb.GroundTruth(depth=encode_image(np.full((480, 640), 2.0, np.float32)),
                        T_cad_body=pose_from_matrix(np.eye(4)), T_body_cam=pose_from_matrix(np.eye(4)))
    frame = FlightFrame(0, pb.StereoFrame(header=pb.Header(stamp_ns=0), info=info), ground_truth=gt)
    stereo, = [m.message for m in RecordedVehicle(depth_camera=True).messages(frame) if m.key == "stereo"]
    points = depth_points_body(stereo, 20, 6.0)
    assert points.shape == (24 * 32, 3) and np.allclose(points[:, 2], 2.0)
    rays = points[:, :2] / points[:, 2:]  # (u - cx) / fx, (v - cy) / fy of the grid's pixels, 0 to 620 / 460
    assert np.allclose(rays[0], (np.array([0, 0]) - [319.5, 239.5]) / 480.0)
    assert np.allclose(rays[-1], (np.array([620, 460]) - [319.5, 239.5]) / 480.0)
    without, = [m.message for m in RecordedVehicle(depth_camera=False).messages(frame) if m.key == "stereo"]
    assert len(depth_points_body(without, 20, 6.0)) == 0


def test_the_backend_hands_depth_to_the_next_keyframe() -> None:
    """FrontEnd.depth: points measured at a stamp reach the localizer with the next keyframe, moved into
    its body frame by the odometry between the two."""
    from macroloc.graph.surfaces import SurfaceIndex
    from macroloc.service.front_end import FrontEnd
    from macroloc.service.inputs import OdometryIn
    from tests.graph.scenes import corridor_model, make_T

    model = corridor_model()
    surfaces = SurfaceIndex(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    backend = FrontEnd.fresh_or_restored(model, None, surfaces=surfaces)
    backend.odometry(OdometryIn(0, np.eye(4)))
    backend.depth(0, np.array([[3.0, 0.0, 0.1], [4.0, 1.0, -0.2]]))
    backend.odometry(OdometryIn(100_000_000, make_T(np.eye(3), np.array([1.5, 0.0, 0.0]))))  # a keyframe (> 1 m)
    (i, points, below), = list(backend.localizer.depth)
    assert i == 1 and np.allclose(points, [[1.5, 0.0, 0.1], [2.5, 1.0, -0.2]]) and len(below) == 0


def test_a_map_with_views_relocalizes_at_the_first_frame(rendered_office_flight: Path, office_path: Path,
                                                          tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Place recognition in the saved map's keyframe views: localized at the first frame, before any door is in
    range; the same map without its views waits for the doors, as a fresh flight does."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.service.state import SavedMapFile

    map_path = tmp_path / "flight.pb"
    rc, first, err = run(["replay", str(rendered_office_flight), "--building", str(office_path), "--json", "--save-map",
                          str(map_path)], capsys)
    assert rc == 0 and first is not None and first["localized"], err
    import matplotlib.axes

    drawn: list[str] = []  # the report's floor plan shows the saved views and where the flight was placed
    for name in ("quiver", "scatter"):
        original = getattr(matplotlib.axes.Axes, name)
        monkeypatch.setattr(matplotlib.axes.Axes, name, lambda self, *a, _f=original, **k: (
            drawn.append(k.get("label", "")), _f(self, *a, **k))[1])
    rc, again, err = run(["replay", str(rendered_office_flight), "--building", str(office_path), "--json", "--map",
                          str(map_path), "--seed", "7", "--report", str(tmp_path / "report")], capsys)
    assert rc == 0 and again is not None, err
    assert again["time_to_localize_s"] == 0.0 and again["wrong_localizations"] == 0
    assert {"saved views", "placed in the saved map"} <= set(drawn)
    # placed where the map's keyframes are: as accurate as the flight that made the map (this 7 s map is itself
    # 0.106 m off: its first doors come in range at 5.5 s, and before them only the odometry holds it along the
    # corridor); the re-localized flight 0.121 m
    assert again["ape_rmse_m"] < first["ape_rmse_m"] + 0.03
    assert len(SavedMapFile.at(map_path).read().views) >= 5
    blind = pb.MapSnapshot.FromString(map_path.read_bytes())
    blind.ClearField("view_poses")
    map_path.write_bytes(blind.SerializeToString())
    rc, blind, err = run(["replay", str(rendered_office_flight), "--building", str(office_path), "--json", "--map",
                          str(map_path), "--seed", "7"], capsys)
    assert rc == 0 and blind is not None, err
    assert blind["time_to_localize_s"] is None or blind["time_to_localize_s"] > 3.0


def test_a_restored_maps_views_place_the_run_and_are_carried_where_it_has_none() -> None:
    """A saved map with views: the restarted backend is placed by them (a keyframe placed at the saved pose) and
    its next saved map holds its own views plus those saved views it has none near, in its own map frame."""
    from macroloc.graph.mapstore import KeyframeView
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import pose_from_matrix
    from macroloc.service.front_end import FrontEnd
    from macroloc.service.localizer_loop import FrameIn
    from macroloc.service.places import Placed
    from macroloc.service.state import view_to_wire
    from tests.graph.scenes import corridor_model, make_T, rot_z

    model = corridor_model()
    rng = np.random.default_rng(0)

    def view() -> KeyframeView:
        return KeyframeView(rng.uniform(1, 5, (30, 3)), rng.integers(0, 256, (30, 32), dtype=np.uint8))

    T_cad_map_old = make_T(rot_z(0.4), np.array([1.0, -2.0, 0.0]))
    here, far = make_T(np.eye(3), np.array([0.5, 0.0, 1.4])), make_T(rot_z(1.0), np.array([6.0, 1.0, 1.4]))
    saved = pb.MapSnapshot(building_sha256=model.sha256, status=pb.PoseEstimate.LOCALIZED,
                           T_cad_map=pose_from_matrix(T_cad_map_old))
    saved.views.extend([view_to_wire(view(), here), view_to_wire(view(), far)])
    backend = FrontEnd.fresh_or_restored(model, saved)
    assert backend.restored is not None and len(backend.restored.placed_views()) == 2
    assert not backend.supersedes_saved()  # not localized yet: the saved map is kept
    T_odom_body = make_T(rot_z(-0.7), np.array([3.0, 4.0, 1.4]))  # the new run's odometry frame is another one
    est = backend.loop.frame(FrameIn(10, T_odom_body, placed=Placed(T_cad_map_old @ here, view())))
    assert est.status == "localized" and est.T_cad_body is not None
    assert np.allclose(est.T_cad_body, T_cad_map_old @ here, atol=1e-6)
    assert backend.supersedes_saved()
    assert len(backend.snapshot("corridor", model.sha256).views) == 0  # the map query's reply carries none
    poses = [T for T, _ in backend.saved_views()]
    assert len(poses) == 2 and np.allclose(poses[0], T_odom_body, atol=1e-6)  # its own; `here` is covered by it
    T_cad_map_new = T_cad_map_old @ here @ np.linalg.inv(T_odom_body)
    assert np.allclose(poses[1], np.linalg.inv(T_cad_map_new) @ T_cad_map_old @ far, atol=1e-5)


def test_only_a_localized_map_with_views_is_placed_in_carried_ones_included() -> None:
    from dataclasses import replace

    from macroloc.graph.mapstore import KeyframeView
    from macroloc.service.places import KeyframePlaces
    from macroloc.service.saved_map import SavedMap

    view = KeyframeView(np.ones((30, 3)), np.zeros((30, 32), np.uint8))
    with_views = SavedMap("sha", np.eye(4), views=[(np.eye(4), view)])
    assert KeyframePlaces(with_views, keep_views=False).active
    assert not KeyframePlaces(replace(with_views, views=[]), keep_views=False).active
    assert not KeyframePlaces(replace(with_views, T_cad_map=None), keep_views=False).active
    assert KeyframePlaces(None, keep_views=True).active and not KeyframePlaces(None, keep_views=False).active


def test_the_graph_section_reaches_the_localizer(tmp_path: Path) -> None:
    """Every [graph] key the config documents for the localizer is the localizer's, from a config file (the
    service and the replay both build their localizer from it)."""
    from macroloc.service.config import load_config
    from macroloc.service.localizer_loop import settings_from_config

    path = tmp_path / "config.toml"
    path.write_text("[graph.anchor]\ncad_link_max_turn_deg = 4.5\n[graph.judge]\nsurface_turn_deg = 0.0\n"
                    "[graph.landmarks]\nassociate_m = 0.7\nfar_range_m = 12.0\n[graph.registration]\n"
                    "surface_retry_s = 2.5\n[graph.far]\nfar_resection = false\n")
    params = settings_from_config(load_config(path).graph).localizer
    assert (params.anchor.cad_link_max_turn_deg, params.judge.surface_turn_deg, params.landmarks.associate_m) == \
        (4.5, 0.0, 0.7)
    assert (params.registration.surface_retry_s, params.landmarks.far_range_m, params.far.far_resection) == \
        (2.5, 12.0, False)


def test_the_vehicles_recorded_odometry_places_each_frame() -> None:
    """A recording with the vehicle's own odometry (`macroloc demo --record`): the vehicle sends every recorded
    sample (`--odometry recorded`), the service places each frame at the sample of its stamp and takes gravity's
    up from the IMU against that odometry; a recording whose first frame carries none is refused, in one line."""
    from macroloc.graph.errors import UserInputError
    from macroloc.graph.rigid import rot_z
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import FlightFrame, encode_image, pose_from_matrix, vector3
    from macroloc.service.front_end import FrontEnd
    from macroloc.service.inputs import InputLimits
    from macroloc.service.offline.replay import replay_as_service
    from macroloc.service.offline.vehicle import RecordedVehicle
    from tests.graph.scenes import corridor_model

    image = np.random.default_rng(0).integers(0, 255, (48, 64), dtype=np.uint8)
    info = pb.CameraInfo(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5, baseline_m=0.1,
                         T_body_cam=pose_from_matrix(np.eye(4)))

    def T_map_body(stamp_ns: int) -> np.ndarray:  # the vehicle's odometry: level, 1 m/s along x, turning 0.2 rad/s
        T = np.eye(4)
        T[:3, :3], T[0, 3] = rot_z(0.2 * stamp_ns * 1e-9), 1.0 * stamp_ns * 1e-9
        return T

    def frame(stamp_ns: int, odometry_at: list[int]) -> FlightFrame:
        imu = [pb.Imu(header=pb.Header(stamp_ns=s), accel_mps2=vector3(T_map_body(s)[:3, :3].T @ [0.0, 0.0, 9.81]),
                      gyro_radps=vector3(np.array([0.0, 0.0, 0.2]))) for s in (stamp_ns - 25_000_000, stamp_ns)]
        stereo = pb.StereoFrame(header=pb.Header(stamp_ns=stamp_ns), camera_id="front",
                                left=encode_image(image, "raw"), right=encode_image(image, "raw"), info=info)
        odometry = [pb.Odometry(header=pb.Header(stamp_ns=s, frame_id="map"),
                                T_map_body=pose_from_matrix(T_map_body(s))) for s in odometry_at]
        return FlightFrame(stamp_ns, stereo, imu=imu, odometry=odometry)

    with pytest.raises(UserInputError, match="carries no vehicle odometry"):
        list(RecordedVehicle("recorded").messages(frame(100_000_000, [])))
    frames = [frame(k * 100_000_000, [k * 100_000_000 - 50_000_000, k * 100_000_000]) for k in range(1, 21)]
    estimates = []
    front_end = FrontEnd.fresh_or_restored(corridor_model(), None)
    replay_as_service(frames, front_end, RecordedVehicle("recorded"), InputLimits(), sink=estimates.append)
    assert len(estimates) == len(frames)
    for f, est in zip(frames, estimates, strict=True):
        assert est.stamp_ns == f.stamp_ns and np.allclose(est.T_map_body, T_map_body(f.stamp_ns))
    up_body = front_end.loop.up_body
    assert up_body is not None and np.allclose(up_body, T_map_body(frames[-1].stamp_ns)[:3, :3].T @ [0, 0, 1.0],
                                               atol=1e-3)


def test_the_visual_odometry_says_how_long_it_only_extrapolated() -> None:
    """The stereo visual odometry (`--observations perception` without the vehicle's odometry) tracks a textured
    wall; a blank view (a wall nearer than stereo measures looks so) loses it, and each such frame reports its
    interval as dead-reckoned, for the graph to trust that stretch of odometry less; tracked again, none."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import FlightFrame, encode_image, pose_from_matrix
    from macroloc.service.visual_odometry import VisualOdometry
    from tests.perception.helpers import RIG, fronto_parallel_pair

    left, right = fronto_parallel_pair(2.0)
    blank = np.full_like(left, 128)
    info = pb.CameraInfo(width=RIG.width_px, height=RIG.height_px, fx=RIG.fx_px, fy=RIG.fy_px, cx=RIG.cx_px,
                         cy=RIG.cy_px, baseline_m=RIG.baseline_m, T_body_cam=pose_from_matrix(np.eye(4)))
    odometry = VisualOdometry()
    reported = []
    for k, (l_img, r_img) in enumerate([(left, right)] * 3 + [(blank, blank)] * 3 + [(left, right)] * 2):
        stamp_ns = k * 33_000_000
        stereo = pb.StereoFrame(header=pb.Header(stamp_ns=stamp_ns), left=encode_image(l_img, "raw"),
                                right=encode_image(r_img, "raw"), info=info)
        odometry(FlightFrame(stamp_ns, stereo), l_img, r_img)
        reported.append(odometry.dead_reckoned_s)
    assert reported[:3] == [0.0] * 3
    assert reported[3:6] == pytest.approx([0.033] * 3)
    assert reported[7] == 0.0  # the textured wall again: re-keyed on the frame before, tracked


def test_the_visual_odometry_dead_reckons_the_height_on_the_imu_while_it_has_lost_track() -> None:
    """1.5 s hovering before a textured wall (tracked; the IMU reads gravity alone), then 1 s blank (lost) while the
    IMU reads a climb at 1 m/s^2: the height follows it (0.5 m), where the last velocity would have kept it."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import FlightFrame, encode_image, pose_from_matrix, vector3
    from macroloc.service.visual_odometry import VisualOdometry
    from tests.perception.helpers import RIG, fronto_parallel_pair

    left, right = fronto_parallel_pair(2.0)
    blank = np.full_like(left, 128)
    R_body_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axes in the body's
    T_body_cam = np.eye(4)
    T_body_cam[:3, :3] = R_body_cam
    info = pb.CameraInfo(width=RIG.width_px, height=RIG.height_px, fx=RIG.fx_px, fy=RIG.fy_px, cx=RIG.cx_px,
                         cy=RIG.cy_px, baseline_m=RIG.baseline_m, T_body_cam=pose_from_matrix(T_body_cam))
    odometry = VisualOdometry()
    frame_ns, n_hover, n_lost = 33_333_333, 45, 30
    heights = []
    for k in range(n_hover + n_lost):
        stamp_ns = (k + 1) * frame_ns
        climbing = k >= n_hover
        l_img, r_img = (blank, blank) if climbing else (left, right)
        f_up = 9.81 + (1.0 if climbing else 0.0)
        imu = [pb.Imu(header=pb.Header(stamp_ns=stamp_ns - frame_ns + (i + 1) * frame_ns // 4),
                      accel_mps2=vector3(np.array([0.0, 0.0, f_up])), gyro_radps=pb.Vector3()) for i in range(4)]
        stereo = pb.StereoFrame(header=pb.Header(stamp_ns=stamp_ns), left=encode_image(l_img, "raw"),
                                right=encode_image(r_img, "raw"), info=info)
        heights.append(odometry(FlightFrame(stamp_ns, stereo, imu=imu), l_img, r_img)[2, 3])
    assert odometry.dead_reckoned_s > 0.0
    assert abs(heights[n_hover - 1]) < 0.01
    assert heights[-1] - heights[n_hover - 1] == pytest.approx(0.5 * 1.0 * (n_lost * frame_ns * 1e-9) ** 2, abs=0.05)


@pytest.mark.parametrize("rekey", [True, False])
def test_a_session_keyframe_s_depth_points_re_key_the_visual_odometry_on_their_sgbm(rekey: bool) -> None:
    """Measuring a session keyframe's depth points (`measure_depth`) makes that frame the odometry's reference
    keyframe too, on the same whole-frame SGBM ([perception.odometry] rekey_at_session_keyframes); off, the
    odometry keeps its own reference and the depth points cost an SGBM of their own."""
    from dataclasses import replace

    from macroloc.perception.params import PerceptionParams
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import FlightFrame, encode_image, pose_from_matrix
    from macroloc.service.visual_odometry import VisualOdometry
    from tests.perception.helpers import RIG, fronto_parallel_pair

    left, right = fronto_parallel_pair(2.0)
    info = pb.CameraInfo(width=RIG.width_px, height=RIG.height_px, fx=RIG.fx_px, fy=RIG.fy_px, cx=RIG.cx_px,
                         cy=RIG.cy_px, baseline_m=RIG.baseline_m, T_body_cam=pose_from_matrix(np.eye(4)))
    params = PerceptionParams()
    params = replace(params, odometry=replace(params.odometry, rekey_at_session_keyframes=rekey))
    odometry = VisualOdometry(params=params)
    pairs = [(left.copy(), right.copy()) for _ in range(3)]  # distinct arrays: one SGBM per frame at most
    for k, (l_img, r_img) in enumerate(pairs):
        stereo = pb.StereoFrame(header=pb.Header(stamp_ns=k * 33_000_000), left=encode_image(l_img, "raw"),
                                right=encode_image(r_img, "raw"), info=info)
        odometry(FlightFrame(k * 33_000_000, stereo), l_img, r_img)
    assert odometry.measure_depth is not None
    vo = odometry._odometry
    assert vo is not None and vo._ref_left is pairs[0][0]  # the first frame's keyframe
    matched = odometry._disparity.computed
    points = odometry.measure_depth()
    assert len(points) > 0 and odometry._disparity.computed == matched + 1  # one SGBM for the frame
    assert (vo._ref_left is pairs[2][0]) == rekey
