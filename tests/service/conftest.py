"""Fixtures shared by the service tests."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest

from macroloc.cli.main import main


@pytest.fixture(scope="session")
def rendered_office_flight(tmp_path_factory: pytest.TempPathFactory, office_path: Path) -> Path:
    """7 s of a rendered flight through the bundled Office_A (seed 1: its first doors in range at 5.5 s)."""
    out = tmp_path_factory.mktemp("rendered") / "office.mcap"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", str(office_path), "--out", str(out), "--duration", "7", "--seed", "1",
                     "--json"]) == 0
    return out
