"""The saved map: one `MapSnapshot` per vehicle under the state directory, written atomically."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from google.protobuf.message import DecodeError

from service.wire.macroloc.v1 import macroloc_pb2 as pb

log = logging.getLogger(__name__)


class MapStore:
    """state_dir/<vehicle>/map.pb; a snapshot of another building (by SHA-256) is ignored on load."""

    def __init__(self, state_dir: Path, vehicle: str) -> None:
        self.path = Path(state_dir).expanduser() / vehicle / "map.pb"

    def save(self, snapshot: pb.MapSnapshot) -> Path:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f"map.pb.tmp{os.getpid()}")
        tmp.write_bytes(snapshot.SerializeToString())
        os.replace(tmp, self.path)  # atomic: a kill mid-write leaves the previous map intact
        return self.path

    def load(self, building_sha256: str) -> pb.MapSnapshot | None:
        if not self.path.exists():
            return None
        try:
            snapshot = pb.MapSnapshot.FromString(self.path.read_bytes())
        except DecodeError:
            log.warning("ignoring unreadable saved map %s", self.path)
            return None
        if snapshot.building_sha256 != building_sha256:
            log.warning("ignoring saved map %s: made for another building model", self.path)
            return None
        return snapshot


class NullMapStore(MapStore):
    """Saves nothing and loads nothing (tests and benchmarks that must start fresh)."""

    def __init__(self) -> None:
        self.path = Path(os.devnull)

    def save(self, snapshot: pb.MapSnapshot) -> Path:
        return self.path

    def load(self, building_sha256: str) -> pb.MapSnapshot | None:
        return None
