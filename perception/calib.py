"""Rectified stereo calibration from ROS camera_info YAML files (`camera_calibration`'s format).

Both spellings seen in the wild are read: the plain ROS YAML, and OpenCV's `%YAML:1.0` variant (as in
`../shared/data/stereo/rtabmap_stereo_rect/`). Matrices are row-major `{rows, cols, data}` maps.
For a rectified pair the projection matrices hold everything: P_left = [f 0 cx 0; 0 f cy 0; 0 0 1 0],
P_right[0, 3] = -f * baseline_m (ROS convention), pixels with x right and y down (optical frame).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from macroloc.common.errors import UserInputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraInfo:
    """One camera's ROS camera_info: image size (px), K (3x3), D, R (3x3), P (3x4)."""

    width_px: int
    height_px: int
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray


@dataclass(frozen=True)
class StereoRig:
    """A rectified pair: intrinsics of the rectified left camera (px) and the baseline (m)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    baseline_m: float
    width_px: int
    height_px: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx_px, 0, self.cx_px], [0, self.fy_px, self.cy_px], [0, 0, 1]], np.float64)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) (u right, v down) of points (N, 3) in the left camera's frame (z forward, in front)."""
        p = np.asarray(points_cam, np.float64).reshape(-1, 3)
        z = np.maximum(p[:, 2], 1e-9)
        return np.stack([self.fx_px * p[:, 0] / z + self.cx_px, self.fy_px * p[:, 1] / z + self.cy_px], axis=1)


def _matrix(fs: cv2.FileStorage, key: str, rows: int, cols: int, source: str) -> np.ndarray:
    node = fs.getNode(key)
    data = node.getNode("data") if node.isMap() else node
    if data.empty() or not data.isSeq() or data.size() != rows * cols:
        raise UserInputError(f"{source}: '{key}' must hold {rows}x{cols} numbers")
    values = np.array([data.at(i).real() for i in range(data.size())], np.float64)
    if not np.all(np.isfinite(values)):
        raise UserInputError(f"{source}: '{key}' holds a non-finite number")
    return values.reshape(rows, cols)


def read_camera_info(path: Path) -> CameraInfo:
    """Read a ROS camera_info YAML file; raises `UserInputError` when it is missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise UserInputError(f"calibration file not found: {path}")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise UserInputError(f"calibration file {path} is not a text file") from None
    body = "\n".join(line for line in text.splitlines() if not line.startswith("%YAML") and line.strip() != "---")
    try:
        fs = cv2.FileStorage("%YAML:1.0\n---\n" + body + "\n", cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # OpenCV's YAML parser reports syntax errors as either
        raise UserInputError(f"calibration file {path} is not camera_info YAML") from None
    try:
        width, height = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
        if width <= 0 or height <= 0:
            raise UserInputError(f"{path}: image_width and image_height must be positive")
        D_node = fs.getNode("distortion_coefficients")
        n_d = D_node.getNode("data").size() if D_node.isMap() else 0
        info = CameraInfo(
            width, height,
            _matrix(fs, "camera_matrix", 3, 3, str(path)),
            _matrix(fs, "distortion_coefficients", 1, n_d, str(path)).ravel() if n_d else np.zeros(0),
            _matrix(fs, "rectification_matrix", 3, 3, str(path)),
            _matrix(fs, "projection_matrix", 3, 4, str(path)),
        )
    finally:
        fs.release()
    return info


def stereo_rig(left: CameraInfo, right: CameraInfo) -> StereoRig:
    """The rectified rig from the two camera_infos (P matrices); checks they describe one rectified pair."""
    P_l, P_r = left.P, right.P
    if (left.width_px, left.height_px) != (right.width_px, right.height_px):
        raise UserInputError("left and right calibrations have different image sizes")
    if P_l[0, 0] <= 0 or P_l[1, 1] <= 0:
        raise UserInputError("left projection matrix has a non-positive focal length")
    if not np.allclose(P_l[:, :3], P_r[:, :3], rtol=1e-3, atol=1e-3):
        raise UserInputError("left and right projection matrices differ: the pair is not rectified together")
    baseline_m = -P_r[0, 3] / P_r[0, 0]  # ROS: P_right[0,3] = -fx * baseline
    if not baseline_m > 0:
        raise UserInputError(f"right projection matrix gives a baseline of {baseline_m:.4f} m (must be > 0)")
    return StereoRig(float(P_l[0, 0]), float(P_l[1, 1]), float(P_l[0, 2]), float(P_l[1, 2]), float(baseline_m),
                     left.width_px, left.height_px)


def read_stereo_rig(left_yaml: Path, right_yaml: Path) -> StereoRig:
    return stereo_rig(read_camera_info(left_yaml), read_camera_info(right_yaml))
