"""A building's prepared assets: everything the service derives from the model file before its first frame.

Each part is cached on disk by the file's SHA-256 and its parameters as soon as it is built (written to a
temporary file, then renamed: a killed process leaves either nothing or a whole file), so a start-up that is
interrupted resumes where it stopped. `macroloc prepare BUILDING` builds them ahead of time; `serve`, `replay`
and `localize` build any part still missing, lazily, through the same functions.

| part | what | cached as |
|---|---|---|
| features | doors and windows (graph.bim.load_building) | `features-*.json` |
| descriptor tables | registration tables, self-maps, layout, pairs (model_index.index_for) | `tables-*` .. `pairs-*` |
| obstacles | the model's solids for planning (load_solids) | `solids-*.npz` |
| wall voxels | walls as voxels for line-of-sight checks (wall_voxels) | `opaque-voxels-*.npy` |
| surfaces | what a camera sees, for checking registrations (surfaces_for) | `surfaces-*.npz` |
| planning grid | each storey's occupancy grid at flight height (kept in memory: built from the cached solids) | — |
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from macroloc.graph.bim import BuildingModel, cache_dir, load_building
from macroloc.graph.building_assets import BuildingSolids, load_solids, surfaces_for
from macroloc.graph.model_index import index_for
from macroloc.graph.planning import Planner
from macroloc.graph.surfaces import SurfaceIndex
from macroloc.service.config import GraphConfig, PlanningConfig

log = logging.getLogger(__name__)


@dataclass
class PreparedPart:
    name: str
    seconds: float  # wall time this run spent on it (near 0 when it came from the cache)


@dataclass
class PreparedBuilding:
    model: BuildingModel
    surfaces: SurfaceIndex | None
    planner: Planner
    parts: list[PreparedPart] = field(default_factory=list)

    def summary(self) -> str:
        return ", ".join(f"{p.name} {p.seconds:.1f} s" for p in self.parts)


def prepare_building(building: Path, graph: GraphConfig, planning: PlanningConfig) -> PreparedBuilding:
    """Build (or read from the cache) every asset of `building` that the service needs, part by part.

    Surfaces and wall voxels come from IFC models only: for a mesh model registrations go unchecked (logged).
    """
    parts: list[PreparedPart] = []

    def timed(name: str, build: Callable[[], object]) -> object:
        t0 = time.perf_counter()
        value = build()
        parts.append(PreparedPart(name, time.perf_counter() - t0))
        log.info("%s: %s ready in %.1f s", building.name, name, parts[-1].seconds)
        return value

    model: BuildingModel = timed("features", lambda: load_building(building))  # type: ignore[assignment]
    log.info("%s: preparing its other assets (each cached once built; `macroloc prepare` builds them ahead)",
             building.name)
    timed("descriptor tables", lambda: index_for(model))
    solids: BuildingSolids = timed("obstacles", lambda: load_solids(building))  # type: ignore[assignment]
    surfaces = timed("surfaces", lambda: surfaces_for(building, line_of_sight=graph.line_of_sight)) \
        if graph.surface_check else None
    p = planning
    planner: Planner = timed("planner", lambda: Planner(model, solids, p.cell_m, p.vehicle_radius_m,
                                                        p.flight_height_m))  # type: ignore[assignment]

    def grids() -> None:
        for elevation in sorted(model.storey_elevations_m.values()):
            planner.grid(elevation + p.flight_height_m)

    timed("planning grids", grids)
    prepared = PreparedBuilding(model, surfaces if isinstance(surfaces, SurfaceIndex) else None, planner, parts)
    log.info("%s: assets in %s (%s)", building.name, cache_dir(), prepared.summary())
    return prepared
