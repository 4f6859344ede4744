"""Stereo visual odometry on rendered stereo pairs of the simulator's test room: a gentle flight with a turn."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.perception.calib import StereoRig
from macroloc.perception.odometry import StereoOdometry, VisualOdometryParams


@pytest.fixture(scope="module")
def flight():  # noqa: ANN201 - [(T_cad_cam, left, right)]
    from macroloc.sim.materials import dress_scene
    from macroloc.sim.render import CameraModel, Lighting, StereoRenderer
    from macroloc.sim.textures import make_texture_layers
    from tests.sim.room import look_at, room_scene

    scene, features = room_scene()
    renderer = StereoRenderer(dress_scene(scene, features, seed=2), make_texture_layers(2), CameraModel())
    lighting = Lighting(positions_cad=np.array([[2.0, 2.0, 2.7], [6.0, 4.0, 2.7]]), colours=np.ones((3, 3))[:2],
                        noise_sigma=0.01)
    frames = []
    try:
        for s in np.linspace(0.0, 1.0, 60):  # 3.2 m along x and 1.2 m along y, the view turning by ~35 deg
            eye = np.array([1.5 + 3.2 * s, 1.2 + 1.2 * s, 1.4])
            yaw = np.radians(60.0 - 35.0 * s)
            T = look_at(eye, eye + [np.cos(yaw), np.sin(yaw), -0.05])
            left, right = renderer.render_stereo(T, lighting, float(len(frames)))
            frames.append((T, left.image_bgr, right))
    finally:
        renderer.release()
    return frames


@pytest.mark.parametrize("tracker", ["klt", "orb"])
def test_follows_a_rendered_flight_within_two_percent_of_its_length(flight, tracker: str) -> None:
    cam = StereoRig(480.0, 480.0, 319.5, 239.5, 0.12, 640, 480)
    vo = StereoOdometry(cam, VisualOdometryParams(tracker=tracker))
    T0 = flight[0][0]
    for _, left, right in flight:
        result = vo.track(left, right)
        assert result.tracked
    truth = np.linalg.inv(T0) @ flight[-1][0]  # the last camera in the first camera's frame
    error = np.linalg.inv(truth) @ result.T_odom_cam
    path_m = np.linalg.norm(truth[:3, 3])
    angle_deg = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert np.linalg.norm(error[:3, 3]) < 0.02 * path_m, (np.linalg.norm(error[:3, 3]), path_m)  # 2 % drift
    assert angle_deg < 1.0  # of a 35 deg turn
