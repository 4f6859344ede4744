"""`macroloc replay FLIGHT --building BUILDING --json [--report DIR] [--observations truth|truth-vo|perception]
[--odometry auto|recorded|simulated|visual] [--map SAVED] [--save-map OUT] [--topic NAME=/ros/topic ...]`: the
service's per-frame path offline, as fast as it runs, scored against ground truth (service.offline.run.replay_offline,
or with --over-zenoh service.offline.replay_zenoh). FLIGHT is a macroloc recording (MCAP) or a ROS 2 bag
(service.offline.ros_bag)."""

from __future__ import annotations

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
        odometry: str = typer.Option("auto", "--odometry", help="The vehicle's odometry: auto (the recording's "
                                     "own where it has one; else with --observations truth the ground truth with a "
                                     "VIO's drift, with perception the service's stereo visual odometry), recorded, "
                                     "simulated (the ground truth with a VIO's drift, seeded by --seed) or visual "
                                     "(the service's stereo visual odometry, the config's service.odometry = "
                                     "visual). The same choice with and without --over-zenoh."),
    ) -> None:
        """Replay a recorded flight through the service's own per-frame path and score it against ground truth.

        Each recorded frame becomes the messages its vehicle sends (IMU, odometry, doors and windows where it sends
        them, the stereo frame), which the service's front end takes as `macroloc serve` does; with --over-zenoh
        they go to a running service instead (lock-step at --speed 0: the same keyframes and poses).

        Prints frames, processing_fps, localized, time_to_localize_s (flight time of the first `localized`),
        ape_rmse_m / ape_max_m (CAD frame, no alignment, frames after localization), rpe_1s_rmse_m,
        wrong_localizations (entries into `localized` more than 1 m or 10 deg off), wrong_while_localized_s
        (flight time `localized` while that far off, e.g. after a drift) and status_final.
        """
        from macroloc.cli.commands._io import existing_file, print_json
        from macroloc.graph.errors import UserInputError
        from macroloc.proto.recording import stereo_frame_count
        from macroloc.service.config import load_config
        from macroloc.service.offline.ros_bag import BagStats, RosTopics, is_ros_bag, open_flight
        from macroloc.service.offline.run import ReplayOptions
        from macroloc.service.progress import track

        options = ReplayOptions(observations, odometry, seed, storey).checked()
        if not flight.exists():
            raise UserInputError(f"recording not found: {flight}")
        is_bag = is_ros_bag(flight)
        if not is_bag:
            existing_file(flight, "recording")
        if is_bag and observations != "perception":
            raise UserInputError("a ROS 2 bag holds no ground-truth doors and windows: use --observations perception")
        cfg = load_config(config)
        if observations == "perception" and cfg.perception.detector_model is not None:
            existing_file(cfg.perception.detector_model, "detector model (perception.detector_model)")
        bag_stats = BagStats()
        frames = track(open_flight(flight, RosTopics.parse(topic or []), cfg.camera, bag_stats),
                       f"replay {flight.name}", total=None if is_bag else stereo_frame_count(flight))
        if over_zenoh:
            from macroloc.service.offline.replay_zenoh import replay_command

            if out is not None or save_map is not None or saved_map is not None or report is not None:
                raise UserInputError("--out, --map, --save-map and --report are the in-process replay's; with "
                                     "--over-zenoh the service keeps its own map (serve --state-dir)")
            doc = replay_command(frames, options, connect or [], vehicle, speed)
        else:
            from macroloc.service.offline.run import replay_offline

            doc = replay_offline(frames, building, cfg, options, saved_map, save_map, out, report).to_json()
        if is_bag:
            doc["bag"] = bag_stats.to_json()
        if json_out:
            print_json(doc)
            return
        from rich.console import Console

        Console().print(doc)
