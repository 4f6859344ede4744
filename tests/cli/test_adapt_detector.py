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


def test_a_recording_that_is_missing_or_labels_only_without_one_are_one_line(tmp_path: Path, capsys) -> None:
    building = str(BUILDINGS / "fzk_haus.ifc")
    for args in (["--recording", str(tmp_path / "none.mcap")], ["--labels-only"]):
        rc = main(["adapt-detector", building, "--out", str(tmp_path / "o"), *args])
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


@pytest.mark.slow
def test_a_recorded_flight_is_labelled_where_its_pose_is_held(tmp_path: Path, capsys) -> None:
    """The user's path: a flight replayed with perception (the generic detector) localizes, and its held frames
    are written with the model's doors as labels and a report of every decision (20 s of Office_A, seed 1:
    localized at about 13 s with the generic detector)."""
    office = BUILDINGS / "office_a.ifc"
    flight = tmp_path / "office.mcap"
    assert main(["simulate", str(office), "--out", str(flight), "--duration", "20", "--seed", "1", "--json"]) == 0
    capsys.readouterr()
    assert main(["adapt-detector", str(office), "--recording", str(flight), "--out", str(tmp_path / "a"),
                 "--labels-only", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    report = json.loads((tmp_path / "a" / "frames" / "report.json").read_text())
    flight_report = report["recordings"]["office.mcap"]
    assert doc["report"] == report and flight_report["wrong_localizations"] == 0
    assert doc["images"] == report["frames"]["labelled"] > 0 and doc["door"] > 0
    assert sum(report["frames"].values()) == flight_report["frames_in_flight"]
    assert (tmp_path / "a" / "frames" / "office.labels.png").is_file()
    assert len(list((tmp_path / "a" / "frames" / "labels").glob("office_*.txt"))) == doc["images"]
