"""Issue 58 item 5's figure: the one-shot CLI's `elapsed_ms` on a campus of identical units, through the CLI.

    python -m bench.bench_cli_campus [--building data/buildings/office_a.ifc] [--units 64] [--n 20]
                                     [--python PY] [--pythonpath DIR] [--out DIR] [--cache DIR] [--profile] [--cpu]
                                     [--baseline-pythonpath DIR [--baseline-cache DIR]]

A campus: `--units` copies of a bundled building's doors and windows on a grid (offset by the extent of its
features + 5 m, as bench.bench_scale's tiling), written as an IFC file the CLI reads (`campus_ifc`: each copy an
IfcDoor / IfcWindow sharing the original's shape, placed absolutely, contained in the original's storey). Its
requests come from `graph.evaluation.make_scenario` (seed 58: K 20/25/30, gravity given, default noise), written as
OBS.json files; each is answered by a fresh `python -m macroloc.cli.main localize CAMPUS --observations OBS --json`
process (the `macroloc` command's entry point), after one warm-up call (which builds the per-building caches on
disk, as `macroloc prepare` would). Printed: the features, `elapsed_ms` (the registration alone) p50 / p95 beside
the target (p95 <= 50 ms), `total_ms` (the command from its start, after Python's start-up and the imports of the
command module) and the wall time per call (the whole process), and the statuses. `--profile`: one call's parts,
timed in a fresh process (start-up, imports, reading the observations, loading the building, the per-building
index, the registration). `--cpu`: each request's registration again in a fresh process, its CPU time.
`--baseline-pythonpath`: other code (a tree of links `macroloc/<folder>` to another worktree's folders, e.g. today's
code) run on each request right before this code's, and the answers compared.
Wall figures depend on the machine's load (2 cores shared here): compare runs made one after the other.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TARGET_P95_MS = 50.0
SEED = 58


def campus_ifc(base_path: Path, units: int, out_path: Path) -> Path:
    """Write `units` copies of the doors and windows of the IFC file `base_path` (the first copy is the original
    file itself, walls and all) on a grid to `out_path`, unless it exists already."""
    if out_path.exists():
        return out_path
    import ifcopenshell
    import ifcopenshell.guid
    import ifcopenshell.util.placement as up
    import ifcopenshell.util.unit as uu

    from macroloc.graph.bim import load_building

    base = load_building(base_path)
    c = base.centroids_cad()
    ext = c.max(axis=0) - c.min(axis=0)
    side = int(np.ceil(np.sqrt(units)))
    ifc = ifcopenshell.open(str(base_path))
    scale = uu.calculate_unit_scale(ifc)  # metres per project length unit (placements are in project units)
    originals = list(ifc.by_type("IfcDoor")) + list(ifc.by_type("IfcWindow"))
    storey_rels: dict[int, object] = {}
    for e in originals:
        from macroloc.graph.bim_ifc import storey_of

        storey = storey_of(e)
        if storey is None or e.ObjectPlacement is None or e.Representation is None:
            continue
        matrix = up.get_local_placement(e.ObjectPlacement)
        for k in range(1, units):
            off = np.array([(k % side) * (ext[0] + 5.0), (k // side) * (ext[1] + 5.0), 0.0]) / scale
            placement = ifc.createIfcLocalPlacement(None, ifc.createIfcAxis2Placement3D(
                ifc.createIfcCartesianPoint([float(v) for v in matrix[:3, 3] + off]),
                ifc.createIfcDirection([float(v) for v in matrix[:3, 2]]),
                ifc.createIfcDirection([float(v) for v in matrix[:3, 0]])))
            copy = ifc.create_entity(e.is_a(), GlobalId=ifcopenshell.guid.new(), OwnerHistory=e.OwnerHistory,
                                     Name=f"u{k}:{e.Name or ''}", ObjectPlacement=placement,
                                     Representation=e.Representation)
            if storey.id() not in storey_rels:
                storey_rels[storey.id()] = ifc.createIfcRelContainedInSpatialStructure(
                    ifcopenshell.guid.new(), None, "campus copies", None, [], storey)
            rel = storey_rels[storey.id()]
            rel.RelatedElements = [*rel.RelatedElements, copy]  # type: ignore[attr-defined]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f"{out_path.stem}.tmp{os.getpid()}.ifc")
    ifc.write(str(tmp))
    os.replace(tmp, out_path)
    return out_path


def write_requests(campus: Path, n: int, out_dir: Path) -> list[Path]:
    """n OBS.json requests on the campus (graph.evaluation.make_scenario, seed SEED, K 20/25/30, gravity)."""
    from macroloc.graph.bim import load_building
    from macroloc.graph.evaluation import ScenarioParams, make_scenario

    model = load_building(campus)
    paths = []
    for i in range(n):
        s = make_scenario(model, i, SEED, ScenarioParams(variant="gravity", k_choices=(20, 25, 30)))
        doc = {"frame": "map",
               "gravity": None if s.obs.gravity_map is None else [float(v) for v in s.obs.gravity_map],
               "features": [{"type": o.type, "corners": np.asarray(o.corners_map).tolist()}
                            for o in s.obs.observations]}
        path = out_dir / f"obs-{i:03d}.json"
        path.write_text(json.dumps(doc))
        paths.append(path)
    return paths


def run_cli(cmd: list[str], campus: Path, obs: Path, env: dict) -> tuple[dict, float]:
    t0 = time.perf_counter()
    p = subprocess.run([*cmd, "localize", str(campus), "--observations", str(obs), "--json"], capture_output=True,
                       text=True, env=env, timeout=300)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} localize failed ({p.returncode}): {p.stderr.strip()[-500:]}")
    return json.loads(p.stdout), wall


PROFILE = """
import json, sys, time
t = [("start", time.perf_counter())]
import macroloc.cli.main  # noqa: F401 - the CLI's own imports (typer, its commands)
t.append(("import the CLI (typer, commands)", time.perf_counter()))
from macroloc.graph.bim import load_building
from macroloc.graph.model_index import index_for
from macroloc.graph.observations import parse_observations
from macroloc.graph.registration import register
t.append(("import the command's modules (numpy, scipy, graph)", time.perf_counter()))
obs = parse_observations(json.loads(open(sys.argv[2]).read()))
t.append(("read the observations", time.perf_counter()))
model = load_building(sys.argv[1])
t.append(("load_building (SHA-256, features cache)", time.perf_counter()))
index_for(model)
t.append(("index_for (per-building assets)", time.perf_counter()))
c0 = time.process_time()
r = register(model, obs)
cpu = time.process_time() - c0
t.append(("register (outside its timed block too)", time.perf_counter()))
print(json.dumps([[name, 1000 * (b - a)] for (_, a), (name, b) in zip(t, t[1:])] + [["elapsed_ms", r.elapsed_ms],
                 ["register CPU ms", 1000 * cpu]]))
"""


def parts(python: list[str], campus: Path, obs: Path, env: dict) -> dict[str, float]:
    """The wall time (ms) of one call's parts in a fresh process (nothing memoised): the interpreter's start, then
    the command's steps in the order it runs them; and the CPU time of its registration (`register CPU ms`: less
    sensitive than wall time to the other jobs on a shared machine)."""
    t0 = time.perf_counter()
    subprocess.run([*python, "-c", "pass"], check=True, env=env)
    start = 1000 * (time.perf_counter() - t0)
    p = subprocess.run([*python, "-c", PROFILE, str(campus), str(obs)], capture_output=True, text=True, env=env,
                       check=True)
    return {"python start-up": start, **dict(json.loads(p.stdout.strip().splitlines()[-1]))}


def percentiles(values: list[float]) -> str:
    return f"p50 {np.median(values):7.1f} / p95 {np.percentile(values, 95):7.1f}"


def run_all(cmd: list[str], campus: Path, requests: list[Path], env: dict) -> list[dict]:
    rows = []
    for path in requests:
        doc, w = run_cli(cmd, campus, path, env)
        rows.append({"request": path.name, "status": doc["status"], "T_cad_map": doc["T_cad_map"],
                     "alternatives": doc["alternatives"], "inliers": doc["inliers"], "elapsed_ms": doc["elapsed_ms"],
                     "total_ms": doc.get("total_ms", float("nan")), "wall_ms": 1000.0 * w})
    return rows


def report(name: str, rows: list[dict], first_wall: float) -> None:
    elapsed = [r["elapsed_ms"] for r in rows]
    p95 = float(np.percentile(elapsed, 95))
    statuses = {s: sum(r["status"] == s for r in rows) for s in ("localized", "ambiguous", "not_localized")}
    print(f"{name}: first call (builds the caches) wall {first_wall:.1f} s")
    print(f"{name}: elapsed_ms {percentiles(elapsed)} ms   target p95 <= {TARGET_P95_MS:.0f} ms: "
          f"{'ok' if p95 <= TARGET_P95_MS else 'MISSED'}")
    print(f"{name}: total_ms   {percentiles([r['total_ms'] for r in rows])} ms")
    print(f"{name}: wall/call  {percentiles([r['wall_ms'] for r in rows])} ms")
    print(f"{name}: statuses " + ", ".join(f"{k} {v}" for k, v in statuses.items()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--units", type=int, default=64)
    ap.add_argument("--n", type=int, default=20, help="requests (one CLI process each)")
    ap.add_argument("--python", default=sys.executable, help="the interpreter that runs the CLI (python -m "
                    "macroloc.cli.main)")
    ap.add_argument("--pythonpath", default=None, help="PYTHONPATH for it (default: none, the installed code)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_cli_campus", help="campus, requests, cache")
    ap.add_argument("--cache", type=Path, default=None, help="MACROLOC_CACHE of the CLI (default: OUT/cache)")
    ap.add_argument("--baseline-pythonpath", default=None, help="also run this code (a package tree of another "
                    "worktree: today's code), each request right after the other (the same load), and compare "
                    "the answers")
    ap.add_argument("--baseline-cache", type=Path, default=None, help="its MACROLOC_CACHE (default: OUT/cache-base)")
    ap.add_argument("--profile", action="store_true", help="also time the parts of one call in a fresh process")
    ap.add_argument("--cpu", action="store_true", help="also the CPU time of each request's registration (a fresh "
                    "process each, in-process timing)")
    ap.add_argument("--json-out", type=Path, default=None, help="per-call results (status, pose, times)")
    args = ap.parse_args(argv)
    python = shlex.split(args.python)
    cmd = [*python, "-m", "macroloc.cli.main"]
    campus = campus_ifc(args.building, args.units, args.out / f"campus-{args.building.stem}-{args.units}.ifc")
    req_dir = args.out / f"requests-{args.units}"
    req_dir.mkdir(parents=True, exist_ok=True)
    requests = write_requests(campus, args.n, req_dir)
    runs = {"new": (args.pythonpath, args.cache or args.out / "cache")}
    if args.baseline_pythonpath:
        runs = {"base": (args.baseline_pythonpath, args.baseline_cache or args.out / "cache-base"), **runs}
    envs, first = {}, {}
    for name, (pythonpath, cache) in runs.items():
        envs[name] = dict(os.environ, MACROLOC_CACHE=str(cache))
        if pythonpath:
            envs[name]["PYTHONPATH"] = pythonpath
        first[name] = run_cli(cmd, campus, requests[0], envs[name])[1]  # builds the per-building caches on disk
    from macroloc.graph.bim import load_building

    print(f"# bench_cli_campus: {args.building.name} x {args.units} = {len(load_building(campus).features)} "
          f"features; {args.n} requests; {' '.join(cmd)}; cores {os.cpu_count()}, "
          f"load average {os.getloadavg()[0]:.1f}")
    for name, (pythonpath, _) in runs.items():
        print(f"# {name}: PYTHONPATH {pythonpath or '-'}")
    if args.profile:
        for name in runs:
            print(f"# {name}: one call's parts (wall; a fresh process):")
            for part, ms in parts(python, campus, requests[0], envs[name]).items():
                print(f"#   {part:<52} {ms:8.1f} ms")
    rows: dict[str, list[dict]] = {name: [] for name in runs}
    for path in requests:  # each request by every code in turn: the same load on the machine for both
        for name in runs:
            rows[name] += run_all(cmd, campus, [path], envs[name])
    for name in runs:
        report(name, rows[name], first[name])
    if args.cpu:  # each request again, in a fresh process: the CPU time of its registration
        cpu: dict[str, list[float]] = {name: [] for name in runs}
        for path in requests:
            for name in runs:
                cpu[name].append(parts(python, campus, path, envs[name])["register CPU ms"])
        for name in runs:
            print(f"{name}: registration CPU ms (the first in a process, as the CLI's) {percentiles(cpu[name])} ms")
    if "base" in rows:
        same = sum(a["status"] == b["status"] and a["T_cad_map"] == b["T_cad_map"]
                   and a["alternatives"] == b["alternatives"] for a, b in zip(rows["base"], rows["new"], strict=True))
        print(f"answers identical to the baseline's (status, T_cad_map, alternatives): {same} of {len(requests)}")
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(rows, indent=1))
    print(f"# load average at the end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
