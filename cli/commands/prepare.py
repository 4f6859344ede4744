"""`macroloc prepare BUILDING`: build a building's cached assets ahead of `serve` (or a first `localize`)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def prepare(
        building: Path = typer.Argument(None, help="IFC file, or a mesh (OBJ, GLB, DAE, ...) of the building "
                                        "(default: the config's service.building)."),
        config: Path = typer.Option(None, "--config", "-c", help="Config file: its graph and planning "
                                    "sections decide which assets are built (surface check, line of sight, grid)."),
        json_out: bool = typer.Option(False, "--json", help="Print each part's wall time as JSON on stdout."),
    ) -> None:
        """Build every asset the service derives from the model: doors and windows, the registration's tables,
        obstacles, wall voxels, surfaces, planning grids. Each is cached (in $MACROLOC_CACHE, else
        ~/.cache/macroloc) as soon as it is built, keyed by the file's SHA-256 and its parameters, so an
        interrupted run resumes and `macroloc serve` then starts in about a second instead of minutes.

        Run it once per building file (and again after changing it); the systemd unit runs it as ExecStartPre
        (`macroloc prepare --config FILE`: a second run only reads the cache).
        """
        from macroloc.cli.commands._io import existing_file, print_json
        from macroloc.graph.bim import cache_dir
        from macroloc.graph.errors import UserInputError
        from macroloc.service.assets import prepare_building
        from macroloc.service.config import load_config
        from macroloc.service.progress import step

        cfg = load_config(config)
        if building is None:
            if cfg.service.building is None:
                raise UserInputError("no building model: pass BUILDING or set service.building in the config")
            building = Path(cfg.service.building)
        existing_file(building, "building model")
        with step(f"preparing {building.name} (cached parts are read; the first time takes minutes)"):
            prepared = prepare_building(building, cfg.graph, cfg.planning)
        if json_out:
            print_json({"building": str(building), "sha256": prepared.model.sha256, "cache": str(cache_dir()),
                        "parts": [{"name": p.name, "seconds": round(p.seconds, 3)} for p in prepared.parts]})
            return
        typer.echo(f"{building.name}: {len(prepared.model.features)} doors and windows; assets ready in "
                   f"{cache_dir()} ({prepared.summary()})")
