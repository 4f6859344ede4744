"""The service's saved map on a long mission: what one save costs with N keyframe views (400 ORB features each, as
place recognition keeps them), views inline in map.pb (how maps were saved before the view log) against the view
log (service.state: only the views new since the last save are written, 10 here, and every pose), in one run
(medians of 5 saves). Then
the carried views' filter (graph.mapstore.carried_views: a restarted run's saved views less those it has its own
near), which runs under the service's lock at every save.

    python -m bench.bench_state
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import row

SIZES = (100, 1000, 3000)
REPEAT = 5  # saves timed, the median printed
NEW_PER_SAVE = 10  # views made between two saves (5 s of flight at ~1 m/s, one view every 0.5 m)


def main() -> None:
    from scipy.spatial.transform import Rotation

    from macroloc.graph.mapstore import KeyframeView, carried_views
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.service.state import SavedMapFile, view_to_wire

    rng = np.random.default_rng(0)

    def pose() -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi)).as_matrix()
        T[:3, 3] = [rng.uniform(0, 40), rng.uniform(0, 20), 1.4]
        return T

    def view() -> KeyframeView:
        return KeyframeView(rng.normal(size=(400, 3)).astype(np.float32),
                            rng.integers(0, 256, (400, 32), dtype=np.uint8))

    print("one save of the map with N keyframe views: inline (before) / view log (now)")
    for n in SIZES:
        views = [(pose(), view()) for _ in range(n + REPEAT * NEW_PER_SAVE)]
        with tempfile.TemporaryDirectory() as tmp:
            inline = [_inline_save(Path(tmp) / "map.pb", views[:n], pb, view_to_wire) for _ in range(REPEAT)]
            inline_ms, inline_bytes = float(np.median([ms for ms, _ in inline])), inline[0][1]
            store = SavedMapFile(Path(tmp), "d1")
            store.save(pb.MapSnapshot(), views[: n - NEW_PER_SAVE])  # the saves before
            log = next(Path(tmp, "d1").glob("views-*.bin"))
            times, written = [], []
            for k in range(REPEAT):  # each save with NEW_PER_SAVE views more
                log_before = log.stat().st_size
                t0 = time.perf_counter()
                store.save(pb.MapSnapshot(), views[: n + k * NEW_PER_SAVE])
                times.append((time.perf_counter() - t0) * 1e3)
                written.append(store.path.stat().st_size + log.stat().st_size - log_before)
            log_ms, log_bytes = float(np.median(times)), float(np.median(written))
        print(row(f"{n} views: time of one save (ms)", f"{inline_ms:.0f} / {log_ms:.1f}", "-"))
        print(row(f"{n} views: bytes written by one save (MB)", f"{inline_bytes / 1e6:.1f} / {log_bytes / 1e6:.2f}",
                  "-"))
    print("carried views' filter, N own and N carried views (under the service's lock at every save)")
    for n in SIZES:
        v = view()
        own = [(pose(), v) for _ in range(n)]
        earlier = [(pose(), v) for _ in range(n)]
        t0 = time.perf_counter()
        kept = carried_views(own, np.eye(4), np.eye(4), earlier)
        print(row(f"{n} + {n} views: carried_views (ms; {len(kept)} kept)",
                  f"{(time.perf_counter() - t0) * 1e3:.0f}", "-"))


def _inline_save(path: Path, views: list, pb, view_to_wire) -> tuple[float, int]:  # noqa: ANN001 - lazy imports
    """A save as the service made it before the view log: every view serialized into map.pb, written atomically."""
    t0 = time.perf_counter()
    snap = pb.MapSnapshot()
    snap.views.extend(view_to_wire(v, T) for T, v in views)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(snap.SerializeToString())
    tmp.replace(path)
    return (time.perf_counter() - t0) * 1e3, path.stat().st_size


if __name__ == "__main__":
    main()
