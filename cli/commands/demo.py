"""`macroloc demo`: the service and a simulated vehicle in any IFC building, the loop closed over Zenoh."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def demo(
        building: Path = typer.Option(None, "--building", help="IFC building (default: the bundled Office_A). Any "
                                      "IFC that macroloc can read: the take-off storey is the one with the most "
                                      "doors and windows, the take-off point one from where a turn shows enough of "
                                      "them, the goal a named room (IfcSpace), else a door, a window or a free "
                                      "cell of another room; a building that cannot be flown says why in one line."),
        storey: str | None = typer.Option(None, "--storey", help="Take off on this storey (its IFC name, as "
                                          "`macroloc features` lists it); default: graph.storey_hint of --config, "
                                          "else chosen by what can be seen there."),
        goal: str | None = typer.Option(None, "--goal", help="Fly to this goal once localized: an IfcSpace's Name "
                                        "or LongName (\"101\", \"Kitchen\"), a door's or window's IFC GlobalId, "
                                        "or CAD coordinates \"x,y,z\" in metres; it sets the take-off storey (the "
                                        "goal's). Default: chosen per seed."),
        seed: list[str] = typer.Option(["0"], "--seed", help="Seed of the flight; several flights: --seed 0,1,2 "
                                       "(or --seed repeated). Each seed draws its own take-off point and goal."),
        out: Path = typer.Option(Path("macroloc-demo.png"), "--out", help="Picture of the flight (PNG); with several "
                                 "seeds, one per seed (NAME-seedN.png)."),
        speedup: float = typer.Option(1.0, "--speedup", help="Simulated seconds per wall-clock second."),
        observations: str = typer.Option("perception", "--observations", help="perception: the simulated "
                                         "vehicle renders its stereo camera and the service's perception chain "
                                         "finds the doors and windows (about a minute a flight on 2 cores); "
                                         "truth: no camera, the doors and windows in view from the model's "
                                         "ground truth with noise and drop-outs (faster; labelled in the output)."),
        detector: Path | None = typer.Option(None, "--detector", help="With --observations perception: the "
                                             "detector (ONNX beside its JSON sidecar). Default: the one adapted to "
                                             "the building and shipped beside it (data/buildings/NAME_detector/), "
                                             "else the generic shipped detector."),
        record: Path | None = typer.Option(None, "--record", help="With --observations perception: write the "
                                           "flight (stereo frames, IMU, the vehicle's odometry, ground truth) to "
                                           "this MCAP file, to run again with `macroloc replay --observations "
                                           "perception` (set perception.detect_every = 1 in a --config to perceive "
                                           "every frame as the service did). With several seeds, NAME-seedN.mcap."),
        lockstep: bool = typer.Option(False, "--lockstep", help="The simulated vehicle's clock waits for the "
                                      "service's answer to each message (no real-time pacing): one seed flies the "
                                      "same flight, to the digit, on an idle or a loaded machine."),
        json_out: bool = typer.Option(False, "--json", help="Print {outcome (reached, not reached, ambiguous: a "
                                      "symmetric building whose rival poses the service will not choose between, "
                                      "localized wrongly: the estimate ended more than graph.anchor.cad_link_m "
                                      "from the simulation's truth, not localized), localized, pose_error_m (the "
                                      "estimate vs the truth when last localized), localization_time_s, "
                                      "goal_error_m, "
                                      "path_length_m, goal_error_pct, reached, rivals (ambiguous: how many poses), "
                                      "storey, start, goal, wall_contacts (the times the vehicle touched or crossed "
                                      "the model's walls: this simulator lets it through), wall_time_s} (a list "
                                      "with several seeds)."),
        listen: list[str] = typer.Option(None, "--listen", help="Zenoh endpoint the service also listens on, e.g. "
                                         "tcp/127.0.0.1:7447, for zenoh-bridge-ros2dds or any subscriber on this "
                                         "machine to watch the demo live (repeatable)."),
        ros: bool = typer.Option(False, "--ros", help="Also publish ROS 2 messages (CDR) on the keys "
                                 "zenoh-bridge-ros2dds maps to /<vehicle>/macroloc/{pose,odometry,path,status}, /tf."),
        px4: bool = typer.Option(False, "--px4", help="Also publish PX4's fmu/in/vehicle_visual_odometry, "
                                 "trajectory_setpoint and offboard_control_mode."),
        foxglove: int = typer.Option(0, "--foxglove", help="Watch the flight live in Foxglove: the service's "
                                     "WebSocket server on this port, 127.0.0.1 (foxglove.port; layout "
                                     "docs/foxglove_layout.json)."),
        vehicle: str = typer.Option("demo", "--vehicle", help="Vehicle name: keys macroloc/<vehicle>/..., ROS "
                                    "topics /<vehicle>/macroloc/..."),
        config: Path | None = typer.Option(None, "--config", "-c", help="The service's config file (JSON or TOML, "
                                           "see dump-config): its graph, perception, planning ... sections; the "
                                           "demo's own flags and its building, vehicle and Zenoh endpoints win."),
    ) -> None:
        """Take off, explore, localize in the BIM, fly to a room given by its IFC name, and report the paper's
        Table 2 row: localization time, error at the goal, and that error as % of the path length.

        Try your own building: `macroloc demo --building MINE.ifc --lockstep --observations truth` first (a
        minute), then without --observations (the rendered camera and the detector: the detector adapted to your
        building where MINE_detector/detector.onnx lies beside it, from `macroloc adapt-detector`, else the
        generic one; the output says which). A building that cannot be flown (no doors or windows, no free space
        at flight height, an unreadable file) says why in one line, exit 2. In a symmetric building the flight
        may end 'ambiguous': the doors and windows seen fit two or more poses equally well, the service says so
        instead of guessing, and the picture marks where each rival pose puts the vehicle.

        The macroloc service and the vehicle agent run on separate Zenoh sessions over loopback TCP; the
        vehicle flies on the service's pose estimates. By default the vehicle renders its stereo camera and the
        service's perception chain finds the doors and windows in the frames, as with a real camera;
        --observations truth feeds the model's ground truth with noise and drop-outs instead (labelled in the
        output).
        """
        import sys

        from macroloc.cli.commands._io import existing_file, print_json
        from macroloc.cli.demo import DEFAULT_BUILDING, DemoParams, outcome_line, plot_flight, result_json, run_demo
        from macroloc.graph.errors import UserInputError
        from macroloc.graph.planning import Planner
        from macroloc.service.config import load_config

        path = existing_file(building, "building model") if building else DEFAULT_BUILDING
        seeds = parse_seeds(seed)
        if speedup <= 0:
            raise UserInputError("--speedup must be positive")
        if observations not in ("truth", "perception"):
            raise UserInputError(f"--observations must be truth or perception, not {observations!r}")
        if detector is not None:
            existing_file(detector, "detector model")
        planning = load_config(config).planning  # checks the file before the first flight
        rows, pictures = [], []
        for s in seeds:
            recording = None if record is None else record if len(seeds) == 1 else \
                record.with_name(f"{record.stem}-seed{s}{record.suffix or '.mcap'}")
            result = run_demo(path, DemoParams(seed=s, speedup=speedup, observations=observations,
                                               detector_model=detector, record=recording, vehicle=vehicle,
                                               listen=tuple(listen or ()), ros=ros, px4=px4, lockstep=lockstep,
                                               config=config, storey=storey, goal=goal, foxglove=foxglove))
            picture = out if len(seeds) == 1 else out.with_name(f"{out.stem}-seed{s}{out.suffix or '.png'}")
            planner = Planner.for_building(path, planning.cell_m, planning.vehicle_radius_m, planning.flight_height_m)
            plot_flight(result, planner, picture)
            rows.append(result)
            pictures.append(picture)
            if not json_out:
                sys.stdout.write(
                    f"seed {s}: {result.storey}, {result.start} -> {result.goal} ({result.observations})\n"
                    f"  {outcome_line(result)}\n"
                    "  | localization time (s) | error at goal (m) | "
                    f"error (% of {result.path_length_m:.1f} m path) |\n"
                    f"  | {result.localization_time_s:21.2f} | {result.goal_error_m:17.3f} | "
                    f"{result.goal_error_pct:27.2f} |\n"
                    f"  reached: {result.reached}, walls touched: {len(result.wall_contacts_xy)} times, wall time "
                    f"{result.wall_time_s:.1f} s, picture {picture}"
                    + (f", recording {recording}" if recording is not None else "") + "\n"
                    + ("  goal: no geo-reference in the model\n" if result.goal_wgs84 is None else
                       "  goal at lat {:.7f}, lon {:.7f}, alt {:.2f} m (WGS84)\n".format(*result.goal_wgs84)))
        if json_out:
            docs = [dict(r.table_row(), seed=r.seed, outcome=r.outcome, localized=r.localized,
                         pose_error_m=r.pose_error_m, observations=r.observations, reached=r.reached,
                         rivals=len(r.rivals_xy), storey=r.storey, start=r.start, goal=r.goal,
                         wall_contacts=len(r.wall_contacts_xy),
                         wall_time_s=round(r.wall_time_s, 1), goal_wgs84=r.goal_wgs84, picture=str(p))
                    for r, p in zip(rows, pictures, strict=True)]
            print_json(docs[0] if len(docs) == 1 else docs)
        elif len(rows) > 1:
            sys.stdout.write(f"all seeds: {[result_json(r)['goal_error_m'] for r in rows]}\n")


def parse_seeds(texts: list[str]) -> list[int]:
    """--seed values, each an integer or a comma-separated list of them ("0,1,2"); UserInputError otherwise."""
    from macroloc.graph.errors import UserInputError

    try:
        return [int(part) for text in texts for part in text.split(",") if part.strip()]
    except ValueError:
        raise UserInputError(f"--seed takes integers, e.g. --seed 0,1,2, not {' '.join(texts)!r}") from None
