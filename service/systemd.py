"""systemd's service notification protocol (sd_notify) for `Type=notify` units with `WatchdogSec`.

systemd passes a datagram socket in `$NOTIFY_SOCKET` (a path, or an abstract name written with a leading `@`) and,
with `WatchdogSec=`, the watchdog period in `$WATCHDOG_USEC`. The service sends `READY=1` once it takes inputs,
`WATCHDOG=1` at least every half period while its worker makes progress, `STATUS=...` for `systemctl status`, and
`STOPPING=1` when it shuts down. A stalled worker stops the pings, so systemd kills and restarts the process.
Outside systemd (no `$NOTIFY_SOCKET`), `notifier_from_environment()` returns a `NullNotifier`.
"""

from __future__ import annotations

import logging
import os
import socket
from typing import Protocol

log = logging.getLogger(__name__)


class Notifier(Protocol):
    watchdog_period_s: float | None

    def ready(self) -> None: ...

    def watchdog(self) -> None: ...

    def status(self, text: str) -> None: ...

    def stopping(self) -> None: ...


class NullNotifier:
    """Not under systemd: every notification is dropped."""

    watchdog_period_s: float | None = None

    def ready(self) -> None:
        pass

    def watchdog(self) -> None:
        pass

    def status(self, text: str) -> None:
        pass

    def stopping(self) -> None:
        pass


class SystemdNotifier:
    """Sends sd_notify datagrams to `socket_path`; `watchdog_period_s` is systemd's WatchdogSec (None: no watchdog)."""

    def __init__(self, socket_path: str, watchdog_period_s: float | None = None) -> None:
        self.address = "\0" + socket_path[1:] if socket_path.startswith("@") else socket_path  # abstract namespace
        self.watchdog_period_s = watchdog_period_s
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    def _send(self, message: str) -> None:
        try:
            self._socket.sendto(message.encode(), self.address)
        except OSError as exc:  # systemd gone or the socket unreachable: the service keeps running
            log.warning("sd_notify %r failed: %s", message.split("=")[0], exc)

    def ready(self) -> None:
        self._send("READY=1")

    def watchdog(self) -> None:
        self._send("WATCHDOG=1")

    def status(self, text: str) -> None:
        self._send("STATUS=" + text.replace("\n", " "))

    def stopping(self) -> None:
        self._send("STOPPING=1")


def notifier_from_environment(environ: dict[str, str] | None = None) -> Notifier:
    """A SystemdNotifier when started by systemd (`$NOTIFY_SOCKET`), else a NullNotifier.

    `$WATCHDOG_USEC` (µs) gives the watchdog period; it applies only to this process (`$WATCHDOG_PID`, when set).
    """
    env = os.environ if environ is None else environ
    path = env.get("NOTIFY_SOCKET", "")
    if not path:
        return NullNotifier()
    period_s = None
    pid = env.get("WATCHDOG_PID", "")
    if env.get("WATCHDOG_USEC", "").isdigit() and (not pid or pid == str(os.getpid())):
        period_s = int(env["WATCHDOG_USEC"]) / 1e6
    return SystemdNotifier(path, period_s)
