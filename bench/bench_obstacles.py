"""Issue 6's OctoMap-or-voxel-grid question: obstacles seen in depth, on rendered depth of an Office_A flight.

    python -m bench.bench_obstacles [--frames 60] [--stride 4]

The planner consumes a 2D grid at flight height. macroloc's `ObstacleLayer` counts depth points per cell in a
height band (a 2D projection of a voxel grid, no ray casting); OctoMap (pyoctomap, the bench extra) inserts
each point with a ray from the camera (free space cleared along it, probabilistic occupancy), then the
occupied leaves in the band are projected to the same grid. Both get the same points, in the same run.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from bench.common import row

ROOT = Path(__file__).resolve().parents[1]


def depth_points(building: Path, n_frames: int, stride: int) -> tuple[list[np.ndarray], list[np.ndarray], float]:
    """CAD-frame points of every stride-th pixel of the rendered depth along a flight, with camera origins."""
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.simulator import SimulationParams, Simulator

    sim = Simulator(building, SimulationParams(seed=1, flight=FlightParams(duration_s=30.0)))
    cam = sim.params.camera
    v, u = np.mgrid[0:cam.height:stride, 0:cam.width:stride]
    clouds, origins = [], []
    for t in np.linspace(0.0, sim.trajectory.duration_s, n_frames):
        T_cad_cam = sim.trajectory.T_cad_body(float(t)) @ sim.T_body_cam
        out = sim.renderer.render(T_cad_cam, sim.lighting, 0.0)
        assert out.depth_m is not None
        z = out.depth_m[v, u]
        ok = (z > 0.1) & (z < 8.0)
        p_cam = np.column_stack([(u[ok] - cam.cx) * z[ok] / cam.fx, (v[ok] - cam.cy) * z[ok] / cam.fy, z[ok]])
        clouds.append(p_cam @ T_cad_cam[:3, :3].T + T_cad_cam[:3, 3])
        origins.append(T_cad_cam[:3, 3].copy())
    z_fly = float(np.mean([o[2] for o in origins]))
    sim.close()
    return clouds, origins, z_fly


def bench(building: Path, n_frames: int, stride: int) -> list[str]:
    from macroloc.graph.planning_grid import ObstacleLayer, OccupancyGrid

    clouds, origins, z_fly = depth_points(building, n_frames, stride)
    cell_m = 0.2
    allp = np.concatenate(clouds)
    lo = allp[:, :2].min(axis=0) - 1.0
    shape = tuple((np.ceil((allp[:, :2].max(axis=0) + 1.0 - lo) / cell_m)).astype(int)[::-1])
    grid = OccupancyGrid(np.zeros(shape, bool), lo, cell_m, z_fly)
    layer = ObstacleLayer(shape)
    t0 = time.perf_counter()
    for p in clouds:
        layer.add_points(grid, p)
    voxel_ms = (time.perf_counter() - t0) * 1000.0 / len(clouds)
    t0 = time.perf_counter()
    occupied_voxel = layer.occupied()
    voxel_query_ms = (time.perf_counter() - t0) * 1000.0
    rows = [row(f"depth points per frame (every {stride}th pixel, < 8 m)", f"{np.mean([len(c) for c in clouds]):.0f}",
                ""),
            row("voxel-grid projection (ObstacleLayer): insert", f"{voxel_ms:.2f} ms/frame", "fits 30 Hz (< 33 ms)",
                voxel_ms < 33.0),
            row("  2D occupied cells (query)", f"{voxel_query_ms:.3f} ms, {int(occupied_voxel.sum())} cells", "")]
    try:
        import pyoctomap
    except ImportError:
        return [*rows, row("OctoMap (pyoctomap)", "not installed", "pip install -e '.[bench]'")]
    tree = pyoctomap.OcTree(cell_m)
    t0 = time.perf_counter()
    for p, o in zip(clouds, origins, strict=True):
        tree.insertPointCloud(np.ascontiguousarray(p, np.float64), np.asarray(o, np.float64), max_range=8.0)
    octo_ms = (time.perf_counter() - t0) * 1000.0 / len(clouds)
    t0 = time.perf_counter()
    occupied_octo = np.zeros(shape, bool)
    for leaf in tree.begin_leafs():
        if tree.isNodeOccupied(leaf):
            x, y, z = leaf.getCoordinate()
            if abs(z - z_fly) <= layer.band_m:
                r, c = int((y - lo[1]) // cell_m), int((x - lo[0]) // cell_m)
                if 0 <= r < shape[0] and 0 <= c < shape[1]:
                    occupied_octo[r, c] = True
    octo_query_ms = (time.perf_counter() - t0) * 1000.0
    agree = float((occupied_octo & occupied_voxel).sum()) / max(1, int((occupied_octo | occupied_voxel).sum()))
    return [*rows,
            row("OctoMap (pyoctomap, ray casting): insert", f"{octo_ms:.1f} ms/frame ({octo_ms / voxel_ms:.0f}x)",
                "fits 30 Hz (< 33 ms)", octo_ms < 33.0),
            row("  2D occupied cells (leaf iteration)", f"{octo_query_ms:.0f} ms, {int(occupied_octo.sum())} cells",
                ""),
            row("  cells both call occupied (IoU)", f"{agree:.2f}", "")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--building", type=Path, default=ROOT / "data" / "buildings" / "office_a.ifc")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--stride", type=int, default=4, help="use every N-th pixel of the depth image")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    print(f"# bench_obstacles on {os.cpu_count()} cores, load average {load:.1f}")
    for line in bench(args.building, args.frames, args.stride):
        print(line)


if __name__ == "__main__":
    main()
