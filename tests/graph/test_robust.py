"""The default registration's vectorised steps (graph/robust.py): each pose's result is what it would be alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from macroloc.graph.model_index import ModelIndex
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.rigid import apply, invert, make_T, rot_z, yaw_rigid_fit
from macroloc.graph.robust import (
    RobustParams,
    _distinct_top,
    _explain,
    _nearest_both,
    _nearest_same_type,
    _prepare,
    _refine_all,
)
from tests.graph.helpers import random_building, random_T


def _scene(seed: int, gravity: bool = True):
    """A random storey, its observations (2 cm corner noise, every third a centroid only, one false door), the true
    T_cad_map', and the prepared observations."""
    rng = np.random.default_rng(seed)
    features = random_building(rng, n=40, size_m=30.0)
    index = ModelIndex.build(features)
    T_map_cad = random_T(rng, 10.0, yaw_only=True) if gravity else random_T(rng, 10.0)
    obs = []
    for k, f in enumerate(features[:14]):
        corners = apply(T_map_cad, f.corners_cad) + rng.normal(0.0, 0.02, (4, 3))
        obs.append(Observation(f.type, corners.mean(axis=0), None if k % 3 == 2 else corners))
    obs.append(Observation("door", apply(T_map_cad, np.array([15.0, 15.0, 1.0])), None))
    gravity_map = T_map_cad[:3, :3] @ np.array([0.0, 0.0, -1.0]) if gravity else None
    prep = _prepare(ObservationSet(obs, gravity_map))
    T_cad_mp = invert(T_map_cad) @ invert(prep.T_mp_m)
    return rng, index, prep, T_cad_mp


@pytest.mark.parametrize("gravity", [True, False])
def test_refining_poses_together_gives_each_its_own_result(gravity: bool) -> None:
    rng, index, prep, T_true = _scene(3, gravity)
    params = RobustParams()
    axis = np.array([0.0, 0.0, 1.0]) if gravity else np.array([0.6, -0.3, 0.74])
    turn = lambda a: make_T(Rotation.from_rotvec(a * axis).as_matrix(), np.zeros(3))  # noqa: E731
    starts = [T_true @ make_T(np.eye(3), [0.1, -0.05, 0.0]) @ turn(0.004),  # near the truth: refined onto it
              T_true @ turn(2.0) @ make_T(np.eye(3), [5.0, 0.0, 0.0]),  # elsewhere
              make_T(np.eye(3), [1e3, 0.0, 0.0])]  # nothing near: stays where it is
    together = _refine_all(starts, prep, index, params)
    for start, pose in zip(starts, together, strict=True):
        (alone,) = _refine_all([start], prep, index, params)
        np.testing.assert_allclose(pose.T, alone.T, atol=1e-12)
        np.testing.assert_array_equal(pose.inliers, alone.inliers)
        assert pose.score == pytest.approx(alone.score, abs=1e-9)
    np.testing.assert_allclose(together[0].T, T_true, atol=0.03)
    assert together[0].inliers.sum() == 14  # the false door explains nothing
    np.testing.assert_array_equal(together[2].T, starts[2])
    assert together[2].score == 0.0


def test_nearest_of_both_kinds_in_one_query_equals_two_queries() -> None:
    """Also where more features of the other type than `NEAREST_ANY` lie nearer than the nearest of the same."""
    rng, index, _, _ = _scene(5)
    windows = index.centroids[index.type_codes == 1]
    points = np.concatenate([rng.uniform(-1.0, 31.0, (500, 3)), windows + rng.normal(0.0, 0.2, windows.shape)])
    types = rng.integers(0, 2, len(points)).astype(np.int8)
    for tau in (0.3, 0.45, 3.0, 12.0):
        d_same, j_same, d_any, j_any = _nearest_both(points, types, index, tau)
        d_s, j_s = _nearest_same_type(points, types, index, upper_m=tau)
        d_a, j_a = index.tree_all.query(points, distance_upper_bound=tau)
        np.testing.assert_array_equal(d_same, d_s)
        np.testing.assert_array_equal(j_same, j_s)
        np.testing.assert_array_equal(d_any, d_a)
        np.testing.assert_array_equal(j_any, j_a)
    # a batch shape (H, N, 3) comes back as (H, N)
    s, j = _explain(points[:60].reshape(4, 15, 3), types[:15], index, 0.45, 0.5)
    assert s.shape == j.shape == (4, 15)


def _distinct_top_one_by_one(order, moved, params, rotations=None, kept=(), limit=None) -> list[int]:
    """The rule of `_distinct_top` written as a plain loop over the hypotheses."""
    limit = params.refine_top if limit is None else limit
    chosen, chosen_R, chosen_m = [], [R for R, _ in kept], [m for _, m in kept]
    for h in order:
        if len(chosen) == limit:
            break
        alike = [np.linalg.norm(m - moved[h], axis=1).mean() <= params.distinct_m / 2
                 and (rotations is None
                      or (np.trace(R.T @ rotations[h]) - 1.0) / 2.0 >= np.cos(np.radians(params.distinct_deg)))
                 for R, m in zip(chosen_R if rotations is not None else [None] * len(chosen_m), chosen_m,
                                 strict=True)]
        if any(alike):
            continue
        chosen.append(int(h))
        chosen_m.append(moved[h])
        chosen_R.append(None if rotations is None else rotations[h])
    return chosen


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distinct_top_keeps_the_best_of_each_group_of_alike_hypotheses(seed: int) -> None:
    """Clusters of near-identical hypotheses (some only turned): the first of each, as the plain loop keeps them."""
    rng = np.random.default_rng(seed)
    params = RobustParams()
    c = rng.uniform(-5.0, 5.0, (20, 3))
    R, t = [], []
    for _ in range(40):
        yaw, shift = rng.uniform(-np.pi, np.pi), rng.uniform(-3.0, 3.0, 3)
        for _ in range(rng.integers(1, 6)):
            R.append(rot_z(yaw + rng.choice([0.0, rng.normal(0.0, 0.15)])))
            t.append(shift + rng.normal(0.0, 0.1, 3))
    R, t = np.array(R), np.array(t)
    moved = np.einsum("hij,nj->hni", R, c) + t[:, None, :]
    order = rng.permutation(len(R))
    kept = [(R[order[3]], moved[order[3]] + 0.05)]
    for rotations in (None, R):
        for limit in (6, 40, len(R)):
            assert _distinct_top(order, moved, params, rotations, kept, limit) == \
                _distinct_top_one_by_one(order, moved, params, rotations, kept, limit)


def test_a_yaw_fit_of_many_point_sets_at_once_drops_the_points_of_weight_zero() -> None:
    from macroloc.graph.rigid import weighted_rigid_fit, weighted_rigid_fits, yaw_rigid_fits

    rng = np.random.default_rng(7)
    src = rng.uniform(-5.0, 5.0, (3, 12, 3))
    T = [random_T(rng, 5.0, yaw_only=True) for _ in range(3)]
    dst = np.stack([apply(T[k], src[k]) + rng.normal(0.0, 0.05, (12, 3)) for k in range(3)])
    w = (rng.random((3, 12)) < 0.6).astype(float)
    w[:, :4] = 1.0
    yaw_all, full_all = yaw_rigid_fits(src, dst, w), weighted_rigid_fits(src, dst, w)
    for k in range(3):
        keep = w[k] > 0
        np.testing.assert_allclose(yaw_all[k], yaw_rigid_fit(src[k][keep], dst[k][keep]), atol=1e-12)
        np.testing.assert_allclose(full_all[k], weighted_rigid_fit(src[k][keep], dst[k][keep]), atol=1e-12)


def test_poses_differ_when_they_move_the_anchor_apart_or_turn() -> None:
    from macroloc.graph.rigid import rotation_angle_deg
    from macroloc.graph.robust import _distinct_T

    rng = np.random.default_rng(11)
    params = RobustParams()
    anchor = rng.uniform(-4.0, 4.0, (9, 3))
    B = random_T(rng, 5.0)
    A = np.stack([B @ make_T(rot_z(rng.normal(0.0, 0.1)), rng.normal(0.0, 0.4, 3)) for _ in range(200)])
    one_by_one = [np.linalg.norm(apply(a, anchor) - apply(B, anchor), axis=1).mean() > params.distinct_m
                  or rotation_angle_deg(a[:3, :3] @ B[:3, :3].T) > params.distinct_deg for a in A]
    assert 20 < sum(one_by_one) < 180  # both kinds are in the sample
    np.testing.assert_array_equal(_distinct_T(A, B, anchor, params), one_by_one)
