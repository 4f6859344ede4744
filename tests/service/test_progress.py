"""Progress on stderr for the long commands (service/progress.py): shown at a terminal, never on stdout, none with
--quiet."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from macroloc.cli.main import main


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory, fzk_path: Path) -> Path:
    from macroloc.sim.truth_flight import write_truth_flight

    return write_truth_flight(fzk_path, tmp_path_factory.mktemp("flight") / "fzk.mcap", seed=0, duration_s=2.0)


@pytest.mark.parametrize("quiet", [False, True])
def test_replay_shows_its_progress_on_stderr_at_a_terminal_and_none_when_quiet(
        flight: Path, fzk_path: Path, quiet: bool, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FORCE_COLOR", "1")  # rich takes stderr for a terminal
    monkeypatch.setenv("COLUMNS", "120")
    argv = ["replay", str(flight), "--building", str(fzk_path), "--json"]
    assert main(["--quiet", *argv] if quiet else argv) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["frames"] == 60  # stdout: the JSON alone
    assert ("60/60" in err) is not quiet and ("replay fzk.mcap" in err) is not quiet


def test_without_a_terminal_there_is_no_progress(flight: Path, fzk_path: Path, capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FORCE_COLOR", raising=False)
    monkeypatch.setenv("TERM", "dumb")
    assert main(["replay", str(flight), "--building", str(fzk_path), "--json"]) == 0
    assert capsys.readouterr().err == ""
