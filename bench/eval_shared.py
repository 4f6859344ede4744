"""The independent harness (`../shared/eval/score_localize.py`) run in one process, for matrices of runs.

The harness spawns `macroloc localize` once per scenario (~1 s of start-up each on 2 cores), so its full matrix
(4 buildings x 3 variants x 2 noise levels x 2 seeds x 200 scenarios) would take hours. This driver loads the
harness from its own folder, unchanged, and replaces only how it runs a command: `macroloc.cli.main.main`
in this process, stdout and stderr captured, exit code returned. Scenarios, the oracle, the scoring and the
printed summary are the harness's own. Figures for the record come from the harness as shipped (one spawn per
scenario) on a subset; this driver's last lines must agree with those on the runs both made.

    python -m bench.eval_shared --eval-dir ../shared/eval -- ../shared/data/bim/X.ifc --n 200 --seed 7 \
        --variant gravity [--sigma 0.10 --drop 0.3 --fp 0.2 --flip 0.1]
    python -m bench.eval_shared --matrix --seeds 8101,8202 --n 200 --out DIR   # issue 38's table

`--matrix` runs every IFC of `--bim-dir` x variants gravity / full / nogravity x the default noise, the hard one
(`--sigma 0.10 --drop 0.3 --fp 0.2 --flip 0.1`) and 3-5 observations (`--k 3,4,5`) x each seed, keeps each run's
log and JSON in `--out`, and prints one row per run and the total of wrong answers (the target: 0).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import sys
import time
from pathlib import Path

MODES = {"default": [], "hard": ["--sigma", "0.10", "--drop", "0.3", "--fp", "0.2", "--flip", "0.1"],
         "k345": ["--k", "3,4,5"]}
VARIANTS = ("gravity", "full", "nogravity")


CONFIG: list[str] = []  # `--config FILE`: added to every `localize` call (e.g. [localize] decision = "posterior")


def in_process_cli(argv: list[str], timeout: float | None = None) -> tuple[int, str, str, float]:
    """`macroloc ARGS` in this process: (exit code, stdout, stderr, wall seconds); argv[0] is the program."""
    from macroloc.cli.main import main

    if CONFIG and len(argv) > 1 and argv[1] == "localize":
        argv = [*argv, "--config", *CONFIG]
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(list(argv[1:]))
        except SystemExit as exc:
            rc = int(exc.code or 0) if not isinstance(exc.code, str) else 1
    return rc, out.getvalue(), err.getvalue(), time.perf_counter() - t0


def run_harness(harness, argv: list[str]) -> None:
    """The harness's main() on `argv` (its own command line, without the program name)."""
    saved = sys.argv
    sys.argv = ["score_localize.py", *argv, "--cmd", "macroloc"]
    try:
        harness.main()
    finally:
        sys.argv = saved


def matrix(harness, bim_dir: Path, seeds: list[int], n: int, out: Path) -> int:
    """Every IFC x variant x mode x seed (module doc); returns the number of wrong answers."""
    out.mkdir(parents=True, exist_ok=True)
    print(f"{'building':<28} {'variant':<9} {'mode':<7} {'seed':>5}  {'succ':>6} {'wrong':>5} {'amb':>5} "
          f"{'not_loc':>7}  {'unamb_succ':>10} {'honest':>7} {'n_amb':>5}  {'p95_ms':>6}", flush=True)
    wrong = 0
    for ifc in sorted(bim_dir.glob("*.ifc")):
        name = ifc.stem.split("__")[-1][:28]
        for variant in VARIANTS:
            for mode, extra in MODES.items():
                for seed in seeds:
                    stem = out / f"{name}-{variant}-{mode}-{seed}"
                    buf = io.StringIO()
                    with contextlib.redirect_stdout(buf):
                        run_harness(harness, [str(ifc), "--n", str(n), "--seed", str(seed), "--variant", variant,
                                              *extra, "--no-contract", "--json-out", f"{stem}.json"])
                    stem.with_suffix(".log").write_text(buf.getvalue())
                    s = json.loads(Path(f"{stem}.json").read_text())["summary"]
                    u, a = s["unambiguous"], s["ambiguous_truth"]
                    wrong += int(s["wrong"])
                    pct = lambda x: "-" if x is None else f"{x:.1f}"  # noqa: E731
                    print(f"{name:<28} {variant:<9} {mode:<7} {seed:>5}  {100.0 * s['success'] / s['n']:>6.1f} "
                          f"{s['wrong']:>5} {s['ambiguous']:>5} {s['not_localized']:>7}  "
                          f"{pct(u.get('success_pct')):>10} {pct(a.get('honest_pct')):>7} {a['n']:>5}  "
                          f"{pct(s.get('elapsed_ms_p95')):>6}", flush=True)
    print(f"wrong answers in all runs: {wrong} (target 0)")
    return wrong


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 epilog="Arguments after -- go to score_localize.py.")
    ap.add_argument("--eval-dir", type=Path, default=Path("../shared/eval"), help="the harness's folder")
    ap.add_argument("--matrix", action="store_true", help="the whole table (module doc)")
    ap.add_argument("--bim-dir", type=Path, default=Path("../shared/data/bim"))
    ap.add_argument("--seeds", default="8101,8202")
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--out", type=Path, default=Path("out/eval_shared"))
    ap.add_argument("--config", default=None, help="a config file every localize call reads (e.g. the posterior "
                    "rule: [localize] decision = \"posterior\")")
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--") if "--" in argv else len(argv)
    args = ap.parse_args(argv[:split])
    if not (args.eval_dir / "score_localize.py").is_file():
        print(f"eval_shared: error: no score_localize.py in {args.eval_dir}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(args.eval_dir.resolve()))
    harness = importlib.import_module("score_localize")
    harness.run_cli = in_process_cli
    CONFIG[:] = [args.config] if args.config else []
    if args.matrix:
        return 1 if matrix(harness, args.bim_dir, [int(x) for x in args.seeds.split(",")], args.n, args.out) else 0
    run_harness(harness, argv[split + 1:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
