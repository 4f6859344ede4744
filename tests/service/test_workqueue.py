"""The worker's queue: light events keep order, heavy frames are bounded by dropping the oldest frame."""

from __future__ import annotations

from macroloc.service.workqueue import WorkQueue


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


def test_counting_ring_keeps_the_latest_and_counts_what_it_pushes_out() -> None:
    import threading

    from macroloc.service.workqueue import CountingRing

    pushed_out: list[int] = []
    ring = CountingRing(4, lambda: pushed_out.append(1))
    for k in range(10):
        ring(k)
    assert len(pushed_out) == 6
    got: list[int] = []
    reader = threading.Thread(target=lambda: got.extend(ring))
    reader.start()
    ring(10)
    ring.close()
    reader.join(timeout=5.0)
    assert not reader.is_alive() and got[:4] == [6, 7, 8, 9] and got[-1] == 10


def test_a_flood_is_taken_or_counted_never_lost_silently(duplex_path, duplex_model, tmp_path) -> None:
    """2000 IMU samples as fast as a session can put them: every one is either taken or counted as pushed out
    of the intake's ring (imu/ring_overflow)."""
    import numpy as np
    import zenoh

    from tests.service.helpers import (
        FakeFlight,
        client,
        free_port,
        running_service,
        service_config,
        wait_for,
        wait_subscribed,
    )

    port = free_port()
    flight = FakeFlight(duplex_model, np.eye(4))
    with running_service(service_config(duplex_path, tmp_path, port)) as service, client(port) as s:
        wait_subscribed(s, "macroloc/t1/imu")
        for k in range(2000):
            s.put("macroloc/t1/imu", flight.imu((k + 1) * 1_000_000, np.eye(4)).SerializeToString(),
                  congestion_control=zenoh.CongestionControl.BLOCK)  # the transport loses none: the ring may

        def accounted() -> int:
            return service.rates["imu"].total + service.drops.counts().get("imu/ring_overflow", 0)  # type: ignore

        wait_for(lambda: accounted() == 2000, 30.0, "every sample taken or counted")
