"""Per-frame ground truth of the doors and windows in view, from the rendered depth and instance buffers.

For each macro-feature whose instance covers at least `min_pixels` of the left image:
  corners_cam: (4, 3) its opening rectangle's corners in the LEFT camera optical frame (x right, y down,
    z forward), metres, in the feature's own corner order;
  corners_px: (4, 2) their projections (pixels; meaningless for a corner behind the camera);
  corner_visible: (4,) a corner is visible when it lies in front of the camera, inside the image, and some
    rendered depth within 3 px of its pixel is not nearer than the corner by more than `occlusion_tol_m`
    (the frame around an opening stands a little proud of its rectangle);
  box_xyxy: the 2D box of the feature's 3D extent (opening rectangle thickened by the element's depth along
    its normal) clipped to the near plane and the image; pixels, OpenCV convention (pixel centres at integers),
    covering whole pixels (the image spans [-0.5, W - 0.5]): it encloses the feature's rendered mask;
  visible_fraction: mask pixels / pixels of the projected opening rectangle (occlusion and image edges).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from macroloc.graph.features import MacroFeature
from macroloc.sim.materials import feature_instance_map
from macroloc.sim.render import CameraModel
from macroloc.sim.scene import SceneGeometry


@dataclass
class FeatureInView:
    index: int  # in the scene's feature list; instance id = index + 1
    id: str
    type: str
    corners_cam: np.ndarray
    corners_px: np.ndarray
    corner_visible: np.ndarray
    box_xyxy: np.ndarray
    mask_pixels: int
    visible_fraction: float


def feature_half_depths(scene: SceneGeometry, features: list[MacroFeature]) -> np.ndarray:
    """(F,) half thickness of each feature's geometry along its normal, metres (0.05 when it has none)."""
    inst = feature_instance_map(features)
    out = np.full(len(features), 0.05)
    for e, gid in enumerate(scene.element_ids):
        k = inst.get(gid, 0)
        if not k:
            continue
        f = features[k - 1]
        pts = scene.triangles_cad[scene.tri_element == e].reshape(-1, 3).astype(np.float64)
        if len(pts):
            out[k - 1] = max(out[k - 1], float(np.abs((pts - f.centroid_cad) @ f.normal_cad).max()))
    return out


def _edge_points(corners: np.ndarray, normal: np.ndarray, half_depth: float, samples: int = 16) -> np.ndarray:
    """Points along the 12 edges of the feature's box (rectangle +- normal * half_depth), (12 * samples, 3)."""
    box = np.concatenate([corners + normal * half_depth, corners - normal * half_depth])
    edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
    a = np.linspace(0.0, 1.0, samples)[:, None]
    return np.concatenate([box[i] * (1 - a) + box[j] * a for i, j in edges])


def features_in_view(features: list[MacroFeature], half_depths: np.ndarray, T_cad_cam: np.ndarray,
                     camera: CameraModel, depth_m: np.ndarray, instance: np.ndarray, min_pixels: int = 30,
                     occlusion_tol_m: float = 0.25) -> list[FeatureInView]:
    """Ground truth of the features visible in one left image (see the module docstring)."""
    counts = np.bincount(instance.reshape(-1), minlength=len(features) + 1)
    T_cam_cad = np.linalg.inv(T_cad_cam)
    R, t = T_cam_cad[:3, :3], T_cam_cad[:3, 3]
    K = camera.K
    w, h = camera.width, camera.height
    out = []
    for k in np.flatnonzero(counts[1:] >= min_pixels):
        f = features[k]
        cam = f.corners_cad @ R.T + t
        z = cam[:, 2]
        px = (cam @ K.T)[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
        visible = (z > camera.near_m) & (px[:, 0] >= -0.5) & (px[:, 0] <= w - 0.5) & (px[:, 1] >= -0.5) \
            & (px[:, 1] <= h - 0.5)
        for c in np.flatnonzero(visible):
            u, v = int(round(px[c, 0])), int(round(px[c, 1]))
            win = depth_m[max(0, v - 3):v + 4, max(0, u - 3):u + 4]
            d = win[win > 0]
            if d.size and float(d.max()) < z[c] - occlusion_tol_m:  # everything around it is nearer: occluded
                visible[c] = False
        edge_all = _edge_points(f.corners_cad, f.normal_cad, float(half_depths[k])) @ R.T + t
        edge = edge_all[edge_all[:, 2] > camera.near_m]
        if len(edge) == 0:
            continue
        epx = (edge @ K.T)[:, :2] / edge[:, 2:3]
        # where the box crosses the near plane its projection is unbounded: take the mask's extent there too
        crosses = bool((edge_all[:, 2] <= camera.near_m).any())
        x0, y0 = epx.min(axis=0) - 0.5
        x1, y1 = epx.max(axis=0) + 0.5
        if crosses:
            ys, xs = np.nonzero(instance == k + 1)
            x0, y0 = min(x0, xs.min() - 0.5), min(y0, ys.min() - 0.5)
            x1, y1 = max(x1, xs.max() + 0.5), max(y1, ys.max() + 0.5)
        box = np.array([max(x0, -0.5), max(y0, -0.5), min(x1, w - 0.5), min(y1, h - 0.5)])
        area = _projected_area(px, z, camera)
        frac = float(min(1.0, counts[k + 1] / area)) if area > 0 else 1.0
        out.append(FeatureInView(int(k), f.id, f.type, cam, px, visible, box, int(counts[k + 1]), frac))
    return out


def _projected_area(px: np.ndarray, z: np.ndarray, camera: CameraModel) -> float:
    """Pixels of the projected opening rectangle inside the image (0 if a corner is behind the camera)."""
    if (z <= camera.near_m).any():
        return 0.0
    poly = px.astype(np.float32).reshape(-1, 1, 2)
    box = np.array([[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]], np.float32)
    inter, _ = cv2.intersectConvexConvex(poly, box.reshape(-1, 1, 2))
    return float(inter)
