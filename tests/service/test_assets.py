"""service.assets and `macroloc prepare`: a building's assets are built part by part, each cached as soon as it is
built, so an interrupted preparation resumes instead of starting over."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from macroloc.cli.main import main
from tests.conftest import BUILDINGS


def test_prepare_builds_every_part_and_a_second_run_builds_nothing(tmp_path: Path, monkeypatch, capsys) -> None:
    import macroloc.graph.model_index as model_index

    monkeypatch.setenv("MACROLOC_CACHE", str(tmp_path / "cache"))
    # the descriptor tables an earlier test of this process built are held in memory, and would not be written
    monkeypatch.setattr(model_index, "_CACHE", {})
    fzk = BUILDINGS / "fzk_haus.ifc"
    assert main(["prepare", str(fzk), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [p["name"] for p in doc["parts"]] == ["features", "descriptor tables", "obstacles", "surfaces", "planner",
                                               "planning grids"]
    cached = sorted(p.name.split("-")[0] for p in (tmp_path / "cache").iterdir())
    assert cached == ["features", "layout", "opaque", "pairs", "seen", "selfmaps", "solids", "surfaces", "tables"]

    import macroloc.graph.bim_ifc as bim_ifc
    import macroloc.graph.building_assets as building_assets
    import macroloc.graph.surfaces as surfaces

    def must_not_run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("rebuilt a cached asset")

    monkeypatch.setattr(bim_ifc, "read_ifc_features", must_not_run)
    monkeypatch.setattr(building_assets, "_read_solids", must_not_run)
    monkeypatch.setattr(surfaces.SurfaceIndex, "from_mesh", must_not_run)
    model_index._CACHE.clear()
    monkeypatch.setattr(model_index, "build_tables", must_not_run)
    monkeypatch.setattr(model_index, "building_self_maps", must_not_run)
    monkeypatch.setattr(model_index, "build_layout", must_not_run)
    monkeypatch.setattr(model_index.ModelIndex, "pairs_of", must_not_run)  # the pair table is read, not built
    assert main(["prepare", str(fzk)]) == 0


def test_an_interrupted_preparation_keeps_what_it_finished(tmp_path: Path, monkeypatch) -> None:
    """The issue's failure: a first call killed by a client's timeout had written nothing, so every later call
    started over (and timed out too). Killed after its first part, `prepare` leaves that part whole."""
    cache = tmp_path / "cache"
    env = {**os.environ, "MACROLOC_CACHE": str(cache)}
    proc = subprocess.Popen([sys.executable, "-m", "macroloc.cli.main", "prepare", str(BUILDINGS / "duplex.ifc")],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    while not list(cache.glob("features-*.json")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    features = list(cache.glob("features-*.json"))
    assert features, "the first part was not written before the kill"
    json.loads(features[0].read_text())  # whole, not truncated

    import macroloc.graph.bim_ifc as bim_ifc

    def must_not_run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the features were parsed again")

    monkeypatch.setenv("MACROLOC_CACHE", str(cache))
    monkeypatch.setattr(bim_ifc, "read_ifc_features", must_not_run)
    from macroloc.graph.bim import load_building

    assert len(load_building(BUILDINGS / "duplex.ifc").features) > 0


def test_prepare_refuses_a_missing_file_in_one_line(tmp_path: Path, capsys) -> None:
    assert main(["prepare", str(tmp_path / "nope.ifc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not found" in err[0]

