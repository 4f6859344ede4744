"""`macroloc replay FLIGHT --building BUILDING --json [--report DIR] [--observations truth|perception]
[--map SAVED] [--save-map OUT] [--topic NAME=/ros/topic ...]`: the whole chain offline, as fast as it runs, scored
against ground truth. FLIGHT is a macroloc recording (MCAP) or a ROS 2 bag (service.offline.ros_bag)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def replay(
        flight: Path = typer.Argument(..., help="Recorded flight: a macroloc MCAP (/stereo, /imu, /ground_truth) "
                                      "or a ROS 2 bag (a folder with metadata.yaml and .db3 or .mcap, or one "
                                      ".mcap of ROS 2 messages)."),
        topic: list[str] = typer.Option(None, "--topic", help="ROS 2 bags: NAME=/ros/topic, NAME one of left, "
                                        "right (Image or CompressedImage), imu (Imu), left_info, right_info "
                                        "(CameraInfo), odometry (Odometry), truth (PoseStamped of the body in the "
                                        "CAD frame); repeatable. Default: the common names (/cam0/image_raw, "
                                        "/camera/left/image_raw, /imu0, /imu, ...)."),
        building: Path = typer.Option(..., "--building", "-b", help="IFC file (or mesh) of the building flown in."),
        observations: str = typer.Option("truth", "--observations", help="truth: ground-truth doors/windows and "
                                         "odometry with realistic noise and drift (the graph alone); truth-vo: the "
                                         "same doors/windows, but the stereo visual odometry on the recorded "
                                         "images; perception: the perception chain and the visual odometry."),
        saved_map: Path | None = typer.Option(None, "--map", help="A saved map of this building to start from, "
                                              "as a restarted `serve` does (from --save-map, or a service's "
                                              "<state_dir>/<vehicle>/map.pb): re-localized from the first frames "
                                              "by its keyframes' views (place recognition, before any door is "
                                              "seen), else by its T_cad_map and its doors."),
        save_map: Path | None = typer.Option(None, "--save-map", help="Write this flight's saved map here at the "
                                             "end (as `serve` saves its own; its view log beside it), with a view "
                                             "(ORB features with stereo depth) every 0.5 m or 15 deg of the "
                                             "flight's keyframes, for place recognition."),
        out: Path | None = typer.Option(None, "--out", help="Write the replay for Foxglove here (MCAP of "
                                        "foxglove.* messages: left image with the detections, transforms cad -> map "
                                        "-> body -> cam, estimate and truth poses, the model's doors, windows and "
                                        "walls, the landmarks, the status)."),
        report: Path | None = typer.Option(None, "--report", help="Write a top-down picture, per-frame figures "
                                           "and result.json into this folder."),
        storey: str | None = typer.Option(None, "--storey", help="Register against this storey's doors and "
                                          "windows only (default: graph.storey_hint of the config)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the noise added to truth observations (and to the "
                                 "simulated odometry sent with --over-zenoh --observations perception)."),
        config: Path | None = typer.Option(None, "--config", help="macroloc config file (JSON/TOML); its "
                                           "graph section sets keyframes, association and status thresholds, its "
                                           "perception section the detector (perception.detector_model)."),
        json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
        over_zenoh: bool = typer.Option(False, "--over-zenoh", help="Publish the recording to a running `macroloc "
                                        "serve` on its Zenoh keys and score the poses it sends back."),
        connect: list[str] = typer.Option(None, "--connect", help="With --over-zenoh: the service's Zenoh "
                                          "endpoint (repeatable; default tcp/127.0.0.1:7447)."),
        vehicle: str = typer.Option("drone1", "--vehicle", help="With --over-zenoh: the service's vehicle name."),
        speed: float = typer.Option(1.0, "--speed", help="With --over-zenoh: 1 = real time, 2 = twice as fast, "
                                    "0 = as fast as possible."),
        one_thread: bool = typer.Option(False, "--one-thread", help="Everything on one thread, in turn. By "
                                        "default one thread reads and decodes the recording and another runs "
                                        "the visual odometry, a few frames ahead of the localizer (the results "
                                        "are the same; processing_fps is higher with two cores free)."),
    ) -> None:
        """Replay a recorded flight through the localizer and score it against ground truth.

        Prints frames, processing_fps, localized, time_to_localize_s (flight time of the first `localized`),
        ape_rmse_m / ape_max_m (CAD frame, no alignment, frames after localization), rpe_1s_rmse_m,
        wrong_localizations (entries into `localized` more than 1 m or 10 deg off), wrong_while_localized_s
        (flight time `localized` while that far off, e.g. after a drift) and status_final.
        """
        from macroloc.cli.commands._io import existing_file, print_json
        from macroloc.graph.bim import load_building
        from macroloc.graph.errors import UserInputError
        from macroloc.service.config import load_config
        from macroloc.service.offline.replay import replay as run_replay
        from macroloc.service.offline.replay_sources import (
            ObservationSource,
            PerceptionSource,
            TruthFeaturesWithVisualOdometry,
            TruthSource,
        )
        from macroloc.service.offline.ros_bag import BagStats, RosTopics, is_ros_bag, open_flight
        from macroloc.service.saved_map import LastEstimate, read_saved_map, write_saved_map
        from macroloc.service.session import session_from_config

        if not flight.exists():
            raise UserInputError(f"recording not found: {flight}")
        is_bag = is_ros_bag(flight)
        if not is_bag:
            existing_file(flight, "recording")
        if observations not in ("truth", "truth-vo", "perception"):
            raise UserInputError(f"--observations must be truth, truth-vo or perception, not {observations!r}")
        if is_bag and observations != "perception":
            raise UserInputError("a ROS 2 bag holds no ground-truth doors and windows: use --observations perception")
        cfg = load_config(config)
        bag_stats = BagStats()
        from macroloc.proto.recording import stereo_frame_count
        from macroloc.service.progress import track

        frames = track(open_flight(flight, RosTopics.parse(topic or []), cfg.camera, bag_stats),
                       f"replay {flight.name}", total=None if is_bag else stereo_frame_count(flight))
        if over_zenoh:  # the service perceives the frames itself unless truth observations are sent along
            import json
            import sys

            from macroloc.service.offline.replay_zenoh import replay_command

            if out is not None:
                raise UserInputError("--out records an in-process replay; with --over-zenoh, record the service")

            doc = replay_command(frames, TruthSource(seed=seed) if observations == "truth" else None, connect or [],
                                 vehicle, speed, seed)
            if json_out:
                print_json(doc)
            else:
                sys.stdout.write(json.dumps(doc, indent=2) + "\n")
            return
        detector = cfg.perception.detector_model
        if observations == "perception" and detector is not None:
            existing_file(detector, "detector model (perception.detector_model)")
        from macroloc.service.progress import step

        with step(f"reading {building.name} (its first time: a minute or more, cached after)"):
            model = load_building(building)
        saved = read_saved_map(saved_map, model) if saved_map is not None else None
        perception = cfg.perception.to_params()
        source: ObservationSource = (TruthSource(seed=seed) if observations == "truth" else
                                     TruthFeaturesWithVisualOdometry(seed=seed, params=perception)
                                     if observations == "truth-vo"
                                     else PerceptionSource(cfg.perception.detect_every, detector, perception))
        storey = model.checked_storey(storey if storey is not None else cfg.graph.storey_hint)
        surfaces = None
        if cfg.graph.surface_check:
            from macroloc.graph.building_assets import surfaces_for

            with step(f"preparing {building.name}'s surfaces (its first time: minutes, cached after)"):
                surfaces = surfaces_for(building, line_of_sight=cfg.graph.line_of_sight)
        from macroloc.service.places import KeyframePlaces

        places = KeyframePlaces(saved, keep_views=save_map is not None, config=perception.place)
        last = LastEstimate()
        recorder = None
        with contextlib.ExitStack() as stack:
            if out is not None:
                from macroloc.service.offline.foxglove_out import FoxgloveWriter, ReplayRecorder
                from macroloc.service.offline.plots import load_wall_mesh

                recorder = ReplayRecorder(stack.enter_context(FoxgloveWriter(out)), model, load_wall_mesh(building))
            result = run_replay(frames, model, source, places=places, recorder=recorder, one_thread=one_thread,
                                sink=last, make=lambda T_body_cam: session_from_config(
                                    cfg, model, saved=saved, surfaces=surfaces, T_body_cam=T_body_cam,
                                    storey_hint=storey))
        if save_map is not None:
            write_saved_map(save_map, result.localizer, last.estimate, saved, building.name, replaces=saved_map)
        if report is not None:
            from macroloc.service.offline.plots import load_wall_mesh
            from macroloc.service.offline.replay_report import write_report

            write_report(result, model, report, load_wall_mesh(building), saved, config=cfg.model_dump(mode="json"))
        doc = result.to_json()
        if is_bag:
            doc["bag"] = bag_stats.to_json()
        if json_out:
            print_json(doc)
            return
        from rich.console import Console

        Console().print(doc)
