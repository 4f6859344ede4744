"""`macroloc inspect`: pictures written, a JSON summary, and clean errors for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macroloc.cli.main import main
from tests.conftest import shared_data

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _assert_png(path: Path) -> None:
    assert path.is_file() and path.stat().st_size > 10_000
    assert path.read_bytes()[:8] == PNG_MAGIC


def test_inspect_duplex_writes_plan_and_kde(duplex_path: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "duplex.png"
    assert main(["inspect", str(duplex_path), "--plot", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["storeys"] == {"Level 1": {"door": 6, "window": 4}, "Level 2": {"door": 8, "window": 18},
                              "Roof": {"door": 0, "window": 2}}
    assert doc["plots"] == [str(out), str(tmp_path / "duplex_kde.png")]
    for p in doc["plots"]:
        _assert_png(Path(p))


def test_inspect_text_summary_without_plot(fzk_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(fzk_path)]) == 0
    text = capsys.readouterr().out
    assert "16 macro-features" in text and "doors" in text


def test_inspect_hospital_mesh(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_data("bim/aws_hospital/aws_robomaker_hospital_floor_01_walls_visual.dae")
    out = tmp_path / "hospital.png"
    assert main(["inspect", str(path), "--plot", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["storeys"] == {"floor_01": {"door": 26, "window": 4}}
    _assert_png(out)


def test_floor_plan_is_reusable(duplex_model) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from macroloc.service.offline.plots import draw_floor_plan, short_ids

    fig, ax = plt.subplots()
    draw_floor_plan(ax, duplex_model, "Level 1", walls=None)
    ax.plot([0, 5], [0, -5], color="red")  # e.g. a trajectory over the plan, same CAD frame
    assert len(ax.lines) >= 10 + 1
    assert set(short_ids(duplex_model).values()) >= {"D0", "W0"}
    plt.close(fig)


@pytest.mark.parametrize("argv", [
    ["inspect", "no/such/building.ifc"],
    ["inspect", "{tmp}/notes.txt"],
    ["inspect", "{tmp}/broken.ifc"],
    ["inspect", "{duplex}", "--plot", "{tmp}/plan.jpg"],
    ["inspect", "{duplex}", "--plot", "{tmp}/no/such/folder/plan.png"],
])
def test_bad_input_exits_2_with_one_line(argv: list[str], tmp_path: Path, duplex_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notes.txt").write_text("not a building")
    (tmp_path / "broken.ifc").write_text("ISO-10303-21;\nthis is not IFC\n")
    args = [a.format(tmp=tmp_path, duplex=duplex_path) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("macroloc: error:") and len(err.splitlines()) == 1
