"""Issue 58 item 5: what a registration needs from the building alone is built before its timed block
(`RegistrationResult.elapsed_ms`) and read from the disk cache by the next process (a one-shot `macroloc localize`
runs one registration per process: built lazily, it was rebuilt inside the timed block on every call)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import macroloc.graph.model_index as model_index
import macroloc.graph.posterior as posterior
import macroloc.graph.registration as registration
import macroloc.graph.robust as robust
from macroloc.graph.evaluation import ScenarioParams, make_scenario
from macroloc.graph.model_index import ModelIndex, index_for
from macroloc.graph.observations import ObservationSet
from macroloc.graph.params import RobustParams

BUILDERS = ("build_tables", "build_layout", "building_self_maps")


def _must_not_run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
    raise AssertionError("rebuilt a cached asset of the building")


def _state(index: ModelIndex) -> list:
    """What an index has built lazily, for it and its storeys."""
    return [(sorted(i._pairs), sorted(i._pair_rows), i._layout is None, i._self_maps is None, sorted(i._assets))
            for i in (index, *index._by_storey.values())]


@pytest.fixture
def fresh_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MACROLOC_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(model_index, "_CACHE", {})  # nothing held in memory: as a new process
    return tmp_path / "cache"


@pytest.mark.parametrize("hint, overrides", [(False, {}), (True, {}), (False, {"pair_max_baseline_m": 25.0})])
def test_the_timed_block_builds_nothing_of_the_building(duplex_model, fresh_cache: Path,
                                                        monkeypatch: pytest.MonkeyPatch, hint: bool,
                                                        overrides: dict) -> None:
    """Between the two clock readings of `register` (elapsed_ms) no per-building asset is built or read: no
    descriptor tables, layout, self-maps, pair table or its row look-up, the posterior's tables (graph.posterior),
    of the building or of the hinted storey (with another pair baseline than the default, its table is prepared
    before the clock starts too)."""
    s = make_scenario(duplex_model, 3, 58, ScenarioParams(variant="gravity", k_choices=(10,)))
    obs = ObservationSet(s.obs.observations, s.obs.gravity_map, s.storey if hint else None)
    index = index_for(duplex_model)
    snapshots: list[list] = []
    timed = {"on": False}
    real = time.perf_counter

    class Clock:  # registration's `time`: its first reading starts the timed block, its second ends it
        @staticmethod
        def perf_counter() -> float:
            timed["on"] = not timed["on"]
            snapshots.append(_state(index))
            return real()

    def refuse_while_timed(name: str, original):  # noqa: ANN001, ANN202
        def call(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            assert not timed["on"], f"{name} inside the registration's timed block"
            return original(*args, **kwargs)
        return call

    monkeypatch.setattr(registration, "time", Clock)
    for name in BUILDERS:
        monkeypatch.setattr(model_index, name, refuse_while_timed(name, getattr(model_index, name)))
    monkeypatch.setattr(ModelIndex, "build", classmethod(refuse_while_timed("ModelIndex.build",
                                                                            ModelIndex.build.__func__)))
    monkeypatch.setattr(ModelIndex, "_set_pairs", refuse_while_timed("the pair table", ModelIndex._set_pairs))
    monkeypatch.setattr(posterior, "_building_arrays", refuse_while_timed("the posterior's tables",
                                                                          posterior._building_arrays))
    result = registration.register(duplex_model, obs, **overrides)
    assert len(snapshots) == 2 and not timed["on"]
    assert snapshots[0] == snapshots[1], "the registration built a per-building asset in its timed block"
    assert result.status in ("localized", "ambiguous", "not_localized")
    if hint:
        assert list(index._by_storey) == [s.storey]


def test_a_second_process_reads_every_asset_from_the_disk_cache(duplex_model, fresh_cache: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """index_for writes the building's assets (and a storey's, for_storey; the posterior's tables with
    graph.robust.prepare) to the cache; with the memory cleared (a new process) they are read back, none rebuilt,
    and equal to what was built."""
    storey = str(duplex_model.features[0].storey)
    built = index_for(duplex_model)
    built_storey = built.for_storey(storey)
    max_m = RobustParams().pair_max_baseline_m
    for index in (built, built_storey):
        robust.prepare(index, RobustParams())
    assert built._pairs[max_m] is not None and built._layout is not None
    names = sorted(p.name.split("-")[0] for p in fresh_cache.iterdir())
    assert names == sorted(["layout", "pairs", "posterior", "selfmaps", "tables"] * 2)
    model_index._CACHE.clear()
    for name in BUILDERS:
        monkeypatch.setattr(model_index, name, _must_not_run)
    monkeypatch.setattr(ModelIndex, "pairs_of", _must_not_run)  # where a pair table and its rows are built
    monkeypatch.setattr(posterior, "_building_arrays", _must_not_run)
    read = index_for(duplex_model)
    read_storey = read.for_storey(storey)
    for index in (read, read_storey):
        robust.prepare(index, RobustParams())
    for a, b in ((built, read), (built_storey, read_storey)):
        ta, tb = posterior._tables(a), posterior._tables(b)
        assert ta.wall_m == tb.wall_m and np.array_equal(ta.alike, tb.alike)
        assert np.array_equal(ta.alike_logw, tb.alike_logw)
        for field in ("i", "j", "v", "d_xy", "dz"):
            got, want = getattr(b._pairs[max_m], field), getattr(a._pairs[max_m], field)
            assert got.dtype == want.dtype and np.array_equal(got, want)
        for got, want in zip(b._pair_rows[max_m], a._pair_rows[max_m], strict=True):
            assert got.dtype == want.dtype and np.array_equal(got, want)
        assert a._layout is not None and b._layout is not None
        for field in ("dilated", "weight", "dz_edges", "d_edges", "w_edges"):
            assert np.array_equal(getattr(b._layout, field), getattr(a._layout, field))
        assert np.array_equal(b.self_maps().lands, a.self_maps().lands)
        assert np.array_equal(b.tables.dist_samples_m, a.tables.dist_samples_m)


def test_a_storey_without_features_is_an_empty_index(duplex_model, fresh_cache: Path) -> None:
    """A storey hint that names no storey of the building (the flight's one-rectangle candidates ask for it) gives
    an index of no features, as before its assets were cached: nothing to cache, nothing raised."""
    assert len(index_for(duplex_model).for_storey("no such storey").features) == 0
