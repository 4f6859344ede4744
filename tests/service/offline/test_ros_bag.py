"""ROS 2 bags as replay sources (service/offline/ros_bag.py, service/ros_in.py): a simulated flight written as a bag
with rosbags (`.db3` and `.mcap` storage, non-default topic names, Image and CompressedImage) reads back as the native
recording's frames; a distorted bag is rectified back to the pinhole images; missing topics are one clean line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from macroloc.cli.main import main
from macroloc.proto.recording import FlightFrame, decode_image, read_flight
from macroloc.service.offline.ros_bag import BagStats, read_ros_bag
from macroloc.service.offline.ros_bag_write import BagTopics, write_ros_bag

TOPICS = BagTopics(left="/drone/stereo/left/image", right="/drone/stereo/right/image",
                   left_info="/drone/stereo/left/info", right_info="/drone/stereo/right/info", imu="/drone/imu",
                   truth="/mocap/body_in_cad")
GIVEN = {"left": TOPICS.left, "right": TOPICS.right, "imu": TOPICS.imu, "left_info": TOPICS.left_info,
         "right_info": TOPICS.right_info, "truth": TOPICS.truth}
DISTORTION = np.array([-0.28, 0.09, 0.0008, -0.0005, -0.012])  # k1, k2, p1, p2, k3: a wide-angle lens's barrel


@pytest.fixture(scope="module")
def short_flight(tmp_path_factory: pytest.TempPathFactory, fzk_path: Path) -> Path:
    """2 s of a rendered flight through FZK-Haus."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("short") / "fzk.mcap"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", str(fzk_path), "--out", str(out), "--duration", "2", "--seed", "0", "--json"]) == 0
    return out


def _same_frames(native: list[FlightFrame], bag: list[FlightFrame]) -> None:
    assert [f.stamp_ns for f in bag] == [f.stamp_ns for f in native]
    for a, b in zip(native, bag, strict=True):
        assert np.array_equal(decode_image(a.stereo.left), decode_image(b.stereo.left))
        assert np.array_equal(decode_image(a.stereo.right), decode_image(b.stereo.right))
        assert b.stereo.info == a.stereo.info
        assert [(s.header.stamp_ns, s.accel_mps2, s.gyro_radps) for s in b.imu] == \
            [(s.header.stamp_ns, s.accel_mps2, s.gyro_radps) for s in a.imu]
        assert b.ground_truth is not None and a.ground_truth is not None
        assert b.ground_truth.T_cad_body == a.ground_truth.T_cad_body


@pytest.mark.parametrize(("storage", "compressed", "single_file"), [("sqlite3", False, False),
                                                                    ("mcap", True, True)])
def test_a_bag_of_a_simulated_flight_reads_as_its_recording(short_flight: Path, tmp_path: Path, storage: str,
                                                            compressed: bool, single_file: bool) -> None:
    bag = write_ros_bag(short_flight, tmp_path / "bag", storage, TOPICS, compressed=compressed)
    path = next(bag.glob("*.mcap")) if single_file else bag  # one .mcap of ROS 2 messages opens alone
    stats = BagStats()
    frames = list(read_ros_bag(path, GIVEN, stats=stats))
    _same_frames(list(read_flight(short_flight)), frames)
    assert stats.unpaired_left == stats.unpaired_right == 0


def _copy_bag(source: Path, out: Path, keep) -> Path:  # noqa: ANN001 - keep(topic, stamp) -> bool
    from rosbags.rosbag2 import Reader, Writer

    with Reader(source) as reader, Writer(out, version=9) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
                 for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            if keep(conn.topic, stamp):
                writer.write(conns[conn.id], stamp, raw)
    return out


def test_images_without_their_partner_are_dropped_and_counted(short_flight: Path, tmp_path: Path) -> None:
    full = write_ros_bag(short_flight, tmp_path / "full", "sqlite3", TOPICS)
    dropped: list[int] = []

    def keep(topic: str, stamp: int) -> bool:
        if topic == TOPICS.right and len(dropped) < 3:
            dropped.append(stamp)  # the first three right images never arrived
            return False
        return True

    cut = _copy_bag(full, tmp_path / "cut", keep)
    stats = BagStats()
    frames = list(read_ros_bag(cut, GIVEN, stats=stats))
    assert len(frames) == len(list(read_flight(short_flight))) - 3
    assert (stats.unpaired_left, stats.unpaired_right) == (3, 0)
    assert not {f.stamp_ns for f in frames} & set(dropped)


def test_a_distorted_bag_is_rectified_back_to_the_pinhole_images(short_flight: Path, tmp_path: Path) -> None:
    bag = write_ros_bag(short_flight, tmp_path / "bag", "sqlite3", TOPICS, distortion=DISTORTION, max_frames=5)
    native = list(read_flight(short_flight))[:5]
    frames = list(read_ros_bag(bag, GIVEN))
    assert len(frames) == 5 and frames[0].stereo.info == native[0].stereo.info
    for a, b in zip(native, frames, strict=True):
        original = decode_image(a.stereo.left).astype(int)
        rectified = decode_image(b.stereo.left).astype(int)
        h, w = original.shape[:2]
        inner = (slice(h // 8, h - h // 8), slice(w // 8, w - w // 8))  # barrel distortion loses the corners
        diff = np.abs(rectified[inner] - original[inner])
        assert np.median(diff) <= 3  # grey levels: two bilinear resamplings of a noisy image
        assert np.median(np.abs(decode_image(b.stereo.left).astype(int) - np.roll(original, 3, axis=1))[inner]) \
            > np.median(diff)  # a 3 px shift is worse: the test sees misalignment


def test_the_camera_mounting_comes_from_tf_static(short_flight: Path, tmp_path: Path) -> None:
    from macroloc.proto.recording import matrix_from_pose
    from macroloc.service.ros_in import TransformTree

    frames = list(read_ros_bag(write_ros_bag(short_flight, tmp_path / "bag", "sqlite3", TOPICS, max_frames=2),
                               GIVEN))
    native = next(iter(read_flight(short_flight)))
    assert np.allclose(matrix_from_pose(frames[0].stereo.info.T_body_cam),
                       matrix_from_pose(native.stereo.info.T_body_cam))

    class Msg:  # TFMessage-like: base_link -> camera_link -> optical
        def __init__(self, parent: str, child: str, xyz: tuple[float, float, float], quat_xyzw: tuple) -> None:
            from types import SimpleNamespace as N

            t, q = N(x=xyz[0], y=xyz[1], z=xyz[2]), N(x=quat_xyzw[0], y=quat_xyzw[1], z=quat_xyzw[2], w=quat_xyzw[3])
            self.transforms = [N(header=N(frame_id=parent), child_frame_id=child,
                                 transform=N(translation=t, rotation=q))]

    tree = TransformTree()
    tree.add(Msg("base_link", "camera_link", (0.1, 0.0, 0.05), (0, 0, 0, 1)))
    tree.add(Msg("camera_link", "camera_optical", (0.0, 0.03, 0.0), (-0.5, 0.5, -0.5, 0.5)))
    T = tree.T_a_b("base_link", "camera_optical")
    assert T is not None and np.allclose(T[:3, 3], [0.1, 0.03, 0.05])
    assert np.allclose(T[:3, 2], [1, 0, 0])  # the optical z looks along the body's x
    assert tree.T_a_b("base_link", "elsewhere") is None


def test_without_camera_info_and_tf_static_the_configured_camera_is_taken(short_flight: Path, tmp_path: Path) -> None:
    from macroloc.proto.recording import matrix_from_pose
    from macroloc.service.config import CameraConfig

    full = write_ros_bag(short_flight, tmp_path / "full", "sqlite3", TOPICS, max_frames=3)
    bare = _copy_bag(full, tmp_path / "bare", lambda topic, _: topic not in ("/tf_static", TOPICS.left_info,
                                                                              TOPICS.right_info))
    T_body_cam = np.eye(4)
    T_body_cam[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    T_body_cam[:3, 3] = [0.2, 0.0, -0.05]
    camera = CameraConfig(fx=470.0, fy=470.0, baseline_m=0.1, T_body_cam=T_body_cam.tolist())
    given = {k: v for k, v in GIVEN.items() if not k.endswith("_info")}
    frame = next(iter(read_ros_bag(bare, given, camera)))
    info = frame.stereo.info
    assert (info.fx, info.baseline_m, info.width) == (470.0, 0.1, 640)
    assert np.allclose(matrix_from_pose(info.T_body_cam), T_body_cam)


def test_missing_or_wrong_topics_are_one_line_naming_what_the_bag_holds(short_flight: Path, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str],
                                                                      fzk_path: Path) -> None:
    bag = write_ros_bag(short_flight, tmp_path / "bag", "sqlite3", TOPICS, max_frames=2)
    base = ["replay", str(bag), "--building", str(fzk_path), "--observations", "perception", "--json"]
    for extra, says in (([], "no left / right / imu topic found"),
                        (["--topic", f"left={TOPICS.imu}"],
                         f"--topic left={TOPICS.imu} is of type sensor_msgs/msg/Imu"),
                        (["--topic", "left=/nope"], "--topic left=/nope is not in the bag"),
                        (["--topic", "lft=/x"], "--topic takes NAME=/ros/topic")):
        assert main(base + extra) == 2
        out, err = capsys.readouterr()
        assert out == "" and len(err.strip().splitlines()) == 1 and says in err, err
        if "found" in says or "type" in says:
            assert f"{TOPICS.left} (sensor_msgs/msg/Image)" in err
    assert main(["replay", str(bag), "--building", str(fzk_path), "--json"]) == 2  # truth needs truth features
    assert "--observations perception" in capsys.readouterr().err


FOXGLOVE_CHANNELS = {"/camera/left/image": "foxglove.CompressedImage",
                     "/camera/left/calibration": "foxglove.CameraCalibration",
                     "/camera/left/detections": "foxglove.ImageAnnotations", "/tf": "foxglove.FrameTransforms",
                     "/pose/truth": "foxglove.PoseInFrame", "/model": "foxglove.SceneUpdate",
                     "/status": "foxglove.Log"}


def test_a_bag_replays_on_the_command_line_with_its_topics_for_foxglove(short_flight: Path, tmp_path: Path,
                                                                        fzk_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_ros_bag(short_flight, tmp_path / "bag", "mcap", TOPICS, compressed=True, max_frames=12)
    argv = ["replay", str(bag), "--building", str(fzk_path), "--observations", "perception", "--json",
            "--out", str(tmp_path / "foxglove.mcap"), "--report", str(tmp_path / "report")]
    for name, topic in GIVEN.items():
        argv += ["--topic", f"{name}={topic}"]
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames"] == 12 and doc["bag"]["frames"] == 12 and doc["bag"]["unpaired_left"] == 0
    assert doc["bag"]["topics"]["truth"] == TOPICS.truth
    assert len((tmp_path / "report" / "truth_tum.txt").read_text().splitlines()) == 12
    counts, first_ns = _decode_with_embedded_schemas(tmp_path / "foxglove.mcap")
    assert {t: n for t, (n, _) in counts.items() if t in FOXGLOVE_CHANNELS} == \
        {t: counts[t][0] for t in FOXGLOVE_CHANNELS} and all(counts[t][1] == s for t, s in FOXGLOVE_CHANNELS.items())
    assert counts["/camera/left/image"][0] == counts["/tf"][0] == 12
    assert first_ns == next(iter(read_flight(short_flight))).stamp_ns  # log times are the flight's stamps


def _decode_with_embedded_schemas(path: Path) -> tuple[dict[str, tuple[int, str]], int]:
    """Every message decoded with nothing but the schema the file embeds (a fresh descriptor pool per schema):
    {topic: (messages, schema name)} and the first log time."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet
    from google.protobuf.descriptor_pool import DescriptorPool
    from google.protobuf.message_factory import GetMessageClass
    from mcap.reader import make_reader

    classes: dict[int, type] = {}
    counts: dict[str, tuple[int, str]] = {}
    first_ns = None
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            assert schema is not None and schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            if schema.id not in classes:
                pool = DescriptorPool()
                for fd in FileDescriptorSet.FromString(schema.data).file:
                    pool.Add(fd)
                classes[schema.id] = GetMessageClass(pool.FindMessageTypeByName(schema.name))
            decoded = classes[schema.id].FromString(message.data)
            assert decoded.SerializeToString() == message.data
            n, _ = counts.get(channel.topic, (0, ""))
            counts[channel.topic] = (n + 1, schema.name)
            first_ns = message.log_time if first_ns is None else first_ns
    assert first_ns is not None
    return counts, first_ns


@pytest.mark.slow  # the service's start on a fresh cache: the building's surfaces and planning grid (~40 s here)
def test_a_bag_plays_into_a_running_service_over_zenoh(short_flight: Path, tmp_path: Path, fzk_path: Path) -> None:
    """`replay BAG --over-zenoh`: the bag's frames (rectified, raw images) on the service's keys; it answers each
    with a pose, scored against the bag's truth."""
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh
    from tests.service.helpers import free_port, loopback, running_service, service_config

    bag = write_ros_bag(short_flight, tmp_path / "bag", "sqlite3", TOPICS, max_frames=10)
    port = free_port()
    cfg = service_config(fzk_path, tmp_path, port)
    cfg.service.perception = True
    with running_service(cfg):
        result = replay_over_zenoh(read_ros_bag(bag, GIVEN), loopback(connect=[f"tcp/127.0.0.1:{port}"]), "t1",
                                   None, speed=1.0)
    assert result.frames == 10 and result.poses >= 5  # a frame may be dropped by the service's ring, not most


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "bgr8", "rgb8", "png", "jpeg"])
def test_each_image_encoding_reads_as_macrolocs_images(encoding: str) -> None:
    import cv2
    from rosbags.typesys import Stores, get_typestore

    from macroloc.service.ros_in import any_image_array

    types = get_typestore(Stores.LATEST).types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="c")
    rng = np.random.default_rng(0)
    bgr = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (5, 5), 0)
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if encoding in ("png", "jpeg"):
        ok, buf = cv2.imencode("." + encoding, bgr)
        msg = types["sensor_msgs/msg/CompressedImage"](header=header, format=encoding, data=buf.ravel())
        image = any_image_array(msg, "sensor_msgs/msg/CompressedImage")
        assert image.shape == bgr.shape
        assert np.median(np.abs(image.astype(int) - bgr)) <= (0 if encoding == "png" else 8)  # JPEG of noise: lossy
        return
    mono16 = (grey.astype(np.uint16) * 256 + 7).astype(">u2")  # big-endian, the low byte below the 8 kept bits
    array = {"mono8": grey, "mono16": mono16, "bgr8": bgr, "rgb8": bgr[:, :, ::-1]}[encoding]
    raw = np.ascontiguousarray(array).view(np.uint8).reshape(48, -1)
    padded = np.hstack([raw, np.zeros((48, 4), np.uint8)])  # a row step longer than the row
    msg = types["sensor_msgs/msg/Image"](header=header, height=48, width=64, encoding=encoding,
                                         is_bigendian=int(encoding == "mono16"), step=padded.shape[1],
                                         data=padded.ravel())
    image = any_image_array(msg, "sensor_msgs/msg/Image")
    assert np.array_equal(image, grey if encoding.startswith("mono") else bgr)


@pytest.fixture(scope="module")
def office_flight_20s(tmp_path_factory: pytest.TempPathFactory, office_path: Path) -> Path:
    """20 s of Office_A seed 1, rendered: its adapted detector localizes it at 14.7 s (the service's shared 7 s
    flight ends `ambiguous` with it: its doors come in range at 5.5 s)."""
    out = tmp_path_factory.mktemp("rendered20") / "office.mcap"
    assert main(["simulate", str(office_path), "--out", str(out), "--duration", "20", "--seed", "1"]) == 0
    return out


@pytest.mark.slow  # three perception replays of a 20 s rendered flight (~1 min each on 2 idle cores)
@pytest.mark.timeout(1500)
def test_bags_of_a_flight_replay_to_the_recordings_figures(office_flight_20s: Path, office_path: Path,
                                                           tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Office_A seed 1 (20 s; the adapted detector localizes it at 14.7 s): the `.db3` bag with Image and the
    `.mcap` with CompressedImage give the native recording's frames, time to localize (within a frame) and APE
    (1 cm)."""
    from macroloc.cli.demo import bundled_detector

    rendered_office_flight = office_flight_20s

    detector = bundled_detector(office_path)
    assert detector is not None
    config = tmp_path / "detector.toml"
    config.write_text(f'[perception]\ndetector_model = "{detector}"\n')

    def replay(path: Path, topics: dict[str, str] | None) -> dict:
        argv = ["replay", str(path), "--building", str(office_path), "--observations", "perception", "--json",
                "--config", str(config)]
        for name, topic in (topics or {}).items():
            argv += ["--topic", f"{name}={topic}"]
        assert main(argv) == 0
        return json.loads(capsys.readouterr().out)

    native = replay(rendered_office_flight, None)
    assert native["localized"]
    for storage, compressed in (("sqlite3", False), ("mcap", True)):
        bag = write_ros_bag(rendered_office_flight, tmp_path / storage, storage, TOPICS, compressed=compressed)
        doc = replay(next(bag.glob("*.mcap")) if storage == "mcap" else bag, GIVEN)
        assert doc["frames"] == native["frames"] and doc["localized"]
        assert abs(doc["time_to_localize_s"] - native["time_to_localize_s"]) <= 1.5 / 30
        assert abs(doc["ape_rmse_m"] - native["ape_rmse_m"]) <= 0.01
