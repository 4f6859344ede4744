"""The operator's live view: Foxglove's WebSocket server (foxglove-sdk) beside the running service.

`macroloc serve --foxglove PORT` (`[foxglove] port`) serves ws://<host>:<port> (loopback unless `[foxglove] host`
says otherwise); Foxglove opens it with docs/foxglove_layout.json. The messages are built by
service.foxglove_channels's `FoxgloveChannels` (the conversions a replay writes to MCAP), protobuf-encoded with
Foxglove's own schemas, plus one JSON channel:
  /model                    foxglove.SceneUpdate      walls (cut at the flight's height), doors (red), windows (blue);
                                                      the features linked to a landmark opaque
  /landmarks                foxglove.SceneUpdate      the flight's landmarks ("cad" once localized, else "map")
  /landmarks/links          foxglove.SceneUpdate      landmark -> the model feature it is linked to
  /pose/estimate            foxglove.PoseInFrame      the body in the CAD frame (once localized), at most pose_rate_hz
  /pose/covariance          foxglove.SceneUpdate      its position covariance, a 2-sigma ellipsoid
  /tf                       foxglove.FrameTransforms  cad -> map (once localized), map -> body, body -> cam
  /hypotheses               foxglove.PosesInFrame     the rival body poses while 'ambiguous' (none while 'exploring':
                                                      the localizer keeps no rival poses before a registration)
  /plan                     foxglove.PosesInFrame     the waypoints with their yaws
  /camera/left/image        foxglove.CompressedImage  the left image, at most `image_rate_hz`
  /camera/left/calibration  foxglove.CameraCalibration
  /camera/left/detections   foxglove.ImageAnnotations that frame's detected doors/windows, outlined
  /status                   foxglove.Log              the localizer's status, at each change
  /diagnostics              JSON                      state, rates, latencies, drops (the Diagnostics message's)

Cost rule: the service's threads only hand a closure to a `DroppingQueue` (it never waits: beyond `queue_size` the
oldest is dropped and counted), and only for channels some client subscribes to (the periodic status excepted: its
last /status is kept for later clients); the view's own thread builds the messages (JPEG, protobuf) and gives them
to the server, whose per-client buffer drops a slow client's oldest messages (foxglove-sdk's
`message_backlog_size`). Images are thinned to `image_rate_hz`, poses (with /tf and the covariance) to
`pose_rate_hz`, on this machine's clock. /model and /status are sent again when a client subscribes to them (the
server keeps no message for late subscribers).
"""

from __future__ import annotations

import importlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol, cast

import numpy as np
from mcap_protobuf.schema import build_file_descriptor_set

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel
from macroloc.graph.localizer import Estimate
from macroloc.graph.sightings import Sighting
from macroloc.graph.wall_mesh import wall_segments_xy
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose
from macroloc.service.foxglove_channels import FoxgloveChannels

log = logging.getLogger(__name__)

PROTOBUF_TOPICS = {  # topic -> Foxglove schema (foxglove_schemas_protobuf.<name>_pb2.<name>)
    "/model": "SceneUpdate", "/landmarks": "SceneUpdate", "/landmarks/links": "SceneUpdate",
    "/pose/estimate": "PoseInFrame", "/pose/covariance": "SceneUpdate", "/tf": "FrameTransforms",
    "/hypotheses": "PosesInFrame", "/plan": "PosesInFrame", "/camera/left/image": "CompressedImage",
    "/camera/left/calibration": "CameraCalibration", "/camera/left/detections": "ImageAnnotations",
    "/status": "Log",
}
DIAGNOSTICS = "/diagnostics"
DIAGNOSTICS_SCHEMA = {"type": "object", "properties": {
    "state": {"type": "string"}, "rates_hz": {"type": "object"}, "latencies_ms": {"type": "object"},
    "dropped": {"type": "object"}, "counts": {"type": "object"}, "keyframes": {"type": "integer"},
    "landmarks": {"type": "integer"}, "live_view_dropped": {"type": "integer"}}}
RESENT_ON_SUBSCRIBE = ("/model", "/status")
POSE_TOPICS = ("/pose/estimate", "/pose/covariance", "/tf")
IMAGE_TOPICS = ("/camera/left/image", "/camera/left/calibration", "/camera/left/detections")
MAP_TOPICS = ("/landmarks", "/landmarks/links", "/hypotheses", "/model")


class LiveView(Protocol):
    """What the service (service.node) hands the live view; every call returns at once."""

    def pose(self, est: Estimate) -> None: ...

    def waypoints(self, msg: pb.Waypoints) -> None: ...

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None: ...

    def frame(self, frame: pb.StereoFrame, stamp_ns: int, sightings: list[Sighting]) -> None:
        """A perceived stereo frame and its sightings (corners in the body frame)."""

    def landmarks(self, features: pb.ObservedFeatures, rivals_cad_body: list[np.ndarray]) -> None:
        """The landmarks (CAD frame with their linked feature ids once localized, else the odometry frame "map")
        and the rival body poses (4x4, CAD frame) an 'ambiguous' registration left."""

    def close(self) -> None: ...


class NullLiveView:
    """No live view ([foxglove] port = 0)."""

    def pose(self, est: Estimate) -> None:
        pass

    def waypoints(self, msg: pb.Waypoints) -> None:
        pass

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        pass

    def frame(self, frame: pb.StereoFrame, stamp_ns: int, sightings: list[Sighting]) -> None:
        pass

    def landmarks(self, features: pb.ObservedFeatures, rivals_cad_body: list[np.ndarray]) -> None:
        pass

    def close(self) -> None:
        pass


class DroppingQueue:
    """Work for one consumer thread. `put` never blocks: a full queue drops its oldest item (counted in
    `dropped`); `get` returns None after `timeout_s`, or at once once closed and empty."""

    def __init__(self, size: int) -> None:
        self._items: deque[Callable[[], None]] = deque()
        self._size = size
        self._cv = threading.Condition()
        self.dropped = 0
        self.closed = False

    def put(self, item: Callable[[], None]) -> None:
        with self._cv:
            if len(self._items) >= self._size:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cv.notify()

    def get(self, timeout_s: float) -> Callable[[], None] | None:
        with self._cv:
            if not self._items and not self.closed:
                self._cv.wait(timeout_s)
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()

    def __len__(self) -> int:
        return len(self._items)


class _Subscriptions:
    """foxglove-sdk's ServerListener: how many clients subscribe to each topic; `on_subscribe(topic)` runs on
    each new subscription (on the server's thread: it must only queue)."""

    def __init__(self, on_subscribe: Callable[[str], None]) -> None:
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self._on_subscribe = on_subscribe

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self.counts[channel.topic] = self.counts.get(channel.topic, 0) + 1
        self._on_subscribe(channel.topic)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self.counts[channel.topic] = max(0, self.counts.get(channel.topic, 0) - 1)

    def wanted(self, *topics: str) -> bool:
        return any(self.counts.get(t, 0) > 0 for t in topics)


class FoxgloveLive:
    """The live view of the module doc: a foxglove-sdk WebSocket server on its own context, and a thread that
    turns the service's estimates, plans, frames and landmarks into its channels. `walls`: loads the building's
    wall mesh (graph.wall_mesh.load_wall_mesh), called once on the view's thread."""

    def __init__(self, model: BuildingModel, walls: Callable[[], Any], host: str, port: int, image_rate_hz: float,
                 queue_size: int, pose_rate_hz: float = 10.0, clock_s: Callable[[], float] = time.monotonic) -> None:
        import foxglove  # the optional extra (macroloc[foxglove]): imported only where a live view is asked for


        self.model, self._load_walls, self._clock_s = model, walls, clock_s
        self._image_period_s = 1.0 / image_rate_hz if image_rate_hz > 0 else float("inf")
        self._last_image_s = -np.inf
        self._pose_period_s = 1.0 / pose_rate_hz if pose_rate_hz > 0 else float("inf")
        self._last_pose_s = -np.inf
        self._T_body_cam = forward_stereo_T_body_cam()  # the simulator's, until a frame gives its own
        self._features = {f.id: f for f in model.features}
        self._wall_mesh: Any = None
        self._walls_loaded = False
        self._matched: set[str] = set()
        self._last_state = ""
        self._pose_z_m: float | None = None  # the flight's height (CAD z) where localized: the walls' cut
        self._sent: dict[str, tuple[bytes, int]] = {}  # the last /model and /status, for late subscribers
        self.queue = DroppingQueue(queue_size)
        self.context = foxglove.Context()
        self._channels = {topic: foxglove.Channel(topic, schema=_protobuf_schema(foxglove, name),
                                                  message_encoding="protobuf", context=self.context)
                          for topic, name in PROTOBUF_TOPICS.items()}
        self._diagnostics = foxglove.Channel(DIAGNOSTICS, schema=DIAGNOSTICS_SCHEMA, message_encoding="json",
                                             context=self.context)
        self.out = FoxgloveChannels(self._write)
        self.subscriptions = _Subscriptions(self._subscribed)
        try:
            # foxglove.ServerListener is a Protocol whose other callbacks the server treats as absent: duck-typed
            self.server = foxglove.start_server(name="macroloc", host=host, port=port, context=self.context,
                                                server_listener=cast(Any, self.subscriptions))
        except Exception as exc:  # the port taken, the address not this machine's
            raise UserInputError(f"the Foxglove live view cannot listen on {host}:{port}: {exc}") from None
        self.port = self.server.port
        self._thread = threading.Thread(target=self._serve, name="foxglove", daemon=True)
        self._thread.start()
        self.queue.put(self._send_model)
        log.info("Foxglove live view on ws://%s:%d", host, self.port)

    # --- called by the service's threads: queue only ------------------------------------------------------------

    def pose(self, est: Estimate) -> None:
        """Thinned to `pose_rate_hz` of this machine's clock, and only while a client subscribes."""
        now_s = self._clock_s()
        if now_s - self._last_pose_s < self._pose_period_s or not self.subscriptions.wanted(*POSE_TOPICS):
            return
        self._last_pose_s = now_s
        self.queue.put(lambda: self._pose(est))

    def waypoints(self, msg: pb.Waypoints) -> None:
        if self.subscriptions.wanted("/plan"):
            self.queue.put(lambda: self._plan(msg))

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        self.queue.put(lambda: self._status(diag, status))  # also keeps /status's last message for late clients

    def frame(self, frame: pb.StereoFrame, stamp_ns: int, sightings: list[Sighting]) -> None:
        """Thinned to `image_rate_hz` of this machine's clock, and only while a client subscribes."""
        now_s = self._clock_s()
        if now_s - self._last_image_s < self._image_period_s or not self.subscriptions.wanted(*IMAGE_TOPICS):
            return
        self._last_image_s = now_s
        self.queue.put(lambda: self._frame(frame, stamp_ns, sightings))

    def landmarks(self, features: pb.ObservedFeatures, rivals_cad_body: list[np.ndarray]) -> None:
        if self.subscriptions.wanted(*MAP_TOPICS):
            self.queue.put(lambda: self._landmarks(features, rivals_cad_body))

    def close(self) -> None:
        """Stop the view's thread (what is queued is dropped) and the server."""
        self.queue.close()
        self._thread.join(timeout=5.0)
        self.server.stop()

    # --- the view's thread --------------------------------------------------------------------------------------

    def _serve(self) -> None:
        while not self.queue.closed:
            item = self.queue.get(timeout_s=0.5)
            if item is None:
                continue
            try:
                item()
            except Exception:  # a message that fails to build must not end the view
                log.exception("live view: a message failed")

    def _subscribed(self, topic: str) -> None:
        if topic in RESENT_ON_SUBSCRIBE:
            self.queue.put(lambda: self._resend(topic))

    def _resend(self, topic: str) -> None:
        if topic in self._sent:
            data, stamp_ns = self._sent[topic]
            self._channels[topic].log(data, log_time=stamp_ns)

    def _write(self, topic: str, message: Any, stamp_ns: int) -> None:
        data = message.SerializeToString()
        self._channels[topic].log(data, log_time=int(stamp_ns))
        if topic in RESENT_ON_SUBSCRIBE:
            self._sent[topic] = (data, int(stamp_ns))

    def _pose(self, est: Estimate) -> None:
        s = est.stamp_ns
        self.out.transforms(s, est.T_map_body, self._T_body_cam, est.T_cad_map)
        if est.T_cad_body is not None:
            self._pose_z_m = float(est.T_cad_body[2, 3])
            self.out.pose("/pose/estimate", s, est.T_cad_body)
            if est.covariance is not None:
                self.out.covariance(s, est.T_cad_body, est.covariance)

    def _plan(self, msg: pb.Waypoints) -> None:
        Ts = []
        for p, yaw in zip(msg.points_cad, msg.yaw_rad if len(msg.yaw_rad) == len(msg.points_cad) else
                          [0.0] * len(msg.points_cad), strict=True):
            c, s = np.cos(yaw), np.sin(yaw)  # yaw about the CAD frame's z (up)
            T = np.eye(4)
            T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
            T[:3, 3] = [p.x, p.y, p.z]
            Ts.append(T)
        self.out.poses("/plan", msg.header.stamp_ns, Ts)

    def _status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        s = diag.header.stamp_ns  # this machine's clock
        if diag.state != self._last_state:
            self.out.status(s, diag.state)
            self._last_state = diag.state
        self._diagnostics.log({"state": diag.state, "rates_hz": dict(diag.rates_hz),
                               "latencies_ms": dict(diag.latencies_ms), "dropped": dict(diag.dropped),
                               "counts": dict(diag.counts), "keyframes": status.keyframes,
                               "landmarks": status.landmarks, "live_view_dropped": self.queue.dropped}, log_time=s)

    def _frame(self, frame: pb.StereoFrame, stamp_ns: int, sightings: list[Sighting]) -> None:
        info = frame.info
        if info.HasField("T_body_cam"):
            self._T_body_cam = matrix_from_pose(info.T_body_cam)
        T_cam_body = np.linalg.inv(self._T_body_cam)
        self.out.image(frame, stamp_ns)
        self.out.detections(stamp_ns, info, [(x.type, x.corners_body @ T_cam_body[:3, :3].T + T_cam_body[:3, 3])
                                             for x in sightings])

    def _landmarks(self, features: pb.ObservedFeatures, rivals_cad_body: list[np.ndarray]) -> None:
        s, frame_id = features.header.stamp_ns, features.header.frame_id
        centres = [np.array([[c.x, c.y, c.z] for c in f.corners]).reshape(-1, 3).mean(axis=0)
                   for f in features.features]
        self.out.landmarks(s, [(str(i), f.type, c) for i, (f, c) in enumerate(zip(features.features, centres,
                                                                                   strict=True))], frame_id)
        linked = [(c, self._features[f.id].centroid_cad) for f, c in zip(features.features, centres, strict=True)
                  if frame_id == "cad" and f.id in self._features]
        self.out.links(s, linked)
        self.out.poses("/hypotheses", s, rivals_cad_body)
        matched = {f.id for f in features.features if frame_id == "cad" and f.id in self._features}
        if matched != self._matched:
            self._matched = matched
            self._send_model(s)

    def _send_model(self, stamp_ns: int = 0) -> None:
        """The doors, windows and the walls cut at the flight's height (else the features' median height)."""
        if not self._walls_loaded:
            self._wall_mesh, self._walls_loaded = self._load_walls(), True
        z_m = self._pose_z_m if self._pose_z_m is not None else \
            float(np.median([f.centroid_cad[2] for f in self.model.features]))
        walls = wall_segments_xy(self._wall_mesh, z_m) if self._wall_mesh is not None else None
        self.out.model(stamp_ns, self.model, self._matched, walls, z_m)


def _protobuf_schema(foxglove: Any, name: str) -> Any:
    """foxglove-sdk's Schema of a Foxglove protobuf message: its FileDescriptorSet (what MCAP writers store)."""
    cls = getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)
    return foxglove.Schema(name=cls.DESCRIPTOR.full_name, encoding="protobuf",
                           data=build_file_descriptor_set(cls).SerializeToString())


def start_live_view(model: BuildingModel, walls: Callable[[], Any], host: str, port: int, image_rate_hz: float,
                    queue_size: int, pose_rate_hz: float = 10.0) -> FoxgloveLive:
    """The live view on host:port; a one-line UserInputError where foxglove-sdk is not installed."""
    try:
        importlib.import_module("foxglove")
    except ImportError:
        raise UserInputError("the Foxglove live view needs foxglove-sdk: pip install 'macroloc[foxglove]'") from None
    return FoxgloveLive(model, walls, host, port, image_rate_hz, queue_size, pose_rate_hz)
