"""Fixtures shared by the graph tests: the test room's surface index, with and without its walls as voxels."""

from __future__ import annotations

import pytest

from macroloc.graph.surfaces import SurfaceIndex, SurfaceParams, WallVoxels
from tests.graph.rooms import room_mesh


@pytest.fixture(scope="session")
def room() -> SurfaceIndex:
    return SurfaceIndex.from_mesh(*room_mesh(), SurfaceParams(spacing_m=0.05))


@pytest.fixture(scope="session")
def room_with_walls() -> SurfaceIndex:
    index = SurfaceIndex.from_mesh(*room_mesh(), SurfaceParams(spacing_m=0.05))
    index.walls = WallVoxels.from_mesh(*room_mesh())
    return index
