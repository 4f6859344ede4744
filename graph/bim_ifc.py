"""Doors and windows of an IFC model, through ifcopenshell.

Every IfcDoor and IfcWindow (subtypes included, e.g. IfcDoorStandardCase) that has geometry becomes a
`MacroFeature` in the CAD frame, metres. ifcopenshell 0.9's geometry with `use-world-coords` already
returns metres, also for millimetre files, so no unit scale is applied to vertices.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from macroloc.graph.errors import BuildingError
from macroloc.graph.features import FeatureType, MacroFeature
from macroloc.graph.rectangle import Rectangle, least_width_direction, opening_rectangle

log = logging.getLogger(__name__)

MAX_COORD_M = 1e7  # 10,000 km: no place on Earth, even in a geo-referenced model's projected coordinates
REVOLVING_DEPTH_RATIO = 1.5  # width < 1.5 x depth: the element's own footprint cannot tell its normal


STEP_TRAILER = b"END-ISO-10303-21;"  # ISO 10303-21: the last statement of every complete STEP (.ifc) file


def check_complete_step(path: Path) -> None:
    """Raise BuildingError when a STEP file lacks its END-ISO-10303-21; trailer: a truncated copy parses without
    error but silently loses the elements written after the cut (and, at the end of the file, whole storeys)."""
    if path.suffix.lower() != ".ifc":
        return
    with path.open("rb") as f:
        f.seek(max(0, path.stat().st_size - 4096))
        tail = f.read().rstrip()
    if not tail.endswith(STEP_TRAILER):
        raise BuildingError(f"{path.name} is truncated or incomplete: it does not end with "
                            f"{STEP_TRAILER.decode()} ({path.stat().st_size} bytes)")


def open_ifc(path: Path):
    import ifcopenshell

    check_complete_step(path)
    ifcopenshell.get_log()  # reading the log empties it: what follows is this file's
    try:
        ifc = ifcopenshell.open(str(path))
    except Exception as exc:  # ifcopenshell raises its own error types for unparsable files
        raise BuildingError(f"cannot read IFC file {path}: {str(exc).splitlines()[0] if str(exc) else exc}") from None
    errors = [line for line in ifcopenshell.get_log().splitlines() if line.startswith("[error]")]
    if errors:  # the parser skips what it cannot read: a damaged value silently changes an element's geometry
        first = errors[0].split("] ", 3)[-1]
        raise BuildingError(f"{path.name} is damaged: {len(errors)} syntax error(s), the first: {first}")
    return ifc


def geometry_settings():
    import ifcopenshell.geom

    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    return settings


def element_vertices(ifc, elements: list, settings) -> dict[int, np.ndarray]:
    """{element id(): (N, 3) world vertices in metres} for the elements that have geometry."""
    import ifcopenshell.geom

    shapes: dict[int, np.ndarray] = {}
    if not elements:
        return shapes
    iterator = ifcopenshell.geom.iterator(settings, ifc, max(1, min(2, os.cpu_count() or 1)), include=elements)
    if not iterator.initialize():
        return shapes
    while True:
        shape: Any = iterator.get()
        verts = np.asarray(shape.geometry.verts, dtype=float).reshape(-1, 3)
        if len(verts):
            shapes[shape.id] = verts
        if not iterator.next():
            break
    return shapes


def storey_of(element):
    """The IfcBuildingStorey an element belongs to: containment, else through its opening and host wall."""
    import ifcopenshell.util.element as ue

    todo, seen = [element], set()
    while todo:
        e = todo.pop(0)
        if e is None or e.id() in seen:
            continue
        seen.add(e.id())
        if e.is_a("IfcBuildingStorey"):
            return e
        container = ue.get_container(e)
        if container is not None:
            todo.append(container)
        aggregate = ue.get_aggregate(e)
        if aggregate is not None:
            todo.append(aggregate)
        for rel in getattr(e, "FillsVoids", None) or []:
            todo.append(rel.RelatingOpeningElement)
        for rel in getattr(e, "VoidsElements", None) or []:
            todo.append(rel.RelatingBuildingElement)
        for rel in getattr(e, "Nests", None) or []:
            todo.append(rel.RelatingObject)
    return None


def _opening_normal(element, settings) -> np.ndarray | None:
    """Least-width direction of the opening element the door fills (for revolving doors)."""
    import ifcopenshell.geom

    for rel in getattr(element, "FillsVoids", None) or []:
        try:
            shape: Any = ifcopenshell.geom.create_shape(settings, rel.RelatingOpeningElement)
        except RuntimeError:
            continue
        verts = np.asarray(shape.geometry.verts, dtype=float).reshape(-1, 3)
        if len(verts) >= 3:
            return least_width_direction(verts[:, :2])
    return None


def _elements_with_absurd_points(ifc, elements: list) -> set[int]:
    """Ids of the elements whose own geometry holds a point beyond MAX_COORD_M (or non-finite).

    The geometry kernel silently drops the faces such a point spans, so the triangulated vertices look sane while
    the element has shrunk or turned: the source points are checked instead (one pass over IfcCartesianPoint).
    """
    import ifcopenshell.util.unit

    limit = MAX_COORD_M / ifcopenshell.util.unit.calculate_unit_scale(ifc)  # in the file's length unit
    bad = {p.id() for p in ifc.by_type("IfcCartesianPoint")
           if not all(math.isfinite(c) and abs(c) <= limit for c in p.Coordinates)}
    if not bad:
        return set()
    return {e.id() for e in elements if any(x.id() in bad for x in ifc.traverse(e, max_levels=None))}


def read_ifc_features(path: Path) -> tuple[list[MacroFeature], dict]:
    """(features, report) of an IFC file. Raises BuildingError for an unreadable file.

    report: {"schema", "elements", "no_geometry": [ids], "non_finite": [ids of elements whose vertices are not
    finite or beyond MAX_COORD_M: dropped], "storeys": [names], "storey_elevations_m": {...}}.
    """
    ifc = open_ifc(path)
    settings = geometry_settings()
    elements = list(ifc.by_type("IfcDoor")) + list(ifc.by_type("IfcWindow"))
    shapes = element_vertices(ifc, elements, settings)
    damaged = _elements_with_absurd_points(ifc, elements)
    features, no_geometry, non_finite = [], [], []
    for e in elements:
        verts = shapes.get(e.id())
        if verts is None:
            no_geometry.append(e.GlobalId)
            continue
        if e.id() in damaged or not np.isfinite(verts).all() or np.abs(verts).max() > MAX_COORD_M:
            non_finite.append(e.GlobalId)
            continue
        rect = opening_rectangle(verts)
        if rect.orientation == "vertical" and rect.width_m < REVOLVING_DEPTH_RATIO * rect.depth_m:
            n_xy = _opening_normal(e, settings)
            if n_xy is not None:
                rect = opening_rectangle(verts, n_xy)
        storey = storey_of(e)
        kind: FeatureType = "door" if e.is_a("IfcDoor") else "window"
        features.append(_feature(e.GlobalId, kind, storey, rect, e.Name))
    storeys = [s.Name or s.GlobalId for s in ifc.by_type("IfcBuildingStorey")]
    elevations = _storey_elevations(ifc)
    if no_geometry:
        log.warning("%s: %d door/window elements without geometry were skipped", path.name, len(no_geometry))
    if non_finite:
        log.warning("%s: %d door/window elements with non-finite or out-of-range vertices were dropped: %s",
                    path.name, len(non_finite), ", ".join(non_finite[:5]))
    report = dict(schema=ifc.schema, elements=len(elements), no_geometry=no_geometry, non_finite=non_finite,
                  storeys=storeys, storey_elevations_m=elevations)
    return features, report


def _feature(gid: str, kind: FeatureType, storey, rect: Rectangle, name) -> MacroFeature:
    return MacroFeature(
        id=gid, type=kind, storey=(storey.Name or storey.GlobalId) if storey is not None else None,
        corners_cad=rect.corners, centroid_cad=rect.centroid, normal_cad=rect.normal,
        width_m=float(rect.width_m), height_m=float(rect.height_m), orientation=rect.orientation,  # type: ignore[arg-type]
        name=name,
    )


def _storey_elevations(ifc) -> dict[str, float]:
    import ifcopenshell.util.placement as up
    import ifcopenshell.util.unit as uu

    scale = uu.calculate_unit_scale(ifc)  # placements are in project units, unlike geometry
    out: dict[str, float] = {}
    for s in ifc.by_type("IfcBuildingStorey"):
        try:
            z = float(up.get_local_placement(s.ObjectPlacement)[2, 3]) * scale
        except Exception:  # noqa: BLE001 - a storey without placement: fall back to its Elevation attribute
            z = float(s.Elevation or 0.0) * scale
        out[s.Name or s.GlobalId] = z
    return out
