"""A door or window as a Pose3 landmark: the frame of its opening rectangle.

The rectangle frame `rect` has its origin at the opening's centroid and the axes (as columns of its
rotation) u (along the wall, horizontal), n (the wall normal, horizontal) and z (up, along gravity),
u = n x z, so that (u, n, z) is right-handed (u x n = z; a reflection would be no rotation at all).
A vertical rectangle fixes this frame up to the sign of n: a door seen from its other side is the same
frame turned by 180 degrees about z (`FLIP_ABOUT_UP`). Observed landmarks take n pointing towards
the camera that first saw them; CAD features take the model's outward normal, and a link between the two
picks whichever of the two CAD frames agrees with the prediction.

Frames: `T_x_rect` maps points from the rectangle frame into frame x (body, map or cad), metres.
"""

from __future__ import annotations

import numpy as np

from macroloc.graph.features import MacroFeature

Z_UP = np.array([0.0, 0.0, 1.0])
FLIP_ABOUT_UP = np.diag([-1.0, -1.0, 1.0, 1.0])  # rotation by pi about the rectangle's z axis


def frame_from_normal(centroid: np.ndarray, normal: np.ndarray, up: np.ndarray = Z_UP) -> np.ndarray:
    """4x4 T_x_rect of a vertical rectangle at `centroid` (3,) with wall normal `normal` (3,) in frame x.

    The normal is made orthogonal to `up` (unit, frame x) before use; u = n x up (right-handed).
    """
    up = np.asarray(up, float) / np.linalg.norm(up)
    n = np.asarray(normal, float) - float(np.dot(normal, up)) * up
    n /= max(float(np.linalg.norm(n)), 1e-12)
    u = np.cross(n, up)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([u, n, up])
    T[:3, 3] = centroid
    return T


def plane_normal(corners: np.ndarray) -> np.ndarray:
    """Unit normal (3,) of the least-squares plane through the corners (4, 3); sign arbitrary."""
    c = np.asarray(corners, float)
    _, _, vt = np.linalg.svd(c - c.mean(axis=0))
    return vt[2]


def observed_frame(corners_x: np.ndarray, up_x: np.ndarray, viewer_x: np.ndarray) -> np.ndarray:
    """T_x_rect of an observed vertical rectangle: corners (4, 3) in frame x (any order), `up_x` the unit up
    direction in x (from gravity), `viewer_x` the camera centre in x; n points towards the viewer."""
    centroid = np.asarray(corners_x, float).mean(axis=0)
    n = plane_normal(corners_x)
    if float(np.dot(n, np.asarray(viewer_x, float) - centroid)) < 0:
        n = -n
    return frame_from_normal(centroid, n, up_x)


def feature_frame_cad(feature: MacroFeature) -> np.ndarray:
    """T_cad_rect of a model feature (vertical doors and windows), n = the model's normal."""
    return frame_from_normal(feature.centroid_cad, feature.normal_cad)


def closer_flip(T_a_rect: np.ndarray, T_a_pred: np.ndarray) -> np.ndarray:
    """T_a_rect or its flip about up, whichever has its normal closer to the predicted frame's normal."""
    if float(np.dot(T_a_rect[:3, 1], T_a_pred[:3, 1])) < 0:
        return T_a_rect @ FLIP_ABOUT_UP
    return T_a_rect


def is_vertical(corners: np.ndarray, up: np.ndarray = Z_UP, max_tilt_deg: float = 30.0) -> bool:
    """True when the rectangle's plane contains the up direction within `max_tilt_deg` (a wall opening)."""
    return abs(float(np.dot(plane_normal(corners), up))) < np.sin(np.radians(max_tilt_deg))
