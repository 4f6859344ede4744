"""Per-key ordering of the stamps of a vehicle's inputs, recovering from a vehicle clock reset.

Per key, stamps must increase. A stamp further ahead of this machine's clock than `max_clock_ahead_ns` is
refused (`not_ahead`: also for inputs that keep no order, such as goals, which may come unstamped). Stamps that
go back by more than `clock_reset_ns` are refused until `CLOCK_CONFIRM` consecutive ones agree among themselves
(each within `clock_reset_ns` after the previous): then they are a new time base (a vehicle clock reset, or the
stamps after one absurd jump ahead), adopted, logged and reported through `on_clock_reset(key, stamp_ns)`, so one
bad stamp cannot hold a key shut until restart.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from macroloc.service.health import DropCounter

log = logging.getLogger(__name__)

CLOCK_CONFIRM = 3  # consecutive, mutually consistent stamps far behind the last one: a new time base
MAX_STAMP_NS = 2**63 - 1  # stamps are int64 downstream (numpy)


class StampGate:
    """Per-key stamp ordering that recovers from a vehicle clock reset (see the module doc)."""

    def __init__(self, drops: DropCounter, reset_ns: int, ahead_ns: int,
                 on_reset: Callable[[str, int], None] | None = None, now_ns: Callable[[], int] = time.time_ns) -> None:
        self.drops = drops
        self.reset_ns = reset_ns
        self.ahead_ns = ahead_ns
        self.on_reset = on_reset
        self.now_ns = now_ns
        self._last: dict[str, int] = {}
        self._candidate: dict[str, tuple[int, int]] = {}  # key -> (last stamp of the new base, how many)

    def not_ahead(self, key: str, stamp_ns: int) -> bool:
        """False (counted as `<key>/future_stamp`) for a stamp more than `ahead_ns` ahead of this machine's clock
        or beyond int64; no order is kept or checked."""
        if stamp_ns > min(MAX_STAMP_NS, self.now_ns() + self.ahead_ns):
            self.drops.drop(f"{key}/future_stamp", f"stamp {stamp_ns} ns is ahead of this machine's clock")
            return False
        return True

    def admit(self, key: str, stamp_ns: int) -> bool:
        """True where the stamp is not ahead (`not_ahead`) and orders after the key's last one, or starts a
        confirmed new time base (module doc)."""
        if not self.not_ahead(key, stamp_ns):
            return False
        last = self._last.get(key)
        if last is None or stamp_ns > last:
            self._last[key] = stamp_ns
            self._candidate.pop(key, None)
            return True
        if last - stamp_ns <= self.reset_ns:
            self.drops.drop(f"{key}/out_of_order", f"stamp {stamp_ns} after {last}")
            return False
        prev, n = self._candidate.get(key, (None, 0))
        n = n + 1 if prev is not None and 0 < stamp_ns - prev <= self.reset_ns else 1
        if n < CLOCK_CONFIRM:
            self._candidate[key] = (stamp_ns, n)
            self.drops.drop(f"{key}/clock_back", f"stamp {stamp_ns} is {(last - stamp_ns) * 1e-9:.1f} s before {last}")
            return False
        del self._candidate[key]
        self._last[key] = stamp_ns
        self.drops.drop(f"{key}/clock_reset")  # counted (not a drop: this message is taken)
        log.warning("%s: %d stamps in a row %.1f s back: a new time base (vehicle clock reset) from %d ns", key,
                    CLOCK_CONFIRM, (last - stamp_ns) * 1e-9, stamp_ns)
        if self.on_reset is not None:
            self.on_reset(key, stamp_ns)
        return True
