"""Run every benchmark in turn (`make bench`); each prints its figures beside the issue's target.

Each runs in its own process, so one benchmark's threads and caches do not colour the next one's figures.
`bench_replay` (simulated 60 s flights) is left out: it takes tens of minutes; run it on its own.
"""

from __future__ import annotations

import subprocess
import sys

BENCHMARKS = ("bench_localize", "bench_posegraph", "bench_perception", "bench_chain", "bench_zenoh", "bench_render",
              "bench_obstacles", "bench_place", "bench_state")


def main() -> int:
    failed = []
    for name in BENCHMARKS:
        print(f"\n== bench.{name}", flush=True)
        if subprocess.run([sys.executable, "-m", f"bench.{name}"]).returncode != 0:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
