"""`replay --over-zenoh`: a recorded flight played into a running service over loopback, and scored."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightWriter, pose_from_matrix, vector3
from macroloc.service.state import SavedMapFile
from tests.service.helpers import free_port, loopback, running_service, service_config, yaw_T


def write_fake_flight(path: Path, model, start: np.ndarray, frames: int = 45) -> Path:  # noqa: ANN001
    """A recording without images worth perceiving: tiny frames, ground truth of every door/window in range."""
    T_body_cam = forward_stereo_T_body_cam()
    image = pb.Image(width=8, height=6, encoding=pb.Image.RAW_MONO8, data=bytes(48))
    with FlightWriter(path) as writer:
        for k in range(frames):
            stamp = (k + 1) * 33_333_333
            T_cad_body = start @ yaw_T(0.05 * k, np.array([0.01 * k, 0.0, 0.0]))
            frame = pb.StereoFrame(camera_id="front", left=image, right=image)
            frame.header.stamp_ns = stamp
            truth = pb.GroundTruth(T_cad_body=pose_from_matrix(T_cad_body), T_body_cam=pose_from_matrix(T_body_cam))
            truth.header.stamp_ns = stamp
            T_cam_cad = np.linalg.inv(T_cad_body @ T_body_cam)
            for f in model.features:
                d = f.centroid_cad - T_cad_body[:3, 3]
                if f.orientation != "vertical" or np.linalg.norm(d[:2]) > 8.0 or abs(d[2]) > 2.0:
                    continue
                corners_cam = f.corners_cad @ T_cam_cad[:3, :3].T + T_cam_cad[:3, 3]
                truth.features_cam.add(type=f.type, id=f.id).corners.extend(vector3(c) for c in corners_cam)
                truth.corner_visible.extend([True] * 4)
            writer.write_stereo(frame)
            writer.write_ground_truth(truth)
    return path


def test_replay_over_zenoh_localizes_and_scores(office_path, office_model, tmp_path) -> None:
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh

    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    start = yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])
    flight = write_fake_flight(tmp_path / "flight.mcap", office_model, start)
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    cfg.service.perception = False
    with running_service(cfg):
        result = replay_over_zenoh(flight, loopback(connect=[f"tcp/127.0.0.1:{port}"]), "t1", TruthSource(seed=1),
                                   speed=0.0)
    assert result.frames == 45 and result.poses > 0
    assert result.localized and result.ape_rmse_m is not None and result.ape_rmse_m < 0.3
    assert result.latency_ms["n"] > 0
    assert result.wrong_localizations == 0 and result.keyframes and result.status_final == "localized"


def test_a_restarted_service_is_placed_by_its_saved_maps_views(rendered_office_flight, office_path, office_model,
                                                               tmp_path) -> None:
    """The service keeps keyframe views in its saved map; restarted, it places the first frames in them and is
    localized before any door is in range. The same saved map stripped of its views waits for the doors."""
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh

    def fly(seed: int):  # noqa: ANN202 - ZenohReplayResult
        port = free_port()
        cfg = service_config(office_path, tmp_path, port)
        with running_service(cfg):
            return replay_over_zenoh(rendered_office_flight, loopback(connect=[f"tcp/127.0.0.1:{port}"]), "t1",
                                     TruthSource(seed=seed), speed=1.0)

    first = fly(0)
    assert first.localized and first.time_to_localize_s is not None and first.time_to_localize_s > 3.0
    state = tmp_path / "t1"
    saved = SavedMapFile(tmp_path, "t1").load(office_model.sha256)
    assert saved is not None and saved.status == pb.PoseEstimate.LOCALIZED and len(saved.views) >= 5
    shutil.copytree(state, tmp_path / "kept")  # map.pb and its view log
    blind = pb.MapSnapshot.FromString((state / "map.pb").read_bytes())
    blind.ClearField("view_poses")
    (state / "map.pb").write_bytes(blind.SerializeToString())
    blind_run = fly(7)
    assert blind_run.time_to_localize_s is None or blind_run.time_to_localize_s > 3.0
    shutil.rmtree(state)
    shutil.copytree(tmp_path / "kept", state)
    again = fly(7)
    assert again.localized and again.time_to_localize_s is not None and again.time_to_localize_s < 0.5
    assert again.ape_rmse_m is not None and again.ape_rmse_m < 0.15


def test_one_saved_map_serve_s_re_localizes_a_replay_and_a_replay_s_the_service(
        rendered_office_flight, office_path, office_model, tmp_path, capsys) -> None:  # noqa: ANN001
    """One saved map for both (service.saved_map): the map `serve` saved under its state_dir, given to `replay
    --map`, localizes the replay at its first frame; a replay's `--save-map`, put where `serve` keeps its map,
    localizes the restarted service at its first frames (placed by the map's keyframe views: this flight's first
    doors come in range at 5.5 s)."""
    import json

    from macroloc.cli.main import main
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh

    def serve(state_dir: Path, seed: int):  # noqa: ANN202 - ZenohReplayResult
        port = free_port()
        with running_service(service_config(office_path, state_dir, port)):
            return replay_over_zenoh(rendered_office_flight, loopback(connect=[f"tcp/127.0.0.1:{port}"]), "t1",
                                     TruthSource(seed=seed), speed=1.0)

    def replay(*tail: str) -> dict:
        assert main(["replay", str(rendered_office_flight), "--building", str(office_path), "--json", *tail]) == 0
        return json.loads(capsys.readouterr().out)

    assert serve(tmp_path / "served", 0).localized
    by_serve = replay("--map", str(tmp_path / "served" / "t1" / "map.pb"), "--seed", "7")
    assert by_serve["time_to_localize_s"] == 0.0 and by_serve["wrong_localizations"] == 0
    assert replay("--save-map", str(tmp_path / "replayed" / "t1" / "map.pb"))["localized"]
    by_replay = serve(tmp_path / "replayed", 7)
    assert by_replay.localized and by_replay.time_to_localize_s is not None and by_replay.time_to_localize_s < 0.5
    assert by_replay.wrong_localizations == 0
