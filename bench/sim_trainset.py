"""Rendered detector training frames: seeded simulated flights through the training buildings, every N-th frame
written as a left image with YOLO labels (0 door, 1 window) by `sim.export.YoloExporter`.

    python -m bench.sim_trainset [--out out/sim_yolo]

Office_A is kept out: it is the building "not used in training" on which `bench.eval_perception_sim` scores the
detector on rendered frames. Only the exported frames are rendered (no MCAP), which is ~10x faster than
`macroloc simulate --yolo`. Called by `python -m macroloc.perception.train` when its rendered-frames folder is missing.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRAIN_BUILDINGS = ("duplex.ifc", "fzk_haus.ifc")
SEEDS = (1, 2, 3)

log = logging.getLogger(__name__)


def export(out: Path, buildings: tuple[str, ...] = TRAIN_BUILDINGS, seeds: tuple[int, ...] = SEEDS,
           duration_s: float = 40.0, every: int = 6) -> dict[str, int]:
    from macroloc.sim.export import render_training_frames

    totals = {"images": 0, "door": 0, "window": 0}
    for name in buildings:
        counts = render_training_frames(ROOT / "data" / "buildings" / name, out, seeds, duration_s, every)
        for k in totals:
            totals[k] += counts[k]
    return totals


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "sim_yolo")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log.info("exported %s to %s", export(args.out), args.out)


if __name__ == "__main__":
    main()
