"""A saved map's keyframe views (the saved map itself: service.saved_map): what place recognition places a new
run's keyframes in, before it sees any door.

A `KeyframeView` is a keyframe's image features with their 3D points (perception.place); a saved map keeps one
every VIEW_SPACING_M or VIEW_SPACING_DEG of a flight, each with its keyframe's pose T_map_body in the saved map's
frame, and an earlier map's views where the flight made none near (`carried_views`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from macroloc.common.views import KeyframeView

__all__ = ["VIEW_SPACING_DEG", "VIEW_SPACING_M", "KeyframeView", "PlacedView", "carried_views"]

VIEW_SPACING_M, VIEW_SPACING_DEG = 0.5, 15.0  # one view of a place will do within this of another


PlacedView = tuple[np.ndarray, KeyframeView]  # (T_map_body, view)


def carried_views(own: list[PlacedView], T_cad_map: np.ndarray, T_cad_earlier: np.ndarray | None,
                  earlier: list[PlacedView], apart_m: float = VIEW_SPACING_M,
                  apart_deg: float = VIEW_SPACING_DEG) -> list[PlacedView]:
    """An earlier map's views (`earlier`: T_map_body in its frame, whose T_cad_map is `T_cad_earlier`) moved into
    the frame of a map with `T_cad_map`, less those within `apart_m` and `apart_deg` of one of its `own`
    (T_map_body, view): the places it has no view of, for a later flight to be placed by, without piling up views
    of the same places flight after flight. None where the earlier map was not localized (`T_cad_earlier` None)."""
    if T_cad_earlier is None:
        return []
    T_map_earlier = np.linalg.inv(T_cad_map) @ T_cad_earlier
    moved = [(T_map_earlier @ T, v) for T, v in earlier]
    if not moved or not own:
        return moved
    A, B = np.array([T for T, _ in moved]), np.array([T for T, _ in own])
    near = cKDTree(B[:, :3, 3]).query_ball_point(A[:, :3, 3], r=apart_m)  # own views within apart_m of each
    cos_apart = np.cos(np.radians(apart_deg))
    # trace(Ra^T Rb) = 1 + 2 cos(angle between them)
    covered = [bool(nb) and bool(((np.einsum("ij,bij->b", A[a, :3, :3], B[nb, :3, :3]) - 1.0) / 2.0 > cos_apart).any())
               for a, nb in enumerate(near)]
    return [m for m, c in zip(moved, covered, strict=True) if not c]
