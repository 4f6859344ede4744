"""A building's walls as one mesh and their cut at a height: what the floor plans, the Foxglove channels and the
live view draw (CAD frame, metres)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def load_wall_mesh(path: str | Path):
    """The building's walls as one trimesh.Trimesh (CAD frame, metres), or None when there are none.

    IFC: every IfcWall (IfcWallStandardCase included) through ifcopenshell geometry in world coordinates
    (already metres); a mesh or Gazebo world: graph.bim_mesh.read_wall_mesh.
    """
    path = Path(path)
    from macroloc.graph.bim import is_ifc

    if not is_ifc(path):
        from macroloc.graph.bim_mesh import read_wall_mesh

        return read_wall_mesh(path)
    import ifcopenshell.geom
    import trimesh

    from macroloc.graph.bim_ifc import geometry_settings, open_ifc

    ifc = open_ifc(path)
    walls = list(ifc.by_type("IfcWall"))
    if not walls:
        return None
    iterator = ifcopenshell.geom.iterator(geometry_settings(), ifc, 1, include=walls)
    parts = []
    if iterator.initialize():
        while True:
            geom = iterator.get().geometry
            verts = np.asarray(geom.verts, dtype=float).reshape(-1, 3)
            faces = np.asarray(geom.faces, dtype=np.int64).reshape(-1, 3)
            if len(verts) and len(faces):
                parts.append(trimesh.Trimesh(vertices=verts, faces=faces, process=False))
            if not iterator.next():
                break
    return trimesh.util.concatenate(parts) if parts else None


def wall_segments_xy(wall_mesh, z_cut_m: float) -> np.ndarray:
    """(S, 2, 2) segments [[x0, y0], [x1, y1]] (CAD frame, metres) where the plane z = z_cut_m cuts the walls."""
    import trimesh

    if wall_mesh is None or len(wall_mesh.faces) == 0:
        return np.zeros((0, 2, 2))
    lines = trimesh.intersections.mesh_plane(wall_mesh, plane_normal=[0.0, 0.0, 1.0],
                                             plane_origin=[0.0, 0.0, float(z_cut_m)])
    return np.asarray(lines, dtype=float).reshape(-1, 2, 3)[:, :, :2]
