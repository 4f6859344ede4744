"""Exact nearest binary descriptors (ORB's 256 bits) by Hamming distance, and Lowe's ratio test on them.

faiss' flat binary index with one thread (as graph.descriptor's: OpenMP's spinning workers cost more than they
give on two shared cores). The same answer as OpenCV's `BFMatcher(NORM_HAMMING).knnMatch(k=2)` and its ratio test:
a pair passes only where the nearest row is strictly nearer than the second, so which of two equally near rows
either library lists first never decides a match.
"""

from __future__ import annotations

import faiss
import numpy as np


class BinaryIndex:
    """Rows of packed binary descriptors (N, bytes) uint8, searched exactly."""

    def __init__(self, descriptors: np.ndarray) -> None:
        faiss.omp_set_num_threads(1)
        self.n = len(descriptors)
        self._index = faiss.IndexBinaryFlat(descriptors.shape[1] * 8)
        if self.n:
            self._index.add(np.ascontiguousarray(descriptors, np.uint8))

    def nearest(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(distances, rows), each (Nq, min(k, n)), nearest first."""
        k = min(k, self.n)
        if k == 0 or len(queries) == 0:
            return np.zeros((len(queries), k), np.int32), np.zeros((len(queries), k), np.int64)
        distance, row = self._index.search(np.ascontiguousarray(queries, np.uint8), k)
        return distance, row

    def ratio_matches(self, queries: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
        """(query rows, index rows) of the queries whose nearest row is nearer than `ratio` times the second
        nearest (Lowe's test), in query order; none where the index holds fewer than two rows."""
        distance, row = self.nearest(queries, 2)
        if distance.shape[1] < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        query = np.flatnonzero(distance[:, 0] < ratio * distance[:, 1])
        return query, row[query, 0]
