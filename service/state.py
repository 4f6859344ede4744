"""The saved map's file (service.saved_map): a `MapSnapshot`, written atomically, and its keyframe views in an
append-only view log beside it. The service's is `<state_dir>/<vehicle>/map.pb` (`SavedMapFile(state_dir,
vehicle)`), a replay's the path of `--save-map` (`SavedMapFile.at(path)`); both are read by `read` (a restart
through `load`, which starts afresh where the file is missing, unreadable or of another building).

A view (perception.place: ~17 KB of ORB features and their points) never changes once made; only its keyframe's
pose does, as the graph is optimized. So `map.pb` holds each view's pose and its record number in the log
(`ViewPose`), and a view's bytes are written once, at the first save that holds it: a long mission's save costs
its new views and the poses, not every view again (3000 views: 53 MB a save otherwise, every 5 s).

Each run writes a log of its own (`views-<time>.bin` beside a `map.pb`, `<stem>.views-<time>.bin` beside a map of
another name), starting with the views it carries from the saved map it
was restarted from; once `map.pb` names the new log, the others are deleted. A record is a 4-byte little-endian
length and a `KeyframeView` message (its pose unset). The log is flushed to disk (fsync) before the `map.pb` that
refers to its records replaces the old one, and `map.pb` itself before the rename: a kill or a power cut at any
point leaves a saved map whose views are all readable (a half-written last record is never referred to, and is
ignored).
"""

from __future__ import annotations

import logging
import os
import struct
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from google.protobuf.message import DecodeError

from macroloc.graph.errors import UserInputError
from macroloc.graph.mapstore import KeyframeView
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose, pose_from_matrix, poses_from_matrices

log = logging.getLogger(__name__)

RECORD_HEADER = struct.Struct("<I")
STATE_MAP_NAME = "map.pb"  # the service's saved map, under <state_dir>/<vehicle>/


class ViewLog:
    """An append-only file of `KeyframeView` records (see module doc)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.records = 0

    def append(self, views: Sequence[KeyframeView]) -> int:
        """Write the views as records, flushed to disk; returns the first one's record number."""
        first = self.records
        if views:
            with open(self.path, "ab") as f:
                end = f.tell()
                try:
                    for view in views:
                        data = view_to_wire(view).SerializeToString()
                        f.write(RECORD_HEADER.pack(len(data)) + data)
                    f.flush()
                    os.fsync(f.fileno())
                except OSError:  # a full disk: no half-written records before the next save's, whose numbers
                    f.truncate(end)  # count from `records`
                    raise
            self.records += len(views)
        return first

    @staticmethod
    def read(path: Path) -> list[bytes]:
        """The complete records of the log at `path`, in order (a half-written last one is left out)."""
        data = path.read_bytes()
        records, at = [], 0
        while at + RECORD_HEADER.size <= len(data):
            (n,) = RECORD_HEADER.unpack_from(data, at)
            if at + RECORD_HEADER.size + n > len(data):
                break
            records.append(data[at + RECORD_HEADER.size: at + RECORD_HEADER.size + n])
            at += RECORD_HEADER.size + n
        return records


def view_to_wire(view: KeyframeView, T_map_body: np.ndarray | None = None) -> pb.KeyframeView:
    """A keyframe view as its message; with its pose, where given (a view log's record has none)."""
    points, descriptors = view.to_bytes()
    msg = pb.KeyframeView(points_body=points, descriptors=descriptors)
    if T_map_body is not None:
        msg.T_map_body.CopyFrom(pose_from_matrix(T_map_body))
    return msg


def view_from_wire(msg: pb.KeyframeView) -> tuple[np.ndarray, KeyframeView]:
    """(T_map_body, view); a malformed view (sizes that disagree) becomes an empty one."""
    try:
        view = KeyframeView.from_bytes(msg.points_body, msg.descriptors)
    except ValueError:
        view = KeyframeView(np.zeros((0, 3)), np.zeros((0, 32), np.uint8))
    return matrix_from_pose(msg.T_map_body), view


class SavedMapFile:
    """A saved map's file and its view log (see module doc): `state_dir/<vehicle>/map.pb`, or any path (`at`)."""

    def __init__(self, state_dir: Path, vehicle: str) -> None:
        self.path = Path(state_dir).expanduser() / vehicle / STATE_MAP_NAME
        self._log: ViewLog | None = None  # this run's, from its first save with views
        # id(view) -> (the view, kept alive so that its id is not reused; its record number)
        self._records: dict[int, tuple[KeyframeView, int]] = {}

    @classmethod
    def at(cls, path: str | Path) -> SavedMapFile:
        """The saved map at `path` (its view log beside it)."""
        out = cls(Path(), "")
        out.path = Path(path).expanduser()
        return out

    @property
    def _log_prefix(self) -> str:
        """Its view logs' names begin so: only its own are replaced, never another saved map's in the folder."""
        return "views-" if self.path.name == STATE_MAP_NAME else f"{self.path.stem}.views-"

    def save(self, snapshot: pb.MapSnapshot, views: Sequence[tuple[np.ndarray, KeyframeView]] = ()) -> Path:
        """Write `snapshot` (its view fields are set here) with the keyframe views (T_map_body, view): the views
        not saved before are appended to this run's log, every view's pose goes into the snapshot."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if views:
            if self._log is None:
                self._log = ViewLog(self.path.with_name(f"{self._log_prefix}{time.time_ns():x}.bin"))
            new = list({id(v): v for _, v in views if id(v) not in self._records}.values())
            first = self._log.append(new)
            self._records.update((id(v), (v, first + k)) for k, v in enumerate(new))
            snapshot.view_log = self._log.path.name
            poses = poses_from_matrices(np.array([T for T, _ in views]))
            snapshot.view_poses.extend(pb.ViewPose(record=self._records[id(v)][1], T_map_body=pose)
                                       for (_, v), pose in zip(views, poses, strict=True))
        tmp = self.path.with_name(f"{self.path.name}.tmp{os.getpid()}")
        with open(tmp, "wb") as f:
            f.write(snapshot.SerializeToString())
            f.flush()
            os.fsync(f.fileno())  # on disk before it replaces the old one: a power cut leaves one or the other
        os.replace(tmp, self.path)  # atomic: a kill mid-write leaves the previous map intact
        _fsync_dir(self.path.parent)
        for other in self.path.parent.glob(f"{self._log_prefix}*.bin"):  # logs the saved map no longer refers to
            if other.name != snapshot.view_log:
                other.unlink(missing_ok=True)
        return self.path

    def read(self) -> pb.MapSnapshot:
        """The saved map with its views (`views`, with their poses) read back from the view log. UserInputError
        where there is none or the file is not a saved map (a JSON map of macroloc before issue 56 is refused in
        so many words: it is to be saved again)."""
        if not self.path.is_file():
            raise UserInputError(f"saved map not found: {self.path}")
        data = self.path.read_bytes()
        if data.lstrip()[:1] == b"{":
            raise UserInputError(f"{self.path} is a JSON map of an earlier macroloc; save the map again with this "
                                 "version (`replay --save-map` or `serve`)")
        try:
            snapshot = pb.MapSnapshot.FromString(data)
        except DecodeError:
            raise UserInputError(f"{self.path} is not a saved map") from None
        if snapshot.view_log:
            self._read_views(snapshot)
        return snapshot

    def load(self, building_sha256: str) -> pb.MapSnapshot | None:
        """`read`, for a restart: None (start afresh) where there is no saved map, where it is unreadable or was
        made in another building (by SHA-256)."""
        if not self.path.exists():
            return None
        try:
            snapshot = self.read()
        except UserInputError as exc:
            log.warning("ignoring the saved map: %s", exc)
            return None
        if snapshot.building_sha256 != building_sha256:
            log.warning("ignoring saved map %s: made for another building model", self.path)
            return None
        return snapshot

    def _read_views(self, snapshot: pb.MapSnapshot) -> None:
        log_path = self.path.with_name(snapshot.view_log)
        records = ViewLog.read(log_path) if log_path.exists() else []
        lost = 0
        for vp in snapshot.view_poses:
            try:
                view = pb.KeyframeView.FromString(records[vp.record])
            except (IndexError, DecodeError):
                lost += 1
                continue
            view.T_map_body.CopyFrom(vp.T_map_body)
            snapshot.views.append(view)
        if lost:
            log.warning("saved map %s: %d of %d keyframe views missing from %s", self.path, lost,
                        len(snapshot.view_poses), log_path.name)
        snapshot.ClearField("view_poses")
        snapshot.ClearField("view_log")


def _fsync_dir(path: Path) -> None:
    """Make a rename in `path` durable (POSIX; a no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class NullSavedMapFile(SavedMapFile):
    """Saves nothing and loads nothing (tests and benchmarks that must start fresh)."""

    def __init__(self) -> None:
        self.path = Path(os.devnull)

    def save(self, snapshot: pb.MapSnapshot, views: Sequence[tuple[np.ndarray, KeyframeView]] = ()) -> Path:
        return self.path

    def load(self, building_sha256: str) -> pb.MapSnapshot | None:
        return None
