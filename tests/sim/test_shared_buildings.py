"""Every building of ../shared/data/bim/ simulates and records without error (slow: ~10-30 s each)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import SHARED_DATA

BIM = SHARED_DATA / "bim"
BUILDINGS = sorted(BIM.glob("*.ifc")) + sorted((BIM / "aws_hospital").glob("*.world")) + sorted(
    (BIM / "aws_hospital").glob("*walls_visual.dae"))


@pytest.mark.slow
@pytest.mark.data
@pytest.mark.parametrize("building", BUILDINGS or [BIM / "absent.ifc"], ids=lambda p: p.name)
def test_building_simulates(building: Path, tmp_path: Path) -> None:
    from macroloc.cli.simulated_flight import simulate_to_mcap
    from macroloc.proto.recording import read_flight
    from macroloc.service.config import load_config
    from tests.conftest import shared_data

    shared_data(str(building.relative_to(SHARED_DATA)))
    cfg = load_config(None, camera={"width": 160, "height": 120, "fx": 120.0, "fy": 120.0, "cx": 79.5, "cy": 59.5},
                      sim={"duration_s": 2.0})
    out = tmp_path / "flight.mcap"
    summary = simulate_to_mcap(building, out, cfg, seed=1, contact_sheet=tmp_path / "sheet.png")
    assert summary["frames"] == 61
    frames = list(read_flight(out))
    assert len(frames) == 61 and all(f.ground_truth is not None for f in frames)
    assert (tmp_path / "sheet.png").is_file()
