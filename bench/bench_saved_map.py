"""Issue 56's saved-map figure: one saved map for `serve` and `replay` (service.saved_map). For each flight, the
map `serve` saves (the flight played into it over Zenoh in lock-step: `[service] lockstep`, each frame waiting
for its answer, so that the machine's load does not change it; truth observations, noise seed 0) is given
to `replay --map` (noise seed 7), and the map `replay --save-map` writes (seed 0) is put where a restarted `serve`
reads its own and the flight is played into it again (seed 7); also `replay --map` into the replay's own map. Each
row: the flight time and frame (30 frames/s) of the first `localized` estimate, APE RMSE after it, wrong entries.

    python -m bench.bench_saved_map FLIGHT.mcap=BUILDING.ifc [...]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
from pathlib import Path

FPS = 30.0  # the simulated recordings' stereo frame rate


def main() -> None:
    from macroloc.cli.main import main as cli
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh
    from tests.service.helpers import free_port, loopback, running_service, service_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("flights", nargs="+", help="FLIGHT.mcap=BUILDING.ifc")
    args = parser.parse_args()

    def serve(flight: Path, building: Path, state_dir: Path, seed: int) -> dict:
        port = free_port()
        cfg = service_config(building, state_dir, port)
        cfg.service.lockstep = True
        with running_service(cfg):
            r = replay_over_zenoh(flight, loopback(connect=[f"tcp/127.0.0.1:{port}"]), "t1", TruthSource(seed=seed),
                                  speed=0.0, answered=True)
        return {"time_to_localize_s": r.time_to_localize_s, "ape_rmse_m": r.ape_rmse_m,
                "wrong_localizations": r.wrong_localizations}

    def replay(flight: Path, building: Path, *tail: str) -> dict:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert cli(["replay", str(flight), "--building", str(building), "--json", *tail]) == 0
        return json.loads(out.getvalue())

    def show(name: str, doc: dict) -> None:
        t = doc["time_to_localize_s"]
        first = "never" if t is None else f"{t:.3f} s (frame {round(t * FPS)})"
        print(f"  {name:<52} first localized {first:<22} APE {doc['ape_rmse_m']!s:<7} "
              f"wrong {doc['wrong_localizations']}", flush=True)

    for pair in args.flights:
        flight, building = (Path(p) for p in pair.split("="))
        print(f"{flight.name} in {building.name}", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            served, replayed = Path(tmp, "served"), Path(tmp, "replayed")
            show("serve, fresh (seed 0; saves its map)", serve(flight, building, served, 0))
            show("replay --map <serve's map.pb> (seed 7)",
                 replay(flight, building, "--map", str(served / "t1" / "map.pb"), "--seed", "7"))
            show("replay --save-map, fresh (seed 0)",
                 replay(flight, building, "--save-map", str(replayed / "t1" / "map.pb")))
            show("serve restarted from the replay's map (seed 7)", serve(flight, building, replayed, 7))
            show("replay --map <the replay's map> (seed 7)",
                 replay(flight, building, "--map", str(replayed / "t1" / "map.pb"), "--seed", "7"))


if __name__ == "__main__":
    main()
