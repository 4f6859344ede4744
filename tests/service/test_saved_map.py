"""The saved map (service.saved_map): one file format and one restore path for `serve` and `replay`; what a run
saves, what a new run in another odometry frame re-localizes by, and the files it refuses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from macroloc.graph.errors import UserInputError
from macroloc.graph.localizer import Localizer, LocalizerParams
from macroloc.graph.mapstore import KeyframeView
from macroloc.graph.posegraph import PoseGraph
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.service.localizer_loop import LoopSettings
from macroloc.service.saved_map import SavedMap, read_saved_map, saved_map_of, write_saved_map
from macroloc.service.state import SavedMapFile
from tests.graph.corridor_flight import UP, fly, model_registrar
from tests.graph.scenes import corridor_model, make_T, rot_z, sightings_from, straight_flight

CORRIDOR = corridor_model()


def test_a_saved_map_re_localizes_a_new_flight_by_the_doors_it_linked(tmp_path: Path) -> None:
    """A flight's saved map, written and read back; a new flight over the same place, its odometry frame elsewhere
    (the saved T_cad_map does not hold for it), is localized by the saved CAD-linked doors from two of them on."""
    poses = straight_flight(40)
    first = fly(CORRIDOR, poses, poses, sigma_m=0.01)
    saved = read_saved_map(write_saved_map(tmp_path / "flight.pb", first, None, None, "corridor"), CORRIDOR)
    assert len(saved.linked) == len(first.links) > 3 and saved.T_cad_map is not None
    T_odom_cad = make_T(rot_z(-1.2), np.array([-4.0, 7.0, 0.0]))
    registrar = saved.registrar(CORRIDOR)(LoopSettings())
    loc = Localizer(CORRIDOR, PoseGraph(), registrar, LocalizerParams())
    rng = np.random.default_rng(5)
    for k, T in enumerate(poses[:6]):
        est = loc.add_keyframe(k, T_odom_cad @ T, sightings_from(CORRIDOR, T, rng=rng, sigma_m=0.01), UP)
        if est.status == "localized":
            break
    assert est.status == "localized" and k <= 4  # two landmarks, each seen twice
    assert est.T_cad_body is not None
    assert np.linalg.norm(est.T_cad_body[:3, 3] - poses[k][:3, 3]) < 0.1


def test_keyframe_views_survive_save_and_load(tmp_path: Path) -> None:
    """A localized flight's keyframe views, with their poses (views of an unlocalized one cannot be placed)."""
    poses = straight_flight(40)
    loc = Localizer(CORRIDOR, PoseGraph(), model_registrar(CORRIDOR), LocalizerParams())
    rng = np.random.default_rng(2)
    views = {k: KeyframeView(rng.uniform(-5, 5, (7 + k, 3)), rng.integers(0, 256, (7 + k, 32), dtype=np.uint8))
             for k in (20, 33)}
    for k, T in enumerate(poses):
        loc.add_keyframe(k, T, sightings_from(CORRIDOR, T), UP, view=views.get(k))
    assert loc.status == "localized"
    saved = read_saved_map(write_saved_map(tmp_path / "flight.pb", loc, None, None, "corridor"), CORRIDOR)
    assert len(saved.placed_views()) == 2
    for k, (T_map_body, view) in zip((20, 33), saved.placed_views(), strict=True):
        assert np.allclose(T_map_body, loc.graph.T_map_body(k))
        assert np.array_equal(view.descriptors, views[k].descriptors)
        assert np.allclose(view.points_body, views[k].points_body, atol=1e-5)  # stored as float32


def test_two_saved_maps_in_one_folder_keep_their_own_view_logs(tmp_path: Path) -> None:
    """A replay's `--save-map a.pb` beside `b.pb` (or a service's map.pb) replaces only its own view log."""
    view = KeyframeView(np.ones((30, 3), np.float32), np.zeros((30, 32), np.uint8))
    snapshot = pb.MapSnapshot(building_sha256=CORRIDOR.sha256, status=pb.PoseEstimate.LOCALIZED)
    for name in ("a.pb", "b.pb", "map.pb", "a.pb"):
        SavedMapFile.at(tmp_path / name).save(pb.MapSnapshot.FromString(snapshot.SerializeToString()),
                                              [(np.eye(4), view)])
    assert sorted(p.name.split("-")[0] for p in tmp_path.glob("*.bin")) == ["a.views", "b.views", "views"]
    for name in ("a.pb", "b.pb", "map.pb"):
        assert len(SavedMapFile.at(tmp_path / name).read().views) == 1
    assert len(SavedMapFile(tmp_path.parent, tmp_path.name).read().views) == 1  # the service's own path


def test_an_old_json_map_another_buildings_and_none_are_refused_in_one_line(tmp_path: Path) -> None:
    old = tmp_path / "map.json"
    old.write_text(json.dumps({"version": 2, "building_sha256": CORRIDOR.sha256, "T_cad_map": None,
                               "keyframes": [], "landmarks": []}))
    with pytest.raises(UserInputError, match="is a JSON map of an earlier macroloc; save the map again"):
        read_saved_map(old, CORRIDOR)
    assert SavedMapFile.at(old).load(CORRIDOR.sha256) is None  # a service starts afresh
    other = SavedMapFile.at(tmp_path / "other.pb").save(pb.MapSnapshot(building_sha256="another-sha"))
    with pytest.raises(UserInputError, match="made in another building"):
        read_saved_map(other, CORRIDOR)
    with pytest.raises(UserInputError, match="saved map not found"):
        read_saved_map(tmp_path / "none.pb", CORRIDOR)


def test_an_unlocalized_saved_map_offers_neither_views_nor_landmarks_to_place() -> None:
    loc = Localizer(CORRIDOR, PoseGraph(), model_registrar(CORRIDOR), LocalizerParams())
    view = KeyframeView(np.ones((30, 3), np.float32), np.zeros((30, 32), np.uint8))
    loc.add_keyframe(0, np.eye(4), [], UP, view=view)
    saved = saved_map_of(loc)
    assert saved.T_cad_map is None and saved.placed_views() == [] and saved.landmarks == []
    assert isinstance(saved, SavedMap)
