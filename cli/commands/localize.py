"""`macroloc localize BUILDING --observations OBS.json --json [--method robust|paper]`."""

from __future__ import annotations

import time
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def localize(
        building: Path = typer.Argument(..., help="IFC file, or a mesh, of the building."),
        observations: Path = typer.Option(..., "--observations", "-o", help="OBS.json: the doors and windows seen, "
                                          "in the map frame, metres: \"features\", each a \"type\" (door or window) "
                                          "with 4 \"corners\" (any order) or a \"centroid\"; optional \"gravity\" "
                                          "(a direction, map frame) and \"hints\": {\"storey\": NAME}. The README "
                                          "has an example."),
        method: str = typer.Option("robust", "--method", help="robust (default) or paper (the paper's algorithm "
                                   "exactly: top-1 Hamming match, 4-point RANSAC)."),
        config: Path = typer.Option(None, "--config", "-c", help="Config file: its localize section's keys "
                                    "(inlier_threshold_m, landing_alpha, min_inliers, seed) tune the "
                                    "robust method; docs/configuration.md."),
        json_out: bool = typer.Option(False, "--json", help="Print the result as JSON on stdout."),
    ) -> None:
        """Find T_cad_map, the pose of this flight's map frame in the building model, from observed doors and windows.

        Answers `localized` (with the pose and the matches), `ambiguous` when two or more different poses explain
        the observations about equally well (a symmetric building, identical storeys: add "hints": {"storey": NAME}
        to OBS.json to settle the storey), or `not_localized`. `elapsed_ms` is the registration alone (no
        import, file reading or per-building pre-processing); `total_ms` the whole command until the answer.
        """
        t_start = time.perf_counter()
        from macroloc.cli.commands._io import print_json, read_json
        from macroloc.graph.bim import load_building
        from macroloc.graph.observations import parse_observations
        from macroloc.graph.registration import register as run_registration

        obs = parse_observations(read_json(observations, "observations file"))
        model = load_building(building)
        params = None  # the method's defaults
        if config is not None and method == "robust":
            from macroloc.service.config import load_config

            params = load_config(config).localize.robust_params()
        result = run_registration(model, obs, method=method, params=params)
        result.total_ms = (time.perf_counter() - t_start) * 1000.0
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
