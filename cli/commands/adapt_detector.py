"""`macroloc adapt-detector BUILDING --out DIR`: a door/window detector adapted to one building, from renders of
its own model or (`--recording`) from a flight the user's own vehicle recorded, labelled by the model where the
service's pose is held (service.offline.self_label), for the config's `perception.detector_model`."""

from __future__ import annotations

from pathlib import Path

import typer


def _seeds(text: str) -> tuple[int, ...]:
    from macroloc.graph.errors import UserInputError

    try:
        seeds = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise UserInputError(f"--seeds must be integers separated by commas, not {text!r}") from None
    if not seeds:
        raise UserInputError("--seeds names no seed")
    return seeds


FINE_TUNE_STEPS = 1000
FINE_TUNE_LR = 1e-3
SCRATCH_STEPS = 2400


def _init_weights(text: str) -> Path | None:
    from macroloc.graph.errors import UserInputError
    from macroloc.perception.train import SHIPPED_WEIGHTS

    if text == "none":
        return None
    path = SHIPPED_WEIGHTS if text == "shipped" else Path(text)
    if not path.is_file():
        raise UserInputError(f"no detector weights at {path}: give --init CHECKPOINT or --init none")
    return path


def training_args(photos: Path, frames: Path, out: Path, init: Path | None, steps: int | None,
                  threads: int) -> list[str]:
    """`perception.train`'s arguments for a building's frames (rendered or labelled from a recording): a fine-tune
    of `init` (FINE_TUNE_STEPS at FINE_TUNE_LR), or from scratch where it is None (SCRATCH_STEPS)."""
    start = ["--init", str(init), "--lr", str(FINE_TUNE_LR)] if init is not None else []
    n_steps = steps or (FINE_TUNE_STEPS if init is not None else SCRATCH_STEPS)
    return ["--facades", str(photos), "--sim", str(frames), "--steps", str(n_steps), "--threads", str(threads),
            "--out", str(out), "--report", str(out / "report"), *start]


def register(app: typer.Typer) -> None:
    @app.command("adapt-detector")
    def adapt_detector(
        building: Path = typer.Argument(..., help="IFC file (or mesh) of the building the drone will fly in."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for the rendered frames (frames/), the model "
                                 "(detector.onnx + detector.json) and its figures (report/)."),
        seeds: str = typer.Option("11,12,13", "--seeds", help="Seeds of the rendered flights, comma-separated "
                                  "(keep them apart from the seeds you evaluate on)."),
        duration: float = typer.Option(40.0, "--duration", min=1.0, help="Length of each rendered flight, s."),
        every: int = typer.Option(6, "--every", min=1, help="Keep every N-th frame of a flight (30 Hz)."),
        steps: int | None = typer.Option(None, "--steps", min=1, help="Training steps (batches of 16; default: "
                                         f"{FINE_TUNE_STEPS} fine-tuning from --init, {SCRATCH_STEPS} from scratch)."),
        init: str = typer.Option("shipped", "--init", help="Weights to fine-tune from: 'shipped' (the real-trained "
                                 "detector's perception/models/detector.pt), a checkpoint.pt of a training run, or "
                                 "'none' to train from scratch."),
        threads: int = typer.Option(2, "--threads", min=1, help="CPU threads for training."),
        facades: Path | None = typer.Option(None, "--facades", help="Real door/window photos with YOLO labels "
                                            "(images/, labels/; default: $MACROLOC_SHARED_DATA/images/facades); "
                                            "with the real indoor photos ($MACROLOC_SHARED_DATA/images/indoor_doors, "
                                            "where present) half of each batch, and the held-out test splits "
                                            "reported."),
        recording: list[Path] = typer.Option(None, "--recording", "-r", help="A flight your own vehicle recorded "
                                             "in this building (a macroloc MCAP, or a ROS 2 bag: a folder with "
                                             "metadata.yaml, or one .mcap of ROS 2 messages): replayed as the "
                                             "service runs it, and its frames labelled by the building's model "
                                             "wherever the pose is held, instead of rendered flights. "
                                             "Repeatable: several flights."),
        topic: list[str] = typer.Option(None, "--topic", help="ROS 2 bags: NAME=/ros/topic, as `macroloc replay "
                                        "--topic`."),
        config: Path | None = typer.Option(None, "--config", help="macroloc config file for the --recording's "
                                           "replay (its detector, cameras, odometry): as `macroloc replay`'s."),
        labels_only: bool = typer.Option(False, "--labels-only", help="With --recording: write the labelled frames "
                                         "and their report, do not train."),
        json_out: bool = typer.Option(False, "--json", help="Print {model, frames, doors, windows, figures}."),
    ) -> None:
        """Adapt the door/window detector to one building: render seeded flights through its model, label every
        door and window in view, train the detector on those frames and the real photos, export it to ONNX.

        By default it fine-tunes the shipped detector (trained on real indoor and facade photos; its weights are
        perception/models/detector.pt) for 1000 steps; `--init none` trains from scratch (2400 steps). On
        held-out Office_A flights (seeds 1-2) door AP50: generic 0.28, from scratch 0.54, fine-tuned 0.61 (6-15 min
        on 1 thread), and the fine-tuned one keeps indoor door AP50 0.86 on real photos (from scratch: 0.51).
        With --recording, the frames are your camera's own: the flight is replayed through the service's per-frame
        path (perception on, the config's detector), and each frame where the pose is held (localized, at most one
        frame per 0.2 s), and each frame of the minute before it was held (labelled from its keyframe in the
        pose graph once anchored), is written with the model's doors and windows in view as labels: occluded ones
        (by the model's own geometry) and ones the pose is too uncertain to box are left out, boxes cut by the
        border are flagged; DIR/frames/report.json counts every decision. The flight must localize with the detector you
        have (the generic one, or an operator's prior). Use it with `perception.detector_model =
        "DIR/detector.onnx"` in the config. Needs torch: pip install -e '.\\[train]'.
        """
        import importlib.util
        import json
        import logging

        from macroloc.cli.commands._io import existing_file, print_json
        from macroloc.graph.errors import UserInputError

        existing_file(building, "building model")
        seed_list = _seeds(seeds)
        init_path = _init_weights(init)
        recordings = list(recording or [])
        for path in recordings:
            if not path.exists():
                raise UserInputError(f"recording not found: {path}")
        if labels_only and not recordings:
            raise UserInputError("--labels-only labels a --recording: give one")
        if recordings and labels_only:
            counts = _self_label(building, recordings, out / "frames", config, topic)
            if json_out:
                print_json(counts)
            else:
                typer.echo(_self_label_line(counts, out / "frames"))
            return
        if importlib.util.find_spec("torch") is None:
            raise UserInputError("adapt-detector trains with torch, which is not installed: "
                                 "pip install -e '.[train]' (or make train)")
        from macroloc.perception.train import SHARED_DATA
        from macroloc.perception.train import main as train_main
        from macroloc.sim.export import render_training_frames

        photos = facades or SHARED_DATA / "images" / "facades"
        if not (photos / "images").is_dir() or not (photos / "labels").is_dir():
            raise UserInputError(f"no facade photos with labels at {photos} (images/, labels/): give --facades")
        from macroloc.service.progress import is_quiet

        if not is_quiet():
            logging.getLogger().setLevel(logging.INFO)  # rendering and training take minutes: show progress
        frames = out / "frames"
        if recordings:
            counts = _self_label(building, recordings, frames, config, topic)
            log_line = _self_label_line(counts, frames)
            if counts["door"] + counts["window"] == 0:
                raise UserInputError(log_line + ": nothing to train on (the flight must localize: see "
                                     "`macroloc replay --report` for why it did not)")
            logging.getLogger(__name__).info(log_line)
        else:
            counts = render_training_frames(building, frames, seed_list, duration, every)
            if counts["door"] + counts["window"] == 0:
                raise UserInputError(f"no door or window came into view in {counts['images']} rendered frames of "
                                     f"{building.name}: try other --seeds or a longer --duration")
        train_main(training_args(photos, frames, out, init_path, steps, threads))
        model = out / "detector.onnx"
        figures = json.loads(model.with_suffix(".json").read_text()).get("figures", {})
        if json_out:
            print_json({"model": str(model), "frames": counts["images"], "doors": counts["door"],
                        "windows": counts["window"], "figures": figures})
            return
        kind = "labelled frames of your flights" if recordings else "rendered frames"
        typer.echo(f"{model}: trained on {counts['images']} {kind} ({counts['door']} doors, "
                   f"{counts['window']} windows); set perception.detector_model to it in the config")


def _self_label(building: Path, recordings: list[Path], frames: Path, config: Path | None,
                topics: list[str] | None) -> dict:
    """Each recording replayed with perception and labelled where its pose is held (service.offline.self_label);
    {"images", "door", "window", "report"}: the report per recording and in total, also written to
    frames/report.json."""
    import json

    from macroloc.service.config import load_config
    from macroloc.service.offline.ros_bag import RosTopics
    from macroloc.service.offline.self_label import label_recording
    from macroloc.sim.scene import occluding_triangles

    cfg = load_config(config)
    occluders = occluding_triangles(building)
    parsed = RosTopics.parse(topics or [])
    per = {path.name: label_recording(path, building, cfg, occluders, frames, topics=parsed) for path in recordings}
    total: dict = {"frames": {}, "boxes": {}, "doors": 0, "windows": 0, "cut": 0, "greyed": 0}
    for r in per.values():
        for part in ("frames", "boxes"):
            for k, n in r[part].items():
                total[part][k] = total[part].get(k, 0) + n
        for k in ("doors", "windows", "cut", "greyed"):
            total[k] += r[k]
    report = {**total, "recordings": per}
    (frames / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    images = total["frames"].get("labelled", 0) + total["frames"].get("labelled_before_fix", 0)
    return {"images": images, "door": total["doors"], "window": total["windows"], "report": report}


def _self_label_line(counts: dict, frames: Path) -> str:
    r = counts["report"]
    seen = sum(r["frames"].values())
    return (f"{frames}: {counts['images']} of {seen} frames labelled ({counts['door']} doors, {counts['window']} "
            f"windows, {r['cut']} cut by the border); frames {r['frames']}, boxes {r['boxes']}")
