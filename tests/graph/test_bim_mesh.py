"""Doors and windows from meshes: small synthetic OBJ/GLB files written with trimesh, and the hospital."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import trimesh

from macroloc.graph.bim import load_building
from macroloc.graph.bim_mesh import read_mesh_features
from macroloc.graph.errors import BuildingError
from tests.conftest import shared_data

HOSPITAL = "bim/aws_hospital"


def _box(extents_xyz: tuple[float, float, float], centre_xyz: tuple[float, float, float]) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents_xyz)
    box.apply_translation(centre_xyz)
    return box


def _frame(centre_x: float, y: float, width: float = 1.0, height: float = 2.2) -> trimesh.Trimesh:
    """A door frame in a wall along x: two jambs and a head touching them, three separate parts."""
    jamb_w, depth = 0.05, 0.2
    parts = [_box((jamb_w, depth, height), (centre_x + s * (width - jamb_w) / 2, y, height / 2)) for s in (-1, 1)]
    parts.append(_box((width - 2 * jamb_w, depth, jamb_w), (centre_x, y, height - jamb_w / 2)))
    return trimesh.util.concatenate(parts)


def building_scene(scale: float = 1.0, z_offset_m: float = 0.0) -> trimesh.Scene:
    """Two door-named boxes, one window-named box, a group of two door frames, a wall, a door sign (metres)."""
    nodes = {
        "door_01": _box((1.0, 0.1, 2.1), (0.0, 0.0, 1.05)),  # in a wall along x: normal +-y
        "Door_02": _box((0.1, 0.9, 2.0), (5.0, 3.0, 1.0)),  # in a wall along y: normal +-x
        "Window_A": _box((1.2, 0.1, 1.0), (2.0, 0.0, 1.5)),
        "doorframes_group": trimesh.util.concatenate([_frame(-4.0, 6.0), _frame(1.0, 6.0)]),
        "wall_main": _box((12.0, 0.2, 3.0), (0.0, 8.0, 1.5)),
        "doorsign_01": _box((0.3, 0.02, 0.2), (0.0, 0.1, 2.3)),
    }
    scene = trimesh.Scene()
    for name, mesh in nodes.items():
        mesh = mesh.copy()
        mesh.apply_translation((0.0, 0.0, z_offset_m))
        mesh.apply_scale(scale)
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    return scene


@pytest.fixture(scope="module")
def obj_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mesh") / "building.obj"
    building_scene().export(path)
    return path


@pytest.fixture(scope="module")
def glb_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scene = building_scene()
    scene.graph.update(frame_to="door_without_mesh", frame_from="world")  # a door node with no geometry
    path = tmp_path_factory.mktemp("mesh") / "building.glb"
    scene.export(path)
    return path


def _by_name(features) -> dict[str, list]:
    out: dict[str, list] = {}
    for f in features:
        out.setdefault(f.name, []).append(f)
    return out


@pytest.mark.parametrize("fixture", ["obj_path", "glb_path"])
def test_synthetic_mesh_types_sizes_normals(fixture: str, request: pytest.FixtureRequest) -> None:
    features, report = read_mesh_features(request.getfixturevalue(fixture))
    assert Counter(f.type for f in features) == {"door": 4, "window": 1}
    named = _by_name(features)
    (d1,) = named["door_01"]
    assert d1.width_m == pytest.approx(1.0, abs=1e-3) and d1.height_m == pytest.approx(2.1, abs=1e-3)
    assert abs(d1.normal_cad @ [0, 1, 0]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(d1.centroid_cad, [0.0, 0.0, 1.05], atol=1e-3)
    (d2,) = named["Door_02"]
    assert d2.width_m == pytest.approx(0.9, abs=1e-3) and d2.height_m == pytest.approx(2.0, abs=1e-3)
    assert abs(d2.normal_cad @ [1, 0, 0]) == pytest.approx(1.0, abs=1e-6)
    (w,) = named["Window_A"]
    assert w.type == "window" and w.width_m == pytest.approx(1.2, abs=1e-3) and w.height_m == pytest.approx(1.0)
    assert "doorsign_01" not in named and "wall_main" not in named  # excluded / not a door or window
    assert all(f.storey == "level_00" for f in features)
    assert report["elements"] == 5


def test_group_is_split_into_instances(obj_path: Path) -> None:
    features, report = read_mesh_features(obj_path)
    frames = sorted(_by_name(features)["doorframes_group"], key=lambda f: f.centroid_cad[0])
    assert len(frames) == 2 and report["groups"]["doorframes_group"]["instances"] == 2
    for f, x in zip(frames, (-4.0, 1.0), strict=True):
        assert f.width_m == pytest.approx(1.0, abs=1e-3) and f.height_m == pytest.approx(2.2, abs=1e-3)
        np.testing.assert_allclose(f.centroid_cad, [x, 6.0, 1.1], atol=1e-3)
    assert len({f.id for f in features}) == len(features)  # ids: node name + instance index, unique


def test_element_without_geometry_is_reported_not_fatal(glb_path: Path) -> None:
    features, report = read_mesh_features(glb_path)
    assert "door_without_mesh" in report["no_geometry"]
    assert len(features) == 5


def test_degenerate_door_is_rejected_not_fatal(tmp_path: Path) -> None:
    scene = building_scene()
    sliver = trimesh.Trimesh(vertices=[[9, 9, 0], [9.01, 9, 0], [9, 9.01, 0]], faces=[[0, 1, 2]])
    scene.add_geometry(sliver, node_name="door_broken", geom_name="door_broken")
    path = tmp_path / "broken.glb"
    scene.export(path)
    features, report = read_mesh_features(path)
    assert any(r.startswith("door_broken") for r in report["rejected_small"])
    assert len(features) == 5


def test_centimetre_file_is_scaled_to_metres(tmp_path: Path) -> None:
    path = tmp_path / "building_cm.obj"  # OBJ declares no unit: guessed from door heights
    building_scene(scale=100.0).export(path)
    features, report = read_mesh_features(path)
    assert report["unit_scale"][path.name]["metres_per_unit"] == pytest.approx(0.01)
    assert _by_name(features)["door_01"][0].height_m == pytest.approx(2.1, abs=1e-3)
    explicit, report = read_mesh_features(path, {"unit_scale": 0.01})
    assert report["unit_scale"][path.name]["source"] == "mesh_rules"
    assert _by_name(explicit)["Door_02"][0].width_m == pytest.approx(0.9, abs=1e-3)


def test_y_up_mesh_with_up_axis_rule(tmp_path: Path) -> None:
    scene = building_scene()
    z_up_to_y_up = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])  # (x, y, z) -> (x, z, -y)
    for name in list(scene.graph.nodes_geometry):
        scene.geometry[scene.graph[name][1]].apply_transform(z_up_to_y_up)
    path = tmp_path / "y_up.glb"
    scene.export(path)
    features, _ = read_mesh_features(path, {"up_axis": "y"})
    (d1,) = _by_name(features)["door_01"]
    assert d1.height_m == pytest.approx(2.1, abs=1e-3)
    np.testing.assert_allclose(d1.centroid_cad, [0.0, 0.0, 1.05], atol=1e-3)


def test_rules_override_and_validation(obj_path: Path) -> None:
    features, _ = read_mesh_features(obj_path, {"door": [r"^door_01$"], "window": []})
    assert [f.name for f in features] == ["door_01"]
    with pytest.raises(BuildingError, match="bad regex"):
        read_mesh_features(obj_path, {"door": ["("]})
    with pytest.raises(BuildingError, match="unit_scale"):
        read_mesh_features(obj_path, {"unit_scale": -1})
    with pytest.raises(BuildingError, match="unknown mesh rule"):
        read_mesh_features(obj_path, {"doors": ["x"]})


def test_height_bands_make_storeys(tmp_path: Path) -> None:
    scene = building_scene()
    upper = building_scene(z_offset_m=3.2)
    for name in list(upper.graph.nodes_geometry):
        transform, geom = upper.graph[name]
        scene.add_geometry(upper.geometry[geom], node_name=f"up_{name}", geom_name=f"up_{geom}", transform=transform)
    path = tmp_path / "two_storeys.glb"
    scene.export(path)
    features, report = read_mesh_features(path)
    assert Counter(f.storey for f in features) == {"level_00": 5, "level_01": 5}
    assert report["storey_elevations_m"]["level_01"] == pytest.approx(3.2, abs=1e-3)


def test_duplicates_are_merged_by_load_building(tmp_path: Path) -> None:
    scene = building_scene()
    scene.add_geometry(_box((1.0, 0.1, 2.1), (0.0, 0.0, 1.05)), node_name="door_01_copy", geom_name="door_01_copy")
    path = tmp_path / "dup.glb"
    scene.export(path)
    model = load_building(path)
    assert model.report["duplicates_merged"] == 1
    assert len(model.features) == 5


def test_unreadable_mesh_is_a_building_error(tmp_path: Path) -> None:
    path = tmp_path / "junk.glb"
    path.write_bytes(b"not a glb at all")
    with pytest.raises(BuildingError):
        read_mesh_features(path)


def test_hospital_floor_01_door_frames_and_windows() -> None:
    path = shared_data(f"{HOSPITAL}/aws_robomaker_hospital_floor_01_walls_visual.dae")
    model = load_building(path)
    assert Counter((f.storey, f.type) for f in model.features) == {("floor_01", "door"): 26,
                                                                   ("floor_01", "window"): 4}
    assert model.report["unit_scale"][path.name]["metres_per_unit"] == pytest.approx(0.01)
    doors = [f for f in model.features if f.type == "door"]
    assert all(0.8 <= f.width_m <= 2.0 and 2.0 <= f.height_m <= 2.5 for f in doors)
    assert all(abs(f.centroid_cad[2] - f.height_m / 2) < 0.05 for f in doors)  # standing on the floor
    for f in model.features:
        assert f.normal_cad[2] == pytest.approx(0.0, abs=1e-9) and np.linalg.norm(f.normal_cad) == pytest.approx(1.0)
    assert not model.report["no_geometry"]
    ids = {f.id for f in model.features}
    assert "aws_robomaker_hospital_floor_01_doorframes_small_visual#0" in ids  # node name + instance index


def test_hospital_world_places_floors_and_reports_missing_models() -> None:
    path = shared_data(f"{HOSPITAL}/hospital_three_floors.world")
    features, report = read_mesh_features(path)
    assert Counter(f.storey for f in features) == {"level_00": 30, "level_01": 30, "level_02": 30}
    assert report["storey_elevations_m"]["level_02"] == pytest.approx(6.0, abs=0.01)
    assert "aws_robomaker_hospital_elevator_01_door" in report["missing_models"]
