"""Doors and windows of the bundled IFC buildings, the per-building cache and the merge of duplicates."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import macroloc.graph.bim_ifc as bim_ifc
from macroloc.graph.bim import load_building, merge_duplicates
from macroloc.graph.features import BuildingModel, MacroFeature


def _counts(model: BuildingModel) -> Counter:
    return Counter((f.storey, f.type) for f in model.features)


def test_duplex_counts_per_storey(duplex_model: BuildingModel) -> None:
    assert _counts(duplex_model) == {("Level 1", "door"): 6, ("Level 1", "window"): 4,
                                     ("Level 2", "door"): 8, ("Level 2", "window"): 18, ("Roof", "window"): 2}
    skylights = [f for f in duplex_model.features if f.storey == "Roof"]
    assert all(f.orientation == "horizontal" for f in skylights)
    for f in skylights:
        np.testing.assert_allclose(f.normal_cad, [0, 0, 1])
    elev = duplex_model.storey_elevations_m
    assert elev["Level 1"] < elev["Level 2"] < elev["Roof"]


def test_fzk_haus_counts(fzk_path: Path) -> None:
    model = load_building(fzk_path)
    assert Counter(f.type for f in model.features) == {"door": 5, "window": 11}
    assert model.report["schema"] == "IFC4"


def test_office_counts_per_storey(office_model: BuildingModel) -> None:
    assert Counter(f.type for f in office_model.features) == {"door": 102, "window": 69}
    assert _counts(office_model) == {("Level 1", "door"): 66, ("Level 1", "window"): 25,
                                     ("Level 2", "door"): 36, ("Level 2", "window"): 44}
    assert office_model.report["no_geometry"] == []


def _assert_rectangles(model: BuildingModel) -> None:
    """Tolerances allow for the cache, which stores corners to 1e-5 m and sizes to 1e-4 m."""
    for f in model.features:
        c = f.corners_cad
        assert np.linalg.norm(f.normal_cad) == pytest.approx(1.0, abs=1e-4)
        np.testing.assert_allclose(c.mean(axis=0), f.centroid_cad, atol=1e-4)
        u, v = c[1] - c[0], c[3] - c[0]
        assert np.linalg.norm(u) == pytest.approx(f.width_m, abs=1e-3)
        assert np.linalg.norm(v) == pytest.approx(f.height_m, abs=1e-3)
        assert u @ v == pytest.approx(0.0, abs=1e-4)  # a right angle
        np.testing.assert_allclose(c[2], c[1] + v, atol=1e-4)  # a parallelogram, hence a rectangle
        assert u @ f.normal_cad == pytest.approx(0.0, abs=1e-4)
        if f.orientation == "vertical":
            assert f.normal_cad[2] == pytest.approx(0.0, abs=1e-9)  # horizontal wall normal
            np.testing.assert_allclose(v / np.linalg.norm(v), [0, 0, 1], atol=1e-4)  # height along z


def test_rectangles_and_normals(duplex_model: BuildingModel, office_model: BuildingModel) -> None:
    _assert_rectangles(duplex_model)
    _assert_rectangles(office_model)


def test_sizes_are_plausible(office_model: BuildingModel) -> None:
    doors = [f for f in office_model.features if f.type == "door"]
    assert np.median([f.height_m for f in doors]) == pytest.approx(2.1, abs=0.4)
    assert all(0.5 < f.width_m < 4.0 for f in doors)


def test_centroid_comes_from_geometry_not_placement(fzk_path: Path) -> None:
    import ifcopenshell.util.placement as up

    ifc = bim_ifc.open_ifc(fzk_path)
    elements = list(ifc.by_type("IfcDoor")) + list(ifc.by_type("IfcWindow"))
    shapes = bim_ifc.element_vertices(ifc, elements, bim_ifc.geometry_settings())
    model = load_building(fzk_path)
    by_id = {f.id: f for f in model.features}
    offsets = []
    for e in elements:
        verts, f = shapes[e.id()], by_id[e.GlobalId]
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        assert np.all(f.centroid_cad >= lo - 1e-6) and np.all(f.centroid_cad <= hi + 1e-6)
        placement_m = up.get_local_placement(e.ObjectPlacement)[:3, 3]  # FZK-Haus is in metres
        offsets.append(np.linalg.norm(placement_m - f.centroid_cad))
    assert max(offsets) > 0.3  # the placement sits at a corner, not at the centre


def test_second_load_is_served_from_cache(duplex_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    first = load_building(duplex_path)

    def must_not_run(path: Path):
        raise AssertionError("the IFC reader ran although the building is cached")

    monkeypatch.setattr(bim_ifc, "read_ifc_features", must_not_run)
    second = load_building(duplex_path)
    assert [f.id for f in second.features] == [f.id for f in first.features]
    np.testing.assert_allclose(second.centroids_cad(), first.centroids_cad(), atol=1e-4)
    with pytest.raises(AssertionError, match="ran although"):
        load_building(duplex_path, use_cache=False)


def _feature(fid: str, kind: str, centroid: list[float]) -> MacroFeature:
    c = np.array(centroid, float)
    corners = c + np.array([[-0.5, 0, -1], [0.5, 0, -1], [0.5, 0, 1], [-0.5, 0, 1]])
    return MacroFeature(id=fid, type=kind, storey="L1", corners_cad=corners,  # type: ignore[arg-type]
                        centroid_cad=c, normal_cad=np.array([0.0, 1.0, 0.0]), width_m=1.0, height_m=2.0)


def test_duplicates_are_merged() -> None:
    features = [_feature("a", "door", [0, 0, 1]), _feature("a-copy", "door", [0.03, 0, 1]),
                _feature("w", "window", [0, 0, 1]), _feature("b", "door", [3, 0, 1])]
    merged, n = merge_duplicates(features)
    assert n == 1
    assert [f.id for f in merged] == ["a", "w", "b"]  # a window at the same place is no duplicate of a door
    assert merged[0].duplicates == ("a-copy",)


def test_an_ifczip_reads_as_its_ifc_and_is_cached(fzk_path: Path, tmp_path: Path) -> None:
    import zipfile

    from macroloc.graph.bim import cache_dir, is_ifc
    from macroloc.service.offline.plots import load_wall_mesh

    zipped = tmp_path / "fzk_haus.ifcZIP"
    with zipfile.ZipFile(zipped, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.write(fzk_path, "fzk_haus.ifc")
    assert is_ifc(zipped)
    plain, from_zip = load_building(fzk_path), load_building(zipped)
    assert [f.id for f in from_zip.features] == [f.id for f in plain.features]
    assert np.allclose([f.centroid_cad for f in from_zip.features], [f.centroid_cad for f in plain.features])
    cached = sorted(cache_dir().glob("features-*.json"), key=lambda p: p.stat().st_mtime)
    assert load_building(zipped).sha256 == from_zip.sha256 and cached[-1].exists()
    walls = load_wall_mesh(zipped)
    assert walls is not None and len(walls.faces) == len(load_wall_mesh(fzk_path).faces)
