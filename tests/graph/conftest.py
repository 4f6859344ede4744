"""Fixtures shared by the graph tests: the test room's surface index, with and without its walls as voxels."""

from __future__ import annotations

import pytest

from macroloc.graph.surfaces import SurfaceIndex, SurfaceParams, WallVoxels
from tests.graph.rooms import room_mesh
from tests.graph.scenes import corridor_model


@pytest.fixture(scope="session")
def room() -> SurfaceIndex:
    return SurfaceIndex.from_mesh(*room_mesh(), SurfaceParams(spacing_m=0.05))


@pytest.fixture(scope="session")
def room_with_walls() -> SurfaceIndex:
    index = SurfaceIndex.from_mesh(*room_mesh(), SurfaceParams(spacing_m=0.05))
    index.walls = WallVoxels.from_mesh(*room_mesh())
    return index


@pytest.fixture(scope="session")
def corridor():  # noqa: ANN201
    """A straight corridor of doors (tests/graph/scenes.py), shared by the pose-graph and localizer tests."""
    return corridor_model()
