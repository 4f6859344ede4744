"""The saved map and its view log (service.state): views written once, poses every save, kills survived."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from macroloc.graph.mapstore import KeyframeView
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.service.state import SavedMapFile, ViewLog, view_from_wire, view_to_wire
from tests.graph.scenes import make_T, rot_z

SHA = "sha-of-the-building"


def _views(n: int, seed: int = 0) -> list[tuple[np.ndarray, KeyframeView]]:
    rng = np.random.default_rng(seed)
    return [(make_T(rot_z(0.1 * k), np.array([0.5 * k, 0.0, 1.4])),
             KeyframeView(rng.uniform(-5, 5, (20 + k, 3)).astype(np.float32),
                          rng.integers(0, 256, (20 + k, 32), dtype=np.uint8))) for k in range(n)]


def _snapshot() -> pb.MapSnapshot:
    return pb.MapSnapshot(building_sha256=SHA, status=pb.PoseEstimate.LOCALIZED, keyframes=3)


def _same(loaded: pb.MapSnapshot, views: list[tuple[np.ndarray, KeyframeView]]) -> None:
    assert len(loaded.views) == len(views)
    for msg, (T, view) in zip(loaded.views, views, strict=True):
        T_loaded, v = view_from_wire(msg)
        assert np.allclose(T_loaded, T, atol=1e-9)
        assert np.array_equal(v.points_body, view.points_body) and np.array_equal(v.descriptors, view.descriptors)


def _logs(tmp_path: Path) -> list[Path]:
    return sorted((tmp_path / "d1").glob("views-*.bin"))


def test_views_are_written_once_and_their_poses_at_every_save(tmp_path: Path) -> None:
    store = SavedMapFile(tmp_path, "d1")
    views = _views(3)
    store.save(_snapshot(), views)
    (log,) = _logs(tmp_path)
    size_3 = log.stat().st_size
    map_size_3 = store.path.stat().st_size
    moved = [(make_T(np.eye(3), np.array([0.0, 0.0, 0.1])) @ T, v) for T, v in views]  # the graph moved them
    more = moved + _views(4, seed=1)[3:]
    store.save(_snapshot(), more)
    assert _logs(tmp_path) == [log]
    assert len(ViewLog.read(log)) == 4  # the three saved before are not written again
    assert log.stat().st_size - size_3 < size_3 / 2  # one view more, not four
    assert store.path.stat().st_size < 2 * map_size_3  # map.pb holds poses, not the views' bytes
    assert map_size_3 < 600
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None and not loaded.view_poses and not loaded.view_log
    _same(loaded, more)


def test_a_restarted_store_writes_a_log_of_its_own_and_drops_the_old_one(tmp_path: Path) -> None:
    first = SavedMapFile(tmp_path, "d1")
    views = _views(3)
    first.save(_snapshot(), views)
    (old,) = _logs(tmp_path)
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None
    carried = [view_from_wire(v) for v in loaded.views][1:]  # the restarted run carries two of them
    second = SavedMapFile(tmp_path, "d1")
    second.save(_snapshot(), carried)
    (new,) = _logs(tmp_path)
    assert new != old and len(ViewLog.read(new)) == 2
    again = SavedMapFile(tmp_path, "d1").load(SHA)
    assert again is not None
    _same(again, views[1:])


def test_a_save_without_views_drops_the_log(tmp_path: Path) -> None:
    store = SavedMapFile(tmp_path, "d1")
    store.save(_snapshot(), _views(2))
    SavedMapFile(tmp_path, "d1").save(_snapshot())
    assert _logs(tmp_path) == []
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None and len(loaded.views) == 0


def test_a_half_written_record_and_a_missing_log_lose_only_their_views(tmp_path: Path, caplog) -> None:  # noqa: ANN001
    store = SavedMapFile(tmp_path, "d1")
    views = _views(3)
    store.save(_snapshot(), views)
    (log,) = _logs(tmp_path)
    data = log.read_bytes()
    records = ViewLog.read(log)
    log.write_bytes(data[: len(data) - len(records[-1]) // 2])  # a kill in the middle of the last record
    assert len(ViewLog.read(log)) == 2
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None
    _same(loaded, views[:2])
    assert "1 of 3 keyframe views missing" in caplog.text
    log.unlink()
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None and len(loaded.views) == 0 and loaded.status == pb.PoseEstimate.LOCALIZED


def test_a_map_saved_with_its_views_inline_still_loads(tmp_path: Path) -> None:
    """Maps saved before the view log held their views in map.pb (field 10)."""
    views = _views(2)
    snap = _snapshot()
    snap.views.extend(view_to_wire(v, T) for T, v in views)
    (tmp_path / "d1").mkdir()
    (tmp_path / "d1" / "map.pb").write_bytes(snap.SerializeToString())
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None
    _same(loaded, views)


def test_a_map_of_another_building_is_ignored(tmp_path: Path) -> None:
    SavedMapFile(tmp_path, "d1").save(_snapshot(), _views(1))
    assert SavedMapFile(tmp_path, "d1").load("another-building") is None


def test_a_failed_append_leaves_no_half_record_behind(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """A write that fails (a full disk) is undone: the next save's records keep the numbers map.pb gives them."""
    import macroloc.service.state as state

    store = SavedMapFile(tmp_path, "d1")
    views = _views(3)
    store.save(_snapshot(), views[:1])
    (log,) = _logs(tmp_path)
    size = log.stat().st_size

    def full_disk(fd: int) -> None:
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(state.os, "fsync", full_disk)
        try:
            store.save(_snapshot(), views[:2])
        except OSError:
            pass
        else:
            raise AssertionError("the failed write was not reported")
    assert log.stat().st_size == size
    store.save(_snapshot(), views)
    loaded = SavedMapFile(tmp_path, "d1").load(SHA)
    assert loaded is not None
    _same(loaded, views)
