"""`macroloc features BUILDING --json`: the doors and windows of a building model, CAD frame, metres."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def features(
        building: Path = typer.Argument(..., help="IFC file, or a mesh (OBJ, GLB, DAE, ...) of the building."),
        json_out: bool = typer.Option(False, "--json", help="Print the contract's JSON document on stdout."),
    ) -> None:
        """List the building's macro-features (doors, windows): id, type, storey, corners, centroid, normal; and the
        model's geo-reference ("geo": origin latitude/longitude/altitude, true-north angle, CRS name where the IFC
        has IfcMapConversion or IfcSite RefLatitude/RefLongitude; null where it has none).

        Features are cached per building file (its SHA-256) in ~/.cache/macroloc, so a second run is fast.
        """
        from macroloc.cli.commands._io import print_json
        from macroloc.graph.bim import load_building
        from macroloc.graph.geo import read_geo_reference

        model = load_building(building)
        geo = read_geo_reference(building)
        if json_out:
            counted = ("no_geometry", "non_finite")  # id lists, reported as counts
            print_json({"unit": "m", "geo": geo.to_json() if geo else None,
                        "features": [f.to_json() for f in model.features], "storeys": model.storeys,
                        "report": {k: (len(v) if isinstance(v, list) and k in counted else v)
                                   for k, v in model.report.items()}})
            return
        from collections import Counter

        from rich.console import Console
        from rich.table import Table

        counts = Counter((f.storey, f.type) for f in model.features)
        table = Table(title=f"{Path(model.source).name}: {len(model.features)} macro-features")
        for col in ("storey", "doors", "windows"):
            table.add_column(col)
        for storey in sorted({s for s, _ in counts}, key=str):
            table.add_row(str(storey), str(counts[(storey, "door")]), str(counts[(storey, "window")]))
        Console().print(table)
        r = model.report
        Console().print(f"elements: {r.get('elements')}, without geometry: {len(r.get('no_geometry', []))}, "
                        f"non-finite geometry (dropped): {len(r.get('non_finite', []))}, "
                        f"duplicates merged: {r.get('duplicates_merged')}")
        Console().print("geo-reference: none in the model" if geo is None else
                        f"geo-reference ({geo.source}): lat {geo.latitude_deg:.7f}, lon {geo.longitude_deg:.7f}, "
                        f"alt {geo.altitude_m:.2f} m, true north {geo.true_north_deg:.2f} deg from +y"
                        + ("" if geo.north_given else " (not given: +y by default)"))
