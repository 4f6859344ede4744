"""Draws docs/foxglove_live.png: the operator's live view (service/foxglove_live.py) as docs/foxglove_layout.json
lays it out, from the messages a WebSocket client received from a demo flight's service (`macroloc demo
--foxglove PORT`, lock-step, the rendered camera and the perception chain). No Foxglove app runs here: the 3D
panel is drawn from above (CAD frame, metres), the Image panel as the image with its annotations, the log and
diagnostics as text, all from the channels' own messages decoded with the schemas the server advertised.
Run: `python scripts/draw_foxglove_live.py [--out docs/foxglove_live.png] [--seed 0]`.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


class Recorder:
    """A Foxglove WebSocket client (subprotocol foxglove.sdk.v1) keeping what the panels would show: every
    channel's last message, the pose's trail, and the last image with detections beside them (same log time)."""

    def __init__(self, port: int) -> None:
        from websockets.sync.client import connect

        self.stack = contextlib.ExitStack()  # websockets 17 wants its connection used as a context manager
        deadline = time.monotonic() + 600.0  # the service starts once the building is prepared
        while True:
            try:
                self.ws = self.stack.enter_context(connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                                           max_size=None))
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        self.last: dict[str, Any] = {}
        self.trail_xy: list[tuple[float, float]] = []
        self.log: list[str] = []
        self.images: dict[int, Any] = {}  # log time -> image, until its detections arrive
        self.shown: tuple[Any, Any] | None = None  # (image, detections) with at least one box
        self.at_first_plan: tuple | None = None  # (last, trail_xy, log, shown) when the first plan came
        self._channels: dict[int, dict] = {}
        self._subs: dict[int, dict] = {}
        self._classes: dict[str, Any] = {}
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            while True:
                frame = self.ws.recv()
                if isinstance(frame, str):
                    self._control(json.loads(frame))
                else:
                    _, sub, log_time_ns = struct.unpack_from("<BIQ", frame)
                    self._message(self._subs[sub], log_time_ns, frame[13:])
        except Exception:  # the server stopped at the end of the flight
            return

    def _control(self, doc: dict) -> None:
        if doc.get("op") != "advertise":
            return
        subs = []
        for c in doc["channels"]:
            self._channels[c["id"]] = c
            self._subs[c["id"]] = c  # subscription id = channel id
            subs.append({"id": c["id"], "channelId": c["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _message(self, channel: dict, log_time_ns: int, payload: bytes) -> None:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        topic = channel["topic"]
        if channel["encoding"] == "json":
            self.last[topic] = json.loads(payload)
            return
        if topic not in self._classes:
            pool = descriptor_pool.DescriptorPool()
            for f in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
                pool.Add(f)
            self._classes[topic] = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
        msg = self._classes[topic].FromString(payload)
        self.last[topic] = msg
        if topic == "/pose/estimate":
            self.trail_xy.append((msg.pose.position.x, msg.pose.position.y))
        elif topic == "/status":
            self.log.append(msg.message)
        elif topic == "/camera/left/image":
            self.images = {log_time_ns: msg}
        elif topic == "/camera/left/detections" and msg.points and log_time_ns in self.images:
            self.shown = (self.images[log_time_ns], msg)
        if topic == "/plan" and msg.poses and self.at_first_plan is None:  # the moment to draw: a fresh plan
            self.at_first_plan = (dict(self.last), list(self.trail_xy), list(self.log), self.shown)


def _yaw(q: Any) -> float:
    return float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))


def _rotation(q: Any) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()


def draw(rec: Recorder, out: Path, title: str) -> None:
    """The panels as they stood when the first plan came (else at the end of the flight)."""
    if rec.at_first_plan is not None:
        rec.last, rec.trail_xy, rec.log, rec.shown = rec.at_first_plan
        title += "\ndrawn as the first plan came"
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    fig = plt.figure(figsize=(15, 8))
    grid = fig.add_gridspec(2, 2, width_ratios=[55, 45], height_ratios=[70, 30])
    ax = fig.add_subplot(grid[:, 0])
    ax.set_title("3D panel, from above: /model /landmarks /landmarks/links /pose/* /plan /hypotheses (cad, m)")
    model = rec.last.get("/model")
    for e in model.entities if model else []:
        for line in e.lines:  # the walls, cut at the flight's height
            pts = np.array([[p.x, p.y] for p in line.points]).reshape(-1, 2, 2)
            ax.plot(pts[:, :, 0].T, pts[:, :, 1].T, color="0.35", lw=0.8)
        for c in e.cubes:  # doors and windows: their width along the box's x axis
            R = _rotation(c.pose.orientation)
            centre = np.array([c.pose.position.x, c.pose.position.y])
            half = R[:2, 0] * c.size.x / 2
            ax.plot(*np.c_[centre - half, centre + half], color=(c.color.r, c.color.g, c.color.b),
                    alpha=max(c.color.a, 0.3), lw=4 if c.color.a > 0.5 else 2, solid_capstyle="butt")
    links = rec.last.get("/landmarks/links")
    for e in links.entities if links else []:
        for line in e.lines:
            pts = np.array([[p.x, p.y] for p in line.points]).reshape(-1, 2, 2)
            ax.plot(pts[:, :, 0].T, pts[:, :, 1].T, color=(0.1, 0.7, 0.3), lw=1.2)
    landmarks = rec.last.get("/landmarks")
    for e in landmarks.entities if landmarks else []:
        for s in e.spheres:
            ax.plot(s.pose.position.x, s.pose.position.y, "o", ms=6, color=(s.color.r, s.color.g, s.color.b),
                    mec="k", mew=0.5)
    plan = rec.last.get("/plan")
    if plan and plan.poses:
        xy = np.array([[p.position.x, p.position.y] for p in plan.poses])
        ax.plot(xy[:, 0], xy[:, 1], "--", color="tab:purple", lw=1.5, label="/plan")
        ax.plot(*xy[-1], "*", ms=16, color="tab:purple")
    hypotheses = rec.last.get("/hypotheses")
    for p in hypotheses.poses if hypotheses else []:
        ax.arrow(p.position.x, p.position.y, 0.8 * np.cos(_yaw(p.orientation)), 0.8 * np.sin(_yaw(p.orientation)),
                 width=0.08, color="0.5")
    if rec.trail_xy:
        trail = np.array(rec.trail_xy)
        ax.plot(trail[:, 0], trail[:, 1], color=(1.0, 0.62, 0.1), lw=1.5, label="/pose/estimate (trail)")
    pose = rec.last.get("/pose/estimate")
    if pose:
        x, y, yaw = pose.pose.position.x, pose.pose.position.y, _yaw(pose.pose.orientation)
        ax.arrow(x, y, np.cos(yaw), np.sin(yaw), width=0.12, color=(1.0, 0.5, 0.0), zorder=5)
    cov = rec.last.get("/pose/covariance")
    if cov and cov.entities and cov.entities[0].spheres:
        s = cov.entities[0].spheres[0]
        R = _rotation(s.pose.orientation)
        C_xy = (R @ np.diag((np.array([s.size.x, s.size.y, s.size.z]) / 2) ** 2) @ R.T)[:2, :2]  # (2 sigma)^2
        w, v = np.linalg.eigh(C_xy)
        ax.add_patch(Ellipse((s.pose.position.x, s.pose.position.y), 2 * np.sqrt(w[1]) * 10, 2 * np.sqrt(w[0]) * 10,
                             angle=float(np.degrees(np.arctan2(v[1, 1], v[0, 1]))), fc=(1.0, 0.62, 0.1, 0.3),
                             ec=(1.0, 0.5, 0.0), label="/pose/covariance, 2 sigma x 10"))
    shown_xy = list(rec.trail_xy) + ([(p.position.x, p.position.y) for p in plan.poses] if plan else [])
    if shown_xy:  # the flight's and the plan's part of the building, as the 3D panel following the body shows it
        lo, hi = np.min(shown_xy, axis=0) - 4.0, np.max(shown_xy, axis=0) + 4.0
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.legend(loc="lower left", fontsize=8)
    ax.grid(alpha=0.2)

    ax_img = fig.add_subplot(grid[0, 1])
    ax_img.set_title("Image panel: /camera/left/image + /camera/left/detections")
    if rec.shown is not None:
        image, detections = rec.shown
        bgr = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
        ax_img.imshow(bgr[:, :, ::-1])
        for outline in detections.points:
            uv = np.array([[p.x, p.y] for p in outline.points])
            uv = np.vstack([uv, uv[:1]])
            c = outline.outline_color
            ax_img.plot(uv[:, 0], uv[:, 1], color=(c.r, c.g, c.b), lw=2)
    ax_img.axis("off")
    ax_log = fig.add_subplot(grid[1, 1])
    ax_log.axis("off")
    diag = rec.last.get("/diagnostics", {})
    rates = {k: round(v, 1) for k, v in diag.get("rates_hz", {}).items() if v}
    latency = {k: round(v, 1) for k, v in diag.get("latencies_ms", {}).items() if k.startswith("frame_to_pose")}
    text = ["Log panel (/status):", *("  " + line for line in rec.log[-4:]), "",
            f"/diagnostics: state {diag.get('state')}, keyframes {diag.get('keyframes')}, landmarks "
            f"{diag.get('landmarks')}", f"  rates (Hz) {rates}", f"  latencies (ms) {latency}",
            f"  live view dropped {diag.get('live_view_dropped')}"]
    ax_log.text(0, 1, "\n".join(text), va="top", family="monospace", fontsize=8, wrap=True)
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "foxglove_live.png")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from macroloc.cli.demo import DEFAULT_BUILDING, DemoParams, run_demo

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    box: dict[str, Any] = {}
    flight = threading.Thread(target=lambda: box.update(result=run_demo(
        DEFAULT_BUILDING, DemoParams(seed=args.seed, lockstep=True, foxglove=port))), daemon=True)
    flight.start()
    rec = Recorder(port)
    flight.join()
    rec.thread.join(timeout=10.0)
    r = box["result"]
    draw(rec, args.out, f"macroloc demo --foxglove {port}, seed {r.seed}, {r.storey} -> {r.goal}: {r.outcome}, "
                        f"localized after {r.localization_time_s:.1f} s")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
