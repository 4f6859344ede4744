"""Soak: several minutes of 30 Hz odometry, IMU and 640x480 stereo frames (plus sightings at 3 Hz) from a
hovering vehicle keep the service's memory flat. (A flying vehicle's pose graph grows with the distance flown:
one keyframe per 0.25 m or 0.15 rad; that growth is the graph's, not the transport's.)"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import encode_image
from tests.service.helpers import (
    FakeFlight,
    client,
    free_port,
    running_service,
    service_config,
    wait_for,
    wait_subscribed,
    yaw_T,
)

SOAK_S = float(os.environ.get("MACROLOC_SOAK_S", "600"))  # the 10 minutes (slow tier)


def rss_mb() -> float:
    """Resident memory of this process (service and vehicle sessions both live here), MB."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.slow
@pytest.mark.timeout(SOAK_S + 600)  # the soak itself, plus a cold start of the service
def test_soak_at_30_hz_keeps_memory_flat(office_path: Path, office_model, tmp_path: Path) -> None:
    if not Path("/proc/self/statm").exists():
        pytest.skip("needs /proc to read the resident memory")
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    centre = door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4]
    flight = FakeFlight(office_model, yaw_T(0.4, np.array([2.0, 1.0, 0.0])))
    rng = np.random.default_rng(0)
    image = (rng.random((480, 640, 3)) * 255).astype(np.uint8)
    frame = pb.StereoFrame(camera_id="front", left=encode_image(image), right=encode_image(np.roll(image, 8, 1)))
    cfg = service_config(office_path, tmp_path, port := free_port())
    cfg.service.perception = False  # the transport and the graph are soaked here, not the detector
    samples: list[tuple[float, float]] = []
    with running_service(cfg) as service, client(port) as s:
        wait_subscribed(s, "macroloc/t1/imu")
        start = time.monotonic()
        k = 0
        while time.monotonic() - start < SOAK_S:
            k += 1
            stamp = k * 33_333_333
            sway = 0.05 * np.sin(k / 30.0)  # hovering: a few centimetres and degrees of sway
            T = yaw_T(0.3 + sway, centre + np.array([sway, -sway, 0.0]))
            s.put("macroloc/t1/imu", flight.imu(stamp, T).SerializeToString())
            s.put("macroloc/t1/odometry", flight.odometry(stamp, T).SerializeToString())
            frame.header.stamp_ns = stamp
            s.put("macroloc/t1/stereo", frame.SerializeToString())
            if k % 10 == 0:
                s.put("macroloc/t1/observations", flight.observations(stamp, T).SerializeToString())
            if k % 300 == 0:
                samples.append((time.monotonic() - start, rss_mb()))
            delay = start + k / 30.0 - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # the vehicle's 30 Hz clock, not a wait in the test
        wait_for(lambda: service.rates["odometry"].total >= k - 5, what="the service kept up")  # type: ignore
        diag = service.diagnostics()  # type: ignore[attr-defined]
    warm = [m for t, m in samples if t > min(60.0, SOAK_S / 3)]
    assert len(warm) >= 2
    growth_mb = warm[-1] - warm[0]
    print(f"soak {SOAK_S:.0f} s, {k} frames: RSS {warm[0]:.0f} -> {warm[-1]:.0f} MB; "
          f"dropped {dict(diag.dropped)}; rates {dict(diag.rates_hz)}")
    assert growth_mb < 40.0, f"memory grew {growth_mb:.1f} MB over the soak: {samples}"
