"""Issue 5's flight figures on rendered flights, as the README's table gives them: time to localize, APE after
localizing and wrong localizations per building, flight seed and noise seed, beside the targets.

    python -m bench.bench_flights [--buildings office_a,jasmin] [--seeds 1-5] [--noise 0,1,2]
                                  [--observations truth] [--jobs 2] [--cache /tmp/macroloc-flights]
                                  [--out RESULTS.json] [--compare BEFORE.json] [--config FILE.toml]
                                  [--one-thread]

Each flight is rendered once (`macroloc simulate BUILDING --seed S --duration 60`, cached in `--cache`, ~1 GB
and ~75 s each) and replayed through the command line as an outside tool would (`macroloc replay --json`),
`--jobs` at a time. `--compare` reads an earlier `--out` and lists every run whose time, APE or wrong count
differs: a change that should not move the figures is checked to the digit. Perception on Office_A takes the
detector adapted to it that ships in data/buildings/office_a_detector; elsewhere it takes `--detector
BUILDING=ONNX` (made by `macroloc adapt-detector`) or the shipped generic one. `--config`: a macroloc config
(TOML) every replay takes, e.g. to fly a setting against its default in two runs. `--one-thread`: each replay
on one thread (`macroloc replay --one-thread`), against the default's reading and odometry thread.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "bim"
BUILDINGS = {"office_a": ROOT / "data/buildings/office_a.ifc",
             "jasmin": SHARED / "osbim__AC90R1-Jasmin-Sun-105-2x3.ifc",
             "duplex": ROOT / "data/buildings/duplex.ifc"}
DETECTORS = {"office_a": ROOT / "data/buildings/office_a_detector/detector.onnx"}
COMPARED = ("time_to_localize_s", "ape_rmse_m", "ape_max_m", "wrong_localizations", "status_final")
TARGET_S, TARGET_APE_M = 5.0, 0.10


@dataclass(frozen=True)
class Run:
    building: str
    seed: int
    observations: str
    noise: int

    @property
    def key(self) -> str:
        return f"{self.building} s{self.seed} {self.observations} noise {self.noise}"


def summary(results: dict[str, dict]) -> list[str]:
    """Per observation kind: runs localized, within the 5 s target, the APE range, wrong localizations; one
    line each, beside the targets."""
    lines = []
    for kind in sorted({k.split()[2] for k in results}):
        mine = [r for k, r in results.items() if k.split()[2] == kind]
        times = [r["time_to_localize_s"] for r in mine if r.get("localized")]
        apes = [r["ape_rmse_m"] for r in mine if r.get("ape_rmse_m") is not None]
        wrong = sum(r["wrong_localizations"] for r in mine)
        within = sum(t <= TARGET_S for t in times)
        ape = f"{min(apes):.3f}-{max(apes):.3f} m" if apes else "-"
        lines.append(f"{kind:<10} localized {len(times)} of {len(mine)}, <= {TARGET_S:g} s on {within} of "
                     f"{len(mine)}, APE RMSE {ape} (target <= {TARGET_APE_M:g} m), wrong {wrong} (target 0)")
    return lines


def differences(before: dict[str, dict], after: dict[str, dict]) -> list[str]:
    """The runs in both whose compared figures differ, one line each: 'KEY: field before -> after, ...'."""
    out = []
    for key in sorted(before.keys() & after.keys()):
        changed = [f"{f} {before[key].get(f)} -> {after[key].get(f)}" for f in COMPARED
                   if before[key].get(f) != after[key].get(f)]
        if changed:
            out.append(f"{key}: " + ", ".join(changed))
    return out


def _numbers(text: str) -> list[int]:
    """'1-5', '0,2,4' or '1-5,91-93' -> the integers."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def _macroloc() -> str:
    return str(Path(sys.executable).with_name("macroloc"))


def _flight(cache: Path, building: str, seed: int) -> Path:
    path = cache / f"{building}-{seed}.mcap"
    if not path.exists():
        print(f"rendering {path.name} ...", flush=True)
        tmp = path.with_suffix(".part.mcap")
        subprocess.run([_macroloc(), "simulate", str(BUILDINGS[building]), "--out", str(tmp), "--seed", str(seed),
                        "--duration", "60"], check=True, stdout=subprocess.DEVNULL)
        tmp.replace(path)
    return path


def _replay(run: Run, flight: Path, configs: dict[str, Path], base: Path | None = None,
            one_thread: bool = False) -> dict:
    cmd = [_macroloc(), "replay", str(flight), "--building", str(BUILDINGS[run.building]), "--json",
           "--observations", run.observations, "--seed", str(run.noise)] + (["--one-thread"] if one_thread else [])
    if run.observations == "perception" and run.building in configs:
        cmd += ["--config", str(configs[run.building])]
    elif base is not None:
        cmd += ["--config", str(base)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout)


def _detector_configs(pairs: list[str], folder: Path, base: Path | None = None) -> dict[str, Path]:
    """Per building, a config naming its detector, on top of `base` (TOML) where given."""
    detectors = dict(DETECTORS)
    for pair in pairs:
        name, _, path = pair.partition("=")
        detectors[name] = Path(path)
    lines = [] if base is None else base.read_text().splitlines()
    configs = {}
    for name, onnx in detectors.items():
        if onnx.exists():
            key = f'detector_model = "{onnx.resolve()}"'
            at = next((i + 1 for i, line in enumerate(lines) if line.strip() == "[perception]"), None)
            text = lines[:at] + [key] + lines[at:] if at is not None else [*lines, "[perception]", key]
            configs[name] = folder / f"{name}.toml"
            configs[name].write_text("\n".join(text) + "\n")
    return configs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buildings", default="office_a,jasmin")
    parser.add_argument("--seeds", default="1-5", help="flight seeds: 1-5 or 1,3")
    parser.add_argument("--noise", default="0,1,2", help="noise seeds of truth and truth-vo (perception: the first)")
    parser.add_argument("--observations", default="truth", help="any of truth,truth-vo,perception")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/macroloc-flights"))
    parser.add_argument("--detector", action="append", default=[], help="BUILDING=ONNX for perception")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--compare", type=Path)
    parser.add_argument("--config", type=Path, help="a macroloc config (TOML) for every replay")
    parser.add_argument("--one-thread", action="store_true", help="each replay on one thread")
    args = parser.parse_args()
    buildings = args.buildings.split(",")
    unknown = [b for b in buildings if b not in BUILDINGS or not BUILDINGS[b].exists()]
    if unknown:
        print(f"bench_flights: unknown or absent building(s): {', '.join(unknown)}", file=sys.stderr)
        return 2
    args.cache.mkdir(parents=True, exist_ok=True)
    noise = _numbers(args.noise)
    runs = [Run(b, s, kind, n) for b in buildings for s in _numbers(args.seeds)
            for kind in args.observations.split(",") for n in (noise[:1] if kind == "perception" else noise)]
    flights = {(b, s): _flight(args.cache, b, s) for b, s in sorted({(r.building, r.seed) for r in runs})}
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(max(1, args.jobs)) as pool:
        configs = _detector_configs(args.detector, Path(tmp), args.config)
        futures = {r.key: pool.submit(_replay, r, flights[(r.building, r.seed)], configs, args.config,
                                          args.one_thread)
                   for r in runs}
        results = {}
        for key, future in futures.items():
            results[key] = future.result()
            r = results[key]
            print(f"{key:<36} " + (r["error"] if "error" in r else
                                   f"{r['time_to_localize_s']!s:>7} s  APE {r['ape_rmse_m']!s:>7} m  "
                                   f"wrong {r['wrong_localizations']}  {r['status_final']}"), flush=True)
    ok = {k: r for k, r in results.items() if "error" not in r}
    print("\n".join(summary(ok)))
    if args.out:
        args.out.write_text(json.dumps(results, indent=1, sort_keys=True))
    if args.compare:
        changed = differences(json.loads(args.compare.read_text()), ok)
        print(f"against {args.compare}: " + ("the same figures on every run in both" if not changed else
                                              f"{len(changed)} runs differ\n  " + "\n  ".join(changed)))
    return 1 if len(ok) < len(results) else 0


if __name__ == "__main__":
    sys.exit(main())
