"""Closed solids are found and wound outward, so that the renderer may cull them from behind without changing
what the camera sees."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.sim.materials import dress_scene
from macroloc.sim.render import CameraModel, Lighting, StereoRenderer
from macroloc.sim.scene import WALL, SceneGeometry, orient_closed_solids
from macroloc.sim.textures import make_texture_layers
from tests.sim.room import look_at, room_scene


def _signed_volume(tris: np.ndarray) -> float:
    t = tris.astype(np.float64)
    return float(np.einsum("ij,ij->", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0)


def _box_triangles(extents, T) -> np.ndarray:  # noqa: ANN001
    m = trimesh.creation.box(extents=extents, transform=T)
    return m.triangles.astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.05, 5.0), min_size=3, max_size=3), st.integers(0, 2**31 - 1), st.booleans(),
       st.booleans())
def test_a_closed_box_ends_up_outward_whatever_its_pose_and_winding(extents, seed, inverted, shuffled) -> None:
    rng = np.random.default_rng(seed)
    T = trimesh.transformations.random_rotation_matrix(rng.random(3))
    T[:3, 3] = rng.uniform(-50, 50, 3)
    tris = _box_triangles(extents, T)
    if inverted:
        tris = tris[:, [0, 2, 1]]
    if shuffled:
        tris = tris[rng.permutation(len(tris))]
    out, closed = orient_closed_solids(tris, np.zeros(len(tris), np.int32))
    assert closed.all()
    assert _signed_volume(out) == pytest.approx(np.prod(extents), rel=1e-3)
    # the same triangles, only their winding may change
    assert np.allclose(np.sort(out.reshape(-1, 3), axis=0), np.sort(tris.reshape(-1, 3), axis=0))


def test_open_shells_inconsistent_winding_and_separate_elements_are_told_apart() -> None:
    box = _box_triangles([1.0, 2.0, 3.0], np.eye(4))
    shifted = box + np.float32([5.0, 0.0, 0.0])
    inconsistent = shifted.copy()
    inconsistent[0] = inconsistent[0, [0, 2, 1]]  # one triangle turned: no longer a consistently wound solid
    tris = np.concatenate([box[2:], box[:, [0, 2, 1]] + np.float32([0, 5, 0]), inconsistent])
    element = np.concatenate([np.zeros(10), np.ones(12), np.full(12, 2)]).astype(np.int32)
    out, closed = orient_closed_solids(tris, element)
    assert not closed[:10].any()  # a box with a face missing: open
    assert closed[10:22].all() and _signed_volume(out[10:22]) > 0  # inside out: turned
    assert not closed[22:].any()


def test_two_touching_boxes_of_different_elements_stay_separate_solids() -> None:
    a = _box_triangles([1.0, 1.0, 1.0], np.eye(4))
    b = a + np.float32([1.0, 0.0, 0.0])  # shares the face x = 0.5 with a, vertex for vertex
    out, closed = orient_closed_solids(np.concatenate([a, b[:, [0, 2, 1]]]),
                                       np.repeat(np.int32([0, 1]), 12))
    assert closed.all()
    assert _signed_volume(out[:12]) > 0 and _signed_volume(out[12:]) > 0


def test_culling_closed_solids_from_behind_changes_no_pixel_of_depth() -> None:
    room, features = room_scene()
    pillar = _box_triangles([0.4, 0.4, 3.0], trimesh.transformations.translation_matrix([5.0, 2.0, 1.5]))
    pillar = pillar[:, [0, 2, 1]]  # modelled inside out
    tris = np.concatenate([room.triangles_cad, pillar])
    element = np.concatenate([room.tri_element, np.full(len(pillar), len(room.element_ids), np.int32)])
    tris, closed = orient_closed_solids(tris, element)
    assert closed[-len(pillar):].all()
    scene = SceneGeometry("room+pillar", "0" * 64, tris, np.concatenate([room.tri_class, np.full(len(pillar), WALL,
                                                                                                  np.int8)]),
                          element, np.full((len(tris), 3), 0.8, np.float32),
                          np.concatenate([room.tri_glass, np.zeros(len(pillar), bool)]),
                          [*room.element_ids, "pillar"], room.space_triangles_cad, closed)
    camera = CameraModel(width=320, height=240, fx=240.0, fy=240.0, cx=159.5, cy=119.5)
    renderer = StereoRenderer(dress_scene(scene, features, seed=1), make_texture_layers(1), camera)
    lighting = Lighting(positions_cad=np.array([[2.0, 2.0, 2.7]]), colours=np.ones((1, 3)), noise_sigma=0.0)
    try:
        assert renderer.chunks.closed.any()
        for eye, target in (([1.0, 1.0, 1.4], [6.0, 2.5, 1.0]), ([7.5, 5.5, 2.0], [4.0, 1.0, 1.0])):
            T = look_at(eye, target)
            renderer.cull_back_faces = True
            culled = renderer.render(T, lighting)
            renderer.cull_back_faces = False
            full = renderer.render(T, lighting)
            assert culled.depth_m is not None and full.depth_m is not None
            pillar_px = np.abs(culled.depth_m - np.linalg.norm(np.subtract(eye, [5.0, 2.0, 1.0]))) < 2.0
            assert pillar_px.any()
            np.testing.assert_array_equal(culled.depth_m, full.depth_m)
            np.testing.assert_array_equal(culled.image_bgr, full.image_bgr)
    finally:
        renderer.release()
