"""The recording contract: what FlightWriter writes, the plain `mcap` library and read_flight read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import (
    TOPIC_GROUND_TRUTH,
    TOPIC_IMU,
    TOPIC_STEREO,
    FlightMetadata,
    FlightWriter,
    decode_image,
    encode_image,
    matrix_from_pose,
    pose_from_matrix,
    read_flight,
    read_metadata,
)


def _T(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def _write_flight(path: Path, n_frames: int = 3, imu_per_frame: int = 4) -> None:
    rng = np.random.default_rng(0)
    meta = FlightMetadata(building="duplex.ifc", building_sha256="ab" * 32, seed=7, storey="Level 1", duration_s=0.1)
    with FlightWriter(path, meta) as writer:
        for i in range(n_frames):
            stamp = (i + 1) * 33_000_000
            for k in range(imu_per_frame):
                s = stamp - (imu_per_frame - 1 - k) * 5_000_000
                writer.write_imu(pb.Imu(header=pb.Header(stamp_ns=s, frame_id="body"),
                                        accel_mps2=pb.Vector3(z=9.81), gyro_radps=pb.Vector3()))
            left = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
            writer.write_stereo(pb.StereoFrame(header=pb.Header(stamp_ns=stamp, frame_id="cam_left", seq=i),
                                               left=encode_image(left), right=encode_image(left, "raw")))
            truth = pb.GroundTruth(header=pb.Header(stamp_ns=stamp, frame_id="cad"),
                                   T_cad_body=pose_from_matrix(_T(0.1 * i, (i, 2.0, 1.4))),
                                   depth=encode_image(np.full((24, 32), 2.5, np.float32)))
            truth.features_cam.add(type="door", id=f"door{i}", box_xyxy=[1, 2, 3, 4])
            truth.corner_visible.extend([True, True, False, True])
            writer.write_ground_truth(truth, encode_image(np.zeros((24, 32), np.uint8)))


def test_pose_round_trip() -> None:
    T = _T(2.5, (1.0, -2.0, 3.0))
    assert np.allclose(matrix_from_pose(pose_from_matrix(T)), T, atol=1e-12)


@pytest.mark.parametrize("encoding", ["png", "raw"])
def test_image_round_trip_is_lossless(encoding: str) -> None:
    img = np.random.default_rng(1).integers(0, 255, (10, 12, 3), dtype=np.uint8)
    assert np.array_equal(decode_image(encode_image(img, encoding)), img)
    depth = np.random.default_rng(2).uniform(0, 9, (10, 12)).astype(np.float32)
    assert np.array_equal(decode_image(encode_image(depth)), depth)


def test_plain_mcap_library_reads_the_file(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path = tmp_path / "flight.mcap"
    _write_flight(path)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        topics = [(ch.topic, schema.name) for schema, ch, _msg, _dec in reader.iter_decoded_messages()]
        fh.seek(0)
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    assert (TOPIC_STEREO, "macroloc.v1.StereoFrame") in topics
    assert (TOPIC_IMU, "macroloc.v1.Imu") in topics
    assert (TOPIC_GROUND_TRUTH, "macroloc.v1.GroundTruth") in topics
    assert meta["macroloc"]["building"] == "duplex.ifc"
    assert set(meta["macroloc"]) >= {"building", "building_sha256", "seed", "storey", "duration_s"}


def test_read_flight_groups_frames(tmp_path: Path) -> None:
    path = tmp_path / "flight.mcap"
    _write_flight(path, n_frames=3, imu_per_frame=4)
    frames = list(read_flight(path))
    assert [f.stereo.header.seq for f in frames] == [0, 1, 2]
    assert all(len(f.imu) == 4 for f in frames)
    assert all(f.ground_truth is not None and f.instances is not None for f in frames)
    assert frames[2].ground_truth is not None and frames[2].ground_truth.features_cam[0].id == "door2"
    assert np.allclose(matrix_from_pose(frames[1].ground_truth.T_cad_body)[:3, 3], (1, 2, 1.4))  # type: ignore[union-attr]
    meta = read_metadata(path)
    assert (meta.seed, meta.storey, meta.building) == (7, "Level 1", "duplex.ifc")


def test_missing_or_bad_file_is_a_user_error(tmp_path: Path) -> None:
    from macroloc.graph.errors import UserInputError

    with pytest.raises(UserInputError):
        list(read_flight(tmp_path / "absent.mcap"))
    bad = tmp_path / "bad.mcap"
    bad.write_text("not mcap")
    with pytest.raises(UserInputError):
        list(read_flight(bad))


def test_pose_round_trip_property() -> None:
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from scipy.spatial.transform import Rotation

    floats = st.floats(-50.0, 50.0, allow_nan=False)

    @settings(max_examples=50, deadline=None)
    @given(st.tuples(floats, floats, floats), st.integers(0, 2**31 - 1))
    def check(t: tuple[float, float, float], seed: int) -> None:
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
        T[:3, 3] = t
        pose = pose_from_matrix(T)
        assert abs(pose.qw**2 + pose.qx**2 + pose.qy**2 + pose.qz**2 - 1.0) < 1e-9
        assert np.allclose(matrix_from_pose(pose), T, atol=1e-9)

    check()


def test_read_flight_gives_each_frame_the_vehicle_odometry_since_the_previous_one(tmp_path: Path) -> None:
    path = tmp_path / "flight.mcap"
    with FlightWriter(path) as writer:
        for k in range(1, 10):  # odometry at 10 ms, frames at 30, 60, 90 ms (the same stamps as three of them)
            odo = pb.Odometry(header=pb.Header(stamp_ns=k * 10_000_000, frame_id="map"),
                              T_map_body=pose_from_matrix(_T(0.0, (k, 0.0, 0.0))))
            writer.write_odometry(odo)
            if k % 3 == 0:
                writer.write_stereo(pb.StereoFrame(header=pb.Header(stamp_ns=k * 10_000_000, frame_id="cam_left")))
    frames = list(read_flight(path))
    assert [[o.header.stamp_ns // 10_000_000 for o in f.odometry] for f in frames] == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert all(matrix_from_pose(f.odometry[-1].T_map_body)[0, 3] == f.stamp_ns // 10_000_000 for f in frames)
    _write_flight(tmp_path / "no_odometry.mcap")
    assert all(f.odometry == [] for f in read_flight(tmp_path / "no_odometry.mcap"))
