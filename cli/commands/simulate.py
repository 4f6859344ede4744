"""`macroloc simulate BUILDING --out FLIGHT.mcap`: fly a simulated stereo drone through a building model and
record it (stereo frames, IMU, ground truth) as the service would receive it, plus a contact sheet PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def simulate(
        building: Path = typer.Argument(..., help="IFC file, or a mesh (OBJ, GLB, DAE, ...) of the building."),
        out: Path = typer.Option(..., "--out", "-o", help="The recording to write (MCAP)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the flight, appearance, lights and noise."),
        appearance_seed: int | None = typer.Option(None, "--appearance-seed", help="Seed of the building's look "
                                                   "alone (textures, furniture, lights; default: --seed). The same "
                                                   "look with another --seed: the same building flown along "
                                                   "another path, e.g. to re-localize into a saved map."),
        duration: float | None = typer.Option(None, "--duration", help="Flight duration, s (config sim.duration_s)."),
        storey: str | None = typer.Option(None, "--storey", help="Storey to fly (default: most doors/windows)."),
        speed: float | None = typer.Option(None, "--speed", help="Cruise speed, m/s (config sim.speed_mps)."),
        contact_sheet: Path | None = typer.Option(None, "--contact-sheet",
                                                  help="Contact sheet PNG (default: beside --out, .png)."),
        yolo: Path | None = typer.Option(None, "--yolo", help="Also export detector training data (left images "
                                         "+ YOLO labels, 0 door 1 window) into this folder (may be shared)."),
        yolo_every: int = typer.Option(10, "--yolo-every", help="Export every N-th frame.", min=1),
        config: Path | None = typer.Option(None, "--config", help="A macroloc config file (JSON or TOML)."),
        json_out: bool = typer.Option(False, "--json", help="Print {frames, duration_s, render_fps, channels}."),
    ) -> None:
        """Simulate a flight: render what a stereo camera on a drone sees while it flies, collision-free, through
        the corridors and rooms of one storey of the building, and record it as MCAP with ground truth.

        Topics: /stereo (StereoFrame), /imu (Imu), /ground_truth (GroundTruth: T_cad_body, T_body_cam, every
        door/window in view with corners in the left camera frame, depth), /ground_truth/instances (mask).
        """
        from macroloc.cli.commands._io import existing_file, print_json
        from macroloc.cli.simulated_flight import simulate_to_mcap
        from macroloc.graph.errors import UserInputError
        from macroloc.service.config import load_config

        existing_file(building, "building model")
        if duration is not None and not (duration > 0 and np.isfinite(duration)):
            raise UserInputError(f"--duration must be a positive number of seconds, not {duration}")
        if speed is not None and not (speed > 0 and np.isfinite(speed)):
            raise UserInputError(f"--speed must be a positive number of m/s, not {speed}")
        if out.suffix.lower() != ".mcap":
            raise UserInputError(f"--out must name an .mcap file, not {out}")
        cfg = load_config(config)
        sim_overrides = {k: v for k, v in (("duration_s", duration), ("speed_mps", speed)) if v is not None}
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update=sim_overrides)})
        sheet = contact_sheet if contact_sheet is not None else out.with_suffix(".png")
        summary = simulate_to_mcap(building, out, cfg, seed=seed, storey=storey, contact_sheet=sheet,
                                   yolo_dir=yolo, yolo_every=yolo_every, appearance_seed=appearance_seed)
        if json_out:
            print_json(summary)
        else:
            typer.echo(f"{summary['frames']} frames, {summary['duration_s']:.1f} s on storey {summary['storey']!r}, "
                       f"{summary['render_fps']:.1f} stereo pairs/s rendered -> {out} (contact sheet {sheet})")
