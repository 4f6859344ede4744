"""`macroloc detect IMAGE... --json`: doors and windows in images, boxes in each image's own pixels."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def detect(
        images: list[Path] = typer.Argument(..., help="Image files (JPG, PNG, ...), colour or grey."),
        json_out: bool = typer.Option(False, "--json", help="Print the contract's JSON document on stdout."),
        plot: Path | None = typer.Option(None, "--plot", help="Folder to write each image with its boxes drawn."),
        model: Path | None = typer.Option(None, "--model", help="ONNX detector (default: the shipped one)."),
        threshold: float | None = typer.Option(None, "--threshold", min=0.0, max=1.0,
                                               help="Score threshold (default: the model's, chosen on its PR curve)."),
    ) -> None:
        """Detect doors and windows with the shipped CNN (ONNX, no torch needed).

        JSON: {"images": [{"path", "detections": [{"type", "score", "box_xyxy", "truncated"}]}]}, boxes x0, y0, x1,
        y1 in pixels; "truncated" (bool): the box reaches within 2 px of the image border (the opening may be cut).
        """
        import cv2

        from macroloc.cli.commands._io import existing_file, print_json, read_image
        from macroloc.perception.detector import DEFAULT_MODEL, Detector
        from macroloc.perception.draw import draw_detections

        model_path = existing_file(model or DEFAULT_MODEL, "detector model")
        loaded = []
        for path in images:
            image = read_image(path, "image", cv2.IMREAD_COLOR)
            loaded.append((path, image))
        detector = Detector(model_path)
        results = []
        for path, image in loaded:
            dets = detector.detect(image, threshold)
            results.append({"path": str(path), "detections": [d.to_json() for d in dets]})
            if plot is not None:
                plot.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(plot / f"{path.stem}_detect.jpg"), draw_detections(image, dets))
        if json_out:
            print_json({"images": results})
            return
        for r in results:
            kinds = [d["type"] for d in r["detections"]]  # type: ignore[index]
            typer.echo(f"{r['path']}: {kinds.count('door')} doors, {kinds.count('window')} windows")
