"""Issue 58: is the posterior calibrated, and what would it decide? The shared harness's scenarios, in-process.

For each scenario of `../shared/eval/scenarios.py` (its own generator, its ambiguity oracle, its scoring
`score_localize.score_run`, all unchanged) the registration runs twice in this process, once per rule
(`RobustParams.decision`: "margin", today's, and "posterior"), and every pose the posterior lists (in the
posterior rule's run: its search seeds from every rectangle) is checked against the truth: right when it puts
every true observed feature within 0.5 m of where the true transform puts it (the harness's line between a correct
answer and a wrong one). Prints:

* the reliability table: per bin of stated probability, the poses stated, the mean stated probability and the
  fraction right (the best pose of each scenario; and every listed pose);
* per rule, the harness's figures: wrong, unambiguous success, honest `ambiguous`, `not_localized`.

    python -m bench.bench_calibration ../shared/data/bim/webifc__Office_A_20110811.ifc --n 50 --seed 5801 \
        [--variant gravity] [--sigma 0.10 --drop 0.3 --fp 0.2 --flip 0.1] [--plot docs/img/x.png] [--json-out F]
    python -m bench.bench_calibration --pool RUN1.json RUN2.json ... [--plot PNG [TITLE]]   # runs together
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

RULES = ("margin", "posterior")
BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 0.999, 1.0 + 1e-9)
RIGHT_M = 0.5  # the harness's WRONG_TRANS_M


def pose_error_m(T_cad_map: np.ndarray, truth_doc: dict) -> float:
    """Max over the true observed features of |T p - T_true p|, p their noise-free centroids in the map frame."""
    true_obs = [o for o in truth_doc["observations"] if o["truth"] != "false_positive"]
    c_cad = np.array([o["centroid_cad"] for o in true_obs])
    T_map_cad = np.array(truth_doc["T_map_cad"])
    p_map = c_cad @ T_map_cad[:3, :3].T + T_map_cad[:3, 3]
    est = p_map @ T_cad_map[:3, :3].T + T_cad_map[:3, 3]
    return float(np.linalg.norm(est - c_cad, axis=1).max())


def run(args: argparse.Namespace) -> dict:
    sys.path.insert(0, str(Path(args.eval_dir).resolve()))
    scenarios = importlib.import_module("scenarios")
    symmetry = importlib.import_module("symmetry")
    truth = importlib.import_module("truth")
    harness = importlib.import_module("score_localize")
    from scipy.spatial import cKDTree

    from macroloc.graph.bim import load_building
    from macroloc.graph.observations import parse_observations
    from macroloc.graph.params import RobustParams
    from macroloc.graph.registration import register

    params = scenarios.params_from(args)
    stated: list[tuple[float, bool, bool]] = []  # (probability, right, is the scenario's best pose)
    records: dict[str, list[dict]] = {r: [] for r in RULES}
    for ifc in args.ifc:
        data = truth.load(ifc)
        oracle = symmetry.Oracle(data)
        trees = {k: cKDTree([f["centroid"] for f in data["features"] if f["type"] == k])
                 for k in ("door", "window") if any(f["type"] == k for f in data["features"])}
        model = load_building(ifc)
        for i in range(args.n):
            obs_doc, truth_doc = scenarios.make_scenario(data, i, seed=args.seed, variant=args.variant, **params)
            check = oracle.check(truth_doc)
            obs = parse_observations(obs_doc)
            amb = bool(check["ambiguous_truth"])
            full = amb and (check.get("support") or 0.0) >= 0.999
            for rule in RULES:
                result = register(model, obs, params=replace(RobustParams(), decision=rule))
                out = result.to_json()
                rec = harness.score_run(truth_doc, out, trees)
                rec.update(ambiguous_truth=full, near_ambiguous=amb and not full, building=Path(ifc).stem,
                           oracle=check)
                records[rule].append(rec)
                if rule == "posterior" and result.posterior is not None:  # the rule's own search (every seed)
                    for k, pose in enumerate(result.posterior["poses"]):
                        right = pose_error_m(np.array(pose["T_cad_map"]), truth_doc) < RIGHT_M
                        stated.append((pose["probability"], right, k == 0))
    return {"stated": stated, "records": records}


def reliability(stated: list[tuple[float, bool, bool]], best_only: bool) -> list[dict]:
    rows = []
    p = np.array([s[0] for s in stated if s[2] or not best_only])
    ok = np.array([s[1] for s in stated if s[2] or not best_only], dtype=bool)
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = (p >= lo) & (p < hi)
        rows.append(dict(lo=lo, hi=min(hi, 1.0), n=int(sel.sum()),
                         stated=float(p[sel].mean()) if sel.any() else None,
                         observed=float(ok[sel].mean()) if sel.any() else None))
    return rows


def summary(records: list[dict], harness) -> dict:
    n = len(records)
    unamb, amb, near = harness.oracle_split(records)
    return dict(n=n, wrong=sum(r["outcome"] == "wrong" for r in records),
                success=sum(r["outcome"] == "success" for r in records),
                unambiguous=unamb, ambiguous_truth=amb, near_ambiguous=near)


def plot(rows_best: list[dict], rows_all: list[dict], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot([0, 1], [0, 1], "k:", lw=1, label="calibrated")
    for rows, style, label in ((rows_all, "s-", "every listed pose"), (rows_best, "o-", "best pose")):
        xs = [r["stated"] for r in rows if r["n"]]
        ys = [r["observed"] for r in rows if r["n"]]
        ax.plot(xs, ys, style, label=label)
        for r in rows:
            if r["n"] and rows is rows_best:
                ax.annotate(str(r["n"]), (r["stated"], r["observed"]), textcoords="offset points", xytext=(4, -10),
                            fontsize=7)
    ax.set_xlabel("stated posterior")
    ax.set_ylabel("observed frequency of being right")
    ax.set_title(title, fontsize=8)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def pooled(paths: list[str], plot_path: str | None, title: str) -> int:
    """The reliability table of several runs' `--json-out` files together (and its picture)."""
    stated = [tuple(s) for p in paths for s in json.loads(Path(p).read_text())["stated"]]
    rows_best, rows_all = reliability(stated, True), reliability(stated, False)  # type: ignore[arg-type]
    print(f"pooled {len(paths)} runs: {sum(1 for s in stated if s[2])} scenarios with a pose")
    print_table(rows_best, rows_all)
    if plot_path:
        plot(rows_best, rows_all, plot_path, title)
    return 0


def print_table(rows_best: list[dict], rows_all: list[dict]) -> None:
    print("reliability (stated posterior bin: poses, mean stated, observed right) — best pose | every listed pose")
    f = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731
    for b, a in zip(rows_best, rows_all, strict=True):
        print(f"  [{b['lo']:.3f}, {b['hi']:.3f})  n={b['n']:>4} stated={f(b['stated'])} observed={f(b['observed'])}"
              f"  |  n={a['n']:>4} stated={f(a['stated'])} observed={f(a['observed'])}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--pool" or argv and argv[0] == "--pool":
        rest = (sys.argv[2:] if argv is None else argv[1:])
        plot_at = rest.index("--plot") if "--plot" in rest else None
        paths = rest[:plot_at] if plot_at is not None else rest
        return pooled(paths, rest[plot_at + 1] if plot_at is not None else None,
                      rest[plot_at + 2] if plot_at is not None and len(rest) > plot_at + 2 else "pooled runs")
    ap.add_argument("ifc", nargs="+")
    ap.add_argument("--eval-dir", default="../shared/eval")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--json-out", default=None)
    argv = sys.argv[1:] if argv is None else argv
    sys.path.insert(0, str(Path(ap.parse_known_args(argv)[0].eval_dir).resolve()))
    importlib.import_module("scenarios").add_params(ap)
    args = ap.parse_args(argv)
    got = run(args)
    harness = importlib.import_module("score_localize")
    rows_best, rows_all = reliability(got["stated"], True), reliability(got["stated"], False)
    print(f"buildings={[Path(f).stem for f in args.ifc]} n={args.n} seed={args.seed} variant={args.variant} "
          f"sigma={args.sigma} drop={args.drop} fp={args.fp} flip={args.flip}")
    print_table(rows_best, rows_all)
    sums = {}
    for rule in RULES:
        s = summary(got["records"][rule], harness)
        sums[rule] = s
        u, a = s["unambiguous"], s["ambiguous_truth"]
        pct = lambda x: "-" if x is None else f"{x:.1f}%"  # noqa: E731
        print(f"rule={rule:<9} wrong={s['wrong']} unambiguous n={u['n']} success={pct(u['success_pct'])} "
              f"ambiguous={pct(u['ambiguous_pct'])} not_localized={pct(u['not_localized_pct'])} | "
              f"ambiguous_truth n={a['n']} honest={pct(a['honest_pct'])} guess={pct(a['guess_pct'])} "
              f"not_localized={pct(a['not_localized_pct'])}")
    if args.plot:
        plot(rows_best, rows_all, args.plot, f"{', '.join(Path(f).stem.split('__')[-1] for f in args.ifc)}; "
             f"seed {args.seed}, {args.variant}, sigma {args.sigma}, n {args.n}")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(dict(best=rows_best, all=rows_all, rules=sums,
                                                       stated=got["stated"], args=vars(args)), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
