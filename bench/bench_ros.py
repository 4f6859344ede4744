"""Frame in -> pose out over Zenoh, the protobuf pose and the ROS 2 pose (CDR) of the same frames, per ROS middleware.

`macroloc serve --ros` in its own process (perception off: a frame's pose comes from odometry, so this is
transport + service + serialization); this process is the vehicle. It first localizes the service with doors
seen from the model's ground truth (Office_A, as the service tests do), then publishes odometry and a 640x480
stereo frame per stamp at 30 Hz and records, per stamp, when `macroloc/bench/pose` (protobuf PoseEstimate) and
the ROS pose (geometry_msgs/msg/PoseWithCovarianceStamped, deserialized here with rosbags) arrive: on the bridge's
key `bench/macroloc/pose` (`[ros] middleware = "bridge"`), or on rmw_zenoh's
`0/bench/macroloc/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_...` with its attachment
(`"rmw_zenoh"`). With `--middleware both` (default) one invocation runs the service once per middleware, one after
the other, on the same machine; the protobuf pose of each service run is the common reference.
With `--foxglove`, the bridge's service runs three times instead: without the live view, then with
`serve --foxglove` and a WebSocket client (`FoxgloveReader`) subscribed to every channel and reading, images at
the default [foxglove] image_rate_hz and at every frame (30 Hz).
Run: `python -m bench.bench_ros [--frames N] [--middleware bridge|rmw_zenoh|both] [--foxglove]`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bench_zenoh import _free_port, stereo_images
from macroloc.sim.vehicle import level_pose

ROOT = Path(__file__).resolve().parents[1]
OFFICE = ROOT / "data" / "buildings" / "office_a.ifc"


def _observations(model, T_cad_body: np.ndarray, stamp_ns: int, rng: np.random.Generator):  # noqa: ANN001, ANN202
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import vector3

    msg = pb.ObservedFeatures()
    msg.header.stamp_ns, msg.header.frame_id = stamp_ns, "body"
    T_body_cad = np.linalg.inv(T_cad_body)
    for f in model.features:
        d = f.centroid_cad - T_cad_body[:3, 3]
        if f.orientation != "vertical" or np.linalg.norm(d[:2]) > 9.0 or abs(d[2]) > 2.0:
            continue
        corners = f.corners_cad @ T_body_cad[:3, :3].T + T_body_cad[:3, 3] + rng.normal(0, 0.02, (4, 3))
        msg.features.add(type=f.type).corners.extend(vector3(c) for c in corners)
    return msg


def ros_pose_key(middleware: str) -> str:
    """The ROS pose's Zenoh key under each middleware (service.ros_transport)."""
    from macroloc.service.ros_transport import dds_type_name, type_hash

    typename = "geometry_msgs/msg/PoseWithCovarianceStamped"
    return f"0/bench/macroloc/pose/{dds_type_name(typename)}/{type_hash(typename)}" if middleware == "rmw_zenoh" \
        else "bench/macroloc/pose"


class FoxgloveReader:
    """A Foxglove WebSocket client (subprotocol foxglove.sdk.v1) that subscribes to every channel the server
    advertises and counts the binary messages it reads, per topic, on its own thread."""

    def __init__(self, port: int, deadline_s: float = 60.0) -> None:
        import json
        import threading

        from websockets.sync.client import connect

        self.stack = contextlib.ExitStack()  # websockets 17 wants its connection used as a context manager
        self.ws = self.stack.enter_context(connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                                   max_size=None))
        channels: dict[int, str] = {}
        end = time.monotonic() + deadline_s
        while len(channels) < 13 and time.monotonic() < end:  # service.foxglove_live's 12 protobuf + 1 JSON
            doc = self.ws.recv(timeout=max(0.01, end - time.monotonic()))
            if isinstance(doc, str) and json.loads(doc).get("op") == "advertise":
                channels.update({c["id"]: c["topic"] for c in json.loads(doc)["channels"]})
        self.topics = {i: channels[cid] for i, cid in enumerate(sorted(channels))}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": cid} for i, cid in
                                                                       enumerate(sorted(channels))]}))
        self.counts: dict[str, int] = {}
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        try:
            while True:
                frame = self.ws.recv()
                if isinstance(frame, bytes) and frame[0] == 1:
                    topic = self.topics[int.from_bytes(frame[1:5], "little")]
                    self.counts[topic] = self.counts.get(topic, 0) + 1
        except Exception:  # closed
            return


def run(frames: int, rate_hz: float = 30.0, middleware: str = "bridge", foxglove_image_hz: float | None = None
        ) -> dict:
    """One service run; `foxglove_image_hz`: with the live view ([foxglove] image_rate_hz) and a client reading
    every channel, else without."""
    import zenoh

    from macroloc.graph.bim import load_building
    from macroloc.proto.keys import Keys, declare_publisher
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import encode_image, pose_from_matrix, vector3
    from macroloc.proto.ros_types import from_cdr, stamp_ns_of
    from macroloc.service.config import ZenohConfig
    from macroloc.service.zenoh_io import session_config

    model = load_building(OFFICE)
    port = _free_port()
    env = dict(os.environ, MACROLOC_SERVICE__PERCEPTION="false", MACROLOC_SERVICE__STATUS_PERIOD_S="5",
               MACROLOC_GRAPH__SURFACE_CHECK="false", MACROLOC_ROS__MIDDLEWARE=middleware)
    fox_port = _free_port()
    if foxglove_image_hz is not None:
        env |= {"MACROLOC_FOXGLOVE__PORT": str(fox_port), "MACROLOC_FOXGLOVE__IMAGE_RATE_HZ": str(foxglove_image_hz)}
    service = subprocess.Popen([str(Path(sys.executable).parent / "macroloc"), "serve", "--building", str(OFFICE),
                                "--vehicle", "bench", "--ros", "--listen", f"tcp/127.0.0.1:{port}",
                                "--state-dir", tempfile.mkdtemp()], env=env, stderr=subprocess.DEVNULL)
    left, right, origin = stereo_images()
    template = pb.StereoFrame(camera_id="front", left=encode_image(left), right=encode_image(right))
    template.info.CopyFrom(pb.CameraInfo(width=640, height=480, fx=480, fy=480, cx=319.5, cy=239.5, baseline_m=0.12))
    keys = Keys("bench")
    got_pb: dict[int, float] = {}
    got_ros: dict[int, float] = {}
    attachments: list[int] = []  # bytes of each ROS sample's attachment (rmw_zenoh: 33)
    localized: list[bool] = []

    def on_pb(sample) -> None:  # noqa: ANN001
        t = time.perf_counter()
        msg = pb.PoseEstimate.FromString(sample.payload.to_bytes())
        got_pb.setdefault(msg.header.stamp_ns, t)
        if msg.status == pb.PoseEstimate.LOCALIZED:
            localized.append(True)

    def on_ros(sample) -> None:  # noqa: ANN001
        t = time.perf_counter()
        msg = from_cdr(sample.payload.to_bytes(), "geometry_msgs/msg/PoseWithCovarianceStamped")
        got_ros.setdefault(stamp_ns_of(msg.header.stamp), t)
        attachments.append(len(sample.attachment.to_bytes()) if sample.attachment is not None else 0)

    door = [f for f in model.features if f.type == "door" and f.storey == "Level 1"][10]
    T = level_pose(door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4], 0.3)
    out: dict = {"middleware": middleware, "images": origin, "frame_bytes": template.ByteSize(),
                 "foxglove_image_hz": foxglove_image_hz}
    reader: FoxgloveReader | None = None
    rng = np.random.default_rng(0)
    try:
        with zenoh.open(session_config(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))) as s:
            subs = [s.declare_subscriber(keys.pose, on_pb), s.declare_subscriber(ros_pose_key(middleware), on_ros)]
            stereo_pub, odo_pub = declare_publisher(s, keys.stereo), declare_publisher(s, keys.odometry)
            while not any(r.ok for r in s.liveliness().get(keys.alive, timeout=1.0)):
                if service.poll() is not None:
                    raise RuntimeError("the service exited")
            if foxglove_image_hz is not None:
                reader = FoxgloveReader(fox_port)
            for k in range(40):  # localize: odometry (= CAD here), gravity, doors in view
                stamp = (k + 1) * 33_000_000
                accel = pb.Imu(accel_mps2=vector3(T[:3, :3].T @ [0, 0, 9.81]), gyro_radps=pb.Vector3())
                accel.header.stamp_ns = stamp
                s.put(keys.imu, accel.SerializeToString())
                odo = pb.Odometry(T_map_body=pose_from_matrix(T))
                odo.header.stamp_ns = stamp
                odo_pub.put(odo.SerializeToString())
                if k % 5 == 0:
                    s.put(keys.observations, _observations(model, T, stamp, rng).SerializeToString())
                T = T @ level_pose(np.array([0.02, 0.0, 0.0]), 0.0)
                time.sleep(0.01)
            deadline = time.perf_counter() + 60
            while not localized and time.perf_counter() < deadline:
                time.sleep(0.05)
            out["localized"] = bool(localized)
            sent: dict[int, float] = {}
            t0 = time.perf_counter()
            for k in range(frames):
                stamp = 10**10 + k * 33_333_333
                odo = pb.Odometry(T_map_body=pose_from_matrix(T))
                odo.header.stamp_ns = stamp - 1
                odo_pub.put(odo.SerializeToString())
                template.header.stamp_ns = stamp
                sent[stamp] = time.perf_counter()
                stereo_pub.put(template.SerializeToString())
                delay = t0 + (k + 1) / rate_hz - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            deadline = time.perf_counter() + 5.0
            while time.perf_counter() < deadline and (max(sent) not in got_pb or max(sent) not in got_ros):
                time.sleep(0.005)
            for name, got in (("protobuf", got_pb), ("ros", got_ros)):
                lat = np.array([(got[k] - sent[k]) * 1e3 for k in sent if k in got])
                out[name] = {"answered": f"{len(lat)}/{frames}",
                             "p50_ms": round(float(np.percentile(lat, 50)), 2) if len(lat) else None,
                             "p99_ms": round(float(np.percentile(lat, 99)), 2) if len(lat) else None}
            out["ros_attachment_bytes"] = sorted(set(attachments))
            if reader is not None:
                out["foxglove_messages"] = dict(sorted(reader.counts.items()))
                reader.stack.close()
            for sub in subs:
                sub.undeclare()
    finally:
        service.send_signal(signal.SIGTERM)
        service.wait(60)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--middleware", choices=("bridge", "rmw_zenoh", "both"), default="both")
    parser.add_argument("--foxglove", action="store_true", help="the bridge without, then with the live view")
    args = parser.parse_args()
    if args.foxglove:
        from macroloc.service.config import FoxgloveConfig

        results = [run(args.frames, middleware="bridge", foxglove_image_hz=hz)
                   for hz in (None, FoxgloveConfig().image_rate_hz, 30.0)]
    else:
        middlewares = ("bridge", "rmw_zenoh") if args.middleware == "both" else (args.middleware,)
        results = [run(args.frames, middleware=m) for m in middlewares]
    print(json.dumps(results))
    for r in results:
        for name in ("protobuf", "ros"):
            live = "" if r["foxglove_image_hz"] is None else f"+foxglove {r['foxglove_image_hz']:g} Hz images"
            label = f"{r['middleware']}{live}/{name}"
            print(f"{label:>36}: frame->pose p50 {r[name]['p50_ms']} ms, p99 {r[name]['p99_ms']} ms, "
                  f"answered {r[name]['answered']} at 30 Hz")


if __name__ == "__main__":
    main()
