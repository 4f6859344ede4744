"""Hostile input over loopback Zenoh to a running service (perception on): each bad kind is counted by key and
kind, the service stays up, poses keep coming, and no LOCALIZED pose goes out that is not finite or lies outside
the model. Issues 39 (a 390 KB PNG that decodes to 20000 x 20000 pixels crashed OpenCV's stereo matcher) and 35.
Run with -s to see the table kind -> sent -> counted -> service state."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import encode_image, vector3
from macroloc.service.config import MacrolocConfig
from tests.perception.helpers import png_bomb
from tests.service.helpers import FakeFlight, client, free_port, running_service, service_config, wait_for, yaw_T
from tests.service.test_service import Collector, _localized_at, fly

VEHICLE = "t1"


def _frame(stamp_ns: int, left: pb.Image, right: pb.Image | None = None, **info: float) -> bytes:
    camera = dict(width=left.width, height=left.height, fx=480.0, fy=480.0, cx=left.width / 2, cy=left.height / 2,
                  baseline_m=0.12) | info
    frame = pb.StereoFrame(camera_id="front", left=left, right=right or left, info=pb.CameraInfo(**camera))
    frame.header.stamp_ns = stamp_ns
    return frame.SerializeToString()


def _odometry(stamp_ns: int, x: float, extra: bytes = b"") -> bytes:
    msg = pb.Odometry()
    msg.header.stamp_ns = stamp_ns
    msg.T_map_body.position.x = x
    msg.T_map_body.qw = 1.0
    return msg.SerializeToString() + extra


def _imu(stamp_ns: int, accel_z: float, gyro_x: float = 0.0, frame: str = "body") -> bytes:
    msg = pb.Imu(accel_mps2=pb.Vector3(z=accel_z), gyro_radps=pb.Vector3(x=gyro_x))
    msg.header.stamp_ns = stamp_ns
    msg.header.frame_id = frame
    return msg.SerializeToString()


def _quaternion_odometry(stamp_ns: int, qw: float) -> bytes:
    msg = pb.Odometry()
    msg.header.stamp_ns = stamp_ns
    msg.T_map_body.qw = qw
    return msg.SerializeToString()


def _goal_stamped(stamp_ns: int) -> bytes:
    msg = pb.Goal(space_name="MENS RR")  # a space Office_A has: only the stamp is wrong
    msg.header.stamp_ns = stamp_ns
    return msg.SerializeToString()


def _three_corners() -> bytes:
    msg = pb.ObservedFeatures()
    msg.header.frame_id = "body"
    msg.header.stamp_ns = 1
    msg.features.add(type="door").corners.extend(vector3(np.array([2.0, y, 0.0])) for y in (0.0, 0.5, 0.9))
    return msg.SerializeToString()


def _features(n: int, far_m: float = 2.0, stamp_ns: int = 1, frame: str = "body") -> bytes:
    msg = pb.ObservedFeatures()
    msg.header.frame_id = frame
    msg.header.stamp_ns = stamp_ns
    for _ in range(n):
        msg.features.add(type="door").corners.extend(
            vector3(np.array([far_m, y, z])) for y, z in ((0, 0), (0.9, 0), (0.9, 2), (0, 2)))
    return msg.SerializeToString()


def hostile() -> list[tuple[str, str, str, list[bytes]]]:
    """(name, key, counted kind, payloads): every kind of bad input the service must survive."""
    bomb = png_bomb(20000, 20000)
    small = encode_image(np.zeros((48, 64), np.uint8))
    half = encode_image(np.zeros((24, 32), np.uint8))
    s = 4 * 10**9
    return [
        ("png bomb 20000x20000, declared so", "stereo", "stereo/image_too_large",
         [_frame(s + 1, pb.Image(width=20000, height=20000, encoding=pb.Image.PNG, data=bomb))]),
        ("png bomb declared 64x48", "stereo", "stereo/image_too_large",
         [_frame(s + 2, pb.Image(width=64, height=48, encoding=pb.Image.PNG, data=bomb))]),
        ("right image smaller than left", "stereo", "stereo/size_mismatch", [_frame(s + 3, small, half)]),
        ("right header smaller than declared", "stereo", "stereo/image_header",
         [_frame(s + 4, small, pb.Image(width=64, height=48, encoding=pb.Image.PNG, data=half.data))]),
        ("camera info fx = 0", "stereo", "stereo/bad_camera_info", [_frame(s + 5, small, fx=0.0)]),
        ("camera info baseline 0", "stereo", "stereo/bad_camera_info", [_frame(s + 6, small, baseline_m=0.0)]),
        ("camera info size differs", "stereo", "stereo/bad_camera_info", [_frame(s + 7, small, width=640)]),
        ("odometry x = 1e300", "odometry", "odometry/out_of_bounds", [_odometry(s, 1e300)]),
        ("odometry x = nan", "odometry", "odometry/nan", [_odometry(s, float("nan"))]),
        ("odometry stamp 2^64-1", "odometry", "odometry/future_stamp", [_odometry(2**64 - 1, 0.0)]),
        ("odometry with a field it lacks", "odometry", "odometry/unknown_fields", [_odometry(s, 0.0, b"\xa0\x06\x01")]),
        ("imu accel 1e308", "imu", "imu/implausible", [_imu(s, 1e308)]),
        ("imu payload of 2 MB", "imu", "imu/too_large", [bytes(2 * 2**20)]),
        ("goal at x = 1e300", "goal", "goal/out_of_bounds", [pb.Goal(position_cad=pb.Vector3(x=1e300))
                                                            .SerializeToString()]),
        ("goal stamp 2^64-1", "goal", "goal/future_stamp", [_goal_stamped(2**64 - 1)]),
        ("imu bytes on the goal key", "goal", "goal/wrong_frame", [_imu(s, 9.81)]),
        ("moving imu bytes on the goal key", "goal", "goal/not_protobuf", [_imu(s, 9.81, gyro_x=0.3)]),
        ("300 features in one message", "observations", "observations/too_many", [_features(300)]),
        ("a door 1e6 m away", "observations", "observations/out_of_bounds",  # its stamp as the flight's then
         [_features(1, 1e6, stamp_ns=2 * 10**9 + 17 * 10**8 + 1)]),
        ("garbage bytes on the stereo key", "stereo", "stereo/not_protobuf", [b"\xff\xff\xff\xff"]),
        ("a camera the service does not know", "stereo", "stereo/unknown_camera",
         [pb.StereoFrame(camera_id="rear", left=small, right=small).SerializeToString()]),
        ("a depth image of another size", "stereo", "stereo/bad_depth",
         [pb.StereoFrame(camera_id="front", left=small, right=small, info=pb.CameraInfo(
             width=64, height=48, fx=480.0, fy=480.0, cx=32.0, cy=24.0, baseline_m=0.12),
             depth=pb.Image(width=8, height=6, encoding=pb.Image.RAW_DEPTH_F32, data=bytes(8 * 6 * 4)))
          .SerializeToString()]),
        ("odometry with a quaternion of norm 2", "odometry", "odometry/nan", [_quaternion_odometry(s, 2.0)]),
        ("imu gyro nan", "imu", "imu/nan", [_imu(s, 9.81, gyro_x=float("nan"))]),
        ("imu gyro 1e6 rad/s", "imu", "imu/implausible", [_imu(s, 9.81, gyro_x=1e6)]),
        ("observations in an unknown frame", "observations", "observations/unknown_frame",
         [_features(1, frame="world")]),
        ("a door with three corners", "observations", "observations/bad_shape", [_three_corners()]),
        ("a goal with no target", "goal", "goal/empty", [pb.Goal().SerializeToString()]),
        ("a goal naming a feature the model lacks", "goal", "goal/unknown_target",
         [pb.Goal(feature_id="no-such-door").SerializeToString()]),
        ("a goal naming a space the model lacks", "goal", "goal/unknown_target",
         [pb.Goal(space_name="Room 9999").SerializeToString()]),
        ("garbage bytes on the observations key", "observations", "observations/not_protobuf", [b"\x0a\xff"]),
    ]


@pytest.fixture(scope="module")
def start_pose(office_model) -> np.ndarray:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    return yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])


@pytest.fixture(scope="module")
def perceiving_config(office_path, tmp_path_factory: pytest.TempPathFactory) -> MacrolocConfig:
    """The service's config with perception on (the frames would reach SGBM, LSD and the detector if let
    through); the model's solids and surfaces built once beforehand, so that the service starts from a warm
    cache (a cold build takes a minute on a busy 2-core machine)."""
    from macroloc.service.serve import build_service

    cfg = service_config(office_path, tmp_path_factory.mktemp("hostile"), free_port())
    cfg.service.perception = True
    build_service(cfg, None)
    return cfg


def test_hostile_input_is_counted_and_the_service_keeps_localizing(perceiving_config, office_model,
                                                                   start_pose) -> None:
    cfg = perceiving_config
    port = int(cfg.zenoh.listen[0].rsplit(":", 1)[1])
    rows: list[tuple[str, int, int, str]] = []
    with running_service(cfg) as service, client(port) as s:
        poses = Collector(s, f"macroloc/{VEHICLE}/pose", pb.PoseEstimate)
        diagnostics = Collector(s, f"macroloc/{VEHICLE}/diagnostics", pb.Diagnostics)
        status_at: list[float] = []
        status_sub = s.declare_subscriber(f"macroloc/{VEHICLE}/status", lambda _: status_at.append(time.monotonic()))
        answer_s: list[float] = []
        flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="a localized pose near the truth")
        counts: Callable[[], dict[str, int]] = service.drops.counts  # type: ignore[attr-defined]
        for name, key, kind, payloads in hostile():
            before = counts().get(kind, 0)
            for payload in payloads:
                s.put(f"macroloc/{VEHICLE}/{key}", payload)
            wait_for(lambda: counts().get(kind, 0) >= before + len(payloads), what=f"{name} counted")  # noqa: B023
            n = len(poses.items)
            t0 = time.monotonic()
            T = fly(s, flight, T, 2, first_stamp_ns=len(rows) * 10**8 + 10**9 * 2)
            wait_for(lambda: len(poses.items) >= n + 2, 5.0, f"poses within 5 s after {name}")  # noqa: B023
            answer_s.append(time.monotonic() - t0)
            rows.append((name, len(payloads), counts()[kind] - before, pb.PoseEstimate.Status.Name(
                poses.last().status)))
        frames_before = service.rates["stereo"].total  # type: ignore[attr-defined]
        s.put(f"macroloc/{VEHICLE}/stereo", _frame(5 * 10**9, encode_image(np.zeros((48, 64), np.uint8))))
        wait_for(lambda: service.rates["stereo"].total > frames_before, what="a good frame taken")  # type: ignore

        # the vehicle's clock restarts from zero: after a few stamps the service takes the new time base
        n = len(poses.items)
        T = fly(s, flight, T, 40, first_stamp_ns=0)
        wait_for(lambda: any(p.header.stamp_ns < 10**9 for p in poses.items[n:]), what="poses on the new clock")
        rows.append(("vehicle clock reset to 0", 40, counts().get("odometry/clock_reset", 0),
                     pb.PoseEstimate.Status.Name(poses.last().status)))
        assert counts().get("odometry/clock_reset") == 1
        wait_for(lambda: _localized_at(poses, T), what="localized again on the new clock")
        kinds = {kind for _, _, kind, _ in hostile()} | {"odometry/clock_back", "odometry/clock_reset"}
        wait_for(lambda: kinds <= set(diagnostics.last().dropped), what="every kind in the published diagnostics")
        limits = service.params.limits  # type: ignore[attr-defined]
        for p in poses.items:
            if p.status == pb.PoseEstimate.LOCALIZED:
                xyz = np.array([p.T_cad_body.position.x, p.T_cad_body.position.y, p.T_cad_body.position.z])
                assert limits.inside_cad(xyz), xyz
        status_sub.undeclare()
    gaps = np.diff(status_at)
    print(f"\nvalid input -> poses after each kind: max {max(answer_s):.2f} s; status every "
          f"{cfg.service.status_period_s} s: {len(status_at)} received, largest gap {gaps.max():.2f} s")
    assert gaps.max() < 5 * cfg.service.status_period_s, "status stopped during the hostile input"
    print("\n| kind | sent | counted | service state after |\n|---|---|---|---|")
    for name, sent, counted, state in rows:
        print(f"| {name} | {sent} | {counted} | up, {state} |")
    assert all(counted == sent for _, sent, counted, _ in rows[:-1])
