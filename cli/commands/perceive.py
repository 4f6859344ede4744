"""`macroloc perceive --left L --right R --calib-left CL --calib-right CR --json`: doors and windows in 3D."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from macroloc.perception.model_check import ModelCheckedPerception
    from macroloc.perception.size_check import OpeningSizes
    from macroloc.service.config import PerceptionConfig


def register(app: typer.Typer) -> None:
    @app.command()
    def perceive(
        left: Path = typer.Option(..., "--left", help="Rectified left image."),
        right: Path = typer.Option(..., "--right", help="Rectified right image."),
        calib_left: Path = typer.Option(..., "--calib-left", help="Left camera_info YAML (ROS format)."),
        calib_right: Path = typer.Option(..., "--calib-right", help="Right camera_info YAML (ROS format)."),
        json_out: bool = typer.Option(False, "--json", help="Print the contract's JSON document on stdout."),
        plot: Path | None = typer.Option(None, "--plot", help="Image file to write with features and sides drawn."),
        gravity: str | None = typer.Option(None, "--gravity", help="Gravity in the camera frame 'gx,gy,gz' if known."),
        model: Path | None = typer.Option(None, "--model", help="ONNX detector (default: the config's "
                                          "perception.detector_model, else the shipped one)."),
        building: Path | None = typer.Option(None, "--building", help="The building's model (IFC or mesh): its "
                                             "doors' and windows' sizes check every feature, and doors are proposed "
                                             "from geometry where the detector sees none."),
        config: Path | None = typer.Option(None, "--config", "-c", help="Config file (JSON or TOML): its "
                                           "perception section's detector_model and its tables lines, "
                                           "plausibility, wall_plane, proposals and size_check; "
                                           "docs/configuration.md."),
    ) -> None:
        """Run the perception chain (detect, LSD sides, SGBM depth, 3D corners) on one rectified stereo pair.

        JSON: {"features": [{"type", "score", "box_xyxy", "corners_cam": [\\[x, y, z] x 4], ...}], "rejected": [...]};
        corners in the left camera's optical frame (x right, y down, z forward), metres, TL, TR, BR, BL;
        "truncated": {"sideways", "vertically"} where the opening may run on past the image border (its corners on
        that side are then the border's, not the opening's); "source": "cnn" | "geometry" | "fused" (a detection a
        geometry proposal agreed with); "size_check": "confirmed" | "rejected" | "unchecked" against the
        --building's doors and windows, with "model_size_m" (width, height, m) of the size it fits and
        "retyped_from" where that size is of the other kind ("unchecked" throughout without --building). A
        rejected detection carries the detector's own "truncated" (bool: its box within 2 px of the image border)
        beside its "reason".
        """
        import cv2
        import numpy as np

        from macroloc.cli.commands._io import existing_file, print_json, read_image
        from macroloc.graph.errors import UserInputError
        from macroloc.perception.calib import read_stereo_rig
        from macroloc.perception.detector import DEFAULT_MODEL
        from macroloc.perception.draw import draw_features
        from macroloc.perception.pipeline import StereoPair

        rig = read_stereo_rig(calib_left, calib_right)
        images = []
        for path, what in ((left, "left image"), (right, "right image")):
            image = read_image(path, what, cv2.IMREAD_UNCHANGED)
            if image.shape[:2] != (rig.height_px, rig.width_px):
                raise UserInputError(f"{what} is {image.shape[1]}x{image.shape[0]}, calibration says "
                                     f"{rig.width_px}x{rig.height_px}")
            images.append(image if image.dtype == np.uint8 else cv2.convertScaleAbs(image, alpha=255.0 / 65535.0))
        gravity_cam = None
        if gravity is not None:
            try:
                g = np.array([float(v) for v in gravity.split(",")])
            except ValueError:
                raise UserInputError(f"--gravity must be three numbers 'gx,gy,gz', got {gravity!r}") from None
            if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) == 0:
                raise UserInputError(f"--gravity must be three finite numbers, not all zero, got {gravity!r}")
            gravity_cam = g / np.linalg.norm(g)
        from macroloc.service.config import load_config

        perception = load_config(config).perception
        model = existing_file(model or perception.detector_model or DEFAULT_MODEL, "detector model")
        sizes = opening_sizes(building) if building is not None else None
        checked = model_checked_chain(perception, model, sizes)
        result = checked.process(StereoPair(images[0], images[1], rig, gravity_cam))
        if plot is not None:
            plot.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(plot), draw_features(images[0], [c.feature for c in result.features], result.rejected))
        if json_out:
            print_json({"features": [c.to_json() for c in result.features],
                        "rejected": [{**r.detection.to_json(), "reason": r.reason} for r in result.rejected],
                        "timings_ms": {k: round(v, 2) for k, v in result.timings_ms.items()}})
            return
        for c in result.features:
            f, size = c.feature, c.size
            fits = f", model {size.matched_wh_m[0]:.2f} x {size.matched_wh_m[1]:.2f} m" if size.matched_wh_m else ""
            typer.echo(f"{f.type} {f.score:.2f} ({c.source}): {f.width_m:.2f} x {f.height_m:.2f} m, tilt "
                       f"{f.tilt_deg:.1f} deg, centre {np.round(f.centroid_cam, 2).tolist()} m, "
                       f"size {size.status}{fits}")
        typer.echo(f"{len(result.features)} features, {len(result.rejected)} detections rejected")


def model_checked_chain(perception: PerceptionConfig, model: Path | None, sizes: OpeningSizes | None
                        ) -> ModelCheckedPerception:
    """`perceive`'s chain: the detector at `model` (None: the shipped one), the [perception] tables' sides, wall
    plane and plausibility limits, and, with the building's `sizes`, its door proposals and size check."""
    from macroloc.perception.model_check import ModelCheckedPerception
    from macroloc.perception.pipeline import Perception

    params = perception.to_params()
    return ModelCheckedPerception(Perception.create(model, params=params), sizes, params.size_check,
                                  params.proposals)


def opening_sizes(building: Path) -> OpeningSizes:
    """The distinct sizes of the building's doors and windows standing in walls (skylights are not seen so)."""
    from macroloc.graph.bim import load_building
    from macroloc.perception.size_check import OpeningSizes

    return OpeningSizes.of((f.type, f.width_m, f.height_m) for f in load_building(building).features
                           if f.orientation == "vertical")
