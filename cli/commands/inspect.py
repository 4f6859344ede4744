"""`macroloc inspect BUILDING [--plot out.png] [--json]`: what macroloc sees in a building model.

Prints the doors and windows per storey; with `--plot` it draws a top-down floor plan per storey
(`out.png`) and the descriptor's KDE-and-bins figure (`out_kde.png`, the paper's Figures 6 and 13).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Annotated

import typer


def storey_counts(model) -> dict[str, dict[str, int]]:
    """{storey: {"door": n, "window": n}} (a feature without storey counts under "none")."""
    counts = Counter((str(f.storey) if f.storey is not None else "none", f.type) for f in model.features)
    storeys = sorted({s for s, _ in counts})
    return {s: {"door": counts[(s, "door")], "window": counts[(s, "window")]} for s in storeys}


def kde_path_for(plot: Path) -> Path:
    """out.png -> out_kde.png (beside it)."""
    return plot.with_name(f"{plot.stem}_kde{plot.suffix or '.png'}")


def inspect_building(building: Path, plot: Path | None, walls: bool = True) -> dict:
    """Load the building and draw its pictures; returns {"plots": [paths], "storeys": counts, "features": n}."""
    from macroloc.graph.bim import load_building
    from macroloc.graph.errors import UserInputError

    model = load_building(building)
    plots: list[str] = []
    if plot is not None:
        if plot.suffix.lower() != ".png":
            raise UserInputError(f"--plot must name a .png file, got {plot}")
        if not plot.parent.exists():
            raise UserInputError(f"folder for --plot does not exist: {plot.parent}")
        from macroloc.service.offline.plots import load_wall_mesh, plot_floor_plans, plot_kde_bins

        wall_mesh = load_wall_mesh(building) if walls else None
        plots.append(str(plot_floor_plans(model, plot, wall_mesh=wall_mesh)))
        if len(model.features) >= 2:
            plots.append(str(plot_kde_bins(model, kde_path_for(plot))))
    return {"building": str(building), "features": len(model.features), "plots": plots,
            "storeys": storey_counts(model), "report": _report_summary(model.report)}


def _report_summary(report: dict) -> dict:
    """The reader's report with long id lists replaced by their lengths."""
    return {k: (len(v) if isinstance(v, list) and k in ("no_geometry", "rejected_small", "ignored_nodes") else v)
            for k, v in report.items() if k != "groups"}


def register(app: typer.Typer) -> None:
    @app.command()
    def inspect(
        building: Annotated[Path, typer.Argument(help="IFC file, or a mesh (OBJ, GLB, DAE, ...) / Gazebo .world.")],
        plot: Annotated[Path | None, typer.Option("--plot", help="Write a top-down floor plan per storey to this "
                                                  "PNG, and the KDE-and-bins figure beside it (NAME_kde.png).")] = None,
        no_walls: Annotated[bool, typer.Option("--no-walls", help="Do not draw the walls' cross-section.")] = False,
        json_out: Annotated[bool, typer.Option("--json", help="Print a JSON document on stdout: "
                                               "plots (paths written), storeys (door/window counts).")] = False,
    ) -> None:
        """Show what macroloc extracts from a building: doors and windows per storey, and pictures of them.

        The floor plan draws doors black and windows blue (the paper's Figure 1) with short labels (D0, W3, ...),
        each opening's normal as a thin tick, and the walls cut 1.2 m above each storey's floor in grey.
        """
        from macroloc.cli.commands._io import existing_file, print_json

        existing_file(building, "building model")
        result = inspect_building(building, plot, walls=not no_walls)
        if json_out:
            print_json(result)
            return
        from rich.console import Console

        console = Console()
        console.print(f"{Path(building).name}: {result['features']} macro-features")
        for storey, n in result["storeys"].items():
            console.print(f"  {storey}: {n['door']} doors, {n['window']} windows")
        for p in result["plots"]:
            console.print(f"wrote {p}")
