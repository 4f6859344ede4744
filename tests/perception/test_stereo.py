import numpy as np
import pytest

from macroloc.perception.stereo import (
    FrameDisparity,
    SgbmMatcher,
    SgbmParams,
    back_project,
    depth_from_disparity,
    ray_cam,
    sample_depth_m,
)
from tests.perception.helpers import RIG, fronto_parallel_pair


def test_back_projection_is_eq2():
    uv = np.array([[RIG.cx_px, RIG.cy_px], [RIG.cx_px + 48.0, RIG.cy_px - 96.0]])
    pts = back_project(uv, np.array([2.0, 5.0]), RIG)
    assert np.allclose(pts[0], [0, 0, 2.0])
    assert np.allclose(pts[1], [5.0 * 48 / 480, -5.0 * 96 / 480, 5.0])  # d * ((u - cx)/fx, (v - cy)/fy, 1)


def test_rays_are_unit_and_pass_through_the_pixels():
    uv = np.array([[10.0, 20.0], [600.0, 400.0]])
    rays = ray_cam(uv, RIG)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    proj = rays[:, :2] / rays[:, 2:] * RIG.fx_px + [RIG.cx_px, RIG.cy_px]
    assert np.allclose(proj, uv)


def test_depth_from_disparity_and_unknowns():
    disp = np.array([[RIG.fx_px * RIG.baseline_m / 4.0, np.nan, 0.0, -1.0]], np.float32)
    depth = depth_from_disparity(disp, RIG)
    assert depth[0, 0] == pytest.approx(4.0, rel=1e-5)
    assert np.all(np.isnan(depth[0, 1:]))


@pytest.mark.parametrize("depth_m", [2.0, 4.5])
def test_sgbm_recovers_a_textured_plane(depth_m: float):
    left, right = fronto_parallel_pair(depth_m)
    disparity = SgbmMatcher().disparity_px(left, right)
    truth = RIG.fx_px * RIG.baseline_m / depth_m
    inner = disparity[20:-20, 20:-20]
    assert np.isfinite(inner).mean() > 0.9
    assert np.nanmedian(np.abs(inner - truth)) < 0.25
    # the left padding keeps the first columns (SGBM's blind band) usable where the match is in view
    assert np.isfinite(disparity[20:-20, 30:60]).mean() > 0.8


def test_no_disparity_puts_the_match_left_of_the_right_image():
    """The padding repeats the right image's first column: a left pixel matched into it (disparity greater than
    its column) has no match in view. 128 disparities on a plane 5 m away (11.5 px) gave 2,787 such pixels down
    the left edge (in Office_A seed 3's frames: walls 5-7 m away measured at 0.5 m); none is kept."""
    from macroloc.perception.stereo import SgbmParams

    left, right = fronto_parallel_pair(5.0)
    disparity = SgbmMatcher(SgbmParams(num_disparities=128)).disparity_px(left, right)
    column = np.arange(disparity.shape[1])
    assert not np.any(disparity > column)
    truth = RIG.fx_px * RIG.baseline_m / 5.0
    in_view = disparity[20:-20, 20:]  # from column 20 on, the true match (11.5 px to the left) is in view
    assert np.isfinite(in_view).mean() > 0.9 and np.nanmedian(np.abs(in_view - truth)) < 0.25


def test_sample_depth_takes_the_median_of_valid_neighbours():
    depth = np.full((5, 10), np.nan, np.float32)
    depth[2, 3:6] = [1.0, 2.0, 9.0]
    out = sample_depth_m(depth, np.array([[4.0, 2.0], [4.0, 0.0], [50.0, 2.0]]))
    assert out[0] == pytest.approx(2.0)
    assert np.isnan(out[1]) and np.isnan(out[2])


def test_the_matcher_is_never_handed_unequal_empty_or_oversized_pairs() -> None:
    """OpenCV's SGBM crashed the process on a 20000 x 20000 pair (segfault in compute): it is refused first."""
    from macroloc.perception.stereo import MAX_PIXELS, SgbmMatcher

    matcher = SgbmMatcher()
    left = np.zeros((48, 64), np.uint8)
    for right in (np.zeros((24, 64), np.uint8), np.zeros((48, 32, 3), np.uint8)):
        with pytest.raises(ValueError, match="not the same size"):
            matcher.disparity_px(left, right)
    with pytest.raises(ValueError):
        matcher.disparity_px(left[:0], left[:0])
    side = int(np.sqrt(MAX_PIXELS)) + 1
    tall = np.lib.stride_tricks.as_strided(np.zeros(1, np.uint8), (side, side), (0, 0))  # no memory behind it
    with pytest.raises(ValueError, match="over"):
        matcher.disparity_px(tall, tall)
    assert matcher.disparity_px(left, left).shape == (48, 64)


@pytest.mark.parametrize("u0", [10, 300])  # near the left edge (padded) and inside (real columns left of it)
def test_a_window_matches_as_the_whole_frame_does(u0: int) -> None:
    left, right = fronto_parallel_pair(3.0)
    matcher = SgbmMatcher(SgbmParams(num_disparities=64))
    whole = matcher.disparity_px(left, right)[100:300, u0:u0 + 200]
    window = matcher.window_px(left, right, 100, 300, u0, u0 + 200)
    assert window.shape == whole.shape
    both = np.isfinite(whole) & np.isfinite(window)
    assert both.mean() > 0.9 and np.median(np.abs(window[both] - whole[both])) < 0.05


def test_a_frame_is_matched_once_for_all_who_ask() -> None:
    left, right = fronto_parallel_pair(3.0)
    shared = FrameDisparity(SgbmMatcher(SgbmParams(num_disparities=64)))
    whole = shared.disparity_px(left, right)
    assert shared.disparity_px(left, right) is whole
    assert np.array_equal(shared.window_px(left, right, 10, 50, 100, 200), whole[10:50, 100:200], equal_nan=True)
    assert shared.computed == 1
    shared.disparity_px(left.copy(), right)  # another pair (another array)
    assert shared.computed == 2


def test_the_last_pairs_matched_are_kept_for_a_thread_that_comes_later() -> None:
    """keep=3: a frame matched by one thread (an odometry run ahead) is found by another (the chain) up to
    two frames later; the first matched is dropped by a fourth. Two threads matching at once get what one
    thread gets."""
    import threading

    pairs = [fronto_parallel_pair(d) for d in (2.0, 2.5, 3.0, 3.5)]
    alone = [SgbmMatcher(SgbmParams(num_disparities=64)).disparity_px(*p) for p in pairs]
    shared = FrameDisparity(SgbmMatcher(SgbmParams(num_disparities=64)), keep=3)
    got: dict[int, np.ndarray] = {}

    def match(k: int) -> None:
        got[k] = shared.disparity_px(*pairs[k])

    threads = [threading.Thread(target=match, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    match(2)
    assert shared.computed == 3
    assert all(np.array_equal(got[k], alone[k], equal_nan=True) for k in (0, 1, 2))
    assert all(shared.disparity_px(*pairs[k]) is got[k] for k in (0, 1, 2)) and shared.computed == 3  # all kept

    in_turn = FrameDisparity(SgbmMatcher(SgbmParams(num_disparities=64)), keep=3)
    first = [in_turn.disparity_px(*p) for p in pairs]  # the fourth drops the first matched
    assert in_turn.computed == 4
    assert in_turn.disparity_px(*pairs[1]) is first[1] and in_turn.computed == 4
    assert in_turn.disparity_px(*pairs[0]) is not first[0] and in_turn.computed == 5
