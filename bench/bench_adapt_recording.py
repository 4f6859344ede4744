"""A detector adapted from a recorded flight (issue 55, item 5), generic vs self-labelled vs truth-labelled, on a
second flight of the same building: door and window AP50 on its frames (truth labels, `bench.bench_self_label`)
and its replay with each detector (time to localize, APE, wrong localizations).

    python -m bench.bench_adapt_recording BUILDING --labelled A.mcap --second B.mcap --out DIR [--steps 1000]

Arms: `generic` (the shipped detector); `self` (`macroloc adapt-detector BUILDING --recording A`: the user's
path, labels from the replay's held poses); `truth` (the same training on A's truth labels at the same cadence:
what perfect labels would give). Each phase is skipped where its output exists (DIR/self/detector.onnx, ...), so
a run stopped can go on. A benchmark: it prints figures, it asserts nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

from bench.bench_self_label import check_labels
from bench.eval_detector import rendered
from macroloc.cli.commands.adapt_detector import training_args
from macroloc.cli.main import main as cli
from macroloc.perception.detector import DEFAULT_MODEL, Detector
from macroloc.perception.train import SHARED_DATA, SHIPPED_WEIGHTS
from macroloc.perception.train import main as train_main
from macroloc.service.config import load_config
from macroloc.service.offline.run import ReplayOptions, replay_flight


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("building", type=Path)
    ap.add_argument("--labelled", type=Path, required=True, help="the flight that is labelled and trained on")
    ap.add_argument("--second", type=Path, required=True, help="the held-out flight of the same building")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    figures: dict = {}
    if not (out / "self" / "detector.onnx").is_file():
        argv = ["adapt-detector", str(args.building), "--recording", str(args.labelled), "--out", str(out / "self"),
                "--threads", str(args.threads), "--json"] + (["--steps", str(args.steps)] if args.steps else [])
        with contextlib.redirect_stdout(io.StringIO()) as printed:
            rc = cli(argv)
        (out / "self.json").write_text(printed.getvalue())
        if rc != 0:
            raise SystemExit(f"adapt-detector failed ({rc}): {printed.getvalue()[-400:]}")
    figures["self_labels"] = json.loads((out / "self" / "frames" / "report.json").read_text())
    figures["self_labels_vs_truth"] = check_labels(args.labelled, out / "self" / "frames",
                                                   truth_out=None if (out / "truth_frames").is_dir()
                                                   else out / "truth_frames")
    if not (out / "truth" / "detector.onnx").is_file():
        train_main(training_args(SHARED_DATA / "images" / "facades", out / "truth_frames", out / "truth",
                                 SHIPPED_WEIGHTS, args.steps, args.threads))
    if not (out / "heldout").is_dir():
        check_labels(args.second, out / "none", truth_out=out / "heldout")
    models = {"generic": DEFAULT_MODEL, "self": out / "self" / "detector.onnx",
              "truth": out / "truth" / "detector.onnx"}
    cfg = load_config(None)
    for arm, model in models.items():
        ap_figs: dict = rendered(Detector(model), [out / "heldout"])["heldout"]
        replayed = replay_flight(args.second, args.building, cfg.model_copy(update={
            "perception": cfg.perception.model_copy(update={"detector_model": model})}),
            ReplayOptions(observations="perception")).result.to_json()
        figures[arm] = {"door_ap50": ap_figs["door"]["ap50"], "window_ap50": ap_figs["window"]["ap50"],
                        "door_n": ap_figs["door"]["n_truth"], "window_n": ap_figs["window"]["n_truth"],
                        **{k: replayed[k] for k in ("localized", "time_to_localize_s", "ape_rmse_m",
                                                    "wrong_localizations", "landmarks", "cad_links")}}
        print(arm, json.dumps(figures[arm]), flush=True)
    (out / "figures.json").write_text(json.dumps(figures, indent=1) + "\n")
    print(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
