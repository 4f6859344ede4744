"""service.systemd on a real datagram socket, and the service's stall detection that feeds (or starves) it."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import numpy as np

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.service.systemd import NullNotifier, SystemdNotifier, notifier_from_environment
from tests.service.helpers import (
    FakeFlight,
    client,
    free_port,
    running_service,
    service_config,
    wait_for,
    wait_subscribed,
)
from tests.service.test_service import Collector


class NotifySocket:
    """systemd's side: a bound AF_UNIX datagram socket collecting what the service sends."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + path[1:] if path.startswith("@") else path)
        self.sock.settimeout(0.05)
        self.messages: list[str] = []

    def drain(self) -> list[str]:
        try:
            while True:
                self.messages.append(self.sock.recv(4096).decode())
        except TimeoutError:
            return self.messages


def test_notifications_reach_a_path_and_an_abstract_socket(tmp_path: Path) -> None:
    for path in (str(tmp_path / "notify"), f"@macroloc-test-{os.getpid()}"):
        listener = NotifySocket(path)
        notifier = notifier_from_environment({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "30000000"})
        assert isinstance(notifier, SystemdNotifier) and notifier.watchdog_period_s == 30.0
        notifier.ready()
        notifier.watchdog()
        notifier.status("stalled\nfor 6 s")
        notifier.stopping()
        assert listener.drain() == ["READY=1", "WATCHDOG=1", "STATUS=stalled for 6 s", "STOPPING=1"]


def test_outside_systemd_nothing_is_sent_and_another_pids_watchdog_is_ignored() -> None:
    assert isinstance(notifier_from_environment({}), NullNotifier)
    other = notifier_from_environment({"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": "1000000",
                                       "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.watchdog_period_s is None
    other.ready()  # an unreachable socket is logged, never raised


def test_a_stalled_worker_withdraws_liveliness_and_starves_the_watchdog(duplex_path, duplex_model, tmp_path) -> None:
    listener = NotifySocket(str(tmp_path / "notify"))
    port = free_port()
    cfg = service_config(duplex_path, tmp_path, port)
    cfg.service.stall_after_s = 0.6
    notifier = SystemdNotifier(str(tmp_path / "notify"), 2.0)
    with running_service(cfg, notifier=notifier) as service, client(port) as s:
        status = Collector(s, "macroloc/t1/status", pb.ServiceStatus)

        def alive() -> bool:
            return any(r.ok is not None for r in s.liveliness().get("macroloc/t1/alive", timeout=2.0))

        wait_for(lambda: "READY=1" in listener.drain() and "WATCHDOG=1" in listener.messages, what="ready, fed")
        assert alive()
        flight = FakeFlight(duplex_model, np.eye(4))
        wait_subscribed(s, "macroloc/t1/imu")
        with service._lock:  # the worker blocks in its next event's handler: a stall
            s.put("macroloc/t1/imu", flight.imu(1, np.eye(4)).SerializeToString())
            wait_for(lambda: not alive(), 15.0, "liveliness withdrawn")
            listener.drain()
            listener.messages.clear()
            n_status = len(status.items)
            time.sleep(1.5)
            assert len(status.items) > n_status, "status stopped during the stall"
            assert "WATCHDOG=1" not in listener.drain(), "the watchdog was fed during a stall"
        wait_for(alive, 15.0, "liveliness restored")
        listener.messages.clear()
        wait_for(lambda: "WATCHDOG=1" in listener.drain(), 15.0, "the watchdog fed again")
    assert "STOPPING=1" in listener.drain()


def test_stop_mid_stall_exits_within_the_units_stop_timeout(duplex_path, tmp_path) -> None:
    """SIGTERM (the stop event) while the worker is stuck on one event: the service still exits well inside
    TimeoutStopSec (30 s) - the queue gets drain_timeout_s, the final save gives up on the stuck worker's lock and
    keeps the map saved last - instead of being SIGKILLed with nothing saved."""
    import threading

    from macroloc.service.serve import build_service
    from macroloc.service.zenoh_io import open_session

    port = free_port()
    cfg = service_config(duplex_path, tmp_path, port)
    cfg.service.drain_timeout_s = 3.0
    stop, box = threading.Event(), {}

    def run() -> None:
        with open_session(cfg.zenoh) as session:
            box["service"] = build_service(cfg, session)
            box["service"].run(stop)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    wait_for(lambda: "service" in box and box["service"].ready.is_set(), 600.0, "service ready")
    service = box["service"]
    release = threading.Event()
    held = threading.Thread(target=lambda: service._lock.acquire() and release.wait(120.0), daemon=True)
    held.start()
    with client(port) as s:
        wait_subscribed(s, "macroloc/t1/imu")
        s.put("macroloc/t1/imu", FakeFlight(None, np.eye(4)).imu(1, np.eye(4)).SerializeToString())
        wait_for(lambda: time.monotonic() - service._worker_beat_s > 1.0, 15.0, "the worker stuck")
    t0 = time.monotonic()
    stop.set()
    thread.join(timeout=60.0)
    stop_s = time.monotonic() - t0
    release.set()
    print(f"stop mid-stall took {stop_s:.1f} s")
    assert not thread.is_alive() and stop_s < 30.0, f"stop took {stop_s:.1f} s"
