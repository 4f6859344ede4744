"""`macroloc serve` (Office_A, perception on) under the PNG bomb and the other hostile stereo frames: its peak
resident memory, whether it stays up and keeps answering, and how long SIGTERM then takes to a clean exit.

The service runs as its own process (as systemd runs it); a vehicle flies a few seconds of odometry and door
sightings, then sends 20 frames whose PNG is ~390 KB and decodes to 20000 x 20000 pixels (declared so, and declared
64 x 48) and 20 whose right image is smaller than the left, then flies on. Printed beside the issue's targets:
peak RSS (VmHWM from /proc, target < 1.5 GB), poses after the bombs, exit status and the time SIGTERM took
(target: within the unit's TimeoutStopSec, 30 s).

    python -m bench.bench_bomb
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from bench.common import row

ROOT = Path(__file__).resolve().parents[1]
MACROLOC = str(Path(sys.executable).parent / "macroloc")


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    sys.path.insert(0, str(ROOT))
    from macroloc.graph.bim import load_building
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import encode_image
    from macroloc.service.zenoh_io import session_config
    from tests.perception.helpers import png_bomb
    from tests.service.helpers import FakeFlight, free_port, loopback, wait_for, yaw_T
    from tests.service.test_hostile_inputs import _frame
    from tests.service.test_service import Collector, fly

    building = ROOT / "data" / "buildings" / "office_a.ifc"
    model = load_building(building)
    state, port = Path(tempfile.mkdtemp(prefix="macroloc-bomb-")), free_port()
    env = dict(os.environ, MACROLOC_SERVICE__PERCEPTION="true")
    proc = subprocess.Popen([MACROLOC, "serve", "--building", str(building), "--vehicle", "b1", "--listen",
                             f"tcp/127.0.0.1:{port}", "--state-dir", str(state)], env=env, stderr=subprocess.DEVNULL)
    door = [f for f in model.features if f.type == "door" and f.storey == "Level 1"][10]
    T = yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])
    flight = FakeFlight(model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
    bomb = png_bomb(20000, 20000)
    small, half = encode_image(np.zeros((48, 64), np.uint8)), encode_image(np.zeros((24, 32), np.uint8))
    try:
        with zenoh.open(session_config(loopback(connect=[f"tcp/127.0.0.1:{port}"]))) as s:
            wait_for(lambda: any(r.ok for r in s.liveliness().get("macroloc/b1/alive", timeout=1.0)), 900.0, "up")
            before_mb = peak_rss_mb(proc.pid)
            poses = Collector(s, "macroloc/b1/pose", pb.PoseEstimate)
            T = fly(s, flight, T, 30, vehicle="b1")
            wait_for(lambda: poses.last() is not None and poses.last().status == pb.PoseEstimate.LOCALIZED, 60.0,
                     "localized")
            t_bombs = time.monotonic()
            for k in range(20):
                stamp = 2 * 10**9 + k * 10**6
                s.put("macroloc/b1/stereo", _frame(stamp, pb.Image(width=20000, height=20000,
                                                                    encoding=pb.Image.PNG, data=bomb)))
                s.put("macroloc/b1/stereo", _frame(stamp + 1, pb.Image(width=64, height=48, encoding=pb.Image.PNG,
                                                                        data=bomb)))
                s.put("macroloc/b1/stereo", _frame(stamp + 2, small, half))
            sent_s = time.monotonic() - t_bombs
            n, t_valid = len(poses.items), time.monotonic()
            T = fly(s, flight, T, 10, first_stamp_ns=3 * 10**9, vehicle="b1")
            wait_for(lambda: len(poses.items) >= n + 10, 60.0, "poses after the bombs")
            answered_s = time.monotonic() - t_valid
            peak_mb = peak_rss_mb(proc.pid)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(120)
        stop_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    print(row("peak RSS before the bombs (VmHWM)", f"{before_mb:.0f} MB", "-"))
    print(row("peak RSS after 60 hostile frames (VmHWM)", f"{peak_mb:.0f} MB", "< 1500 MB", peak_mb < 1500))
    print(row("60 hostile frames sent", f"in {sent_s:.1f} s", "-"))
    print(row("service up: 10 poses after 10 valid inputs", f"in {answered_s:.2f} s", "within 5 s", answered_s < 5.0))
    print(row("SIGTERM -> exit (status)", f"{stop_s:.1f} s ({rc})", "< 30 s, 0", stop_s < 30.0 and rc == 0))


if __name__ == "__main__":
    main()
