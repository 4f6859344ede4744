"""The worker's queue: light events keep order, heavy frames are bounded by dropping the oldest frame."""

from __future__ import annotations

from service.workqueue import WorkQueue


def test_heavy_items_beyond_the_bound_push_out_the_oldest_frame_only() -> None:
    q = WorkQueue(heavy_max=2)
    q.put("odo1", heavy=False)
    for k in range(4):
        q.put(f"frame{k}", heavy=True)
    q.put("odo2", heavy=False)
    got = [q.get(timeout_s=0.0) for _ in range(len(q))]
    assert got == ["odo1", "frame2", "frame3", "odo2"]
    assert q.dropped == 2
    assert q.get(timeout_s=0.0) is None


def test_light_items_are_bounded_too() -> None:
    q = WorkQueue(heavy_max=1, light_max=3)
    for k in range(5):
        q.put(k, heavy=False)
    assert [q.get(0.0) for _ in range(3)] == [2, 3, 4] and q.dropped == 2
