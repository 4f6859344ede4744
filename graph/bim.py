"""Reading a building model (IFC or mesh) into macro-features, with the per-building cache.

`load_building(path)` is what every command calls: it dispatches on the file type, merges coincident
duplicates, orients normals, and caches the result by the file's SHA-256 and the parameters.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from macroloc.graph.errors import BuildingError
from macroloc.graph.features import BuildingModel, MacroFeature

log = logging.getLogger(__name__)

EXTRACTOR_VERSION = 1
DUPLICATE_TOL_M = 0.10  # same type, centroids closer than this: one physical feature exported twice
IFC_SUFFIXES = {".ifc", ".ifczip"}  # .ifczip: a zip holding one .ifc (ifcopenshell.open unzips it)
MESH_SUFFIXES = {".obj", ".glb", ".gltf", ".dae", ".ply", ".stl", ".off", ".world"}


def is_ifc(path: str | Path) -> bool:
    """An IFC model (`.ifc`, or `.ifczip` holding one), read with ifcopenshell; anything else is a mesh."""
    return Path(path).suffix.lower() in IFC_SUFFIXES


def cache_dir() -> Path:
    """$MACROLOC_CACHE, else $XDG_CACHE_HOME/macroloc, else ~/.cache/macroloc."""
    env = os.environ.get("MACROLOC_CACHE")
    base = Path(env) if env else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "macroloc"
    base.mkdir(parents=True, exist_ok=True)
    return base


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def cache_key(sha256: str, params: dict) -> str:
    blob = json.dumps(dict(params, version=EXTRACTOR_VERSION), sort_keys=True)
    return f"{sha256[:32]}-{hashlib.sha256(blob.encode()).hexdigest()[:12]}"


def load_building(path: str | Path, mesh_rules: dict | None = None, use_cache: bool = True) -> BuildingModel:
    """Macro-features of the building at `path` (IFC, or a mesh with name->type rules), CAD frame, metres."""
    path = Path(path)
    if not path.exists():
        raise BuildingError(f"building model not found: {path}")
    if not path.is_file():
        raise BuildingError(f"building model is not a file: {path}")
    suffix = path.suffix.lower()
    if suffix not in IFC_SUFFIXES | MESH_SUFFIXES:
        raise BuildingError(f"unsupported building model type {suffix!r} (IFC, or a mesh: OBJ, GLB, DAE, ...)")
    if suffix in IFC_SUFFIXES:
        from macroloc.graph.bim_ifc import check_complete_step

        check_complete_step(path)  # before the cache: a truncated file must never be answered from it
    sha = file_sha256(path)
    params = {"mesh_rules": mesh_rules or {}, "reader": 2}  # reader 2: damaged IFCs refused, non-finite dropped
    cached = cache_dir() / f"features-{cache_key(sha, params)}.json"
    if use_cache and cached.exists():
        try:
            model = model_from_json(json.loads(cached.read_text()))
            model.source = str(path)  # the same bytes may live under another name
            return model
        except (ValueError, KeyError):
            log.warning("ignoring unreadable cache file %s", cached)
    if suffix in IFC_SUFFIXES:
        from macroloc.graph.bim_ifc import read_ifc_features

        features, report = read_ifc_features(path)
    else:
        from macroloc.graph.bim_mesh import read_mesh_features

        features, report = read_mesh_features(path, mesh_rules)
    features, merged = merge_duplicates(features)
    features = orient_normals(features)
    report["duplicates_merged"] = merged
    model = BuildingModel(source=str(path), sha256=sha, features=features,
                          storeys=list(report.get("storeys", [])),
                          storey_elevations_m=dict(report.get("storey_elevations_m", {})), report=report)
    if not features:
        raise BuildingError(f"{path.name}: no door or window with geometry found")
    doc = model_to_json(model)
    tmp = cached.with_suffix(f".tmp{os.getpid()}")
    tmp.write_text(json.dumps(doc))
    os.replace(tmp, cached)
    # the model as its cache holds it (coordinates to 10 um): the same numbers whether or not the cache existed
    return model_from_json(doc)


def merge_duplicates(features: list[MacroFeature]) -> tuple[list[MacroFeature], int]:
    """Keep one of each group of same-type features whose centroids lie within DUPLICATE_TOL_M."""
    from scipy.spatial import cKDTree

    if len(features) < 2:
        return features, 0
    cents = np.array([f.centroid_cad for f in features])
    tree = cKDTree(cents)
    taken: set[int] = set()
    out = []
    for i, f in enumerate(features):
        if i in taken:
            continue
        group = [j for j in tree.query_ball_point(cents[i], DUPLICATE_TOL_M) if j != i and features[j].type == f.type
                 and j not in taken]
        taken.update(group)
        out.append(_replace(f, duplicates=tuple(features[j].id for j in group)))
    return out, len(features) - len(out)


def orient_normals(features: list[MacroFeature]) -> list[MacroFeature]:
    """Sign convention: vertical features' normals point away from the horizontal centre of all features."""
    if not features:
        return features
    centre = np.mean([f.centroid_cad for f in features], axis=0)
    out = []
    for f in features:
        if f.orientation == "vertical" and float(np.dot((f.centroid_cad - centre)[:2], f.normal_cad[:2])) < 0:
            f = _replace(f, normal_cad=-f.normal_cad, corners_cad=f.corners_cad[[1, 0, 3, 2]])
        out.append(f)
    return out


def _replace(f: MacroFeature, **changes) -> MacroFeature:
    from dataclasses import replace

    return replace(f, **changes)


def model_to_json(model: BuildingModel) -> dict:
    return dict(source=model.source, sha256=model.sha256, storeys=model.storeys,
                storey_elevations_m=model.storey_elevations_m, report=model.report,
                features=[dict(f.to_json(), name=f.name, duplicates=list(f.duplicates)) for f in model.features])


def model_from_json(doc: dict) -> BuildingModel:
    feats = [MacroFeature(id=d["id"], type=d["type"], storey=d["storey"], corners_cad=np.array(d["corners"], float),
                          centroid_cad=np.array(d["centroid"], float), normal_cad=np.array(d["normal"], float),
                          width_m=d["width"], height_m=d["height"], orientation=d["orientation"], name=d.get("name"),
                          duplicates=tuple(d.get("duplicates", ()))) for d in doc["features"]]
    return BuildingModel(source=doc["source"], sha256=doc["sha256"], features=feats, storeys=doc["storeys"],
                         storey_elevations_m=doc["storey_elevations_m"], report=doc["report"])
