"""Property tests for the rigid-transform kernels (paper eqs. 11–17)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.rigid import (
    apply,
    invert,
    levelled,
    levelled_about,
    rot_z,
    rotation_aligning,
    weighted_rigid_fit,
    yaw_rigid_fit,
)
from tests.graph.helpers import random_T

seeds = st.integers(0, 2**32 - 1)


@given(seeds)
@settings(max_examples=60, deadline=None)
def test_weighted_fit_recovers_a_random_rigid_motion(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_T(rng)
    src = rng.uniform(-10, 10, (int(rng.integers(3, 30)), 3))
    w = rng.uniform(0.1, 2.0, len(src))
    T_est = weighted_rigid_fit(src, apply(T, src), w)
    assert np.allclose(T_est, T, atol=1e-8)


@given(seeds)
@settings(max_examples=30, deadline=None)
def test_weighted_fit_never_returns_a_reflection(seed: int) -> None:
    rng = np.random.default_rng(seed)
    src = rng.uniform(-5, 5, (6, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])  # best orthogonal map is a reflection
    T = weighted_rigid_fit(src, mirrored)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_weights_pull_the_fit_towards_heavy_points() -> None:
    rng = np.random.default_rng(3)
    src = rng.uniform(-5, 5, (10, 3))
    dst = src.copy()
    dst[0] += [3.0, 0, 0]  # one outlier
    light = weighted_rigid_fit(src, dst, np.r_[1e-6, np.ones(9)])
    assert np.allclose(apply(light, src[1:]), dst[1:], atol=1e-4)


@given(seeds)
@settings(max_examples=40, deadline=None)
def test_yaw_fit_recovers_yaw_and_translation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_T(rng, yaw_only=True)
    src = rng.uniform(-10, 10, (8, 3))
    assert np.allclose(yaw_rigid_fit(src, apply(T, src)), T, atol=1e-8)


@given(seeds)
@settings(max_examples=40, deadline=None)
def test_inverse_and_composition(seed: int) -> None:
    rng = np.random.default_rng(seed)
    A, B = random_T(rng), random_T(rng)
    p = rng.normal(size=(5, 3))
    assert np.allclose(apply(A @ B, p), apply(A, apply(B, p)))
    assert np.allclose(apply(invert(A), apply(A, p)), p)


@given(st.lists(st.floats(-1, 1), min_size=6, max_size=6))
def test_rotation_aligning_maps_a_onto_b(v: list[float]) -> None:
    a, b = np.array(v[:3]), np.array(v[3:])
    if np.linalg.norm(a) < 1e-3 or np.linalg.norm(b) < 1e-3:
        return
    R = rotation_aligning(a, b)
    assert np.allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-9)
    assert np.isclose(np.linalg.det(R), 1.0) and np.allclose(R @ R.T, np.eye(3), atol=1e-12)


@given(st.floats(-np.pi, np.pi), st.floats(0.0, np.radians(30.0)), st.floats(-np.pi, np.pi))
@settings(max_examples=60, deadline=None)
def test_levelled_removes_the_tilt_and_keeps_heading_and_position(yaw: float, tilt: float, tilt_dir: float) -> None:
    """A yaw-only transform tilted by up to 30 deg (about any horizontal axis): levelled() gives back the
    yaw-only one, its translation untouched."""
    axis = np.array([np.cos(tilt_dir), np.sin(tilt_dir), 0.0])
    tilted_z = np.cos(tilt) * np.array([0.0, 0.0, 1.0]) + np.sin(tilt) * np.cross(axis, [0.0, 0.0, 1.0])
    T = np.eye(4)
    T[:3, :3] = rotation_aligning(np.array([0.0, 0.0, 1.0]), tilted_z) @ rot_z(yaw)
    T[:3, 3] = [1.0, -2.0, 3.0]
    L = levelled(T)
    assert np.allclose(L[:3, 2], [0.0, 0.0, 1.0], atol=1e-12)
    assert np.isclose(np.linalg.det(L[:3, :3]), 1.0) and np.allclose(L[3], [0, 0, 0, 1])
    assert np.allclose(L[:3, 3], T[:3, 3])
    assert np.allclose(L[:3, :3], rot_z(yaw), atol=1e-9)


@given(st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3), st.floats(-np.pi, np.pi))
@settings(max_examples=40, deadline=None)
def test_levelled_to_a_measured_up_puts_that_up_on_z(tilt: list[float], yaw: float) -> None:
    """With a measured up in the child frame (gravity), the child is turned until that up is the parent's z."""
    up_child = np.array([tilt[0], tilt[1], 1.0 + tilt[2]])
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw) @ rotation_aligning(np.array([0.0, 0.0, 1.0]), np.array([0.1, -0.2, 1.0]))
    L = levelled(T, up_child)
    assert np.allclose(L[:3, :3] @ (up_child / np.linalg.norm(up_child)), [0.0, 0.0, 1.0], atol=1e-9)
    assert np.allclose(L[:3, 3], T[:3, 3]) and np.isclose(np.linalg.det(L[:3, :3]), 1.0)


@settings(max_examples=25, deadline=None)
@given(tilt=st.floats(0.0, 0.5), tilt_dir=st.floats(-np.pi, np.pi), yaw=st.floats(-np.pi, np.pi),
       point=st.lists(st.floats(-50, 50), min_size=3, max_size=3))
def test_levelled_about_a_point_keeps_that_point_and_levels_as_levelled(tilt: float, tilt_dir: float, yaw: float,
                                                                      point: list[float]) -> None:
    """levelled_about(T, p) has levelled(T)'s rotation and puts p where T put it."""
    axis = np.array([np.cos(tilt_dir), np.sin(tilt_dir), 0.0])
    T = np.eye(4)
    T[:3, :3] = rotation_aligning(np.array([0.0, 0.0, 1.0]), np.cos(tilt) * np.array([0.0, 0.0, 1.0])
                                  + np.sin(tilt) * np.cross(axis, [0.0, 0.0, 1.0])) @ rot_z(yaw)
    T[:3, 3] = [30.0, -12.0, 0.5]
    p = np.array(point)
    L = levelled_about(T, p)
    assert np.allclose(L[:3, :3], levelled(T)[:3, :3], atol=1e-12)
    assert np.allclose(apply(L, p[None]), apply(T, p[None]), atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(yaws=st.lists(st.floats(-10, 10), min_size=1, max_size=6))
def test_rot_z_of_many_angles_is_each_angles_rotation(yaws: list[float]) -> None:
    many = rot_z(np.array(yaws))
    assert many.shape == (len(yaws), 3, 3)
    for R, yaw in zip(many, yaws, strict=True):
        assert np.allclose(R, rot_z(yaw))
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R[:2, 0], [np.cos(yaw), np.sin(yaw)]) and np.allclose(R[2], [0.0, 0.0, 1.0])
