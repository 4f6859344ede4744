"""The 2D occupancy grid of paper §3.3: the building model's cross-section at flight height, plus what was seen.

Grid convention: cell (row, col) covers x in [x0 + col·cell, x0 + (col+1)·cell), y in [y0 + row·cell, ...)
of the CAD frame (metres, z up); its centre is `cell_centre_cad`. Everything here is in the CAD frame.

The static layer comes from the building's solids (walls, slabs, stairs, railings, furniture, …) cut by the
horizontal plane z = storey elevation + flight height. Doors, windows, openings and spaces are left out, and
ifcopenshell subtracts the openings from the walls, so doorways are gaps in the section: a drone passes.
Outside the building is not planned through (`outside_cells`): an exterior door is a way in, not a short cut
along the façade, where the model knows no floor and the vehicle would be localized by the ground's depth
(docs/measurements.md, "The planner keeps the vehicle inside the building").
The dynamic layer counts depth points (CAD frame) inside a height band around the flight height: a 2D
projection of a voxel grid, which is all a 2D planner consumes: 0.9 ms per frame of 18,500 depth points
against 11 ms for an OctoMap with ray casting (pyoctomap, 13x; `python -m bench.bench_obstacles`). It does not
clear cells seen free again, as OctoMap would: an obstacle that leaves stays until the layer is reset.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from macroloc.graph.building_assets import BuildingSolids

log = logging.getLogger(__name__)


@dataclass
class OccupancyGrid:
    """A horizontal occupancy grid at height z_cad. occupied: (H, W) bool, True = an obstacle in that cell."""

    occupied: np.ndarray
    origin_xy_cad: np.ndarray  # (2,) x, y of the corner of cell (0, 0), metres
    cell_m: float
    z_cad: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupied.shape  # type: ignore[return-value]

    def cell_of(self, xy_cad: np.ndarray) -> tuple[int, int]:
        """The (row, col) holding the CAD point (x, y), clipped into the grid."""
        col, row = np.floor((np.asarray(xy_cad, float)[:2] - self.origin_xy_cad) / self.cell_m).astype(int)
        h, w = self.shape
        return int(np.clip(row, 0, h - 1)), int(np.clip(col, 0, w - 1))

    def contains(self, xy_cad: np.ndarray) -> bool:
        """True when the CAD point (x, y) is finite and on the grid (not clipped into it)."""
        xy = np.asarray(xy_cad, float)[:2]
        if not np.isfinite(xy).all():
            return False
        h, w = self.shape
        extent_xy = np.array([w, h], float) * self.cell_m
        return bool(((xy >= self.origin_xy_cad) & (xy < self.origin_xy_cad + extent_xy)).all())

    def centre_cad(self, cells_rc: np.ndarray) -> np.ndarray:
        """(N, 2) rows/cols -> (N, 3) CAD points at cell centres, z = z_cad."""
        rc = np.asarray(cells_rc, float).reshape(-1, 2)
        xy = self.origin_xy_cad + (rc[:, ::-1] + 0.5) * self.cell_m
        return np.column_stack([xy, np.full(len(xy), self.z_cad)])


def section_grid(solids: BuildingSolids, z_cad: float, cell_m: float, margin_m: float = 1.0) -> OccupancyGrid:
    """The cross-section of the solids by the plane z = z_cad, rasterised into cells of cell_m metres."""
    import trimesh.intersections

    v = solids.vertices_cad
    lo = v[:, :2].min(axis=0) - margin_m
    hi = v[:, :2].max(axis=0) + margin_m
    w, h = (np.ceil((hi - lo) / cell_m).astype(int) + 1).tolist()
    occupied = np.zeros((h, w), np.uint8)
    tri_z = v[solids.faces][:, :, 2]
    crossing = solids.faces[(tri_z.min(axis=1) <= z_cad) & (tri_z.max(axis=1) >= z_cad)]
    if len(crossing):
        segments = trimesh.intersections.mesh_plane(
            trimesh.Trimesh(v, crossing, process=False), plane_normal=[0, 0, 1], plane_origin=[0, 0, z_cad])
        draw_lines(occupied, segments[:, :, :2], lo, cell_m, thickness=1)
    return OccupancyGrid(occupied.astype(bool), lo, cell_m, z_cad)


def draw_lines(image: np.ndarray, segments_xy: np.ndarray, origin_xy: np.ndarray, cell_m: float,
               thickness: int) -> None:
    """Set the cells of `image` (H, W) that the CAD segments (N, 2, 2: ends, x y) cross, on the grid with its
    corner at `origin_xy` and cells of `cell_m` metres (x -> col, y -> row; sub-cell precision)."""
    import cv2

    pts = np.round((np.asarray(segments_xy, float) - origin_xy) / cell_m * 16 - 8).astype(np.int32)  # 4 fraction bits
    for a, b in pts:
        cv2.line(image, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, thickness, cv2.LINE_8, 4)


def outside_cells(grid: OccupancyGrid, openings_cad: list[np.ndarray]) -> np.ndarray:
    """(H, W) bool: the grid's cells outside the building, those reachable from the grid's border (4-connected)
    without crossing the section's walls or a door's or window's opening. `openings_cad`: each opening's corners
    (K, 3), CAD frame; those whose height spans the grid's are closed by a line across them (two cells thick: the
    section's wall faces and the opening's plane need not meet on one cell)."""
    from scipy import ndimage

    closed = grid.occupied.astype(np.uint8)
    for corners in openings_cad:
        c = np.asarray(corners, float).reshape(-1, 3)
        if not c[:, 2].min() <= grid.z_cad <= c[:, 2].max():
            continue
        xy = c[:, :2]
        far = np.linalg.norm(xy[:, None] - xy[None], axis=2)
        a, b = np.unravel_index(int(np.argmax(far)), far.shape)  # the opening's two ends along its wall
        draw_lines(closed, xy[[a, b]][None], grid.origin_xy_cad, grid.cell_m, thickness=2)
    labels, _ = ndimage.label(closed == 0)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    return np.isin(labels, border[border > 0])


class ObstacleLayer:
    """Obstacles seen in depth that the model lacks: hits per cell of points within a band around z_cad."""

    def __init__(self, shape: tuple[int, int], min_hits: int = 3, band_m: float = 0.5) -> None:
        self.hits = np.zeros(shape, np.int32)
        self.min_hits = min_hits
        self.band_m = band_m

    def add_points(self, grid: OccupancyGrid, points_cad: np.ndarray) -> int:
        """Count (N, 3) CAD points within ±band_m of the grid's height; returns how many were counted."""
        p = np.asarray(points_cad, float).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1) & (np.abs(p[:, 2] - grid.z_cad) <= self.band_m)]
        rc = np.floor((p[:, :2] - grid.origin_xy_cad) / grid.cell_m).astype(int)[:, ::-1]
        inside = (rc >= 0).all(axis=1) & (rc[:, 0] < self.hits.shape[0]) & (rc[:, 1] < self.hits.shape[1])
        np.add.at(self.hits, (rc[inside, 0], rc[inside, 1]), 1)
        return int(inside.sum())

    def occupied(self) -> np.ndarray:
        return self.hits >= self.min_hits


def inflate(occupied: np.ndarray, radius_m: float, cell_m: float) -> np.ndarray:
    """Free cells (True) whose centre is farther than radius_m from every occupied cell's centre."""
    from scipy.ndimage import distance_transform_edt

    if not occupied.any():
        return np.ones_like(occupied, bool)
    return distance_transform_edt(~occupied) * cell_m > radius_m
