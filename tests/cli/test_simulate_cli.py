"""`macroloc simulate` end to end on a bundled building: JSON summary, MCAP contract, contact sheet, YOLO export."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from macroloc.cli.main import main
from macroloc.proto.recording import (
    TOPIC_GROUND_TRUTH,
    TOPIC_IMU,
    TOPIC_STEREO,
    decode_image,
    matrix_from_pose,
    read_flight,
    read_metadata,
)

SMALL_CAMERA = {"camera": {"width": 160, "height": 120, "fx": 120.0, "fy": 120.0, "cx": 79.5, "cy": 59.5}}


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory, duplex_path: Path):
    tmp = tmp_path_factory.mktemp("sim")
    cfg = tmp / "small.json"
    cfg.write_text(json.dumps(SMALL_CAMERA))
    out = tmp / "flight.mcap"
    yolo = tmp / "yolo"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["simulate", str(duplex_path), "--out", str(out), "--duration", "1.0", "--seed", "3",
                   "--config", str(cfg), "--yolo", str(yolo), "--yolo-every", "5", "--json"])
    assert rc == 0
    return out, json.loads(buf.getvalue()), yolo


def test_json_summary(flight) -> None:
    out, summary, _ = flight
    assert {"frames", "duration_s", "render_fps", "channels"} <= set(summary)
    assert summary["frames"] == 31 and summary["duration_s"] == pytest.approx(1.0)
    assert summary["render_fps"] > 0
    assert summary["channels"][TOPIC_STEREO] == 31 and summary["channels"][TOPIC_GROUND_TRUTH] == 31
    assert summary["channels"][TOPIC_IMU] == 201
    assert Path(summary["contact_sheet"]).is_file()


def test_recording_follows_the_contract(flight, duplex_model) -> None:
    out, _, _ = flight
    meta = read_metadata(out)
    assert meta.building == "duplex.ifc" and meta.seed == 3 and meta.storey and meta.building_sha256
    frames = list(read_flight(out))
    assert len(frames) == 31
    ids = {f.id for f in duplex_model.features}
    n_features = 0
    for fr in frames:
        gt = fr.ground_truth
        assert gt is not None and gt.header.stamp_ns == fr.stereo.header.stamp_ns
        assert fr.stereo.info.width == 160 and fr.stereo.info.baseline_m == pytest.approx(0.12)
        left = decode_image(fr.stereo.left)
        assert left.shape == (120, 160, 3)
        assert len(gt.corner_visible) == 4 * len(gt.features_cam)
        T_body_cam = matrix_from_pose(gt.T_body_cam)
        assert np.allclose(T_body_cam[:3, 2], [1, 0, 0]) and np.allclose(T_body_cam[:3, 0], [0, -1, 0])
        depth = decode_image(gt.depth)
        assert depth.dtype == np.float32 and depth.shape == (120, 160)
        mask = decode_image(fr.instances) if fr.instances is not None else None
        assert mask is not None and mask.max() <= len(gt.features_cam)
        for j, f in enumerate(gt.features_cam):
            assert f.id in ids and f.type in ("door", "window") and len(f.corners) == 4
            assert (mask == j + 1).any()
            n_features += 1
    assert n_features > 0  # a second of flight through the duplex sees doors or windows
    imu_total = sum(len(fr.imu) for fr in frames)
    assert imu_total >= 195  # samples up to the last frame's stamp


def test_ground_truth_corners_project_into_their_boxes(flight) -> None:
    out, _, _ = flight
    for fr in read_flight(out):
        assert fr.ground_truth is not None
        info = fr.stereo.info
        for k, f in enumerate(fr.ground_truth.features_cam):
            x0, y0, x1, y1 = f.box_xyxy
            for c, vis in zip(f.corners, fr.ground_truth.corner_visible[4 * k:4 * k + 4], strict=True):
                if vis:
                    u, v = info.fx * c.x / c.z + info.cx, info.fy * c.y / c.z + info.cy
                    assert x0 - 1 <= u <= x1 + 1 and y0 - 1 <= v <= y1 + 1


def test_yolo_export(flight) -> None:
    _, summary, yolo = flight
    images = sorted((yolo / "images").glob("*.jpg"))
    labels = sorted((yolo / "labels").glob("*.txt"))
    assert len(images) == len(labels) == 7 == summary["yolo"]["images"]
    assert (yolo / "data.yaml").read_text().count(":") >= 3
    for lab in labels:
        for line in lab.read_text().splitlines():
            cls, *box = line.split()
            assert cls in ("0", "1")
            vals = np.array(box, float)
            assert len(vals) == 4 and np.all(vals >= 0) and np.all(vals <= 1)


def test_bad_inputs_exit_2_with_one_line(tmp_path: Path, duplex_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["simulate", str(tmp_path / "absent.ifc"), "--out", str(tmp_path / "f.mcap")]) == 2
    assert main(["simulate", str(duplex_path), "--out", str(tmp_path / "f.mcap"), "--storey", "Nope"]) == 2
    assert main(["simulate", str(duplex_path), "--out", str(tmp_path / "f.mcap"), "--duration", "-1"]) == 2
    assert main(["simulate", str(duplex_path), "--out", str(tmp_path / "f.txt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("macroloc: error:") for line in err)


def test_the_appearance_seed_keeps_the_path_and_changes_only_the_look(duplex_path: Path) -> None:
    """`--appearance-seed`: the same building flown along another path. Seed 2 with the look of seed 1 flies seed
    2's path under seed 1's lights and textures."""
    from macroloc.sim.simulator import SimulationParams, Simulator

    sims = {}
    for name, seed, look in (("path 2 look 1", 2, 1), ("path 2", 2, None), ("path 1", 1, None)):
        sims[name] = Simulator(duplex_path, SimulationParams(seed=seed, appearance_seed=look))
    try:
        t = np.linspace(0.0, 3.0, 7)
        poses = {name: np.array([sim.trajectory.T_cad_body(s) for s in t]) for name, sim in sims.items()}
        assert np.allclose(poses["path 2 look 1"], poses["path 2"])
        assert not np.allclose(poses["path 2"], poses["path 1"])
        lights = {name: sim.lighting.colours for name, sim in sims.items()}
        assert np.array_equal(lights["path 2 look 1"], lights["path 1"])
        assert not np.array_equal(lights["path 2 look 1"], lights["path 2"])
    finally:
        for sim in sims.values():
            sim.close()


def test_the_recording_plays_in_foxglove_beside_its_own_channels(flight) -> None:
    """Foxglove's Image and 3D panels: the left image with its camera, the transforms cad -> body -> cam, the truth
    pose and the model, in Foxglove's own schemas, each decodable from the schema embedded in the file."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out, summary, _ = flight
    schemas: dict[str, str] = {}
    counts: dict[str, int] = {}
    with open(out, "rb") as fh:
        for schema, channel, message, decoded in make_reader(fh, decoder_factories=[DecoderFactory()]) \
                .iter_decoded_messages(topics=["/camera/left/image", "/camera/left/calibration", "/tf",
                                               "/pose/truth", "/model"]):
            schemas[channel.topic] = schema.name
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/tf":
                assert {(t.parent_frame_id, t.child_frame_id) for t in decoded.transforms} == \
                    {("cad", "body"), ("body", "cam")}
                assert decoded.transforms[0].timestamp.ToNanoseconds() == message.log_time
    assert schemas == {"/camera/left/image": "foxglove.CompressedImage",
                       "/camera/left/calibration": "foxglove.CameraCalibration", "/tf": "foxglove.FrameTransforms",
                       "/pose/truth": "foxglove.PoseInFrame", "/model": "foxglove.SceneUpdate"}
    assert counts["/camera/left/image"] == counts["/tf"] == summary["frames"] and counts["/model"] == 1
    assert len(list(read_flight(out))) == summary["frames"]  # the native reader passes over them
