"""The renderer against geometry: depth equals ray casting, boxes enclose masks, stereo recovers depth."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.sim.groundtruth import feature_half_depths, features_in_view
from macroloc.sim.materials import DOUBLE_DOOR_STYLE, PHOTO_STYLE, door_style, dress_scene
from macroloc.sim.render import KIND_DOOR, CameraModel, Lighting, StereoRenderer
from macroloc.sim.textures import make_texture_layers
from tests.sim.room import look_at, ray_cast_depth, room_scene

SMALL = CameraModel(width=320, height=240, fx=240.0, fy=240.0, cx=159.5, cy=119.5, baseline_m=0.12)


def _lighting() -> Lighting:
    return Lighting(positions_cad=np.array([[2.0, 2.0, 2.7], [6.0, 4.0, 2.7]]), colours=np.ones((2, 3)),
                    noise_sigma=0.01)


@pytest.fixture(scope="module")
def room():
    scene, features = room_scene()
    return scene, features


@pytest.fixture(scope="module")
def renderer(room):
    scene, features = room
    r = StereoRenderer(dress_scene(scene, features, seed=3), make_texture_layers(3), SMALL)
    yield r
    r.release()


@pytest.fixture(scope="module")
def renderer_vga(room):
    scene, features = room
    r = StereoRenderer(dress_scene(scene, features, seed=4), make_texture_layers(4), CameraModel())
    yield r
    r.release()


def test_rendered_depth_equals_ray_cast_depth(room, renderer) -> None:
    scene, _ = room
    T = look_at([1.0, 1.0, 1.4], [6.0, 5.5, 1.0])
    out = renderer.render(T, _lighting())
    assert out.depth_m is not None
    rng = np.random.default_rng(0)
    uv = np.column_stack([rng.integers(0, SMALL.width, 600), rng.integers(0, SMALL.height, 600)])
    opaque = scene.triangles_cad[~scene.tri_glass]
    ray = ray_cast_depth(opaque, T, SMALL.K, uv.astype(float))
    rendered = out.depth_m[uv[:, 1], uv[:, 0]]
    both = np.isfinite(ray) & (rendered > 0)
    assert both.mean() > 0.95
    err = np.abs(rendered[both] - ray[both])
    assert np.median(err) < 1e-3
    assert np.mean(err < 5e-3) > 0.98  # a few pixels on silhouette edges may differ


def test_image_is_textured_and_row_zero_is_the_top(room, renderer) -> None:
    T = look_at([4.0, 3.0, 1.5], [4.0, 5.9, 1.5])  # level, facing the door wall: ceiling above, floor below
    out = renderer.render(T, _lighting())
    assert out.image_bgr.shape == (SMALL.height, SMALL.width, 3) and out.image_bgr.dtype == np.uint8
    assert out.depth_m is not None
    top, bottom = out.depth_m[0, SMALL.width // 2], out.depth_m[-1, SMALL.width // 2]
    ceiling_z = 1.5 - top * (0 - SMALL.cy) / SMALL.fy  # cam y is down: a point at row 0 lies above
    floor_z = 1.5 - bottom * (SMALL.height - 1 - SMALL.cy) / SMALL.fy
    assert ceiling_z == pytest.approx(3.0, abs=0.02) and floor_z == pytest.approx(0.0, abs=0.02)
    grey = out.image_bgr.mean(axis=2)
    assert grey[40:200, 20:100].std() > 3.0  # the wall carries texture, not a flat colour


def test_ground_truth_boxes_enclose_masks_and_corners(room, renderer) -> None:
    scene, features = room
    half = feature_half_depths(scene, features)
    for eye, target in (([3.5, 2.0, 1.4], [3.5, 6.0, 1.2]), ([5.0, 1.0, 1.5], [8.0, 3.5, 1.5]),
                        ([2.0, 4.0, 1.2], [7.0, 5.0, 1.2])):
        T = look_at(eye, target)
        out = renderer.render(T, _lighting())
        assert out.depth_m is not None and out.instance is not None
        seen = features_in_view(features, half, T, SMALL, out.depth_m, out.instance)
        assert seen, "the door or the window must be in view"
        for f in seen:
            ys, xs = np.nonzero(out.instance == f.index + 1)
            x0, y0, x1, y1 = f.box_xyxy
            # boxes are in pixels with pixel centres at integers and cover whole pixels: [i - 0.5, i + 0.5]
            assert xs.min() - 0.5 >= x0 - 1e-6 and xs.max() + 0.5 <= x1 + 1e-6
            assert ys.min() - 0.5 >= y0 - 1e-6 and ys.max() + 0.5 <= y1 + 1e-6
            corners_vis = f.corners_px[f.corner_visible]
            assert np.all((corners_vis >= -0.5) & (corners_vis <= [SMALL.width - 0.5, SMALL.height - 0.5]))


def test_window_mask_covers_its_glass_and_depth_sees_through(room, renderer) -> None:
    T = look_at([5.0, 2.75, 1.6], [8.0, 2.75, 1.6])
    out = renderer.render(T, _lighting())
    assert out.instance is not None and out.depth_m is not None
    centre = (SMALL.height // 2, SMALL.width // 2)
    assert out.instance[centre] == 2  # window1 is feature 1 -> instance 2, also on its pane
    assert out.depth_m[centre] == 0.0 or out.depth_m[centre] > 3.5  # through the glass: sky or outside


def test_occluded_corner_is_not_visible(room, renderer) -> None:
    scene, features = room
    half = feature_half_depths(scene, features)
    # from inside the room looking along the door wall, the door's far corners are behind nothing: all visible
    T = look_at([3.5, 3.0, 1.2], [3.5, 6.0, 1.0])
    out = renderer.render(T, _lighting())
    assert out.depth_m is not None and out.instance is not None
    door = next(f for f in features_in_view(features, half, T, SMALL, out.depth_m, out.instance) if f.id == "door1")
    assert door.corner_visible.sum() >= 2
    # a fake occluder: pretend everything is 0.5 m away: no corner can be visible
    near = np.full_like(out.depth_m, 0.5)
    door = next(f for f in features_in_view(features, half, T, SMALL, near, out.instance) if f.id == "door1")
    assert not door.corner_visible.any()


def test_sgbm_recovers_true_depth_on_rendered_pair(room, renderer_vga) -> None:
    import cv2

    cam = renderer_vga.camera
    T = look_at([0.8, 0.8, 1.4], [6.0, 5.0, 1.1])
    left, right = renderer_vga.render_stereo(T, _lighting())
    assert left.depth_m is not None
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=5, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(cv2.cvtColor(left.image_bgr, cv2.COLOR_BGR2GRAY),
                        cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)).astype(np.float32) / 16.0
    truth = left.depth_m
    sel = (truth > 2.0) & (truth < 6.0) & (disp > 0.5)
    assert sel.mean() > 0.3
    est = cam.fx * cam.baseline_m / disp[sel]
    rel = np.abs(est - truth[sel]) / truth[sel]
    assert np.median(rel) < 0.03


def test_two_renderers_in_one_process_each_draw_their_own_scene(room, renderer, renderer_vga) -> None:
    """Each renderer owns an EGL context; the one created last must not capture the other's draws."""
    T = look_at([1.0, 1.0, 1.4], [6.0, 5.5, 1.0])
    small = renderer.render(T, _lighting())
    vga = renderer_vga.render(T, _lighting())
    again = renderer.render(T, _lighting())
    assert small.image_bgr.shape[:2] == (SMALL.height, SMALL.width)
    assert vga.image_bgr.shape[:2] == (480, 640)
    assert small.depth_m is not None and again.depth_m is not None
    np.testing.assert_array_equal(small.depth_m, again.depth_m)


@pytest.mark.parametrize("width_m, double_share", [(0.8, (0.0, 0.0)), (1.02, (0.1, 0.3)), (1.8, (0.78, 0.92))])
def test_wide_openings_are_mostly_double_doors(width_m, double_share) -> None:
    rng = np.random.default_rng(0)
    styles = np.array([door_style(width_m, rng) for _ in range(600)])
    assert np.all(styles == np.round(styles)) and styles.min() >= 0
    assert styles.max() < PHOTO_STYLE - 0.5  # below the shader's photo threshold
    double = np.mean(styles >= DOUBLE_DOOR_STYLE)
    assert double_share[0] <= double <= double_share[1]


def _door_strips(renderer_for_style, style: float) -> tuple[float, float]:
    """Mean grey of the door's central column and of the columns a quarter in from each side, at mid-height."""
    r = renderer_for_style(style)
    out = r.render(look_at([3.5, 4.4, 1.1], [3.5, 5.9, 1.1]), _lighting(), frame_seed=1.0)
    r.release()
    assert out.instance is not None
    cols = np.flatnonzero((out.instance == 1).any(axis=0))
    rows = np.flatnonzero((out.instance == 1).any(axis=1))
    x0, x1, yc = cols.min(), cols.max(), (rows.min() + rows.max()) // 2
    grey = out.image_bgr.mean(axis=2)[yc - 10:yc + 10]
    xc, q = (x0 + x1) // 2, (x1 - x0) // 4
    return float(grey[:, xc - 1:xc + 2].min(axis=1).mean()), float(grey[:, [xc - q, xc + q]].mean())


def test_a_double_door_shows_where_its_leaves_meet(room) -> None:
    scene, features = room
    base = dress_scene(scene, features, seed=3)
    door = np.abs(base[:, 13] - KIND_DOOR) < 0.5

    def renderer_for_style(style: float) -> StereoRenderer:
        verts = base.copy()
        verts[door, 14] = style
        return StereoRenderer(verts, make_texture_layers(3), SMALL)

    gap, leaves = _door_strips(renderer_for_style, DOUBLE_DOOR_STYLE + 3)  # two flush leaves with kick plates
    assert gap < 0.6 * leaves
    gap, leaves = _door_strips(renderer_for_style, 3)  # one flush leaf: nothing at its middle
    assert gap > 0.8 * leaves
