"""Rendered detector training frames: seeded simulated flights through the training buildings, every N-th frame
written as a left image with YOLO labels (0 door, 1 window) by `sim.export.YoloExporter`.

    python -m bench.sim_trainset [--out out/sim_yolo]

Office_A is kept out: it is the building "not used in training" on which `bench.eval_perception_sim` scores the
detector on rendered frames. Only the exported frames are rendered (no MCAP), which is ~10x faster than
`macroloc simulate --yolo`. Called by `python -m perception.train` when its rendered-frames folder is missing.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRAIN_BUILDINGS = ("duplex.ifc", "fzk_haus.ifc")
SEEDS = (1, 2, 3)

log = logging.getLogger(__name__)


def export(out: Path, buildings: tuple[str, ...] = TRAIN_BUILDINGS, seeds: tuple[int, ...] = SEEDS,
           duration_s: float = 40.0, every: int = 6) -> dict[str, int]:
    from sim.export import YoloExporter
    from sim.flight import FlightParams
    from sim.simulator import SimulationParams, Simulator

    totals = {"images": 0, "door": 0, "window": 0}
    for name in buildings:
        for seed in seeds:
            t0 = time.time()
            sim = Simulator(ROOT / "data" / "buildings" / name, SimulationParams(seed=seed,
                                                                                 flight=FlightParams(duration_s=duration_s)))
            exporter = YoloExporter(out, f"{Path(name).stem}_s{seed}", every_n=1)
            times = sim.frame_times_s
            for i in range(0, len(times), every):
                frame = sim.render_at(i, float(times[i]))
                exporter.add(i, frame.left_bgr, frame.features)
            sim.close()
            for k in totals:
                totals[k] += exporter.counts[k]
            log.info("%s seed %d: %s in %.0f s", name, seed, exporter.counts, time.time() - t0)
    return totals


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "sim_yolo")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log.info("exported %s to %s", export(args.out), args.out)


if __name__ == "__main__":
    main()
