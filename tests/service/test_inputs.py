"""service.inputs: every kind of bad input is refused at the edge and counted by key and kind; good input passes.
(Over loopback Zenoh with a running service: tests/service/test_hostile_inputs.py.)"""

from __future__ import annotations

import json

import numpy as np
import pytest

from macroloc.graph.errors import UserInputError
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import decode_image, encode_image, pose_from_matrix, vector3
from macroloc.service.health import DropCounter
from macroloc.service.inputs import InputLimits, InputParser
from tests.perception.helpers import png_bomb

BOUNDS = (np.array([-10.0, -10.0, -5.0]), np.array([30.0, 20.0, 15.0]))
LIMITS = InputLimits(bounds_cad=BOUNDS, max_odometry_m=60.0)


def _parser(limits: InputLimits = LIMITS) -> tuple[InputParser, DropCounter]:
    drops = DropCounter()
    return InputParser(["front"], drops, limits), drops


def info(width: int = 64, height: int = 48, **kw: float) -> pb.CameraInfo:
    values = dict(fx=60.0, fy=60.0, cx=31.5, cy=23.5, baseline_m=0.12) | kw
    return pb.CameraInfo(width=width, height=height, **values)


def stereo(stamp_ns: int = 1, left: pb.Image | None = None, right: pb.Image | None = None,
           camera: pb.CameraInfo | None = None) -> bytes:
    image = encode_image(np.zeros((48, 64), np.uint8))
    frame = pb.StereoFrame(camera_id="front", left=left or image, right=right or image)
    if camera is not None:
        frame.info.CopyFrom(camera)
    frame.header.stamp_ns = stamp_ns
    return frame.SerializeToString()


def odometry(stamp_ns: int, xyz: tuple[float, float, float] = (1.0, 2.0, 0.5)) -> bytes:
    T = np.eye(4)
    T[:3, 3] = xyz
    msg = pb.Odometry(T_map_body=pose_from_matrix(T))
    msg.header.stamp_ns = stamp_ns
    return msg.SerializeToString()


def imu(stamp_ns: int, accel: tuple[float, float, float] = (0.0, 0.0, 9.81), frame: str = "body",
        gyro_x: float = 0.01) -> bytes:
    msg = pb.Imu(accel_mps2=vector3(np.array(accel)), gyro_radps=pb.Vector3(x=gyro_x))
    msg.header.stamp_ns = stamp_ns
    msg.header.frame_id = frame
    return msg.SerializeToString()


def test_good_frames_pass_and_a_frame_without_camera_info_is_taken() -> None:
    parser, drops = _parser()
    assert parser.stereo(stereo(1, camera=info()), 0) is not None
    assert parser.stereo(stereo(2), 0) is not None  # no calibration: a pose from the odometry, nothing perceived
    raw = encode_image(np.zeros((48, 64, 3), np.uint8), "raw")
    assert parser.stereo(stereo(3, raw, raw, info()), 0) is not None
    assert drops.counts() == {}


@pytest.mark.parametrize(("kind", "payload"), [
    ("image_too_large", lambda: stereo(1, pb.Image(width=20000, height=20000, encoding=pb.Image.PNG,
                                                  data=png_bomb(20000, 20000)),
                                       pb.Image(width=20000, height=20000, encoding=pb.Image.PNG,
                                                data=png_bomb(20000, 20000)))),
    ("image_too_large", lambda: stereo(1, pb.Image(width=64, height=48, encoding=pb.Image.PNG,
                                                  data=png_bomb(20000, 20000)))),  # declared small, is a bomb
    ("image_header", lambda: stereo(1, pb.Image(width=64, height=48, encoding=pb.Image.JPEG, data=b"\xff\xd8junk"))),
    ("size_mismatch", lambda: stereo(1, right=encode_image(np.zeros((24, 32), np.uint8)))),
    ("image_header", lambda: stereo(1, right=pb.Image(width=64, height=48, encoding=pb.Image.PNG,
                                                      data=encode_image(np.zeros((24, 32), np.uint8)).data))),
    ("bad_image", lambda: stereo(1, pb.Image(width=64, height=48, encoding=pb.Image.RAW_MONO8, data=b"x"))),
    ("bad_camera_info", lambda: stereo(1, camera=info(fx=0.0))),
    ("bad_camera_info", lambda: stereo(1, camera=info(baseline_m=0.0))),
    ("bad_camera_info", lambda: stereo(1, camera=info(fy=float("nan")))),
    ("bad_camera_info", lambda: stereo(1, camera=info(width=640, height=480))),
    ("unknown_camera", lambda: pb.StereoFrame(camera_id="rear").SerializeToString()),
])
def test_bad_frames_never_reach_a_decoder(kind: str, payload) -> None:  # noqa: ANN001 - a payload factory
    parser, drops = _parser()
    assert parser.stereo(payload(), 0) is None
    assert drops.counts() == {f"stereo/{kind}": 1}


def test_recorded_images_are_checked_before_decoding() -> None:
    bomb = pb.Image(width=20000, height=20000, encoding=pb.Image.PNG, data=png_bomb(20000, 20000))
    with pytest.raises(UserInputError, match="cap"):
        decode_image(bomb)
    with pytest.raises(UserInputError, match="header says 20000x20000"):
        decode_image(pb.Image(width=64, height=48, encoding=pb.Image.PNG, data=bomb.data))
    with pytest.raises(UserInputError, match="raw image"):
        decode_image(pb.Image(width=64, height=48, encoding=pb.Image.RAW_MONO8, data=b"xx"))
    assert decode_image(encode_image(np.zeros((48, 64), np.uint8))).shape == (48, 64)


def test_values_beyond_what_a_vehicle_sends_are_refused() -> None:
    parser, drops = _parser()
    assert parser.odometry(odometry(1)) is not None
    assert parser.odometry(odometry(2, (1e300, 0.0, 0.0))) is None
    assert parser.odometry(odometry(3, (70.0, 0.0, 0.0))) is None  # beyond the model's diagonal + margin
    assert parser.imu(imu(1, (0.0, 0.0, 1e308))) is None
    assert parser.imu(imu(2)) is not None
    goal = pb.Goal(position_cad=pb.Vector3(x=1e300))
    assert parser.goal(goal.SerializeToString()) is None
    assert parser.goal(pb.Goal(position_cad=pb.Vector3(x=40.0)).SerializeToString()) is None
    assert parser.goal(pb.Goal(position_cad=pb.Vector3(x=25.0)).SerializeToString()) is not None
    obs = pb.ObservedFeatures()
    obs.header.frame_id = "body"
    obs.features.add(type="door").corners.extend(vector3(np.array([80.0, y, z])) for y, z in
                                                 ((0, 0), (1, 0), (1, 2), (0, 2)))
    assert parser.observations(obs.SerializeToString()).features == []  # type: ignore[union-attr]
    many = pb.ObservedFeatures()
    for _ in range(LIMITS.max_features + 1):
        many.features.add(type="window", centroid=pb.Vector3(x=1.0))
    assert parser.observations(many.SerializeToString()) is None
    assert drops.counts() == {"odometry/out_of_bounds": 2, "imu/implausible": 1, "goal/out_of_bounds": 2,
                              "observations/out_of_bounds": 1, "observations/too_many": 1}


def test_a_message_of_another_type_or_with_garbage_is_refused() -> None:
    parser, drops = _parser()
    assert parser.goal(imu(5)) is None  # an Imu on the goal key: its gyro (field 3) is no UTF-8 feature id,
    assert parser.goal(imu(5, gyro_x=0.0)) is None  # a still one's header says "body",
    assert parser.goal(imu(5, frame="", gyro_x=0.0)) is None  # and without a frame its feature id is empty
    assert parser.odometry(odometry(1) + b"\xa0\x06\x01") is None  # field 100, a varint: not an Odometry's
    assert parser.imu(b"\x08" * 10) is None
    assert parser.imu(bytes(LIMITS.max_message_bytes + 1)) is None
    counts = drops.counts()
    assert counts["goal/not_protobuf"] == 1 and counts["goal/wrong_frame"] == 1 and counts["goal/empty"] == 1
    assert counts["odometry/unknown_fields"] == 1 and counts["imu/too_large"] == 1 and sum(counts.values()) == 6, \
        counts


def test_a_clock_reset_starts_a_new_time_base_and_a_future_stamp_blocks_nothing() -> None:
    resets: list[tuple[str, int]] = []
    drops = DropCounter()
    parser = InputParser(["front"], drops, LIMITS, on_clock_reset=lambda key, stamp: resets.append((key, stamp)))
    base = 1_000 * 10**9
    for k in range(5):
        assert parser.odometry(odometry(base + k * 10**8)) is not None
    assert parser.odometry(odometry(2**64 - 1)) is None  # absurd: refused, so it cannot hold the key shut
    assert parser.odometry(odometry(base + 10**9)) is not None
    assert parser.odometry(odometry(base + 10**9 - 10**8)) is None  # plain reordering
    taken = [parser.odometry(odometry(10**8 * (k + 1))) is not None for k in range(5)]  # the clock restarted
    assert taken == [False, False, True, True, True]
    assert resets == [("odometry", 3 * 10**8)]
    hour_ns = 3600 * 10**9  # one stamp an hour ahead (within the clock's reach) is taken, and then outlived
    assert parser.odometry(odometry(hour_ns)) is not None
    assert [parser.odometry(odometry(10**9 + k * 10**8)) is not None for k in range(4)] == [False, False, True, True]
    assert drops.counts() == {"odometry/future_stamp": 1, "odometry/out_of_order": 1, "odometry/clock_back": 4,
                              "odometry/clock_reset": 2}


def test_a_goal_stamped_beyond_the_clock_is_refused_as_every_input_is() -> None:
    """Issue 57 item 6: a goal stamped 2^64-1 (or a day and more ahead) is refused and counted as goal/future_stamp,
    as odometry, IMU, observations and frames are; an unstamped goal and one an hour ahead are taken, in any order."""
    now_ns = 1_800_000_000 * 10**9
    drops = DropCounter()
    parser = InputParser(["front"], drops, LIMITS)
    parser.stamps.now_ns = lambda: now_ns

    def goal(stamp_ns: int) -> bytes:
        msg = pb.Goal(position_cad=pb.Vector3(x=25.0))
        msg.header.stamp_ns = stamp_ns
        return msg.SerializeToString()

    assert parser.goal(goal(2**64 - 1)) is None
    assert parser.goal(goal(now_ns + 86_400 * 10**9 + 1)) is None
    assert parser.goal(goal(now_ns + 3600 * 10**9)) is not None
    assert parser.goal(goal(0)) is not None  # unstamped
    assert parser.goal(goal(now_ns)) is not None
    assert drops.counts() == {"goal/future_stamp": 2}


def test_a_replayed_recording_s_bomb_is_refused_before_decoding_and_counted(office_path, tmp_path, capsys) -> None:
    """The offline path is the service's: `macroloc replay` hands recorded frames to the service's parser, which
    refuses a frame whose PNG would decode to 20000 x 20000 pixels before decoding it (here the visual odometry
    would have decoded it), as it refuses one sent on the wire; the replay goes on and its JSON counts it."""
    from macroloc.cli.main import main
    from macroloc.proto.recording import FlightWriter

    bomb = pb.Image(width=640, height=480, encoding=pb.Image.PNG, data=png_bomb(20000, 20000))
    flight = tmp_path / "bomb.mcap"
    with FlightWriter(flight) as writer:
        frame = pb.StereoFrame(header=pb.Header(stamp_ns=10**8), camera_id="front", left=bomb, right=bomb,
                               info=info(640, 480, fx=480.0, fy=480.0, cx=319.5, cy=239.5))
        writer.write_stereo(frame)
        writer.write_ground_truth(pb.GroundTruth(header=pb.Header(stamp_ns=10**8), T_cad_body=pose_from_matrix(
            np.eye(4)), T_body_cam=pose_from_matrix(np.eye(4))))
    rc = main(["replay", str(flight), "--building", str(office_path), "--observations", "truth-vo", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert rc == 0 and doc["frames"] == 1 and not doc["localized"]
    assert sum(n for kind, n in doc["dropped"].items() if kind.startswith("stereo/image")) == 1, doc["dropped"]


def test_no_pose_outside_the_model_or_not_finite_goes_out() -> None:
    from macroloc.graph.localizer import Estimate
    from macroloc.service.front_end import plausible

    def est(xyz: tuple[float, float, float], cov: float = 0.01) -> Estimate:
        T = np.eye(4)
        T[:3, 3] = xyz
        return Estimate(1, "localized", np.eye(4), T_cad_body=T, T_cad_map=np.eye(4), covariance=np.full((6, 6), cov))

    assert plausible(est((1.0, 2.0, 1.0)), LIMITS)
    assert plausible(Estimate(1, "exploring", np.eye(4)), LIMITS)  # no CAD pose yet
    for bad in (est((1e297, 0.0, 0.0)), est((np.nan, 0.0, 0.0)), est((0.0, 0.0, 100.0)), est((1.0, 2.0, 1.0), np.inf)):
        assert not plausible(bad, LIMITS)


def test_the_pixel_cap_is_a_config_key_that_dump_config_shows(capsys, monkeypatch) -> None:
    import json

    from macroloc.cli.main import main
    from macroloc.service.config import load_config
    from macroloc.service.inputs import limits_from_config

    assert main(["dump-config"]) == 0
    assert json.loads(capsys.readouterr().out)["inputs"]["max_image_pixels"] == 4096 * 4096
    monkeypatch.setenv("MACROLOC_INPUTS__MAX_IMAGE_PIXELS", "3072")
    limits = limits_from_config(load_config().inputs)
    assert limits.max_image_pixels == 3072
    parser = InputParser(["front"], DropCounter(), limits)
    assert parser.stereo(stereo(1), 0) is not None  # 64 x 48 = 3072 pixels
    image = encode_image(np.zeros((48, 65), np.uint8))
    assert parser.stereo(stereo(2, image, image), 0) is None
