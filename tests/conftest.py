"""Shared fixtures: bundled buildings, the optional ../shared/data, an isolated cache per session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BUILDINGS = ROOT / "data" / "buildings"
SHARED_DATA = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data"))


def shared_data(relative: str) -> Path:
    """A path under ../shared/data, or skip the test with the reason when it is absent."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"needs {path} (the shared real-data folder beside the checkout), which is absent")
    return path


@pytest.fixture(scope="session", autouse=True)
def _isolated_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    os.environ["MACROLOC_CACHE"] = str(tmp_path_factory.mktemp("macroloc-cache"))


@pytest.fixture(scope="session")
def duplex_path() -> Path:
    return BUILDINGS / "duplex.ifc"


@pytest.fixture(scope="session")
def fzk_path() -> Path:
    return BUILDINGS / "fzk_haus.ifc"


@pytest.fixture(scope="session")
def office_path() -> Path:
    return BUILDINGS / "office_a.ifc"


@pytest.fixture(scope="session")
def office_model(office_path: Path):
    from macroloc.graph.bim import load_building

    return load_building(office_path)


@pytest.fixture(scope="session")
def duplex_model(duplex_path: Path):
    from macroloc.graph.bim import load_building

    return load_building(duplex_path)
