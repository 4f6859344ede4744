"""`macroloc perceive --left L --right R --calib-left CL --calib-right CR --json`: doors and windows in 3D."""

from __future__ import annotations

from pathlib import Path

import typer


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
        model: Path | None = typer.Option(None, "--model", help="ONNX detector (default: the shipped one)."),
    ) -> None:
        """Run the perception chain (detect, LSD sides, SGBM depth, 3D corners) on one rectified stereo pair.

        JSON: {"features": [{"type", "score", "box_xyxy", "corners_cam": [\\[x, y, z] x 4], ...}], "rejected": [...]};
        corners in the left camera's optical frame (x right, y down, z forward), metres, TL, TR, BR, BL;
        "truncated": {"sideways", "vertically"} where the opening may run on past the image border (its corners on
        that side are then the border's, not the opening's). A rejected detection carries the detector's own
        "truncated" (bool: its box within 2 px of the image border) beside its "reason".
        """
        import cv2
        import numpy as np

        from macroloc.graph.errors import UserInputError
        from macroloc.perception.calib import read_stereo_rig
        from macroloc.perception.detector import DEFAULT_MODEL
        from macroloc.perception.draw import draw_features
        from macroloc.perception.pipeline import Perception, StereoPair
        from macroloc.service.commands._io import existing_file, print_json, read_image

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
        chain = Perception.create(existing_file(model or DEFAULT_MODEL, "detector model"))
        result = chain.process(StereoPair(images[0], images[1], rig, gravity_cam))
        if plot is not None:
            plot.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(plot), draw_features(images[0], result.features, result.rejected))
        if json_out:
            print_json({"features": [f.to_json() for f in result.features],
                        "rejected": [{**r.detection.to_json(), "reason": r.reason} for r in result.rejected],
                        "timings_ms": {k: round(v, 2) for k, v in result.timings_ms.items()}})
            return
        for f in result.features:
            typer.echo(f"{f.type} {f.score:.2f}: {f.width_m:.2f} x {f.height_m:.2f} m, tilt {f.tilt_deg:.1f} deg, "
                       f"centre {np.round(f.centroid_cam, 2).tolist()} m")
        typer.echo(f"{len(result.features)} features, {len(result.rejected)} detections rejected")
