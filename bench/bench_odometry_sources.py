"""Issue 57: the vehicle's own odometry, three ways. The same flight is played into `macroloc serve` over Zenoh
(`replay --over-zenoh --observations truth`) once per odometry source, each run with a fresh service and state:

- `macroloc`: macroloc's own `Odometry` on `macroloc/<vehicle>/odometry` (the reference);
- `ros`: only a ROS `nav_msgs/msg/Odometry` on `/vio/odometry` over rmw_zenoh's keys (`[ros] middleware =
  "rmw_zenoh"`, `[ros] odometry`), with its attachment and liveliness (macroloc's own rmw_zenoh publisher);
- `ros-bridge`: the same message on zenoh-bridge-ros2dds's key `vio/odometry`;
- `px4`: only PX4's `fmu/out/vehicle_odometry` (`[px4] take_odometry`): the same poses turned to NED/FRD
  (`service.ned`), float32 position and quaternion, `timestamp_sample` in microseconds, bridge keys.

The poses and stamps are the same in every run (the replay's TruthSource: ground-truth sightings with realistic
errors and a drifting odometry, seeded); only the odometry's message and key differ. Every stamp of the flight
(frames, IMU, truth) is cut to whole microseconds for all sources, as on a PX4 vehicle whose cameras are stamped on
PX4's clock: `timestamp_sample` has no finer unit, and the service answers a frame at its odometry's stamp, so
with nanosecond frame stamps off the microsecond grid PX4's poses would come at stamps no frame has. Flights are
ground-truth-only recordings (sim.truth_flight, no images: the service runs without perception). The service
runs lock-step (`[service] lockstep = true`) unless `--no-lockstep`; the replay plays at `--speed` (0, the default:
as fast as the service answers, each frame's pose waited for before the next frame, as a lock-step vehicle does).

    python -m bench.bench_odometry_sources [--buildings Office_A,Jasmin-Sun] [--seeds 31] [--duration 35]
        [--sources macroloc,ros,px4] [--repeats 2] [--speed 0] [--out /tmp/macroloc-odometry-sources]

Prints one row per run: localized, time to localize (flight s), APE RMSE (m, CAD frame, no alignment), wrong
localizations, keyframes (the service's last status), frames answered, the service's odometry drops.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from macroloc.proto.recording import FlightFrame

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "bim"
BUILDINGS = {"Office_A": ROOT / "data/buildings/office_a.ifc",
             "Jasmin-Sun": SHARED / "osbim__AC90R1-Jasmin-Sun-105-2x3.ifc",
             "FZK-Haus": ROOT / "data/buildings/fzk_haus.ifc"}
SOURCES = ("macroloc", "ros", "ros-bridge", "px4")
ROS_TOPIC = "/vio/odometry"
VEHICLE = "bench"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def service_env(source: str, lockstep: bool) -> dict[str, str]:
    """The service's configuration (environment overrides) for an odometry source."""
    env = {"MACROLOC_SERVICE__PERCEPTION": "false", "MACROLOC_SERVICE__STATUS_PERIOD_S": "0.2",
           "MACROLOC_SERVICE__LOCKSTEP": str(lockstep).lower()}
    if source in ("ros", "ros-bridge"):
        env |= {"MACROLOC_ROS__ENABLED": "true", "MACROLOC_ROS__ODOMETRY": ROS_TOPIC,
                "MACROLOC_ROS__MIDDLEWARE": "rmw_zenoh" if source == "ros" else "bridge"}
    elif source == "px4":
        env |= {"MACROLOC_PX4__TAKE_ODOMETRY": "true"}
    return env


def ros_odometry_cdr(odo) -> bytes:  # noqa: ANN001 - pb.Odometry
    """nav_msgs/msg/Odometry of a wire Odometry: base_link (FLU) in the VIO's odom frame, the stamp as it is."""
    from macroloc.proto.recording import matrix_from_pose
    from macroloc.proto.ros_types import header, msg, to_cdr
    from macroloc.service.ned import quat_wxyz_from_matrix

    T = matrix_from_pose(odo.T_map_body)
    w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
    vector = msg("geometry_msgs/msg/Vector3")
    pose = msg("geometry_msgs/msg/Pose")(position=msg("geometry_msgs/msg/Point")(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                         orientation=msg("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))
    twist = msg("geometry_msgs/msg/Twist")(linear=vector(x=0.0, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.0))
    m = msg("nav_msgs/msg/Odometry")(
        header=header(odo.header.stamp_ns, "odom"), child_frame_id="base_link",
        pose=msg("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.eye(6).ravel() * 1e-4),
        twist=msg("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=np.zeros(36)))
    return to_cdr(m, "nav_msgs/msg/Odometry")


def px4_odometry_cdr(odo) -> bytes:  # noqa: ANN001 - pb.Odometry
    """px4_msgs/msg/VehicleOdometry of a wire Odometry: NED position, FRD attitude (service.ned), float32 as PX4
    sends them, timestamp_sample = the stamp in whole microseconds (PX4's unit)."""
    from macroloc.proto.recording import matrix_from_pose
    from macroloc.proto.ros_types import msg, to_cdr
    from macroloc.service.ned import T_ned_frd_from_T_enu_flu, quat_wxyz_from_matrix

    T = T_ned_frd_from_T_enu_flu(matrix_from_pose(odo.T_map_body))
    nan3 = np.full(3, np.nan, np.float32)
    us = odo.header.stamp_ns // 1000
    m = msg("px4_msgs/msg/VehicleOdometry")(
        timestamp=us, timestamp_sample=us, pose_frame=1, position=T[:3, 3].astype(np.float32),
        q=quat_wxyz_from_matrix(T[:3, :3]).astype(np.float32), velocity_frame=1, velocity=nan3,
        angular_velocity=nan3, position_variance=nan3, orientation_variance=nan3, velocity_variance=nan3,
        reset_counter=0, quality=100)
    return to_cdr(m, "px4_msgs/msg/VehicleOdometry")


def odometry_out(source: str) -> Callable | None:
    """The replay's odometry sender for a source (None: macroloc's own message)."""
    if source == "macroloc":
        return None
    from macroloc.service.odometry_in import PX4_ODOMETRY, ROS_ODOMETRY
    from macroloc.service.px4 import Px4Keys
    from macroloc.service.ros_out import RosKeys
    from macroloc.service.ros_transport import make_ros_transport

    def sender(session):  # noqa: ANN001, ANN202 - zenoh.Session -> Callable[[pb.Odometry], None]
        if source == "px4":
            transport = make_ros_transport("bridge", session)
            publisher = transport.publisher(Px4Keys("").vehicle_odometry, PX4_ODOMETRY)
            return lambda odo: publisher.put(px4_odometry_cdr(odo))
        transport = make_ros_transport("rmw_zenoh" if source == "ros" else "bridge", session, 0, "/vio")
        publisher = transport.publisher(RosKeys(VEHICLE).of(ROS_TOPIC), ROS_ODOMETRY)
        return lambda odo: publisher.put(ros_odometry_cdr(odo))

    return sender


def on_microseconds(frames: Iterable[FlightFrame]) -> Iterator[FlightFrame]:
    """The flight with every stamp cut to whole microseconds (module doc)."""
    def cut(header) -> None:  # noqa: ANN001 - pb.Header
        header.stamp_ns -= header.stamp_ns % 1000

    for frame in frames:
        frame.stamp_ns -= frame.stamp_ns % 1000
        for m in (frame.stereo, *frame.imu, *frame.odometry, frame.ground_truth):
            if m is not None:
                cut(m.header)
        yield frame


def run(flight: Path, building: Path, source: str, seed: int, lockstep: bool, speed: float) -> dict:
    """One fresh `macroloc serve` (own process, own state) and the flight played into it."""
    import zenoh

    from macroloc.proto.keys import Keys
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import read_flight
    from macroloc.service.config import ZenohConfig
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh
    from macroloc.service.zenoh_io import session_config

    port = _free_port()
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)  # noqa: SIM115 - read after the run
    service = subprocess.Popen([str(Path(sys.executable).parent / "macroloc"), "serve", "--building", str(building),
                                "--vehicle", VEHICLE, "--listen", f"tcp/127.0.0.1:{port}",
                                "--state-dir", tempfile.mkdtemp()],
                               env=dict(os.environ, **service_env(source, lockstep)), stderr=log, stdout=log)
    cfg = ZenohConfig(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], listen=[])
    drops: dict[str, int] = {}
    try:
        with zenoh.open(session_config(cfg)) as s:  # the service's drop counts, read at the end
            def on_diag(sample) -> None:  # noqa: ANN001
                drops.update(pb.Diagnostics.FromString(sample.payload.to_bytes()).dropped)

            sub = s.declare_subscriber(Keys(VEHICLE).diagnostics, on_diag)
            start = time.perf_counter()
            result = replay_over_zenoh(on_microseconds(read_flight(flight)), cfg, VEHICLE, TruthSource(seed=seed),
                                       speed=speed, wait_s=600.0, odometry_out=odometry_out(source),
                                       answered=lockstep and speed == 0)
            time.sleep(0.5)
            sub.undeclare()
    finally:
        service.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            service.wait(60)
        if service.poll() is None:
            service.kill()
    out = result.to_json()
    out["wall_s"] = round(time.perf_counter() - start, 1)
    out["drops"] = {k: v for k, v in drops.items() if v and k.split("/")[0] in ("odometry", "observations", "stereo")}
    out["log"] = log.name
    return out


def main() -> None:
    from macroloc.sim.truth_flight import write_truth_flight

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buildings", default="Office_A,Jasmin-Sun")
    parser.add_argument("--seeds", default="31")
    parser.add_argument("--duration", type=float, default=35.0)
    parser.add_argument("--sources", default="macroloc,ros,px4")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--speed", type=float, default=0.0, help="replay speed: 1 real time, 0 lock-step")
    parser.add_argument("--no-lockstep", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("/tmp/macroloc-odometry-sources"))
    parser.add_argument("--json", type=Path, help="also write every run's result here")
    args = parser.parse_args()
    sources = args.sources.split(",")
    assert all(s in SOURCES for s in sources), f"sources: {SOURCES}"
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    print(f"{'building':<11} {'seed':>4} {'odometry':<10} {'run':>3} {'localized':>9} {'t_loc s':>8} {'APE m':>7} "
          f"{'wrong':>5} {'kf':>4} {'answered':>9} {'final':>10} {'wall s':>6}  drops", flush=True)
    for name in args.buildings.split(","):
        building = BUILDINGS[name]
        for seed in (int(s) for s in args.seeds.split(",")):
            flight = args.out / f"{building.stem}-{int(args.duration)}s-{seed}.mcap"
            if not flight.exists():
                write_truth_flight(building, flight, seed=seed, duration_s=args.duration)
            for source in sources:
                for k in range(args.repeats):
                    r = run(flight, building, source, seed, not args.no_lockstep, args.speed)
                    rows.append({"building": name, "seed": seed, "source": source, "run": k + 1, **r})
                    print(f"{name:<11} {seed:>4} {source:<10} {k + 1:>3} {'yes' if r['localized'] else 'no':>9} "
                          f"{r['time_to_localize_s']!s:>8} {r['ape_rmse_m']!s:>7} {r['wrong_localizations']:>5} "
                          f"{r['keyframes']!s:>4} {r['poses']:>4}/{r['frames']:<4} {r['status_final']!s:>10} "
                          f"{r['wall_s']:>6}  {r['drops'] or ''}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
