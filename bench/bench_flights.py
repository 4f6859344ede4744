"""Issue 5's flight figures on rendered flights, as the README's table gives them: time to localize, APE after
localizing and wrong localizations per building, flight seed and noise seed, beside the targets.

    python -m bench.bench_flights [--buildings office_a,jasmin] [--seeds 1-5] [--noise 0,1,2]
                                  [--observations truth] [--odometry auto] [--over-zenoh] [--duration 60]
                                  [--jobs 2] [--cache /tmp/macroloc-flights] [--out RESULTS.json]
                                  [--compare BEFORE.json] [--config FILE.toml]

Each flight is rendered once (`macroloc simulate BUILDING --seed S --duration D`, cached in `--cache`; a 60 s
flight is ~1 GB and ~75 s of an idle machine's time) and replayed through the service's own per-frame path, one
library call per run (service.offline.run.replay_offline, as `macroloc replay --json`), each run in its own worker
process, `--jobs` at a time. `--odometry`: the vehicle's odometry (auto, recorded, simulated, visual; as `macroloc
replay --odometry`). `--over-zenoh`: each run also played into a `macroloc serve` started in the run's process
(lock-step, on a free loopback port, with an empty state directory) as its vehicle sends it (speed 0, each frame
waiting for its answer: service.offline.replay_zenoh), its figures beside the offline ones under the run's key
followed by `over-zenoh`, and the runs whose figures differ between the two listed: the offline replay is the
service, so none should. `--compare` reads an earlier `--out` and lists every run whose time, APE or wrong count
differs: a change that should not move the figures is checked to the digit. Perception on Office_A takes the
detector adapted to it that ships in data/buildings/office_a_detector; elsewhere it takes `--detector
BUILDING=ONNX` (made by `macroloc adapt-detector`) or the shipped generic one. `--config`: a macroloc config
(TOML) every replay takes, e.g. to fly a setting against its default in two runs.
"""

from __future__ import annotations

import argparse
import itertools
import json
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "bim"
BUILDINGS = {"office_a": ROOT / "data/buildings/office_a.ifc",
             "jasmin": SHARED / "osbim__AC90R1-Jasmin-Sun-105-2x3.ifc",
             "duplex": ROOT / "data/buildings/duplex.ifc"}
DETECTORS = {"office_a": ROOT / "data/buildings/office_a_detector/detector.onnx"}
COMPARED = ("time_to_localize_s", "ape_rmse_m", "ape_max_m", "wrong_localizations", "status_final")
# the figures both transports give, compared to the decimals the
# over-Zenoh JSON keeps (service.offline.replay_zenoh: the time to 1 ms; the offline JSON's to 0.1 ms)
COMPARED_TRANSPORTS = ("time_to_localize_s", "ape_rmse_m", "ape_max_m", "wrong_localizations",
                       "wrong_while_localized_s", "status_final", "keyframes", "landmarks", "cad_links", "wrong_links")
TRANSPORT_DECIMALS = {"time_to_localize_s": 3, "ape_rmse_m": 4, "ape_max_m": 4, "wrong_while_localized_s": 3}
OVER_ZENOH = "over-zenoh"  # the last word of a run's key played into a service
TARGET_S, TARGET_APE_M = 5.0, 0.10
SERVICE_READY_S = 600.0  # a cold building cache on a loaded machine takes minutes; a dead service fails at once


@dataclass(frozen=True)
class Run:
    building: str
    seed: int
    observations: str
    noise: int
    odometry: str = "auto"
    over_zenoh: bool = False

    @property
    def key(self) -> str:
        return f"{self.building} s{self.seed} {self.observations} noise {self.noise}" + \
            (f" {OVER_ZENOH}" if self.over_zenoh else "")


def _group(key: str) -> str:
    """A run's line in the summary: its observation kind, and `over-zenoh` where played into a service."""
    words = key.split()
    return words[2] + (f" {OVER_ZENOH}" if words[-1] == OVER_ZENOH else "")


def summary(results: dict[str, dict]) -> list[str]:
    """Per observation kind (offline and over Zenoh apart): runs localized, within the 5 s target, the APE range,
    wrong localizations; one line each, beside the targets."""
    lines = []
    for kind in sorted({_group(k) for k in results}):
        mine = [r for k, r in results.items() if _group(k) == kind]
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


def transport_differences(results: dict[str, dict]) -> list[str]:
    """The runs replayed both offline and over Zenoh whose figures differ between the two (COMPARED_TRANSPORTS),
    one line each: 'KEY: field offline -> over Zenoh, ...'."""
    out = []
    for key in sorted(k for k in results if not k.endswith(OVER_ZENOH)):
        served = results.get(f"{key} {OVER_ZENOH}")
        if served is None or "error" in served or "error" in results[key]:
            continue
        changed = [f"{f} {results[key].get(f)} -> {served.get(f)}" for f in COMPARED_TRANSPORTS
                   if _kept(f, results[key].get(f)) != _kept(f, served.get(f))]
        if changed:
            out.append(f"{key}: " + ", ".join(changed))
    return out


def _kept(field: str, value: object) -> object:
    """`value` to the decimals both transports keep of `field` (TRANSPORT_DECIMALS)."""
    return round(value, TRANSPORT_DECIMALS[field]) if field in TRANSPORT_DECIMALS and \
        isinstance(value, float) else value


def _numbers(text: str) -> list[int]:
    """'1-5', '0,2,4' or '1-5,91-93' -> the integers."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def _macroloc() -> str:
    return str(Path(sys.executable).with_name("macroloc"))


def _flight(cache: Path, building: str, seed: int, duration_s: float = 60.0) -> Path:
    """The flight rendered once per building, seed and duration (the default's name without the duration, as
    earlier caches hold it)."""
    name = f"{building}-{seed}" + ("" if duration_s == 60.0 else f"-{duration_s:g}s")
    path = cache / f"{name}.mcap"
    if not path.exists():
        print(f"rendering {path.name} ...", flush=True)
        tmp = path.with_suffix(".part.mcap")
        subprocess.run([_macroloc(), "simulate", str(BUILDINGS[building]), "--out", str(tmp), "--seed", str(seed),
                        "--duration", f"{duration_s:g}", "--contact-sheet", str(path.with_suffix(".png"))],
                       check=True, stdout=subprocess.DEVNULL)
        tmp.replace(path)
    return path


def replay_run(run: Run, flight: Path, config: Path | None = None, detector: Path | None = None) -> dict:
    """One run's JSON (`macroloc replay --json`'s keys): `flight` in `run.building` through the service's per-frame
    path, offline or (`run.over_zenoh`) played into a service started here; with `config` (TOML) and, for
    perception, the `detector` (ONNX) in place of the config's. A failure is the run's {"error": message}."""
    from macroloc.service.config import load_config
    from macroloc.service.offline.run import ReplayOptions, replay_offline

    try:
        cfg = load_config(config)
        if run.observations == "perception" and detector is not None:
            cfg = cfg.model_copy(update={"perception": cfg.perception.model_copy(
                update={"detector_model": detector.resolve()})})
        options = ReplayOptions(run.observations, run.odometry, run.noise).checked()
        if run.over_zenoh:
            return _served(flight, BUILDINGS[run.building], cfg, options)
        return replay_offline(flight, BUILDINGS[run.building], cfg, options).to_json()
    except Exception as exc:  # noqa: BLE001 - a run's failure is its row, as the CLI's exit was
        return {"error": f"{type(exc).__name__}: {exc}"}


def _served(flight: Path, building: Path, cfg, options) -> dict:  # noqa: ANN001 - MacrolocConfig, ReplayOptions
    """`flight` played into a lock-step `macroloc serve` in this process, configured as the offline replay
    configures the service (service.offline.run.service_config_for), on a free loopback port with an empty state
    directory (no saved map to restore); the vehicle sends what the offline replay's sends (vehicle_for)."""
    from macroloc.proto.recording import read_flight
    from macroloc.service.config import ZenohConfig
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh
    from macroloc.service.offline.run import service_config_for, vehicle_for

    frames = iter(read_flight(flight))
    first = next(frames, None)
    served = service_config_for(cfg, options, vehicle_for(options, first).choice)
    port, vehicle = _free_port(), f"bench{os.getpid()}"
    with tempfile.TemporaryDirectory(prefix="bench-flights-") as state:
        service = served.service.model_copy(update={"building": building, "state_dir": Path(state),
                                                    "vehicle": vehicle, "lockstep": True,
                                                    "status_period_s": 0.2})  # its last status soon after the end
        served = served.model_copy(update={"service": service, "zenoh": ZenohConfig(
            mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[])})
        with _running_service(served):
            result = replay_over_zenoh(itertools.chain([first] if first is not None else [], frames),
                                       ZenohConfig(mode="peer", listen=[], connect=served.zenoh.listen), vehicle,
                                       None, speed=0.0, answered=True,
                                       sender=vehicle_for(options, first, visual_if_none=False))
    return result.to_json()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def _running_service(cfg) -> Iterator[None]:  # noqa: ANN001 - MacrolocConfig
    """`macroloc serve` with `cfg` in a thread on its own session, once ready; stopped and joined on exit."""
    from macroloc.service.serve import build_service
    from macroloc.service.zenoh_io import open_session

    stop, box = threading.Event(), {}

    def serve() -> None:
        with open_session(cfg.zenoh) as session:
            box["service"] = build_service(cfg, session)
            box["service"].run(stop)

    thread = threading.Thread(target=serve, name="bench-serve", daemon=True)
    thread.start()
    deadline = time.monotonic() + SERVICE_READY_S
    while not ("service" in box and box["service"].ready.is_set()):
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the service died while starting" if not thread.is_alive() else
                               f"the service was not ready after {SERVICE_READY_S:g} s")
        time.sleep(0.05)
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=60.0)


def _detectors(pairs: list[str]) -> dict[str, Path]:
    """Per building, the detector its perception runs take: the shipped ones, then `--detector BUILDING=ONNX`."""
    detectors = {name: onnx for name, onnx in DETECTORS.items() if onnx.exists()}
    for pair in pairs:
        name, _, path = pair.partition("=")
        detectors[name] = Path(path)
    return detectors


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buildings", default="office_a,jasmin")
    parser.add_argument("--seeds", default="1-5", help="flight seeds: 1-5 or 1,3")
    parser.add_argument("--noise", default="0,1,2", help="noise seeds of truth and truth-vo (perception: the first)")
    parser.add_argument("--observations", default="truth", help="any of truth,truth-vo,perception")
    parser.add_argument("--odometry", default="auto", help="the vehicle's: auto, recorded, simulated or visual")
    parser.add_argument("--over-zenoh", action="store_true", help="also play each run into a lock-step service")
    parser.add_argument("--duration", type=float, default=60.0, help="flight duration, s (rendered per duration)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/macroloc-flights"))
    parser.add_argument("--detector", action="append", default=[], help="BUILDING=ONNX for perception")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--compare", type=Path)
    parser.add_argument("--config", type=Path, help="a macroloc config (TOML) for every replay")
    args = parser.parse_args()
    buildings = args.buildings.split(",")
    unknown = [b for b in buildings if b not in BUILDINGS or not BUILDINGS[b].exists()]
    if unknown:
        print(f"bench_flights: unknown or absent building(s): {', '.join(unknown)}", file=sys.stderr)
        return 2
    if not args.duration > 0:
        print(f"bench_flights: --duration must be positive, not {args.duration}", file=sys.stderr)
        return 2
    args.cache.mkdir(parents=True, exist_ok=True)
    noise = _numbers(args.noise)
    runs = [Run(b, s, kind, n, args.odometry, served) for b in buildings for s in _numbers(args.seeds)
            for kind in args.observations.split(",") for n in (noise[:1] if kind == "perception" else noise)
            for served in ((False, True) if args.over_zenoh else (False,))]
    flights = {(b, s): _flight(args.cache, b, s, args.duration)
               for b, s in sorted({(r.building, r.seed) for r in runs})}
    detectors = _detectors(args.detector)
    # a fresh process per run: nothing cached in memory carries from one run to the next
    with ProcessPoolExecutor(max(1, args.jobs), mp_context=multiprocessing.get_context("spawn"),
                             max_tasks_per_child=1) as pool:
        futures = {r.key: pool.submit(replay_run, r, flights[(r.building, r.seed)], args.config,
                                      detectors.get(r.building)) for r in runs}
        results = {}
        for key, future in futures.items():
            results[key] = future.result()
            r = results[key]
            print(f"{key:<47} " + (r["error"] if "error" in r else
                                   f"{r['time_to_localize_s']!s:>7} s  APE {r['ape_rmse_m']!s:>7} m  "
                                   f"wrong {r['wrong_localizations']}  keyframes {r.get('keyframes')}  "
                                   f"{r['status_final']}"), flush=True)
    ok = {k: r for k, r in results.items() if "error" not in r}
    print("\n".join(summary(ok)))
    moved = transport_differences(results)
    if args.over_zenoh:
        print("offline against over Zenoh: " + ("the same figures on every run replayed both ways" if not moved else
                                                f"{len(moved)} runs differ\n  " + "\n  ".join(moved)))
    if args.out:
        args.out.write_text(json.dumps(results, indent=1, sort_keys=True))
    if args.compare:
        changed = differences(json.loads(args.compare.read_text()), ok)
        print(f"against {args.compare}: " + ("the same figures on every run in both" if not changed else
                                              f"{len(changed)} runs differ\n  " + "\n  ".join(changed)))
    return 1 if len(ok) < len(results) or moved else 0  # a run failed, or the two transports differ


if __name__ == "__main__":
    sys.exit(main())
