"""`macroloc localize BUILDING --observations OBS.json --json [--method robust|paper]`."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def localize(
        building: Path = typer.Argument(..., help="IFC file, or a mesh, of the building."),
        observations: Path = typer.Option(..., "--observations", "-o", help="OBS.json: observed doors/windows in "
                                          "the map frame (see DESIGN.md), optional gravity and storey hint."),
        method: str = typer.Option("robust", "--method", help="robust (default) or paper (the paper's algorithm "
                                   "exactly: top-1 Hamming match, 4-point RANSAC)."),
        json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
    ) -> None:
        """Find T_cad_map, the pose of this flight's map frame in the building model, from observed doors and windows.

        Answers `localized` (with the pose and the matches), `ambiguous` when two or more different poses explain
        the observations about equally well (a symmetric building, identical storeys: add "hints": {"storey": NAME}
        to OBS.json to settle the storey), or `not_localized`.
        """
        from macroloc.graph.bim import load_building
        from macroloc.graph.observations import parse_observations
        from macroloc.graph.registration import register as run_registration
        from macroloc.service.commands._io import print_json, read_json

        obs = parse_observations(read_json(observations, "observations file"))
        model = load_building(building)
        result = run_registration(model, obs, method=method)
        if json_out:
            print_json(result.to_json())
            return
        from rich.console import Console

        c = Console()
        c.print(f"[bold]{result.status}[/bold]  inliers={result.inliers}  storey={result.storey}  "
                f"{result.elapsed_ms:.1f} ms")
        if result.T_cad_map is not None:
            c.print("T_cad_map =")
            c.print(result.T_cad_map.round(4))
