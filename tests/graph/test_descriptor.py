"""The paper's descriptor: KDE look-up tables, the Figure 7 layout, Hamming distance, invariance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.descriptor import (
    build_tables,
    describe,
    encode,
    hamming,
    kde_bin_edges,
    match_top_k,
    neighbour_geometry,
    silverman_bandwidth,
)
from macroloc.graph.rigid import apply
from tests.graph.helpers import random_T


def test_silverman_bandwidth_is_eq_8() -> None:
    x = np.random.default_rng(0).normal(0, 2.0, 500)
    sigma = np.std(x, ddof=1)
    assert silverman_bandwidth(x) == pytest.approx((4 * sigma**5 / (3 * 500)) ** 0.2)
    assert silverman_bandwidth(x) == pytest.approx(1.06 * sigma * 500 ** -0.2, rel=1e-2)


def test_bins_split_well_separated_modes_at_their_minima() -> None:
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(2.0, 0.1, 400), rng.normal(5.0, 0.1, 400), rng.normal(9.0, 0.1, 400)])
    edges = kde_bin_edges(x, 256)
    assert len(edges) == 2
    assert 2.3 < edges[0] < 4.7 and 5.3 < edges[1] < 8.7


def test_a_unimodal_distribution_gives_one_bin() -> None:
    x = np.random.default_rng(2).normal(0.0, 1.0, 1000)
    assert len(kde_bin_edges(x, 256)) == 0


def test_bins_never_exceed_their_bit_field() -> None:
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(m, 0.01, 30) for m in np.arange(0, 300, 1.0)])  # 300 sharp modes
    assert len(kde_bin_edges(x, 128)) <= 127


def test_distance_field_is_the_length_of_vec_i_and_angle_is_to_the_base() -> None:
    # x at the origin, base v0 at (1,0,0); neighbour 1 at (0,2,0): |vec_1| = 2, angle 90 deg.
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [-3, 0, 0], [0, 0, 4], [5, 5, 5]], dtype=float)
    dists, angles, counts = neighbour_geometry(pts)
    assert counts[0] == 4
    assert np.allclose(dists[0], [2, 3, 4, np.sqrt(75)])
    assert np.allclose(np.degrees(angles[0][:3]), [90, 180, 90])


def test_layout_of_figure_7() -> None:
    from macroloc.graph.descriptor import DescriptorTables

    # one edge at 0.5: values below -> bin 0, above -> bin 1
    tables = DescriptorTables(np.zeros(1), np.zeros(1), np.array([0.5]), np.array([0.5]))
    code = encode(["window"], np.array([[1.0, 0.0, 1.0, 0.0]]), np.array([[1.0, 1.0, 0.0, 0.0]]), tables)[0]
    bits = format(int(code), "064b")
    # [type][angle1:7][dist1:8][angle2:8][dist2:8][angle3:8][dist3:8][angle4:8][dist4:8]
    assert bits[0] == "1"
    assert int(bits[1:8], 2) == 1 and int(bits[8:16], 2) == 1
    assert int(bits[16:24], 2) == 1 and int(bits[24:32], 2) == 0
    assert int(bits[32:40], 2) == 0 and int(bits[40:48], 2) == 1
    assert int(bits[48:56], 2) == 0 and int(bits[56:64], 2) == 0


def test_hamming_is_xor_popcount_and_64_across_types() -> None:
    a = np.array([0b1011, (1 << 63) | 0b1], dtype=np.uint64)
    b = np.array([0b0001, 0b1], dtype=np.uint64)
    d = hamming(a, b)
    assert d[0, 0] == 2 and d[0, 1] == 2
    assert d[1, 0] == 64 and d[1, 1] == 64


def test_match_top_k_agrees_with_brute_force() -> None:
    rng = np.random.default_rng(4)
    obs = rng.integers(0, 2**62, 50, dtype=np.uint64)
    model = rng.integers(0, 2**62, 300, dtype=np.uint64)
    idx, dist = match_top_k(obs, model, k=3, chunk=7)
    full = hamming(obs, model)
    assert np.array_equal(dist[:, 0], full.min(axis=1))
    assert np.all(np.take_along_axis(full, idx, axis=1) == dist)
    assert np.all(np.diff(dist, axis=1) >= 0)


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=25, deadline=None)
def test_model_descriptors_are_unchanged_by_moving_the_model(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 50, (60, 3))
    types = rng.choice(["door", "window"], 60)
    tables = build_tables(pts)
    moved = apply(random_T(rng), pts)
    assert np.array_equal(describe(pts, types, tables), describe(moved, types, tables))


def test_real_building_tables(office_model) -> None:
    tables = build_tables(office_model.centroids_cad())
    assert tables.n_dist_bins >= 2 and tables.n_angle_bins >= 1
    assert len(tables.dist_samples_m) == 4 * len(office_model.features)
