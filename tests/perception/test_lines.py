import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.perception.lines import join_segments, refine_box
from tests.perception.helpers import door_image


def _pieces(p0, p1, n, gap_px):
    """Split the segment p0-p1 into n pieces separated by gaps of gap_px (along the segment)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = np.linalg.norm(p1 - p0)
    d = (p1 - p0) / length
    piece = (length - (n - 1) * gap_px) / n
    return [np.stack([p0 + d * i * (piece + gap_px), p0 + d * (i * (piece + gap_px) + piece)]) for i in range(n)]


@settings(max_examples=60, deadline=None)
@given(st.floats(60, 120), st.floats(-15, 15), st.integers(2, 5), st.floats(0.5, 9.5), st.floats(50, 300))
def test_broken_pieces_within_the_paper_thresholds_are_joined(u0, tilt_deg, n, gap_px, length):
    t = np.radians(tilt_deg)
    p0 = np.array([u0, 20.0])
    p1 = p0 + length * np.array([np.sin(t), np.cos(t)])
    pieces = _pieces(p0, p1, n, gap_px)
    rng = np.random.default_rng(0)
    joined = join_segments([pieces[i] for i in rng.permutation(n)])
    assert len(joined) == 1
    assert np.allclose(sorted(joined[0][:, 1]), sorted([p0[1], p1[1]]), atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.floats(2.5, 30), st.floats(10.5, 40))
def test_pieces_beyond_the_thresholds_stay_apart(angle_deg, gap_px):
    a = np.array([[100.0, 10.0], [100.0, 110.0]])
    t = np.radians(angle_deg)
    turned = np.array([[100.0, 112.0], [100.0 + 80 * np.sin(t), 112.0 + 80 * np.cos(t)]])
    far = np.array([[100.0, 110.0 + gap_px], [100.0, 200.0 + gap_px]])
    assert len(join_segments([a, turned])) == 2  # angle > 2 deg
    assert len(join_segments([a, far])) == 2  # gap > 10 px


def test_sides_of_a_door_with_broken_edges():
    truth = (200, 100, 300, 380)
    image = door_image(truth)
    box = (190.0, 95.0, 312.0, 385.0)  # a detector box a little off
    sides = refine_box(image, box)
    assert sides.from_lines == (True, True)
    assert np.allclose(sides.left_px[:, 0], truth[0], atol=1.5)
    assert np.allclose(sides.right_px[:, 0], truth[2], atol=1.5)
    assert np.allclose(sides.left_px[:, 1], [box[1], box[3]])  # extended to the box's rows


def test_without_lines_the_sides_fall_back_to_the_strongest_edge():
    image = np.full((480, 640), 128, np.uint8)
    sides = refine_box(image, (100.0, 100.0, 200.0, 300.0))
    assert sides.from_lines == (False, False)
    assert np.allclose(sides.left_px[:, 0], 100.0) and np.allclose(sides.right_px[:, 0], 200.0)
