"""Rectangle frames of doors and windows: proper rotations, the flip, observed == model frames."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.landmarks import FLIP_ABOUT_UP, closer_flip, frame_from_normal, is_vertical, observed_frame
from tests.graph.scenes import door, make_T, rot_z

angles = st.floats(-np.pi, np.pi, allow_nan=False)
coords = st.floats(-50, 50, allow_nan=False)


@given(yaw=angles, x=coords, y=coords, tilt=st.floats(-0.3, 0.3))
def test_frame_is_a_proper_rotation_with_n_and_up(yaw: float, x: float, y: float, tilt: float) -> None:
    n = np.array([np.cos(yaw), np.sin(yaw), tilt])
    T = frame_from_normal(np.array([x, y, 1.0]), n)
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(R), 1.0)  # a reflection here broke the whole graph once
    assert np.allclose(R[:, 2], [0, 0, 1])
    assert np.allclose(R[:, 1], [np.cos(yaw), np.sin(yaw), 0.0], atol=1e-9)


@given(yaw=angles, x=coords, y=coords, view_side=st.sampled_from([-1.0, 1.0]), body_yaw=angles)
@settings(max_examples=50)
def test_observed_frame_equals_the_model_frame_up_to_the_flip(yaw: float, x: float, y: float, view_side: float,
                                                               body_yaw: float) -> None:
    f = door("D", (x, y), (np.cos(yaw), np.sin(yaw)))
    viewer = f.centroid_cad + 3.0 * view_side * f.normal_cad
    T_cad_body = make_T(rot_z(body_yaw), viewer)
    T_body_cad = np.linalg.inv(T_cad_body)
    corners_body = (T_body_cad[:3, :3] @ f.corners_cad.T).T + T_body_cad[:3, 3]
    T_body_rect = observed_frame(corners_body[[2, 0, 3, 1]], np.array([0, 0, 1.0]), np.zeros(3))
    T_cad_rect = T_cad_body @ T_body_rect
    T_model = frame_from_normal(f.centroid_cad, f.normal_cad)
    assert np.allclose(closer_flip(T_model, T_cad_rect), T_cad_rect, atol=1e-6)
    assert float(np.dot(T_cad_rect[:3, 1], viewer - f.centroid_cad)) > 0  # n faces the viewer


def test_flip_is_a_half_turn_about_up() -> None:
    assert np.allclose(FLIP_ABOUT_UP @ FLIP_ABOUT_UP, np.eye(4))
    assert np.isclose(np.linalg.det(FLIP_ABOUT_UP[:3, :3]), 1.0)


def test_vertical_and_horizontal_rectangles() -> None:
    f = door("D", (0.0, 0.0), (1.0, 0.0))
    assert is_vertical(f.corners_cad)
    skylight = np.array([[0, 0, 3.0], [1, 0, 3.0], [1, 1, 3.0], [0, 1, 3.0]])
    assert not is_vertical(skylight)
