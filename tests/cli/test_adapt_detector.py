"""`macroloc adapt-detector`: renders a building's own frames, trains on them, exports a loadable detector."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macroloc.cli.main import main
from tests.conftest import BUILDINGS, shared_data


def test_bad_seeds_and_missing_photos_are_one_line(tmp_path: Path, capsys) -> None:
    building = str(BUILDINGS / "fzk_haus.ifc")
    for args in (["--seeds", "one,two"], ["--facades", str(tmp_path / "none")]):
        rc = main(["adapt-detector", building, "--out", str(tmp_path / "o"), *args])
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_adapts_on_a_few_rendered_frames_and_exports_a_loadable_model(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")
    from macroloc.perception.detector import Detector

    facades = shared_data("images/facades")
    rc = main(["adapt-detector", str(BUILDINGS / "fzk_haus.ifc"), "--out", str(tmp_path), "--facades", str(facades),
               "--seeds", "1", "--duration", "4", "--every", "15", "--steps", "3", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames"] >= 8 and doc["doors"] + doc["windows"] > 0
    sidecar = json.loads((tmp_path / "detector.json").read_text())
    assert sidecar["trained_on"]["rendered_frames"] == doc["frames"]
    assert sidecar["training"]["init"]["path"].endswith("detector.pt")  # fine-tuned from the shipped weights
    assert len(list((tmp_path / "frames" / "labels").glob("*.txt"))) == doc["frames"]
    import numpy as np

    Detector(Path(doc["model"])).detect(np.zeros((480, 640, 3), np.uint8))  # loads and runs
