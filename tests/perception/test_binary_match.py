"""Exact binary nearest neighbours and the ratio test (perception.binary_match) against OpenCV's brute force."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.perception.binary_match import BinaryIndex


def _descriptors(n_rows: int, n_queries: int, seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Random rows, and queries of which the first are near copies of rows (~2 bits flipped)."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, 256, (n_rows, 32), dtype=np.uint8)
    queries = rng.integers(0, 256, (n_queries, 32), dtype=np.uint8)
    copied = min(n_rows, n_queries)
    queries[:copied] = rows[:copied] ^ (rng.random((copied, 32)) < 0.01).astype(np.uint8)
    return rows, queries, copied


@settings(max_examples=25, deadline=None)
@given(n_rows=st.integers(0, 300), n_queries=st.integers(1, 40), seed=st.integers(0, 2**31 - 1))
def test_the_index_finds_the_nearest_descriptors_as_the_brute_force_matcher(n_rows: int, n_queries: int,
                                                                           seed: int) -> None:
    """The index (faiss, exact) gives OpenCV's brute-force Hamming distances to the two nearest rows; near
    copies of stored rows (a few bits flipped) are found at their own row."""
    rows, queries, copied = _descriptors(n_rows, n_queries, seed)
    distance, row = BinaryIndex(rows).nearest(queries, k=2)
    assert distance.shape == row.shape == (n_queries, min(2, n_rows))
    if n_rows == 0:
        return
    brute = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(queries, rows, k=2)
    np.testing.assert_array_equal(distance, [[m.distance for m in pair] for pair in brute])
    np.testing.assert_array_equal(distance, np.take_along_axis(
        np.unpackbits(queries[:, None] ^ rows[None], axis=2).sum(axis=2), row, axis=1))
    near = distance[:copied, 0] < 20  # the copy, unless a random row lies as near (all but impossible)
    assert near.all() and (row[:copied, 0] == np.arange(copied)).all()


@settings(max_examples=40, deadline=None)
@given(n_rows=st.integers(0, 300), n_queries=st.integers(0, 300), seed=st.integers(0, 2**31 - 1),
       ratio=st.sampled_from([0.6, 0.8, 1.0]), duplicates=st.booleans())
def test_ratio_matches_are_opencv_s_knn_match_and_ratio_test(n_rows: int, n_queries: int, seed: int, ratio: float,
                                                             duplicates: bool) -> None:
    """The pairs passing Lowe's test are those of BFMatcher.knnMatch(k=2), pair for pair, also where rows repeat
    (equal distances: the order of ties never decides a pair) and with fewer than two rows (none)."""
    rows, queries, _ = _descriptors(n_rows, n_queries, seed)
    if duplicates and n_rows > 1:
        rows[1::2] = rows[0::2][:len(rows[1::2])]  # every row twice: the two nearest tie
        rows[-1] = rows[0] ^ np.uint8(1)
    query, train = BinaryIndex(rows).ratio_matches(queries, ratio)
    expected = ([(m.queryIdx, m.trainIdx) for m, n in (p for p in cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(
        queries, rows, k=2) if len(p) == 2) if m.distance < ratio * n.distance] if len(queries) and n_rows else [])
    assert list(zip(query.tolist(), train.tolist(), strict=True)) == expected
