"""The edge frame of a rectangle whose corners come in any order (graph/rectangle.py)."""

from __future__ import annotations

import numpy as np

from macroloc.graph.rectangle import unordered_edges


def _noisy_windows(rng: np.random.Generator, n: int, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """n copies of a 0.9 x 1.4 m window in the x-z plane, corners shuffled, N(0, sigma^2) on every coordinate;
    and each copy's order (n, 4): which corner of the window (0 to 3 around it) each given corner is."""
    corners = np.array([[0.0, 0.0, 0.0], [0.9, 0.0, 0.0], [0.9, 0.0, 1.4], [0.0, 0.0, 1.4]])
    order = np.stack([rng.permutation(4) for _ in range(n)])
    return corners[order] + rng.normal(0.0, sigma_m, (n, 4, 3)), order


def test_exact_corners_in_any_order_give_the_sides_and_a_closed_parallelogram() -> None:
    rng = np.random.default_rng(0)
    p, _ = _noisy_windows(rng, 24, 0.0)
    a, b, la, lb, closure = unordered_edges(p)
    assert np.allclose(np.sort(np.stack([la, lb], axis=1), axis=1), [0.9, 1.4])
    assert np.allclose(closure, 0.0)
    assert np.allclose(np.einsum("rc,rc->r", a, b), 0.0)
    assert np.allclose(np.abs(np.cross(a, b)[:, 1]), 1.0)  # the normal is the wall's (y)


def test_the_diagonal_is_the_pairing_that_closes_not_the_farthest_corner() -> None:
    """With 10 cm corner noise a 0.9 x 1.4 m window's long side (1.4 m) and diagonal (1.66 m) can swap places as
    corner 0's farthest corner; the pairing that closes best keeps both sides in 2000 of 2000 draws."""
    p, order = _noisy_windows(np.random.default_rng(1), 2000, 0.10)
    _, _, la, lb, _ = unordered_edges(p)
    assert np.minimum(la, lb).min() > 0.5  # a wrong diagonal leaves a side near zero (1.50 x 0.13 m seen)
    assert np.all(np.abs(np.sort(np.stack([la, lb], axis=1), axis=1) - [0.9, 1.4]) < 0.4)
    farthest = 1 + np.argmax(np.linalg.norm(p[:, 1:] - p[:, :1], axis=2), axis=1)
    rows = np.arange(len(p))
    assert np.any(order[rows, farthest] != (order[:, 0] + 2) % 4)  # draws where the farthest corner is no diagonal
