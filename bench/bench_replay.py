"""Issue 5's flight figures with `--observations truth`: time to localize, APE after localization, wrong
localizations, per building and seed; re-localization into a saved map.

    python -m bench.bench_replay [--seeds 0,1,2] [--duration 60] [--start open|random] [--out /tmp/macroloc-flights]

Flights are ground-truth-only recordings (sim.truth_flight: a take-off turn on the spot, then a random
walk through the storey's free space), replayed as the service runs them (service.offline.run.replay_flight: the
service's front end from the default config); re-localization: the flight again, with another noise seed, from the
map the first run saved. A rendered simulator flight can be replayed the same way with `macroloc replay FLIGHT
--building B --json`.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from bench.common import row

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "bim"
BUILDINGS = {"Office_A": ROOT / "data/buildings/office_a.ifc",
             "Jasmin-Sun": SHARED / "osbim__AC90R1-Jasmin-Sun-105-2x3.ifc",
             "duplex": ROOT / "data/buildings/duplex.ifc"}


def main() -> None:
    from macroloc.service.config import load_config
    from macroloc.service.offline.run import ReplayOptions, replay_flight
    from macroloc.sim.truth_flight import write_truth_flight

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--start", default="open", choices=["open", "random"])
    parser.add_argument("--out", type=Path, default=Path("/tmp/macroloc-flights"))
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    cfg = load_config(None)  # the service's front end (service.front_end.make_front_end), default config
    print(f"{'building':<11} {'seed':>4} {'localize s':>10} {'APE rmse':>9} {'APE max':>8} {'wrong':>5} "
          f"{'links':>5} {'bad links':>9} {'final':>10} {'relocalize (proc s / flight s)':>32}")
    for name, path in BUILDINGS.items():
        if not path.exists():
            print(f"{name}: {path} absent, skipped")
            continue
        for seed in seeds:
            flight = args.out / f"{path.stem}-{args.start}-{int(args.duration)}s-{seed}.mcap"
            if not flight.exists():
                write_truth_flight(path, flight, seed=seed, duration_s=args.duration, start=args.start)
            first = replay_flight(flight, path, cfg, ReplayOptions(seed=seed))
            r = first.result
            j = r.to_json()
            reloc = "-"
            saved = first.save_map(flight.with_suffix(".map.pb"), path) if r.localized else None
            if saved is not None:  # re-flown into its saved map, with another noise seed
                again = replay_flight(flight, path, cfg, ReplayOptions(seed=seed + 100), saved_map=saved).result
                reloc = f"{again.processing_to_localize_s:.3f} / {again.time_to_localize_s:.2f}" if again.localized \
                    else "not localized"
            print(f"{name:<11} {seed:>4} {j['time_to_localize_s']!s:>10} {j['ape_rmse_m']!s:>9} "
                  f"{j['ape_max_m']!s:>8} {j['wrong_localizations']:>5} {j['cad_links']:>5} {j['wrong_links']:>9} "
                  f"{j['status_final']:>10} {reloc:>32}")
    print(row("targets", "", "localize <= 5 s, APE RMSE <= 0.10 m, 0 wrong, re-localize <= 0.3 s processing"))


if __name__ == "__main__":
    main()
