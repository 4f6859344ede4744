"""Place recognition in a stored map (perception.place) on rendered stereo pairs of the simulator's test room:
views kept along one path, a view from between them and off it placed, a room that looks different and a pose
tilted from gravity refused."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.graph.mapstore import KeyframeView
from macroloc.graph.rigid import rotation_angle_deg
from macroloc.perception.calib import StereoRig
from macroloc.perception.place import PlaceRecognizer
from tests.graph.scenes import make_T, rot_z

RIG = StereoRig(480.0, 480.0, 319.5, 239.5, 0.12, 640, 480)
T_CAD_MAP = make_T(rot_z(0.7), np.array([3.0, -2.0, 0.0]))  # the stored flight's map frame, somewhere in the room
UP = np.array([0.0, 0.0, 1.0])


def camera_at(s: float, side_m: float = 0.0, turn_deg: float = 0.0) -> np.ndarray:
    """T_cad_cam along the stored path (s in [0, 1]: 3 m along x, the view turning from 60 to 30 deg), moved
    `side_m` across it and turned by `turn_deg`."""
    from tests.sim.room import look_at

    yaw = np.radians(60.0 - 30.0 * s + turn_deg)
    eye = np.array([1.5 + 3.0 * s, 1.2 + 1.0 * s + side_m, 1.4])
    return look_at(eye, eye + [np.cos(yaw), np.sin(yaw), -0.05])


@pytest.fixture(scope="module")
def room():  # noqa: ANN201 - (T_body_cam, stored [(T_map_body, view)], {name: (T_map_body, left image)})
    from macroloc.common.geometry import forward_stereo_T_body_cam
    from macroloc.sim.materials import dress_scene
    from macroloc.sim.render import CameraModel, Lighting, StereoRenderer
    from macroloc.sim.textures import make_texture_layers
    from tests.sim.room import room_scene

    scene, features = room_scene()
    T_body_cam = forward_stereo_T_body_cam(RIG.baseline_m)
    lighting = Lighting(positions_cad=np.array([[2.0, 2.0, 2.7], [6.0, 4.0, 2.7]]), colours=np.ones((2, 3)),
                        noise_sigma=0.01)
    recognizer = PlaceRecognizer(RIG, T_body_cam)

    def T_map_body(T_cad_cam: np.ndarray) -> np.ndarray:
        return np.linalg.inv(T_CAD_MAP) @ T_cad_cam @ np.linalg.inv(T_body_cam)

    stored, views = [], {}
    for seed, shots in ((2, {"between": camera_at(0.5, side_m=0.25, turn_deg=6.0)}),
                        (5, {"other look": camera_at(0.5, side_m=0.25, turn_deg=6.0)})):
        renderer = StereoRenderer(dress_scene(scene, features, seed=seed), make_texture_layers(seed), CameraModel())
        try:
            if seed == 2:
                for k, s in enumerate(np.linspace(0.0, 1.0, 7)):
                    left, right = renderer.render_stereo(camera_at(s), lighting, float(k))
                    stored.append((T_map_body(camera_at(s)), recognizer.describe(left.image_bgr, right)))
            for name, T_cad_cam in shots.items():
                left, _ = renderer.render_stereo(T_cad_cam, lighting, 99.0)
                views[name] = (T_map_body(T_cad_cam), left.image_bgr)
        finally:
            renderer.release()
    return T_body_cam, stored, views


def test_stored_views_hold_points_with_depth_strongest_first(room) -> None:  # noqa: ANN001
    _, stored, _ = room
    for _, view in stored:
        assert 100 <= len(view.points_body) <= 400 and view.descriptors.shape == (len(view.points_body), 32)
        assert np.all(view.points_body[:, 0] > 0.3)  # in front of the body (x forward), where the room's walls are


def test_a_view_between_the_stored_ones_and_off_their_path_is_placed(room) -> None:  # noqa: ANN001
    T_body_cam, stored, views = room
    recognizer = PlaceRecognizer(RIG, T_body_cam)
    recognizer.use(stored)
    T_true, left = views["between"]
    match = recognizer.place(left, UP)
    assert match is not None and match.inliers >= 40
    error = np.linalg.inv(T_true) @ match.T_map_body
    assert np.linalg.norm(error[:3, 3]) < 0.03 and rotation_angle_deg(error[:3, :3]) < 0.5  # 7 mm, 0.08 deg here
    assert match.view in (2, 3, 4)  # the stored views nearest to it


def test_a_room_that_looks_different_is_not_placed(room) -> None:  # noqa: ANN001
    T_body_cam, stored, views = room
    recognizer = PlaceRecognizer(RIG, T_body_cam)
    recognizer.use(stored)
    assert recognizer.place(views["other look"][1], UP) is None


def test_a_pose_tilted_from_gravity_is_refused(room) -> None:  # noqa: ANN001
    T_body_cam, stored, views = room
    recognizer = PlaceRecognizer(RIG, T_body_cam)
    recognizer.use(stored)
    left = views["between"][1]
    assert recognizer.place(left, UP) is not None
    tilt = np.radians(10.0)
    assert recognizer.place(left, np.array([np.sin(tilt), 0.0, np.cos(tilt)])) is None


def test_without_stored_views_nothing_is_placed(room) -> None:  # noqa: ANN001
    T_body_cam, _, views = room
    recognizer = PlaceRecognizer(RIG, T_body_cam)
    recognizer.use([(np.eye(4), KeyframeView(np.zeros((0, 3)), np.zeros((0, 32), np.uint8)))])
    assert not recognizer.has_views and recognizer.place(views["between"][1], UP) is None


def test_twin_places_that_look_alike_are_not_guessed(room) -> None:  # noqa: ANN001
    """The stored views again, as if seen in a twin room 12 m away and half a turn about (a symmetric building
    whose halves look alike; a few bits of each descriptor differ, as no two places look the same to the bit).
    Both explain the image: no answer. Either room alone is placed."""
    T_body_cam, stored, views = room
    rng = np.random.default_rng(1)
    T_twin = make_T(rot_z(np.pi), np.array([12.0, 0.0, 0.0]))
    twins = []
    for T_map_body, view in stored:
        flips = np.zeros(view.descriptors.shape, np.uint8)
        byte = rng.integers(0, 32, (len(flips), 2))
        flips[np.arange(len(flips))[:, None], byte] = 1 << rng.integers(0, 8, byte.shape).astype(np.uint8)
        twins.append((T_twin @ T_map_body, KeyframeView(view.points_body, view.descriptors ^ flips)))
    left = views["between"][1]
    for alone in (stored, twins):
        recognizer = PlaceRecognizer(RIG, T_body_cam)
        recognizer.use(alone)
        assert recognizer.place(left, UP) is not None
    recognizer = PlaceRecognizer(RIG, T_body_cam)
    recognizer.use(stored + twins)
    assert recognizer.place(left, UP) is None
