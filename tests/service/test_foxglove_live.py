"""The operator's live view (service/foxglove_live.py): a WebSocket client speaking Foxglove's protocol (not a
browser) connects to the service's server, subscribes to every channel and decodes each message with the schema
the server advertised; a client that never reads, with the view's own thread stuck, does not hold up the frames."""

from __future__ import annotations

import base64
import contextlib
import functools
import json
import struct
import threading
import time
from typing import Any

import cv2
import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.graph.localizer import Estimate
from macroloc.graph.sightings import Sighting
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import encode_image
from macroloc.service.config import FoxgloveConfig
from macroloc.service.foxglove_live import DIAGNOSTICS, PROTOBUF_TOPICS, DroppingQueue, FoxgloveLive
from tests.service.helpers import FakeFlight, client, free_port, running_service, service_config, wait_for, yaw_T
from tests.service.test_service import Collector, fly

websockets_sync = pytest.importorskip("websockets.sync.client")
SUBPROTOCOL = "foxglove.sdk.v1"  # foxglove-sdk 0.30's server refuses a client offering only foxglove.websocket.v1


class FoxgloveClient:
    """Foxglove's WebSocket protocol from the client's side: JSON `serverInfo`/`advertise` in, `subscribe` out,
    binary message data (opcode 1, uint32 subscription id, uint64 log time, payload; little-endian) in. A reader
    thread decodes every message with the advertised schema (protobuf FileDescriptorSet, or JSON)."""

    def __init__(self, port: int, read: bool = True) -> None:
        self._stack = contextlib.ExitStack()  # websockets 17 wants its connection used as a context manager
        self.ws = self._stack.enter_context(websockets_sync.connect(
            f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None, max_queue=1 if not read else 64))
        self.channels: dict[int, dict] = {}  # channel id -> its advertisement
        self.by_sub: dict[int, dict] = {}  # subscription id -> channel
        self.messages: dict[str, list[Any]] = {}  # topic -> decoded messages
        self._classes: dict[int, Any] = {}
        self._lock = threading.Lock()
        if read:
            threading.Thread(target=self._read, daemon=True).start()

    def advertised(self) -> set[str]:
        with self._lock:
            return {c["topic"] for c in self.channels.values()}

    def subscribe_all(self) -> None:
        with self._lock:
            subs = [{"id": i, "channelId": cid} for i, cid in enumerate(sorted(self.channels))]
            self.by_sub = {s["id"]: self.channels[s["channelId"]] for s in subs}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def of(self, topic: str) -> list[Any]:
        with self._lock:
            return list(self.messages.get(topic, []))

    def read_until_advertised(self, topics: set[str], timeout_s: float = 20.0) -> None:
        """Read on this thread (for a client without a reader) until `topics` are advertised."""
        deadline = time.monotonic() + timeout_s
        while not topics <= self.advertised():
            self._handle(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))

    def _read(self) -> None:
        try:
            while True:
                self._handle(self.ws.recv())
        except Exception:  # closed
            return

    def _handle(self, frame: str | bytes) -> None:
        if isinstance(frame, str):
            doc = json.loads(frame)
            if doc.get("op") == "advertise":
                with self._lock:
                    for c in doc["channels"]:
                        self.channels[c["id"]] = c
            return
        opcode, sub_id, _log_time_ns = struct.unpack_from("<BIQ", frame)
        assert opcode == 1
        with self._lock:
            channel = self.by_sub[sub_id]
        message = self._decode(channel, frame[13:])
        with self._lock:
            self.messages.setdefault(channel["topic"], []).append(message)

    def _decode(self, channel: dict, payload: bytes) -> Any:
        if channel["encoding"] == "json":
            return json.loads(payload)
        assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
        if channel["id"] not in self._classes:  # the advertised FileDescriptorSet, not our own classes
            fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
            pool = descriptor_pool.DescriptorPool()
            for f in fds.file:
                pool.Add(f)
            self._classes[channel["id"]] = message_factory.GetMessageClass(
                pool.FindMessageTypeByName(channel["schemaName"]))
        return self._classes[channel["id"]].FromString(payload)

    def close(self) -> None:
        self._stack.close()


def _stereo(stamp_ns: int, left: np.ndarray) -> bytes:
    frame = pb.StereoFrame(camera_id="front", left=encode_image(left), right=encode_image(left),
                           info=pb.CameraInfo(width=left.shape[1], height=left.shape[0], fx=100.0, fy=100.0,
                                              cx=left.shape[1] / 2, cy=left.shape[0] / 2, baseline_m=0.12))
    frame.header.stamp_ns = stamp_ns
    return frame.SerializeToString()


def _links_end_on_opaque_features(view: FoxgloveClient, model: Any) -> bool:
    """Whether every link of the last /landmarks/links ends on the centroid of a feature the last /model shows
    opaque (linked)."""
    links, models = view.of("/landmarks/links"), view.of("/model")
    if not links or not models or not links[-1].entities[0].lines:
        return False
    opaque = {e.id.split("/", 1)[1] for e in models[-1].entities if e.cubes and e.cubes[0].color.a > 0.5}
    centroids = [f.centroid_cad for f in model.features if f.id in opaque]
    return bool(centroids) and all(min(np.linalg.norm(c - [end.x, end.y, end.z]) for c in centroids) < 1e-6
                                   for end in links[-1].entities[0].lines[0].points[1::2])


@pytest.fixture(scope="module")
def start_pose(office_model) -> np.ndarray:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    return yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])


def test_a_client_receives_every_channel_with_its_schema(office_path, office_model, start_pose, tmp_path) -> None:
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    cfg.foxglove = FoxgloveConfig(port=free_port(), image_rate_hz=100.0, pose_rate_hz=100.0)
    cfg.graph.surface_check = False  # four doors in range register without the walls' check (faster to start)
    expected = set(PROTOBUF_TOPICS) | {DIAGNOSTICS}
    with running_service(cfg), client(port) as s:
        view = FoxgloveClient(cfg.foxglove.port)
        wait_for(lambda: expected <= view.advertised(), what="every channel advertised")
        view.subscribe_all()
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: (p := poses.last()) is not None and p.status == pb.PoseEstimate.LOCALIZED, what="localized")
        s.put("macroloc/t1/goal", pb.Goal(space_name="MENS RR").SerializeToString())
        image = np.zeros((48, 64, 3), np.uint8)
        image[10:30, 20:40] = (0, 200, 255)
        for k in range(5):  # frames after the flight's last odometry: answered from it, shown in the view
            s.put("macroloc/t1/stereo", _stereo(40 * 33_000_000 + k, image))
        wait_for(lambda: all(view.of(t) for t in expected), 60.0,
                 what=f"a message on every channel (missing: {sorted(t for t in expected if not view.of(t))})")
        wait_for(lambda: view.of("/landmarks/links") and view.of("/landmarks/links")[-1].entities[0].lines,
                 what="links once localized")
        # the model is sent again after the links when the linked set changes: wait for the one that matches them
        wait_for(lambda: _links_end_on_opaque_features(view, office_model), what="links ending on opaque features")
        # the status log follows the service's status period, which may come after the pose that said localized
        wait_for(lambda: any(m.message == "status: localized" for m in view.of("/status")), what="the status log")
        view.close()

    by_topic = {c["topic"]: c for c in view.channels.values()}
    for topic, name in PROTOBUF_TOPICS.items():
        assert by_topic[topic]["schemaName"] == f"foxglove.{name}", topic
    assert by_topic[DIAGNOSTICS]["encoding"] == "json"
    # the pose, in the CAD frame, where the vehicle is
    pose = view.of("/pose/estimate")[-1]
    assert pose.frame_id == "cad"
    assert np.linalg.norm(np.array([pose.pose.position.x, pose.pose.position.y, pose.pose.position.z])
                          - T[:3, 3]) < 0.3
    ellipsoid = view.of("/pose/covariance")[-1].entities[0].spheres[0]
    assert 0 < ellipsoid.size.x < 1.0 and 0 < ellipsoid.size.z < 1.0  # 4 sigma of a localized pose: centimetres
    tf = {(t.parent_frame_id, t.child_frame_id) for m in view.of("/tf") for t in m.transforms}
    assert {("cad", "map"), ("map", "body"), ("body", "cam")} <= tf
    # the building: doors, windows and walls; the features the landmarks are linked to opaque
    model = view.of("/model")[-1]
    ids = {e.id for e in model.entities}
    assert {i for i in ids if i.startswith("door/")} and {i for i in ids if i.startswith("window/")}
    assert "walls" in ids and len(next(e for e in model.entities if e.id == "walls").lines[0].points) > 10
    opaque = {e.id.split("/", 1)[1] for e in model.entities if e.cubes and e.cubes[0].color.a > 0.5}
    landmarks = view.of("/landmarks")[-1]
    assert len(landmarks.entities) >= 3 and landmarks.entities[0].frame_id == "cad"
    links = view.of("/landmarks/links")[-1].entities[0].lines[0].points
    assert len(opaque) >= 3 and len(links) >= 6
    # the plan, the image and its (here empty: perception is off) detections, status and diagnostics
    plan = view.of("/plan")[-1]
    assert plan.frame_id == "cad" and len(plan.poses) >= 2
    jpeg = view.of("/camera/left/image")[-1]
    assert jpeg.format == "jpeg"
    assert cv2.imdecode(np.frombuffer(jpeg.data, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)
    assert view.of("/camera/left/calibration")[-1].width == 64
    assert list(view.of("/camera/left/detections")[-1].points) == []
    assert any(m.message == "status: localized" for m in view.of("/status"))
    assert view.of("/hypotheses")[-1].frame_id == "cad"  # no rival poses here: the building is not ambiguous
    diagnostics = view.of(DIAGNOSTICS)[-1]
    assert diagnostics["state"] == "localized" and diagnostics["rates_hz"]["stereo"] >= 0


def test_a_client_that_never_reads_does_not_hold_up_the_frames(office_path, tmp_path, monkeypatch) -> None:
    """The view's thread stuck (its wall loader never returns) and a client that subscribes and never reads: each
    frame is still answered and taken by the worker before the next is sent (a worker held up by the view would
    keep the next frame queued), and the view's queue drops instead."""
    stuck = threading.Event()
    monkeypatch.setattr("macroloc.service.offline.plots.load_wall_mesh", lambda path: stuck.wait(120.0))
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    cfg.foxglove = FoxgloveConfig(port=free_port(), image_rate_hz=1000.0, pose_rate_hz=1000.0, queue_size=4)
    n = 40
    try:
        with running_service(cfg) as service, client(port) as s:
            view = FoxgloveClient(cfg.foxglove.port, read=False)
            view.read_until_advertised(set(PROTOBUF_TOPICS))
            view.subscribe_all()
            wait_for(lambda: service.live.subscriptions.wanted("/camera/left/image"), what="subscribed")
            poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
            image = (np.random.default_rng(0).random((120, 160, 3)) * 255).astype(np.uint8)

            def taken(stamp: int, frames: int) -> bool:
                answered = any(p.header.stamp_ns == stamp for p in list(poses.items))
                return answered and service.rates["stereo"].total == frames and len(service.queue) == 0

            for k in range(n):
                stamp = (k + 1) * 33_000_000
                odometry = pb.Odometry()
                odometry.header.stamp_ns = stamp - 1  # the frame's own pose is then its answer's
                odometry.T_map_body.qw = 1.0
                s.put("macroloc/t1/odometry", odometry.SerializeToString())
                s.put("macroloc/t1/stereo", _stereo(stamp, image))
                wait_for(functools.partial(taken, stamp, k + 1), what=f"frame {k} answered and taken by the worker")
            diagnostics = service.diagnostics()
            assert diagnostics.dropped["queue_overrun"] == 0, "the worker was held up"
            assert service.live.queue.dropped > 0, "the view's queue should have dropped (its thread is stuck)"
            view.close()
    finally:
        stuck.set()


def test_the_dropping_queue_never_blocks_and_drops_the_oldest() -> None:
    q = DroppingQueue(3)
    for k in range(10):
        q.put(lambda k=k: k)  # type: ignore[misc]
    assert q.dropped == 7 and len(q) == 3
    assert [q.get(0.0)() for _ in range(3)] == [7, 8, 9]  # type: ignore[misc]
    assert q.get(0.0) is None


def test_images_and_poses_are_thinned_to_their_rates_and_sent_only_to_subscribers(office_model) -> None:
    """At 2 Hz images and 8 Hz poses, 3 s of 32 Hz frames and 64 Hz poses queue 6 images and 24 poses; nothing
    is queued for a channel nobody subscribes to. (Steps of 1/64 s: exact in binary, no rounding at the periods.)"""
    now_s = [0.0]
    live = FoxgloveLive(office_model, lambda: None, "127.0.0.1", free_port(), image_rate_hz=2.0, queue_size=1000,
                        pose_rate_hz=8.0, clock_s=lambda: now_s[0])
    try:
        live.queue.close()  # the view's thread stops: what is queued stays to be counted
        live._thread.join(5.0)
        live.queue.closed = False
        frame = pb.StereoFrame.FromString(_stereo(5, np.zeros((48, 64, 3), np.uint8)))
        estimate = Estimate(1, "exploring", np.eye(4))

        def run(seconds: float) -> int:
            before = len(live.queue)
            for k in range(int(seconds * 64)):  # 64 Hz poses, every other one with a frame
                now_s[0] += 1 / 64
                live.pose(estimate)
                if k % 2 == 0:
                    live.frame(frame, k, [])
            return len(live.queue) - before

        assert run(1.0) == 0  # no client
        live.subscriptions.counts.update({"/camera/left/image": 1, "/tf": 1})
        assert run(3.0) == 6 + 24
    finally:
        live.queue.closed = True
        live.server.stop()


def test_detected_boxes_are_drawn_where_the_camera_sees_them(office_model) -> None:
    """A door 4 m ahead of the camera, seen as a sighting in the body frame: its outline on the image is its
    corners projected with the frame's intrinsics."""
    live = FoxgloveLive(office_model, lambda: None, "127.0.0.1", free_port(), image_rate_hz=100.0, queue_size=8)
    try:
        view = FoxgloveClient(live.port)
        wait_for(lambda: set(PROTOBUF_TOPICS) <= view.advertised(), what="advertised")
        view.subscribe_all()
        wait_for(lambda: live.subscriptions.wanted("/camera/left/detections"), what="subscribed")
        corners_cam = np.array([[-0.5, -1.0, 4.0], [0.5, -1.0, 4.0], [0.5, 1.0, 4.0], [-0.5, 1.0, 4.0]])
        T_body_cam = forward_stereo_T_body_cam()
        corners_body = corners_cam @ T_body_cam[:3, :3].T + T_body_cam[:3, 3]
        frame = pb.StereoFrame.FromString(_stereo(5, np.zeros((480, 640, 3), np.uint8)))
        live.frame(frame, 5, [Sighting("door", corners_body)])
        wait_for(lambda: view.of("/camera/left/detections"), what="detections")
        outline = view.of("/camera/left/detections")[-1].points[0]
        uv = np.array([[p.x, p.y] for p in outline.points])
        expected = np.c_[100.0 * corners_cam[:, 0] / 4.0 + 320.0, 100.0 * corners_cam[:, 1] / 4.0 + 240.0]
        np.testing.assert_allclose(uv, expected, atol=1e-6)
        assert outline.outline_color.r > 0.8  # a door: red
        view.close()
    finally:
        live.close()


def test_demo_passes_its_foxglove_port_to_the_service(office_path, tmp_path) -> None:
    from macroloc.cli.demo import DemoParams, demo_config

    file = tmp_path / "c.toml"
    file.write_text("[foxglove]\nport = 9001\nimage_rate_hz = 5.0\n")
    cfg = demo_config(office_path, DemoParams(foxglove=8765, config=file, observations="truth"), 7447, "Level 1")
    assert (cfg.foxglove.port, cfg.foxglove.image_rate_hz) == (8765, 5.0)
    assert demo_config(office_path, DemoParams(config=file, observations="truth"), 7447, "Level 1").foxglove.port \
        == 9001  # no flag: the file's
    assert demo_config(office_path, DemoParams(observations="truth"), 7447, "Level 1").foxglove.port == 0  # off


def test_the_shipped_layout_shows_the_live_view_channels() -> None:
    """docs/foxglove_layout.json names the live view's channels (and the replay's /pose/truth), none that no one
    publishes."""
    from pathlib import Path

    layout = json.loads((Path(__file__).resolve().parents[2] / "docs" / "foxglove_layout.json").read_text())
    panels = layout["configById"]
    shown = set(panels["3D!macroloc"]["topics"]) | {panels["Image!macroloc"]["imageMode"]["imageTopic"],
                                                    panels["RosOut!macroloc"]["topicToRender"],
                                                    panels["RawMessages!macroloc"]["topicPath"]}
    shown |= set(panels["Image!macroloc"]["imageMode"]["annotations"])
    live = set(PROTOBUF_TOPICS) | {DIAGNOSTICS}
    assert shown - live == {"/pose/truth"}
    assert live - shown == {"/tf", "/camera/left/calibration"}  # the 3D panel's transforms; the Image's calibration


def test_a_port_in_use_is_one_clear_line(office_model) -> None:
    from macroloc.graph.errors import UserInputError

    first = FoxgloveLive(office_model, lambda: None, "127.0.0.1", 0, image_rate_hz=2.0, queue_size=8)
    try:
        with pytest.raises(UserInputError, match=f"cannot listen on 127.0.0.1:{first.port}: .*in use"):
            FoxgloveLive(office_model, lambda: None, "127.0.0.1", first.port, image_rate_hz=2.0, queue_size=8)
    finally:
        first.close()


def test_rival_poses_and_landmarks_before_localizing(office_model) -> None:
    """While ambiguous the rival body poses go out on /hypotheses (CAD frame); landmarks not yet in the CAD frame go
    out in "map" with no links, and the model is not re-sent for them."""
    live = FoxgloveLive(office_model, lambda: None, "127.0.0.1", 0, image_rate_hz=2.0, queue_size=8)
    try:
        view = FoxgloveClient(live.port)
        wait_for(lambda: set(PROTOBUF_TOPICS) <= view.advertised(), what="advertised")
        view.subscribe_all()
        wait_for(lambda: live.subscriptions.wanted("/hypotheses") and view.of("/model"), what="subscribed")
        diagnostics = pb.Diagnostics(state="ambiguous")
        live.status(diagnostics, pb.ServiceStatus())  # a marker: one connection's messages arrive in order
        wait_for(lambda: view.of(DIAGNOSTICS), what="the first marker")
        models_before = len(view.of("/model"))
        features = pb.ObservedFeatures()
        features.header.stamp_ns, features.header.frame_id = 7, "map"
        door = next(f for f in office_model.features if f.type == "door")
        features.features.add(type="door", id=door.id).corners.extend(
            pb.Vector3(x=c[0], y=c[1], z=c[2]) for c in door.corners_cad)
        rivals = [yaw_T(0.0, np.array([1.0, 2.0, 1.2])), yaw_T(np.pi, np.array([9.0, -2.0, 1.2]))]
        live.landmarks(features, rivals)
        live.status(diagnostics, pb.ServiceStatus())
        wait_for(lambda: view.of("/hypotheses") and len(view.of(DIAGNOSTICS)) == 2, what="hypotheses, the marker")
        hypotheses = view.of("/hypotheses")[-1]
        assert hypotheses.frame_id == "cad" and len(hypotheses.poses) == 2
        assert [(p.position.x, p.position.y) for p in hypotheses.poses] == [(1.0, 2.0), (9.0, -2.0)]
        assert abs(abs(hypotheses.poses[1].orientation.z) - 1.0) < 1e-9  # half a turn about z
        assert view.of("/landmarks")[-1].entities[0].frame_id == "map"
        assert not view.of("/landmarks/links")[-1].entities[0].lines  # no links before the CAD frame
        assert len(view.of("/model")) == models_before  # nothing linked: the model is not sent again
        view.close()
    finally:
        live.close()
