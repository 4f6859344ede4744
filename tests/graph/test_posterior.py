"""The generative model of observations and the posterior over poses (graph/posterior.py, issue 58).

Issue 38's two look-alike situations, each decided by the stated probabilities with the arithmetic checked by hand:
a false detection that coincides with a door only the rival storey has, and a door the rival storey has in view
that nobody saw. And a symmetric building (the duplex) stays `ambiguous` at any number of observations."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.model_index import ModelIndex, index_for
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.params import ObservationModel, RobustParams
from macroloc.graph.posterior import (
    Sigmas,
    _within_hull,  # the in-view test's kernel, tested directly
    decide,
    features_in_view,
    pose_evidence,
    posterior,
)
from macroloc.graph.rectangle import opening_rectangle
from macroloc.graph.registration import register
from macroloc.graph.rigid import apply, invert, make_T
from macroloc.graph.verify import observed_shapes
from tests.graph.helpers import box_vertices, random_building, random_T

MODEL = ObservationModel(wall_per_feature_m=3.0)  # the wall per feature given, not measured: the arithmetic by hand


def _yaw_T(yaw_deg: float, t) -> np.ndarray:
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return make_T(R, np.asarray(t, dtype=float))


def _door(fid: str, centre_xy, normal_xy, storey: str, z0: float) -> MacroFeature:
    r = opening_rectangle(box_vertices(np.array([*centre_xy, z0 + 1.05]), normal_xy, 0.9, 2.1))
    return MacroFeature(fid, "door", storey, r.corners, r.centroid, r.normal, r.width_m, r.height_m)


def _moved(f: MacroFeature, S: np.ndarray, fid: str, storey: str) -> MacroFeature:
    return MacroFeature(fid, f.type, storey, apply(S, f.corners_cad), apply(S, f.centroid_cad),
                        S[:3, :3] @ f.normal_cad, f.width_m, f.height_m)


def _observe(features: list[MacroFeature], T_map_cad: np.ndarray) -> list[Observation]:
    """Noise-free observations (corners in another order, the map frame)."""
    return [Observation(f.type, apply(T_map_cad, f.centroid_cad), apply(T_map_cad, f.corners_cad[[2, 0, 3, 1]]))
            for f in features]


def _storey_pair() -> tuple[list[MacroFeature], list[MacroFeature], np.ndarray, MacroFeature]:
    """Storey L1 (24 features at random) and L2, L1 turned 180 degrees about (10, 10) and 3 m up, plus one door X on
    L2 that L1 lacks, near the image of the seen features' middle (in view there: the tests check it) and at least
    1.5 m from every feature (the first such spot on a 0.5 m grid, nearest first)."""
    rng = np.random.default_rng(5)
    lower = random_building(rng, n=24, size_m=20.0)
    S = _yaw_T(180.0, (20.0, 20.0, 3.0))  # L1 -> L2
    upper = [_moved(f, S, f.id + "'", "L2") for f in lower]
    middle = apply(S, np.mean([f.centroid_cad for f in _seen(lower)], axis=0))[:2]
    grid = [np.array([dx, dy]) for dx in np.arange(-3.0, 3.01, 0.5) for dy in np.arange(-3.0, 3.01, 0.5)]
    spot = next(middle + d for d in sorted(grid, key=lambda d: float(np.linalg.norm(d)))
                if min(np.linalg.norm(f.centroid_cad[:2] - middle - d) for f in upper) > 1.5)
    return lower, upper, S, _door("X", spot, (1, 0), "L2", 3.0)


def _seen(lower: list[MacroFeature]) -> list[MacroFeature]:
    """The 8 features of L1 nearest its first."""
    return sorted(lower, key=lambda f: float(np.linalg.norm(f.centroid_cad[:2] - lower[0].centroid_cad[:2])))[:8]


def _perfect_match_over_false(sig: Sigmas, model: ObservationModel, index: ModelIndex, z_cad: float,
                              sides: tuple[float, float]) -> float:
    """log [density of an observation matched with zero residuals, same type / density of a false detection at
    height z_cad (CAD) with these sides], by hand from the module doc: (1 - p_miss)(1 - p_swap) N3(0; s_c)
    N(0; s_s)^2 N_sphere(0; s_n) over f / (W 2) N1(0; s_c) N_sphere(0; s_n) (a mean_m [N(z - z_m; s_c)
    N(short - short_m; s_s) N(long - long_m; s_s)] + (1 - a) / (band x size area)), m the building's features, a
    the alike share; the normal's peak cancels."""
    m = model
    match = (np.log((1 - m.miss_probability) * (1 - m.swap_probability)) - 1.5 * np.log(2 * np.pi)
             - 3 * np.log(sig.centroid_m) - np.log(2 * np.pi) - 2 * np.log(sig.size_m))
    gauss = lambda r, s: np.exp(-0.5 * (r / s) ** 2) / (np.sqrt(2 * np.pi) * s)  # noqa: E731
    short, long_ = min(sides), max(sides)
    alike = np.mean([gauss(z_cad - c[2], sig.centroid_m) * gauss(short - min(u, v), sig.size_m)
                     * gauss(long_ - max(u, v), sig.size_m)
                     for c, u, v in zip(index.centroids, index.len_u, index.len_v, strict=True)])
    shape = m.false_alike_fraction * alike + (1 - m.false_alike_fraction) / (m.false_band_m * m.false_size_area_m2)
    false = (np.log(m.false_detection_fraction / (m.wall_per_feature_m * 2.0)) - 0.5 * np.log(2 * np.pi)
             - np.log(sig.centroid_m) + np.log(shape))
    return float(match - false)


def test_decide_names_the_best_the_poses_sharing_the_mass_or_none() -> None:
    assert decide(np.array([0.995, 0.005]), 0.01) == ("localized", [0])
    assert decide(np.array([0.3, 0.6, 0.05]), 0.01) == ("not_localized", [])
    assert decide(np.array([0.3, 0.6, 0.05]), 0.05) == ("ambiguous", [1, 0, 2])
    assert decide(np.array([0.55, 0.449]), 0.01) == ("ambiguous", [0, 1])
    p, none = posterior(np.array([0.0, np.log(3.0)]), np.log(1e-9))
    assert p == pytest.approx([0.25, 0.75], rel=1e-6) and none == pytest.approx(1e-9 / 4, rel=1e-3)


def test_a_false_detection_on_the_door_only_the_rival_storey_has_is_weighed_as_rare() -> None:
    """The seen 8 features of L1 plus a false detection exactly where the door X, which only L2 has, lands under
    the rival pose (L2): the rival explains all 9, the truth 8 and one false detection. Both predict every feature
    in view seen. So P(rival) / P(truth) = the density of a perfect match over a false detection's there (hand
    arithmetic, `_perfect_match_over_false`; the false detection looks like one of the building's doors, so only
    its place along the wall is the rare part): about e^8.3, P(rival) = 0.99975. The rule follows the number and
    names the rival: a false detection that lands within the noise of a door only the rival storey has is a
    coincidence this rare, and the answer is then wrong that rarely (the harness's figures, docs/measurements.md)."""
    lower, upper, S, extra = _storey_pair()
    index = ModelIndex.build(lower + upper + [extra])
    seen = _seen(lower)
    T_map_cad = _yaw_T(40.0, (3.0, -2.0, 0.0))
    obs = _observe(seen, T_map_cad) + _observe([extra], T_map_cad @ invert(S))  # at S^-1(X), on nothing in L1
    shapes = observed_shapes(obs, np.zeros(len(obs), dtype=np.int8))
    truth, rival = invert(T_map_cad), S @ invert(T_map_cad)
    ev = pose_evidence(np.stack([truth, rival]), shapes, index, MODEL)
    assert list(ev.missed) == [0, 0]
    assert list((ev.match >= 0).sum(axis=1)) == [8, 9]
    sig = Sigmas.of(shapes, MODEL)
    fp_truth_cad = apply(invert(S), extra.centroid_cad)  # where the truth puts the false detection: L1, nothing there
    ratio = _perfect_match_over_false(sig, MODEL, index, float(fp_truth_cad[2]), (extra.width_m, extra.height_m))
    assert ev.loglik[1] - ev.loglik[0] == pytest.approx(ratio, abs=0.02)  # the model's table rounds to 1 cm
    p, _ = posterior(ev.loglik, -np.inf)
    assert p[1] == pytest.approx(1.0 / (1.0 + np.exp(-ratio)), abs=1e-3)
    assert ratio > np.log((1 - MODEL.epsilon) / MODEL.epsilon)  # e^8.3: P(rival) = 0.99975
    assert decide(p, MODEL.epsilon) == ("localized", [1])


def test_a_door_the_rival_storey_has_in_view_that_nobody_saw_costs_the_rival_the_miss_rate() -> None:
    """The same 8 features seen, no false detection; the rival storey L2 has the door X in the middle of what
    they survey. Both poses explain all 8 alike; the rival predicts X in view and unseen: P(truth) / P(rival) =
    1 / p_miss, so P(truth) = 1 / (1 + p_miss) = 0.87: not enough to say localized, and not a guess either:
    `ambiguous`, the two poses named. Each such door seen nowhere divides the rival by p_miss again."""
    lower, upper, S, extra = _storey_pair()
    index = ModelIndex.build(lower + upper + [extra])
    seen = _seen(lower)
    T_map_cad = _yaw_T(40.0, (3.0, -2.0, 0.0))
    obs = _observe(seen, T_map_cad)
    shapes = observed_shapes(obs, np.zeros(len(obs), dtype=np.int8))
    ev = pose_evidence(np.stack([invert(T_map_cad), S @ invert(T_map_cad)]), shapes, index, MODEL)
    assert list(ev.missed) == [0, 1]
    assert ev.loglik[0] - ev.loglik[1] == pytest.approx(-np.log(MODEL.miss_probability), abs=1e-6)
    p, _ = posterior(ev.loglik, -np.inf)
    assert p[0] == pytest.approx(1.0 / (1.0 + MODEL.miss_probability), rel=1e-9)
    assert decide(p, MODEL.epsilon) == ("ambiguous", [0, 1])
    # the registration, deciding by the posterior, says the same
    r = register(BuildingModel("pair", "test-storey-pair-x", lower + upper + [extra]),
                 ObservationSet(obs, np.array([0.0, 0.0, -1.0])), params=replace(RobustParams(), decision="posterior"))
    assert r.status == "ambiguous", r.posterior
    probs = sorted(q["probability"] for q in r.posterior["poses"])[::-1]
    assert probs[0] == pytest.approx(1.0 / (1.0 + MODEL.miss_probability), abs=1e-3)


@pytest.mark.parametrize("k", [3, 5, 8, 12, None])
def test_the_duplex_stays_ambiguous_at_any_number_of_observations(duplex_model, k: int | None) -> None:
    """The duplex is 180-degree symmetric on every storey: whatever part of a storey is seen, the pose and its turn
    explain it alike, and the posterior splits between them however many doors and windows come in."""
    rng = np.random.default_rng(58 + (k or 0))
    level2 = [f for f in duplex_model.features if f.storey == "Level 2"]
    for _ in range(2):
        chosen = level2 if k is None else [level2[i] for i in rng.choice(len(level2), k, replace=False)]
        T = random_T(rng, yaw_only=True)
        obs = _observe(chosen, T)
        r = register(duplex_model, ObservationSet(obs, T[:3, :3] @ np.array([0.0, 0.0, -1.0])),
                     params=replace(RobustParams(), decision="posterior"))
        assert r.status == "ambiguous", (k, r.posterior)
        probs = [q["probability"] for q in r.posterior["poses"]]
        assert probs[0] < 1.0 - MODEL.epsilon and len(probs) >= 2 and sum(probs) >= 1.0 - MODEL.epsilon


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=30, deadline=None)
def test_in_view_is_within_the_margin_of_the_hull_as_qhull_gives_it(seed: int) -> None:
    """The in-view test's hull (a monotone chain) gives qhull's half-planes: the same points within the margin."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(int(rng.integers(3, 30)), 2)) * 5.0
    query = rng.normal(size=(300, 2)) * 7.0
    hull = ConvexHull(points)
    expected = np.all(query @ hull.equations[:, :2].T + hull.equations[:, 2] <= 0.5, axis=1)
    assert (_within_hull(points, query, 0.5) == expected).all()


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=20, deadline=None)
def test_the_hull_kept_for_a_matched_set_gives_the_features_in_view_of_each_pose(seed: int) -> None:
    """`features_in_view` with one search's hull cache: for level poses (the cached hull moved with the pose) and
    tilted ones (a hull of their own) the same features as without it."""
    rng = np.random.default_rng(seed)
    features = random_building(rng, 40)
    index = index_for(BuildingModel("random", f"test-hull-cache-{seed}", features))
    shapes = observed_shapes(_observe(features[:12], np.eye(4)), np.zeros(12, dtype=np.int8))
    matched = rng.random(12) < 0.7
    matched[:3] = True
    hulls: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
    for k in range(6):
        T = _yaw_T(float(rng.uniform(-180, 180)), rng.normal(size=3)) if k % 3 else random_T(rng)
        expected = features_in_view(T, matched, shapes, index, MODEL)
        assert np.array_equal(features_in_view(T, matched, shapes, index, MODEL, hulls), expected)
    assert len(hulls) == 1


def test_in_view_of_collinear_observations_is_a_strip_about_their_segment() -> None:
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    assert list(_within_hull(line, np.array([[1.0, 0.4], [1.0, 0.6], [2.4, 0.0], [2.6, 0.0]]), 0.5)) == [
        True, False, True, False]
