"""The surface check (graph.surfaces) and how the localizer uses it to choose among candidate poses.

The room: a 12 x 7 m box with a 4 m partition from one wall, walls 3 m tall, floor and ceiling; the walls are
sampled for the check, the floor and ceiling apart, for fitting heights. Depth points are what a camera in the
room sees of the walls (and of the floor); `seen_points` casts the camera's lines of sight, for the checks that
ask what it could not have seen.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from macroloc.graph.features import BuildingModel
from macroloc.graph.localizer import Estimate, Localizer, LocalizerParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import FirstOfRegistrar, ModelRegistrar, Registrar
from macroloc.graph.relocalize import Alignment
from macroloc.graph.rigid import apply, rotation_angle_deg
from macroloc.graph.surfaces import SurfaceIndex, SurfaceParams, WallVoxels, align_to_surfaces, band_points, floor_points
from tests.graph.scenes import corridor_model, door, make_T, rot_z, sightings_from

UP = np.array([0.0, 0.0, 1.0])


def quad(a, b, c, d) -> tuple[np.ndarray, np.ndarray]:
    return np.array([a, b, c, d], float), np.array([[0, 1, 2], [0, 2, 3]])


def wall(x0, y0, x1, y1, h=3.0):  # noqa: ANN001, ANN201
    return quad((x0, y0, 0), (x1, y1, 0), (x1, y1, h), (x0, y0, h))


def room_mesh() -> tuple[np.ndarray, np.ndarray]:
    parts = [wall(0, 0, 12, 0), wall(12, 0, 12, 7), wall(12, 7, 0, 7), wall(0, 7, 0, 0), wall(5, 0, 5, 4),
             quad((0, 0, 0), (12, 0, 0), (12, 7, 0), (0, 7, 0)), quad((0, 0, 3), (12, 0, 3), (12, 7, 3), (0, 7, 3))]
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.vstack(vertices), np.vstack(faces)


@pytest.fixture(scope="module")
def room() -> SurfaceIndex:
    return SurfaceIndex.from_mesh(*room_mesh(), SurfaceParams(spacing_m=0.05))


@pytest.fixture(scope="module")
def room_with_walls() -> SurfaceIndex:
    index = SurfaceIndex.from_mesh(*room_mesh(), SurfaceParams(spacing_m=0.05))
    index.walls = WallVoxels.from_mesh(*room_mesh())
    return index


# the room's walls seen from above: x0 y0 x1 y1
WALL_SEGMENTS = np.array([[0, 0, 12, 0], [12, 0, 12, 7], [12, 7, 0, 7], [0, 7, 0, 0], [5, 0, 5, 4]], float)



def seen_points(rng: np.random.Generator, camera_xy: np.ndarray, n: int = 150, z: float = 1.4,
                segments: np.ndarray = WALL_SEGMENTS) -> np.ndarray:
    """What a camera at `camera_xy` in the room (or the walls `segments`) measures around it (CAD): the nearest
    wall along random horizontal directions, at heights about its own."""
    a = rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.cos(a), np.sin(a)])
    nearest = np.full(n, np.inf)
    for x0, y0, x1, y1 in segments:
        e, w = np.array([x1 - x0, y1 - y0]), np.array([x0, y0]) - camera_xy
        den = d[:, 0] * e[1] - d[:, 1] * e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[0] * e[1] - w[1] * e[0]) / den  # along the line of sight
            s = (w[0] * d[:, 1] - w[1] * d[:, 0]) / den  # along the wall
        hit = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1) & (t < nearest)
        nearest[hit] = t[hit]
    xy = camera_xy + d * nearest[:, None]
    return np.column_stack([xy, z + rng.uniform(-0.4, 0.4, n)])


def wall_points(rng: np.random.Generator, n: int = 400, z: float = 1.4, n_walls: int = 5) -> np.ndarray:
    """Points on the walls at about camera height (CAD), as a camera turning in the room would measure them."""
    v, f = room_mesh()
    walls = v[f[: 2 * n_walls]]  # the walls' triangles (2 each)
    k = rng.integers(0, len(walls), n)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    p = (1 - s)[:, None] * walls[k, 0] + (s * (1 - r2))[:, None] * walls[k, 1] + (s * r2)[:, None] * walls[k, 2]
    p[:, 2] = z + rng.uniform(-0.4, 0.4, n)
    return p


def test_samples_cover_the_walls_only(room: SurfaceIndex) -> None:
    wall_area = 2 * (12 + 7) * 3.0 + 4 * 3.0  # each wall is one quad
    assert len(room) == pytest.approx(wall_area / 0.05**2, rel=0.02)
    assert np.abs(room.samples_cad[:, 2] - 1.5).max() <= 1.5 + 1e-9
    on_wall = ((np.abs(room.samples_cad[:, 0]) < 1e-9) | (np.abs(room.samples_cad[:, 0] - 12) < 1e-9)
               | (np.abs(room.samples_cad[:, 1]) < 1e-9) | (np.abs(room.samples_cad[:, 1] - 7) < 1e-9)
               | ((np.abs(room.samples_cad[:, 0] - 5) < 1e-9) & (room.samples_cad[:, 1] <= 4 + 1e-9)))
    assert on_wall.all()  # floor and ceiling (horizontal) are not among the walls' samples ...
    assert room.horizontal is not None  # ... but apart, every 0.2 m, for fitting heights
    _, floors, normals = room.horizontal
    assert len(floors) == pytest.approx(2 * 12 * 7 / 0.2**2, rel=0.05)
    assert np.allclose(np.minimum(np.abs(floors[:, 2]), np.abs(floors[:, 2] - 3.0)), 0.0)
    assert np.allclose(np.abs(normals[:, 2]), 1.0)


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), tx=st.floats(-20, 20), ty=st.floats(-20, 20), seed=st.integers(0, 1000))
def test_support_is_full_at_the_true_pose_in_any_map_frame(room: SurfaceIndex, yaw: float, tx: float, ty: float,
                                                          seed: int) -> None:
    """Points measured in an arbitrary map frame, moved back by the true T_cad_map, all lie on the walls."""
    points_cad = wall_points(np.random.default_rng(seed))
    T_map_cad = make_T(rot_z(yaw), np.array([tx, ty, 0.3]))
    points_map = apply(T_map_cad, points_cad)
    assert room.support(apply(np.linalg.inv(T_map_cad), points_map)) == 1.0


def test_supports_of_many_poses_at_once_are_each_poses_support(room: SurfaceIndex) -> None:
    rng = np.random.default_rng(4)
    points = wall_points(rng, 300)
    poses = [make_T(rot_z(a), np.array([dx, 0.0, 0.0])) for a, dx in ((0.0, 0.0), (0.2, 0.5), (1.0, 2.0))]
    sets = np.stack([apply(T, points) for T in poses])
    assert room.supports(sets) == pytest.approx([room.support(s) for s in sets])
    assert room.supports(sets)[0] == 1.0 and room.supports(sets)[2] < 0.9
    assert room.supports(np.zeros((0, 5, 3))).shape == (0,)


def test_support_falls_when_the_pose_is_off(room: SurfaceIndex) -> None:
    points = wall_points(np.random.default_rng(1))
    assert room.support(points) == 1.0
    for T in (make_T(np.eye(3), np.array([1.0, 0.0, 0.0])), make_T(np.eye(3), np.array([0.0, 1.0, 0.0])),
              make_T(rot_z(np.radians(10)), np.zeros(3))):
        assert room.support(apply(T, points)) < 0.7
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))  # the outer walls onto themselves
    assert 0.7 < room.support(apply(half_turn, points)) < 0.95  # only the partition's points tell
    assert room.support(np.zeros((0, 3))) == 0.0


def test_a_point_behind_a_wall_is_seen_through_it(room_with_walls: SurfaceIndex) -> None:
    """Points on the far wall (x = 12 m) behind the partition (x = 5 m, y < 4 m): on a surface, but a camera in
    the partition's pocket cannot see them; from the other side of the partition it can."""
    walls = room_with_walls.walls
    assert walls is not None
    far = np.column_stack([np.full(50, 12.0), np.linspace(0.5, 3.5, 50), np.full(50, 1.4)])
    pocket, open_side = np.array([2.0, 2.0, 1.4]), np.array([8.0, 2.0, 1.4])
    assert walls.seen_through(np.tile(pocket, (50, 1)), far).all()
    assert not walls.seen_through(np.tile(open_side, (50, 1)), far).any()
    on_far = room_with_walls.check(far, np.tile(pocket, (50, 1)))
    assert on_far.support == 1.0 and on_far.seen_through == 1.0 and on_far.score == 0.0
    assert room_with_walls.check(far).score == 1.0  # without the cameras: support alone
    # past the partition's end (y > 4 m) the line of sight is free
    past = np.column_stack([np.linspace(8.0, 11.0, 20), np.full(20, 7.0), np.full(20, 1.4)])
    assert not walls.seen_through(np.tile([2.0, 3.5, 1.4], (20, 1)), past).any()
    # a point measured a little behind its wall (depth noise) is not seen through it; a metre behind, it is
    camera = np.array([[10.0, 3.0, 1.4]])
    assert not walls.seen_through(camera, np.array([[12.1, 3.0, 1.4]])).any()
    assert walls.seen_through(camera, np.array([[13.0, 3.0, 1.4]])).all()


def test_support_allows_for_the_depth_noise_of_far_points_and_the_score_does_not(room_with_walls: SurfaceIndex) -> None:
    """A far wall measured 1.5 sigmas of stereo depth noise short (11 m away: sigma 0.6 m) is still on the model's
    surface by `support` (the check's absolute test: is this pose consistent with what was measured?), not by
    `score` (its comparison of poses, as sharp as the near points allow). A near point as far off its wall is off
    by both."""
    p = room_with_walls.params
    camera = np.array([1.0, 5.5, 1.4])
    wall_points = np.column_stack([np.full(30, 12.0), np.linspace(4.6, 6.4, 30), np.full(30, 1.4)])
    ray = wall_points - camera
    r = np.linalg.norm(ray, axis=1, keepdims=True)
    short = wall_points - ray / r * 1.5 * p.depth_sigma_per_m2 * r**2
    origins = np.tile(camera, (len(short), 1))
    far = room_with_walls.check(short, origins)
    assert far.support == 1.0 and far.seen_through == 0.0 and far.score == 0.0
    assert room_with_walls.check(wall_points, origins).score == 1.0
    assert room_with_walls.check(short).support == 0.0  # without the cameras no range is known: the fixed tolerance
    near_camera = np.array([10.0, 5.5, 1.4])
    off = np.column_stack([np.full(30, 11.4), np.linspace(4.6, 6.4, 30), np.full(30, 1.4)])  # 0.6 m short of x = 12
    near = room_with_walls.check(off, np.tile(near_camera, (len(off), 1)))
    assert near.support == 0.0 and near.score == 0.0


@settings(max_examples=20, deadline=None)
@given(x=st.floats(5.5, 11.5), y=st.floats(0.5, 6.5), noise=st.floats(0.0, 1.0), seed=st.integers(0, 1000))
def test_what_a_camera_sees_is_never_seen_through_a_wall(room_with_walls: SurfaceIndex, x: float, y: float,
                                                         noise: float, seed: int) -> None:
    """Anywhere in the room, the points a camera measures (with up to one sigma of depth noise along the line of
    sight) lie on surfaces and in sight, and a pose a metre off is seen through walls for some of them. (A line of
    sight that passes the partition's end within a voxel's diagonal may be taken for one through it, and only
    such a line: a few in a hundred, more the nearer the camera is to that end.)"""
    rng = np.random.default_rng(seed)
    points = seen_points(rng, np.array([x, y]), 300)
    origins = np.tile([x, y, 1.4], (len(points), 1))
    check = room_with_walls.check(points, origins)
    grazing = _passes_near(origins[:, :2], points[:, :2], np.array([5.0, 4.0]), 0.15)
    assert not np.any(seen_through(room_with_walls, points, origins) & ~grazing) and check.support > 0.95
    off = make_T(rot_z(0.5), np.array([1.0, 0.5, 0.0]))
    assert room_with_walls.check(apply(off, points), apply(off, origins)).score < check.score - 0.2
    ray = points - origins
    r = np.linalg.norm(ray, axis=1, keepdims=True)
    sign = rng.choice([-1.0, 1.0], (len(points), 1))
    noisy = points + ray / r * noise * room_with_walls.params.depth_sigma_per_m2 * r**2 * sign
    assert not np.any(seen_through(room_with_walls, noisy, origins) & ~grazing)  # (support falls beyond 0.2 m of noise)


def seen_through(index: SurfaceIndex, points: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """(N,) bool: which points the index's check counts as seen through a wall."""
    assert index.walls is not None
    return index.walls.seen_through(origins, points, index.params.depth_sigma_per_m2, index.params.sight_margin_m)


def _passes_near(a: np.ndarray, b: np.ndarray, c: np.ndarray, within: float) -> np.ndarray:
    """(N,) bool: the segments a -> b (N, 2) pass within `within` of the point c (2,)."""
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", c - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return np.asarray(np.linalg.norm(a + t[:, None] * d - c, axis=1) < within)


def test_voxels_of_an_empty_model_block_nothing() -> None:
    walls = WallVoxels.from_mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert len(walls) == 0 and not walls.seen_through(np.zeros((3, 3)), np.ones((3, 3))).any()


def test_band_points_keep_the_camera_height_and_range() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(-10, 10, (20000, 3))
    kept = band_points(points, np.array([0.0, 0.0, 2.0]), half_height_m=0.5, max_range_m=8.0, max_points=10_000)
    assert len(kept) and np.abs(kept[:, 2]).max() <= 0.5 and np.linalg.norm(kept, axis=1).max() <= 8.0
    expected = (np.abs(points[:, 2]) <= 0.5) & (np.linalg.norm(points, axis=1) <= 8.0)
    assert len(kept) == expected.sum()
    assert len(band_points(points, UP, max_points=50)) == 50


# --- the localizer's choice among candidate poses --------------------------------------------------------------


class CandidatesRegistrar:
    """Answers every registration with the given candidate poses (T_cad_map, inliers), as 'ambiguous' or, for
    `localized`, naming the first one; tries from 2 landmarks, trusts from 4."""

    min_landmarks = 4
    candidates_from = 2

    def __init__(self, candidates: list[np.ndarray], localized: bool = False) -> None:
        self.candidates = candidates
        self.localized = localized
        self.calls = 0

    def __call__(self, landmarks, corners_map) -> Alignment:  # noqa: ANN001
        self.calls += 1
        status = "localized" if self.localized else "ambiguous"
        return Alignment(status, self.candidates[0], [], len(landmarks), [(T, len(landmarks))
                                                                           for T in self.candidates])


T_TRUE = make_T(np.eye(3), np.array([2.0, 3.5, 0.0]))  # T_cad_map: the flight starts 2 m into the room
T_WRONG = make_T(rot_z(0.35), np.array([3.0, 2.0, 0.0]))  # 20 degrees and a metre or so off


def fly_in_room(room: SurfaceIndex | None, registrar: Registrar, with_points: bool = True,
                n_walls: int = 5, **params: float) -> Localizer:
    """Three keyframes that see two doors of a corridor model (the registrar ignores where they are) and the
    room's walls around the flight; `params`: LocalizerParams beside the defaults."""
    model = corridor_model()
    rng = np.random.default_rng(3)
    loc = Localizer(model, PoseGraph(), registrar, LocalizerParams(surface_min_points=100, **params),  # type: ignore[arg-type]
                    surfaces=room)
    T_cad_body_doors = make_T(np.eye(3), np.array([1.0, 0.0, 1.4]))  # where two doors are in view
    for k in range(3):
        T_map_body = make_T(np.eye(3), np.array([0.1 * k, 0.0, 1.4]))
        T_cad_body = T_TRUE @ T_map_body
        points_cad = wall_points(rng, 150, n_walls=n_walls)
        points_body = apply(np.linalg.inv(T_cad_body), points_cad) if with_points else None
        sightings = sightings_from(model, T_cad_body_doors)[:2]
        loc.add_keyframe(k * 100_000_000, T_map_body, sightings, UP, points_body=points_body)
    return loc


def test_the_walls_choose_the_true_candidate(room: SurfaceIndex) -> None:
    for order in ([T_WRONG, T_TRUE], [T_TRUE, T_WRONG]):
        loc = fly_in_room(room, CandidatesRegistrar(order))
        assert loc.status == "localized"
        T_cad_map = loc.graph.T_cad_map()
        assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05
        assert loc.judge.checks and max(loc.judge.checks[-1][1]) == 1.0


def test_two_landmarks_without_depth_stay_ambiguous(room: SurfaceIndex) -> None:
    registrar = CandidatesRegistrar([T_WRONG, T_TRUE])
    assert fly_in_room(room, registrar, with_points=False).status == "exploring"  # 4 landmarks needed
    assert registrar.calls == 0
    assert fly_in_room(None, CandidatesRegistrar([T_WRONG, T_TRUE])).status == "exploring"


def test_walls_that_cannot_tell_the_candidates_apart_leave_it_ambiguous() -> None:
    """A box room without the partition is the same after a half-turn about its centre (like the duplex):
    both poses put every point on a wall, and the status stays ambiguous."""
    v, f = room_mesh()
    box = SurfaceIndex.from_mesh(v, f[:8], SurfaceParams(spacing_m=0.05))  # the 4 outer walls
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    loc = fly_in_room(box, CandidatesRegistrar([T_TRUE, half_turn @ T_TRUE]), n_walls=4)
    assert loc.judge.checks[-1][1] == [1.0, 1.0]
    assert loc.status == "ambiguous" and loc.graph.T_cad_map() is None
    same = T_TRUE @ make_T(np.eye(3), np.array([0.0, 0.0, 0.1]))  # 0.1 m apart: one pose, not a rival
    assert fly_in_room(box, CandidatesRegistrar([T_TRUE, same]), n_walls=4).status == "localized"


@pytest.mark.parametrize(("margin_unfit", "status"), [(0.15, "localized"), (0.2, "localized"),
                                                      (0.25, "ambiguous"), (0.3, "ambiguous")])
def test_a_rival_the_walls_do_not_fit_blocks_only_within_its_own_margin(room: SurfaceIndex, margin_unfit: float,
                                                                        status: str) -> None:
    """The room half-turned about its centre keeps the outer walls and loses the partition: that pose puts the
    partition's points (a fifth) off every wall, so it scores 0.77 against the true pose's 1.0 and does not fit
    the walls itself (support below 0.9). It rivals the true pose only within `surface_margin_unfit` (here the
    demo's seed 1 with perception: a corridor 18.6 m along, 0.71-0.86 of its points on the walls)."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    loc = fly_in_room(room, CandidatesRegistrar([half_turn @ T_TRUE, T_TRUE]), surface_margin_unfit=margin_unfit)
    assert sorted(loc.judge.checks[-1][1]) == pytest.approx([0.77, 1.0], abs=0.03)
    assert loc.status == status
    if status == "localized":
        T_cad_map = loc.graph.T_cad_map()
        assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05


def test_candidates_from_one_door_keep_the_full_margin_against_a_rival_that_does_not_fit(room: SurfaceIndex) -> None:
    """From one door a candidate is coarse, and the true one may be the pose that fits badly (the duplex: 2.8 deg
    off, 42 % of its points seen through a wall, its twin at 0.994): there, every other candidate rivals within
    `surface_margin`, fitting or not."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    loc = fly_in_room(room, PartialRegistrar([half_turn @ T_TRUE, T_TRUE]), surface_margin_unfit=0.15)
    assert sorted(loc.judge.checks[-1][1]) == pytest.approx([0.77, 1.0], abs=0.03)
    assert loc.status == "ambiguous" and loc.graph.T_cad_map() is None


def test_a_stored_maps_candidates_the_walls_refuse_hand_over_to_the_model(room: SurfaceIndex) -> None:
    """Re-localization: the stored map's candidates are checked first; where the walls refuse them all (the
    flight is not where the stored map was made), the model's are checked in the same attempt."""
    stored, model = CandidatesRegistrar([T_WRONG]), CandidatesRegistrar([T_WRONG, T_TRUE])
    loc = fly_in_room(room, FirstOfRegistrar([stored, model]))
    assert loc.status == "localized" and stored.calls >= 1 and model.calls >= 1
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05


def test_stored_candidates_the_walls_confirm_need_no_model_search(room: SurfaceIndex) -> None:
    stored, model = CandidatesRegistrar([T_WRONG, T_TRUE]), CandidatesRegistrar([T_TRUE])
    loc = fly_in_room(room, FirstOfRegistrar([stored, model]))
    assert loc.status == "localized" and stored.calls >= 1 and model.calls == 0


class PartialRegistrar(CandidatesRegistrar):
    """As CandidatesRegistrar, its candidates explaining one landmark fewer than it is given (a stored map that
    lacks one of the doors seen)."""

    def __call__(self, landmarks, corners_map) -> Alignment:  # noqa: ANN001
        result = super().__call__(landmarks, corners_map)
        result.candidates = [(T, n - 1) for T, n in result.candidates]
        return result


def test_stored_candidates_the_walls_fit_alike_need_no_model_search() -> None:
    """Two stored candidates fit the walls alike and each explains every landmark: the model's candidates
    (every pose explaining as many) hold both, so searching it cannot settle it either. Where they explain
    fewer, the model's doors may: it is asked."""
    v, f = room_mesh()
    box = SurfaceIndex.from_mesh(v, f[:8], SurfaceParams(spacing_m=0.05))  # the 4 outer walls
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    stored, model = CandidatesRegistrar([T_TRUE, half_turn @ T_TRUE]), CandidatesRegistrar([T_TRUE])
    loc = fly_in_room(box, FirstOfRegistrar([stored, model]), n_walls=4)
    assert loc.status == "ambiguous" and stored.calls >= 1 and model.calls == 0
    partial = PartialRegistrar([T_TRUE, half_turn @ T_TRUE])
    loc = fly_in_room(box, FirstOfRegistrar([partial, model]), n_walls=4)
    assert loc.status == "localized" and partial.calls >= 1 and model.calls >= 1


def test_a_registrars_answer_the_walls_contradict_is_refused_and_the_next_one_asked(
        room_with_walls: SurfaceIndex) -> None:
    """A stored map's two doors matched to two other stored doors (Office_A seed 4 flown with seed 3's map):
    'localized' by the registrar, while under it half the points would have been seen through a wall. Refused,
    and the model's candidates are checked in the same attempt."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0])) @ T_TRUE
    alone = fly_seeing(room_with_walls, CandidatesRegistrar([half_turn], localized=True), NEAR_THE_PARTITION_END)
    assert alone.status == "ambiguous" and alone.graph.T_cad_map() is None
    stored, model = CandidatesRegistrar([half_turn], localized=True), CandidatesRegistrar([half_turn, T_TRUE])
    loc = fly_seeing(room_with_walls, FirstOfRegistrar([stored, model]), NEAR_THE_PARTITION_END)
    assert loc.status == "localized" and model.calls >= 1
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05


def fly_seeing(room: SurfaceIndex, registrar: CandidatesRegistrar, cameras_cad: list[np.ndarray],
               params: LocalizerParams | None = None) -> Localizer:
    """Keyframes at `cameras_cad` (x, y; the map frame is T_TRUE's) with what a camera there sees of the room,
    and two door sightings for the registrar (which ignores where they are)."""
    model = corridor_model()
    rng = np.random.default_rng(6)
    loc = Localizer(model, PoseGraph(), registrar, params or LocalizerParams(surface_min_points=100), surfaces=room)
    sightings = sightings_from(model, make_T(np.eye(3), np.array([1.0, 0.0, 1.4])))[:2]
    for k, xy in enumerate(cameras_cad):
        T_cad_body = make_T(np.eye(3), np.array([xy[0], xy[1], 1.4]))
        T_map_body = np.linalg.inv(T_TRUE) @ T_cad_body
        points_body = apply(np.linalg.inv(T_cad_body), seen_points(rng, np.asarray(xy, float)))
        loc.add_keyframe(k * 100_000_000, T_map_body, sightings, UP, points_body=points_body)
    return loc


NEAR_THE_PARTITION_END = [np.array([6.5, 6.0]), np.array([6.8, 5.7]), np.array([7.1, 5.4])]


def test_lines_of_sight_tell_apart_what_the_surfaces_cannot(room: SurfaceIndex,
                                                            room_with_walls: SurfaceIndex) -> None:
    """Near the partition's end, the half-turn about the room's centre puts >= 90 % of the points on walls too,
    within the margin of the true pose: by the surfaces alone the status stays ambiguous. Under it the camera
    would have seen a third of them through the partition, and the lines of sight settle it."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    loc = fly_seeing(room, CandidatesRegistrar([half_turn @ T_TRUE, T_TRUE]), NEAR_THE_PARTITION_END)
    assert loc.status == "ambiguous" and min(loc.judge.checks[-1][1]) >= 0.9
    loc = fly_seeing(room_with_walls, CandidatesRegistrar([half_turn @ T_TRUE, T_TRUE]), NEAR_THE_PARTITION_END)
    assert loc.status == "localized"
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05
    half_turn_score, true_score = loc.judge.checks[-1][1]
    assert true_score > 0.95 and half_turn_score < true_score - 0.3


def test_a_candidate_a_little_off_is_fitted_to_the_walls_before_the_check(room_with_walls: SurfaceIndex) -> None:
    """A pose from two doors' coarse corners, 0.3 m and 3 degrees off: a third of the points miss their walls,
    and as it stands the check cannot confirm it; fitted to the walls first, it is the true pose."""
    off = T_TRUE @ make_T(rot_z(np.radians(3.0)), np.array([0.3, -0.2, 0.0]))
    cameras = [np.array([8.0, 2.0]), np.array([8.3, 2.5]), np.array([8.6, 3.0])]
    unfitted = fly_seeing(room_with_walls, CandidatesRegistrar([off, T_WRONG]), cameras,
                          LocalizerParams(surface_min_points=100, surface_refine_m=0.0))
    assert unfitted.status == "ambiguous" and max(unfitted.judge.checks[-1][1]) < 0.9
    fitted = fly_seeing(room_with_walls, CandidatesRegistrar([off, T_WRONG]), cameras)
    assert fitted.status == "localized"
    T_cad_map = fitted.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05
    assert rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T) < 1.0  # from 3 (the graph has moved it since)


def test_a_localized_answer_the_walls_contradict_is_refused(room: SurfaceIndex) -> None:
    loc = fly_in_room(room, CandidatesRegistrar([T_WRONG, T_TRUE], localized=True))
    assert loc.status == "ambiguous" and loc.graph.T_cad_map() is None
    loc = fly_in_room(room, CandidatesRegistrar([T_TRUE, T_WRONG], localized=True))
    assert loc.status == "localized"


# --- point-to-plane fit of a keyframe's depth to the walls ------------------------------------------------------


@settings(max_examples=15, deadline=None)
@given(dx=st.floats(-0.2, 0.2), dy=st.floats(-0.2, 0.2), dyaw_deg=st.floats(-3, 3), seed=st.integers(0, 1000))
@example(dx=0.125, dy=0.0, dyaw_deg=3.0, seed=126)  # left 0.13 deg of pitch when each step's tilt was damped to 0
def test_fit_to_the_walls_recovers_a_perturbed_pose(room: SurfaceIndex, dx: float, dy: float, dyaw_deg: float,
                                                    seed: int) -> None:
    T_cad_body = make_T(rot_z(0.3), np.array([3.0, 2.5, 1.4]))
    points_body = apply(np.linalg.inv(T_cad_body), wall_points(np.random.default_rng(seed), 300))
    guess = T_cad_body @ make_T(rot_z(np.radians(dyaw_deg)), np.array([dx, dy, 0.0]))
    fit = align_to_surfaces(room, points_body, guess)
    assert fit is not None and fit.inliers == 300
    assert np.linalg.norm(fit.T_cad_body[:3, 3] - T_cad_body[:3, 3]) < 0.01
    assert rotation_angle_deg(fit.T_cad_body[:3, :3] @ T_cad_body[:3, :3].T) < 0.1
    # vertical walls fix x, y and yaw, not the height: (almost) no information along z
    cov = np.linalg.inv(fit.information)
    assert np.sqrt(cov[5, 5]) > 100 * np.sqrt(cov[3, 3])


def test_the_height_can_be_held_where_a_sloped_face_would_set_it_alone() -> None:
    """The walls hardly see the height; a few sloped faces (a roof's underside, a stair's stringer) then set it
    alone, and a wrong match to one moves it by tenths (Jasmin-Sun seed 5: a candidate pose fitted 0.54 m too
    high, held by the graph for 4 s). `hold_height` keeps the initial pose's height."""
    v, f = room_mesh()
    slope = quad((6, 6.9, 1.0), (11, 6.9, 1.0), (11, 6.15, 2.0), (6, 6.15, 2.0))  # 53 deg, by the far wall
    index = SurfaceIndex.from_mesh(np.vstack([v, slope[0]]), np.vstack([f, slope[1] + len(v)]),
                                   SurfaceParams(spacing_m=0.05))
    T_cad_body = make_T(np.eye(3), np.array([8.0, 3.0, 1.4]))
    rng = np.random.default_rng(0)
    on_slope = np.column_stack([rng.uniform(6.5, 10.5, 40), np.full(40, 6.525), np.full(40, 1.5)])
    points_cad = np.vstack([wall_points(rng, 300), on_slope + [0.0, 0.0, 0.3]])  # seen 0.3 m higher than modelled
    points_body = apply(np.linalg.inv(T_cad_body), points_cad)
    free = align_to_surfaces(index, points_body, T_cad_body)
    held = align_to_surfaces(index, points_body, T_cad_body, hold_height=True)
    assert free is not None and held is not None
    assert abs(free.T_cad_body[2, 3] - T_cad_body[2, 3]) > 0.2  # the sloped face alone moved it
    assert abs(held.T_cad_body[2, 3] - T_cad_body[2, 3]) < 0.001
    assert np.linalg.norm(held.T_cad_body[:2, 3] - T_cad_body[:2, 3]) < 0.05  # the walls hold x, y against its pull


def test_a_slabs_underside_is_no_floor() -> None:
    """A 0.2 m slab: its top is open above, its underside is covered by the slab itself and is left out (a point
    on the floor would otherwise find it before the top's next sample and be pulled 0.2 m down)."""
    top = quad((0, 0, 0), (6, 0, 0), (6, 5, 0), (0, 5, 0))
    bottom = quad((0, 0, -0.2), (0, 5, -0.2), (6, 5, -0.2), (6, 0, -0.2))
    index = SurfaceIndex.from_mesh(np.vstack([top[0], bottom[0]]), np.vstack([top[1], bottom[1] + 4]))
    assert index.horizontal is not None
    heights = index.horizontal[1][:, 2]
    assert len(heights) == pytest.approx(30 / 0.2**2, rel=0.1)
    assert np.mean(np.abs(heights) > 1e-9) < 0.01  # (a sample or two by the edge may find no top within 0.4 m)


def floor_points_cad(rng: np.random.Generator, n: int = 150) -> np.ndarray:
    """Points on the floor (z = 0) ahead of a camera at (3, 2.5) looking along yaw 0.3 rad, 1-4 m away."""
    r, a = rng.uniform(1.0, 4.0, n), rng.uniform(-0.5, 0.5, n) + 0.3
    return np.column_stack([3.0 + r * np.cos(a), 2.5 + r * np.sin(a), np.zeros(n)])


@settings(max_examples=15, deadline=None)
@given(dx=st.floats(-0.2, 0.2), dz=st.floats(-0.2, 0.2), dyaw_deg=st.floats(-3, 3), seed=st.integers(0, 1000))
def test_the_floor_fixes_the_height(room: SurfaceIndex, dx: float, dz: float, dyaw_deg: float, seed: int) -> None:
    """Floor points with the walls' (floor_points picks them by their height below the camera): the fit
    recovers a perturbed height as well, and now carries information along z."""
    rng = np.random.default_rng(seed)
    T_cad_body = make_T(rot_z(0.3), np.array([3.0, 2.5, 1.4]))
    seen_body = apply(np.linalg.inv(T_cad_body), np.vstack([wall_points(rng, 300), floor_points_cad(rng)]))
    below = floor_points(seen_body, UP, seed=seed)
    assert len(below) == 100 and np.allclose(apply(T_cad_body, below)[:, 2], 0.0)  # the floor's, at most 100
    band = band_points(seen_body, UP, seed=seed)
    guess = T_cad_body @ make_T(rot_z(np.radians(dyaw_deg)), np.array([dx, 0.0, dz]))
    fit = align_to_surfaces(room, band, guess, below)
    assert fit is not None
    assert np.linalg.norm(fit.T_cad_body[:3, 3] - T_cad_body[:3, 3]) < 0.01
    assert 1.0 / np.sqrt(fit.information[5, 5]) < 0.03  # the floor's points measure the height to cm
    walls_only = SurfaceIndex(room.samples_cad, room.params, room.normals_cad)  # no horizontal samples
    for fit in (align_to_surfaces(walls_only, band, guess, below), align_to_surfaces(room, band, guess)):
        assert fit is not None and abs(fit.T_cad_body[2, 3] - guess[2, 3]) < 0.005  # z stays where it was guessed
        assert fit.information[5, 5] < 1e-4 * fit.information[3, 3]  # and says (next to) nothing about it


def box_mesh(x0: float, x1: float, y0: float, y1: float, z0: float = 0.0,
             z1: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], float)  # 4 ix + 2 iy + iz
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, np.array([(a, b, c) for a, b, c, _ in quads] + [(a, c, d) for a, _, c, d in quads])


def test_a_face_behind_a_panel_is_neither_sampled_nor_fitted_to() -> None:
    """Office_A seed 12: a 5 cm panel stands 0.29 m in front of a 0.31 m wall. The wall's face behind the panel
    is seen by no camera, but sampled it made a second fit: the panel's points on it, the points of the wall
    beside the panel on the wall's far face, all 0.34 m deeper. Its samples are left out (the walls' voxels
    close it in on both sides); a pose 0.2-0.34 m off then fits back to the true one."""
    parts = [box_mesh(0, 4, 0.19, 0.50), box_mesh(1, 3, -0.15, -0.10, 0.3, 2.7), box_mesh(-0.2, 0.0, -4.0, 0.19)]
    v = np.vstack([p[0] for p in parts])
    f = np.vstack([p[1] + 8 * k for k, p in enumerate(parts)])
    walls = WallVoxels.from_mesh(v, f)
    every = SurfaceIndex.from_mesh(v, f, SurfaceParams(spacing_m=0.05))
    seen = SurfaceIndex.from_mesh(v, f, SurfaceParams(spacing_m=0.05), walls=walls)
    assert seen.walls is walls

    def on_face(index: SurfaceIndex, y: float, x0: float, x1: float) -> int:
        P = index.samples_cad
        return int(((np.abs(P[:, 1] - y) < 0.01) & (P[:, 0] > x0) & (P[:, 0] < x1) & (P[:, 2] > 0.6)
                    & (P[:, 2] < 2.4)).sum())

    assert on_face(every, 0.19, 1.3, 2.7) > 500 and on_face(seen, 0.19, 1.3, 2.7) == 0  # behind the panel
    for y, x0, x1 in ((0.19, 0.2, 0.7), (-0.15, 1.3, 2.7), (0.50, 1.3, 2.7)):  # beside it, its front, far face
        assert on_face(seen, y, x0, x1) == on_face(every, y, x0, x1) > 200
    rng = np.random.default_rng(0)  # what a camera at (2, -2.5) sees: the panel, the wall beside it, a side wall
    points_cad = np.vstack([
        np.column_stack([rng.uniform(1, 3, 300), np.full(300, -0.15), rng.uniform(0.8, 2.0, 300)]),
        np.column_stack([np.r_[rng.uniform(0.05, 0.95, 60), rng.uniform(3.05, 3.95, 60)], np.full(120, 0.19),
                         rng.uniform(0.8, 2.0, 120)]),
        np.column_stack([np.zeros(150), rng.uniform(-3.0, 0.1, 150), rng.uniform(0.8, 2.0, 150)])])
    T_cad_body = make_T(np.eye(3), np.array([2.0, -2.5, 1.4]))
    points_body = apply(np.linalg.inv(T_cad_body), points_cad)
    for dy in (0.2, 0.34):
        guess = make_T(np.eye(3), np.array([2.0, -2.5 + dy, 1.4]))
        deeper, true = align_to_surfaces(every, points_body, guess), align_to_surfaces(seen, points_body, guess)
        assert deeper is not None and abs(deeper.T_cad_body[1, 3] - T_cad_body[1, 3] - 0.34) < 0.03
        assert true is not None and np.linalg.norm(true.T_cad_body[:3, 3] - T_cad_body[:3, 3]) < 0.06


def test_no_fit_far_from_any_wall(room: SurfaceIndex) -> None:
    points_body = wall_points(np.random.default_rng(4), 300)
    assert align_to_surfaces(room, points_body, make_T(np.eye(3), np.array([40.0, 40.0, 0.0]))) is None


def test_a_measured_cad_pose_moves_the_keyframe() -> None:
    """PoseGraph.add_cad_pose: between(T_map_cad, T_map_body) = T_cad_body pulls the keyframe (the anchor is
    fixed by a tight prior here) along the directions its information holds."""
    import gtsam

    from macroloc.graph.posegraph import ANCHOR, pose3

    graph = PoseGraph()
    graph.add_first_keyframe(np.eye(4))
    graph.add_keyframe(make_T(np.eye(3), np.array([1.0, 0.0, 0.0])), np.full(6, 0.5), make_T(np.eye(3), [1.0, 0, 0]))
    graph.add_anchor(np.eye(4))
    graph._add(gtsam.PriorFactorPose3(ANCHOR, pose3(np.eye(4)), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    info = np.diag([1e4, 1e4, 1e4, 1e4, 1e4, 1e-6])  # z free
    graph.add_cad_pose(1, make_T(np.eye(3), np.array([1.3, -0.2, 5.0])), info)
    graph.update(extra_iterations=2)
    t = graph.T_map_body(1)[:3, 3]
    assert abs(t[0] - 1.3) < 0.02 and abs(t[1] + 0.2) < 0.02 and abs(t[2]) < 0.05


def test_the_check_is_retried_as_the_walls_come_into_view(room: SurfaceIndex) -> None:
    """Two doors and the outer walls only: the half-turn about the room's centre fits as well, and the status
    stays ambiguous; once the partition comes into view the same two doors settle it, with no new landmark."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    registrar = CandidatesRegistrar([half_turn @ T_TRUE, T_TRUE])
    model = corridor_model()
    rng = np.random.default_rng(5)
    loc = Localizer(model, PoseGraph(), registrar, LocalizerParams(surface_min_points=100), surfaces=room)
    sightings = sightings_from(model, make_T(np.eye(3), np.array([1.0, 0.0, 1.4])))[:2]
    statuses = []
    for k in range(8):
        T_map_body = make_T(np.eye(3), np.array([0.05 * k, 0.0, 1.4]))
        if k < 3:
            points_cad = wall_points(rng, 150, n_walls=4)
        else:  # the partition (x = 5 m, y in 0..4 m)
            points_cad = np.column_stack([np.full(300, 5.0), rng.uniform(0, 4, 300), rng.uniform(1.0, 1.8, 300)])
        points_body = apply(np.linalg.inv(T_TRUE @ T_map_body), points_cad)
        loc.add_keyframe(k * 500_000_000, T_map_body, sightings, UP, points_body=points_body)
        statuses.append(loc.status)
    assert statuses[2] == "ambiguous" and statuses[-1] == "localized"
    assert registrar.calls >= 2  # retried with the same two landmarks
    T_cad_map = loc.graph.T_cad_map()  # the true pose, not the half-turn 10 m away (the graph has moved it a
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.1  # few cm since)


def doors_on_the_room(centres_normals: list[tuple[tuple[float, float], tuple[float, float]]]) -> BuildingModel:
    """Alike 0.9 x 2.1 m doors on the room's walls (centre xy, normal xy into the room)."""
    feats = [door(f"D{k:02d}", c, n) for k, (c, n) in enumerate(centres_normals)]
    return BuildingModel(source="room", sha256=f"room-doors-{len(feats)}-{feats[0].centroid_cad[0]}",
                         features=feats, storeys=["L1"])


def fly_facing_doors(model: BuildingModel, room: SurfaceIndex, seen: tuple[str, ...], camera_xy: tuple[float, float],
                     yaw: float, params: LocalizerParams | None = None, seen_turn_deg: float = 0.0,
                     keyframes: int = 3, estimates: list[Estimate] | None = None,
                     depth_offset: tuple[int, np.ndarray] | None = None) -> Localizer:
    """Keyframes 0.5 s apart (the map frame is T_TRUE's) from `camera_xy` on, 0.1 m further along x each,
    facing `yaw`, with what a camera there sees of the room all around and sightings of the doors `seen` alone
    (no other door in view); the real registrar. `seen_turn_deg`: the doors are seen turned this much about the
    vertical through their mean centre (one door: its corners' plane off, as perception's are on a door seen
    obliquely; two: their corners coarse at range, each a few tenths of a metre off). Each keyframe's estimate
    is appended to `estimates`, where given. `depth_offset` (k, xyz): keyframe k's depth points are that far off
    (CAD frame, m), as a biased stereo frame's are."""
    registrar = ModelRegistrar(model, min_landmarks=4, candidates_from=1)
    params = params or LocalizerParams(surface_min_points=100)
    loc = Localizer(model, PoseGraph(), registrar, params, surfaces=room)
    rng = np.random.default_rng(8)
    for k in range(keyframes):
        xy = np.array(camera_xy) + np.array([0.1 * k, 0.0])
        T_cad_body = make_T(rot_z(yaw), np.array([xy[0], xy[1], 1.4]))
        sightings = sorted((s for s in sightings_from(model, T_cad_body) if s.truth_id in seen),
                           key=lambda s: str(s.truth_id))
        assert len(sightings) == len(seen)
        centre = np.mean([s.corners_body.mean(axis=0) for s in sightings], axis=0)
        R = rot_z(np.radians(seen_turn_deg))
        sightings = [replace(s, corners_body=(s.corners_body - centre) @ R.T + centre) for s in sightings]
        points_cad = seen_points(rng, xy)
        if depth_offset is not None and depth_offset[0] == k:
            points_cad = points_cad + depth_offset[1]
        points_body = apply(np.linalg.inv(T_cad_body), points_cad)
        estimate = loc.add_keyframe(k * 500_000_000, np.linalg.inv(T_TRUE) @ T_cad_body, sightings, UP,
                                    points_body=points_body)
        if estimates is not None:
            estimates.append(estimate)
    return loc


FOURTEEN_DOORS = [((x, 0.0), (0, 1)) for x in (1.0, 3.0, 7.0, 9.0, 11.0)] \
    + [((x, 7.0), (0, -1)) for x in (1.5, 4.0, 6.5, 9.0, 11.0)] \
    + [((12.0, y), (-1, 0)) for y in (2.0, 5.0)] + [((0.0, y), (1, 0)) for y in (3.0, 6.0)]


def test_one_door_and_the_walls_localize(room_with_walls: SurfaceIndex) -> None:
    """Fourteen alike doors on the room's walls: one door in view gives 28 candidate poses (each door, from
    either side). The 8 that the points fit best unfitted are fitted to the walls and checked, and the walls
    single out the true one: localized from one landmark."""
    model = doors_on_the_room(FOURTEEN_DOORS)
    loc = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2)
    assert loc.judge.screens and loc.judge.screens[0][0] == 28
    assert loc.status == "localized" and len(loc.landmarks) == 1
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05
    assert rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T) < 0.5
    assert loc.links == {0: "D03"}


def test_a_door_seen_turned_is_turned_back_by_the_walls(room_with_walls: SurfaceIndex) -> None:
    """The one door in view is seen with its plane 15 deg off (perception's corners on a door seen obliquely
    were 12-24 deg off, always the same way). Every candidate pose from it is 15 deg off; turned about the door
    to the heading that fits the walls best, the true one is found, and the door is linked by its position only
    (its orientation disagrees with the model's), so the flight keeps the walls' heading. Not turned, no
    candidate fits. Linked by its orientation too, the door turns the flight to fit it, unless the walls' fits
    hold it: the keyframe that localizes is fitted to them before the door is linked, and each later one from
    there (fitted after the link, each fit was refused as a turn too large, and the flight ended 14 deg off)."""
    model = doors_on_the_room(FOURTEEN_DOORS)
    base = LocalizerParams(surface_min_points=100)
    loc = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2, base, seen_turn_deg=15.0,
                              keyframes=12)
    assert loc.status == "localized" and loc.links == {0: "D03"}
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.1
    assert rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T) < 1.0
    not_turned = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2,
                                  replace(base, surface_turn_deg=0.0), seen_turn_deg=15.0, keyframes=12)
    assert not_turned.status != "localized" and not_turned.graph.T_cad_map() is None
    for surface_fit, turned_deg in ((False, (5.0, 90.0)), (True, (0.0, 1.0))):
        oriented = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2,
                                    replace(base, cad_link_max_turn_deg=180.0, surface_fit=surface_fit),
                                    seen_turn_deg=15.0, keyframes=12)
        T_oriented = oriented.graph.T_cad_map()
        assert oriented.status == "localized" and T_oriented is not None
        assert turned_deg[0] < rotation_angle_deg(T_oriented[:3, :3] @ T_TRUE[:3, :3].T) < turned_deg[1]


@pytest.mark.parametrize("seen", [("D03", "D04"), ("D02", "D03")])
def test_two_doors_seen_turned_are_turned_back_by_the_walls(room_with_walls: SurfaceIndex,
                                                            seen: tuple[str, str]) -> None:
    """Two doors 2 m apart, seen 8 deg turned about their midpoint (each 0.14 m off): every candidate pose from
    them is 8 deg off, which the wall fit does not take back (perception, Office_A seed 5: 5-13 deg from two or
    three doors). Turned about one of them, keeping both by their CAD doors, the walls find the true heading,
    and the pose they chose holds from the keyframe that localizes: that keyframe is fitted to the walls before
    the two doors are linked (linked first, they pulled it 0.09 m and 1.6 deg off). Turning only candidates from
    one door, none fits."""
    model = doors_on_the_room(FOURTEEN_DOORS)
    base = LocalizerParams(surface_min_points=100)
    estimates: list[Estimate] = []
    loc = fly_facing_doors(model, room_with_walls, seen, (9.0, 3.5), -np.pi / 2, base, seen_turn_deg=8.0,
                           keyframes=6, estimates=estimates)
    assert loc.status == "localized" and sorted(loc.links.values()) == list(seen)
    k, T_first = next((k, e.T_cad_body) for k, e in enumerate(estimates) if e.T_cad_body is not None)
    T_cad_body_true = make_T(rot_z(-np.pi / 2), np.array([9.0 + 0.1 * k, 3.5, 1.4]))
    assert np.linalg.norm(T_first[:3, 3] - T_cad_body_true[:3, 3]) < 0.03
    assert rotation_angle_deg(T_first[:3, :3] @ T_cad_body_true[:3, :3].T) < 0.5
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.05
    assert rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T) < 0.5
    one_door_only = fly_facing_doors(model, room_with_walls, seen, (9.0, 3.5), -np.pi / 2,
                                     replace(base, surface_turn_max_inliers=1), seen_turn_deg=8.0, keyframes=6)
    assert one_door_only.status == "ambiguous" and one_door_only.graph.T_cad_map() is None


def test_the_keyframe_that_localizes_is_fitted_by_the_window_s_points(room_with_walls: SurfaceIndex) -> None:
    """The keyframe that localizes sees its walls 0.25 m off (its depth biased: clutter the model lacks, a poor
    stereo frame); the keyframes before it saw them right. Fitted to the walls by the window's points, as the
    pose was chosen, it stays within 0.08 m; by its own points alone (a one-keyframe window), the fit moves it
    0.24 m (`truth`, Office_A seed 5: such a fit moved a pose from 0.13 to 0.50 m off, too far for its door to be
    linked)."""
    model = doors_on_the_room(FOURTEEN_DOORS)

    def first_pose_error_m(window_keyframes: int) -> float:
        params = LocalizerParams(surface_min_points=100, min_sightings_to_register=4,
                                 surface_window_keyframes=window_keyframes)
        estimates: list[Estimate] = []
        fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2, params, keyframes=6,
                         estimates=estimates, depth_offset=(3, np.array([0.25, 0.0, 0.0])))
        k, T_first = next((k, e.T_cad_body) for k, e in enumerate(estimates) if e.T_cad_body is not None)
        assert k == 3  # the fourth sighting of the door: the biased keyframe localizes
        return float(np.linalg.norm(T_first[:3, 3] - np.array([9.0 + 0.1 * k, 3.5, 1.4])))

    assert first_pose_error_m(60) < 0.08
    assert first_pose_error_m(1) > 0.2


def test_a_turn_keeps_the_candidates_doors_by_their_cad_doors(room_with_walls: SurfaceIndex) -> None:
    """Doors D02 and D04, 4 m apart, both by their CAD doors under a candidate pose; the walls fit best with the
    candidate turned 14 deg about D02, which would put D04 0.97 m from its door (the registration's tolerance
    is 0.6 m). The turn goes only as far as keeps D04 by it: the walls may turn a pose, not unmake its match."""
    model = doors_on_the_room(FOURTEEN_DOORS)
    loc = fly_facing_doors(model, room_with_walls, ("D02", "D04"), (9.0, 3.5), -np.pi / 2)
    centroid_cad = {f.id: f.centroid_cad for f in model.features}
    about_d02 = centroid_cad["D02"]

    def turn_about_d02(deg: float) -> np.ndarray:
        R = rot_z(np.radians(deg))
        return make_T(R, about_d02 - R @ about_d02)

    T_candidate = turn_about_d02(0.5) @ T_TRUE  # D02 exact, so the turn is about it
    walls_cad = seen_points(np.random.default_rng(3), np.array([9.0, 3.5]), n=300)
    points_map = apply(np.linalg.inv(T_candidate) @ turn_about_d02(-14.0), walls_cad)  # fit 14 deg further
    (T_turned,) = loc.judge.turned([(T_candidate, 2)], points_map, 2, 2, loc.landmark_centres_map())
    turn_deg = rotation_angle_deg(T_turned[:3, :3] @ T_candidate[:3, :3].T)
    assert 3.0 < turn_deg < 8.6
    for key, door_id in loc.links.items():
        x_cad = apply(T_turned, loc.graph.T_map_rect(key)[:3, 3][None])[0]
        assert np.linalg.norm(x_cad - centroid_cad[door_id]) <= 0.6


def test_one_door_in_a_room_alike_after_a_half_turn_stays_ambiguous() -> None:
    """The box room (no partition) with two doors placed alike after a half-turn about its centre: the walls
    fit both of the door's candidate poses, and one landmark is no answer."""
    v, f = room_mesh()
    box = SurfaceIndex.from_mesh(v, f[:8], SurfaceParams(spacing_m=0.05))  # the 4 outer walls
    box.walls = WallVoxels.from_mesh(v, f[:8])
    model = doors_on_the_room([((9.0, 0.0), (0, 1)), ((3.0, 7.0), (0, -1))])
    loc = fly_facing_doors(model, box, ("D00",), (9.0, 3.5), -np.pi / 2)
    second, best = sorted(loc.judge.checks[-1][1])[-2:]
    assert best - second < 0.05  # the half-turn fits as well
    assert loc.status == "ambiguous" and loc.graph.T_cad_map() is None and not loc.links


def fly_seeing_a_far_door(model: BuildingModel, room: SurfaceIndex, params: LocalizerParams,
                          far_lift_m: float = 0.0) -> Localizer:
    """Ten keyframes, 0.5 s apart, at (10.5, 3.5) in the box room facing -x and drifting back 5 cm each: door D00
    4.9 m away and door D02 10.5 m away (beyond the 7 m sighting range) in view, the walls all around; the real
    registrar, from one landmark. `far_lift_m`: D02 is seen this much higher than it is."""
    registrar = ModelRegistrar(model, min_landmarks=4, candidates_from=1)
    loc = Localizer(model, PoseGraph(), registrar, params, surfaces=room)
    rng = np.random.default_rng(5)
    lift = np.array([0.0, 0.0, far_lift_m])
    for k in range(10):
        xy = np.array([10.5 + 0.05 * k, 3.5])
        T_cad_body = make_T(rot_z(np.pi), np.array([xy[0], xy[1], 1.4]))
        sightings = [s for s in sightings_from(model, T_cad_body, max_range_m=12.0) if s.truth_id in ("D00", "D02")]
        assert len(sightings) == 2
        sightings = [replace(s, corners_body=s.corners_body + lift) if s.truth_id == "D02" else s for s in sightings]
        points_body = apply(np.linalg.inv(T_cad_body), seen_points(rng, xy, segments=WALL_SEGMENTS[:4]))
        loc.add_keyframe(k * 500_000_000, np.linalg.inv(T_TRUE) @ T_cad_body, sightings, UP, points_body=points_body)
    return loc


def test_a_far_doors_bearing_tells_apart_poses_the_walls_fit_alike() -> None:
    """The box room is the same after a half-turn, and so are its near doors (D00, D01). A door 10.5 m away
    (D02), too far to be a landmark, is where the true pose puts a door of the model and where the half-turn
    puts none: its bearing settles what the walls cannot. Without far sightings, or where the far door has its
    half-turned twin too, the status stays ambiguous."""
    v, f = room_mesh()
    box = SurfaceIndex.from_mesh(v, f[:8], SurfaceParams(spacing_m=0.05))  # the 4 outer walls
    box.walls = WallVoxels.from_mesh(v, f[:8])
    near = [((7.0, 0.0), (0, 1)), ((5.0, 7.0), (0, -1))]  # D00 and its half-turned twin D01
    model = doors_on_the_room([*near, ((0.0, 3.5), (1, 0))])
    params = LocalizerParams(surface_min_points=100)
    loc = fly_seeing_a_far_door(model, box, params)
    assert loc.status == "localized" and len(loc.landmarks) == 1
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.1
    assert loc.links == {0: "D00"}
    newest = loc.graph.T_map_body(loc.graph.n_keyframes - 1)
    assert loc.far.explained(T_cad_map, loc.far.in_map(), newest) == 1.0
    second, best = sorted(loc.judge.checks[-1][1])[-2:]
    assert best - second < 0.05  # the walls alone fit the half-turn as well
    without_far = fly_seeing_a_far_door(model, box, replace(params, far_range_m=params.max_range_m))
    assert without_far.status == "ambiguous" and without_far.graph.T_cad_map() is None
    twins = doors_on_the_room([*near, ((0.0, 3.5), (1, 0)), ((12.0, 3.5), (-1, 0))])
    assert fly_seeing_a_far_door(twins, box, params).status == "ambiguous"
    # a candidate's height is coarse (one door's corners): 0.8 m at 10.5 m (4.4 deg of elevation) still explains
    # the far door; 3 m (a storey, 16 deg) does not
    assert fly_seeing_a_far_door(model, box, params, far_lift_m=0.8).status == "localized"
    assert fly_seeing_a_far_door(model, box, params, far_lift_m=3.0).status == "ambiguous"


@settings(max_examples=15, deadline=None)
@given(off_deg=st.floats(3.5, 3.9), sign=st.sampled_from([-1.0, 1.0]))
@example(off_deg=3.5, sign=-1.0)
@example(off_deg=3.9, sign=1.0)
def test_a_candidate_a_few_degrees_off_still_explains_the_far_door_it_sees(off_deg: float, sign: float) -> None:
    """A candidate's heading, from a door or two and the walls, is ~2 deg off (perception, Office_A seed 4: 1.9
    deg). Turned 3.5-3.9 deg either way about the newest camera, the localized pose puts the far door D02 (10.5 m)
    beyond the 3 deg bearing tolerance (the older keyframes' cameras, up to 0.45 m from the pivot, see it up to 0.15
    deg less turned); the far check turns it back by up to `far_turn_deg` (2 deg) and it explains D02 again.
    Without the turn it does not, and the half-turned pose explains nothing, turned or not."""
    v, f = room_mesh()
    box = SurfaceIndex.from_mesh(v, f[:8], SurfaceParams(spacing_m=0.05))
    box.walls = WallVoxels.from_mesh(v, f[:8])
    model = doors_on_the_room([((7.0, 0.0), (0, 1)), ((5.0, 7.0), (0, -1)), ((0.0, 3.5), (1, 0))])
    params = LocalizerParams(surface_min_points=100)
    loc = fly_seeing_a_far_door(model, box, params)
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None
    camera = apply(T_cad_map @ loc.graph.T_map_body(loc.graph.n_keyframes - 1), loc.viewer_body[None])[0]

    def turned(deg: float, about: np.ndarray) -> np.ndarray:
        R = rot_z(np.radians(deg))
        return make_T(R, about - R @ about) @ T_cad_map

    far = loc.far.in_map()
    assert far is not None
    newest = loc.graph.T_map_body(loc.graph.n_keyframes - 1)
    T_off = turned(sign * off_deg, camera)
    assert loc.far.explained(T_off, far, newest) == 1.0
    loc.far.params = replace(params, far_turn_deg=0.0)
    assert loc.far.explained(T_off, far, newest) == 0.0
    assert loc.far.explained(T_cad_map, far, newest) == 1.0
    loc.far.params = params
    half_turned = turned(180.0, np.array([6.0, 3.5, 0.0]))  # the box room's centre: its walls fit alike
    assert loc.far.explained(half_turned, far, newest) == 0.0


def test_the_walls_turn_back_a_pose_localized_degrees_off(room_with_walls: SurfaceIndex) -> None:
    """A pose localized from one door carries the detector's error in that door's orientation (5.5 deg on
    Office_A seed 9, where every later fit to the walls turned the pose more than the 5 deg then allowed and was
    refused: 2.2 m off after 30 s). While the pose settles after localizing, the walls' fits may turn it back;
    later a turn that large is a fit to a wrong wall (Jasmin-Sun seed 11 had 6-28 deg ones mid-flight)."""
    pivot = np.array([8.0, 3.5, 0.0])
    R = rot_z(np.radians(8.0))
    T_off = make_T(R, pivot - R @ pivot) @ T_TRUE  # 8 deg off about the flight's start
    cameras = [np.array([8.0 + 0.2 * k, 3.5 - 0.1 * k]) for k in range(10)]
    base = LocalizerParams(surface_min_points=100, surface_refine_m=0.0)
    errors = []
    never_settling = replace(base, surface_fit_settling_keyframes=0)
    for params in (base, replace(base, surface_fit_settling_turn_deg=5.0), never_settling):
        loc = fly_seeing(room_with_walls, CandidatesRegistrar([T_off], localized=True), cameras, params)
        T_cad_map = loc.graph.T_cad_map()
        assert loc.status == "localized" and T_cad_map is not None
        errors.append(rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T))
    assert errors[0] < 1.0 and errors[1] > 7.0 and errors[2] > 7.0


class SilentRegistrar:
    """Never answers: what a flight that has seen no door yet gets from registration."""

    min_landmarks = 4
    candidates_from = 2

    def __call__(self, landmarks, corners_map) -> Alignment:  # noqa: ANN001
        return Alignment("not_localized", None)


def fly_placed(room: SurfaceIndex, cameras_cad: list[np.ndarray], placed_T_cad_map: np.ndarray | None,
               params: LocalizerParams | None = None, every_s: float = 1.0) -> Localizer:
    """Keyframes at `cameras_cad` (map frame T_TRUE's), `every_s` apart, seeing the room's walls and no door;
    each placed in a stored map as if by place recognition at T_cad_map = `placed_T_cad_map` (None: never)."""
    rng = np.random.default_rng(8)
    loc = Localizer(corridor_model(), PoseGraph(), SilentRegistrar(), params or LocalizerParams(surface_min_points=100),
                    surfaces=room)
    for k, xy in enumerate(cameras_cad):
        T_cad_body = make_T(np.eye(3), np.array([xy[0], xy[1], 1.4]))
        T_map_body = np.linalg.inv(T_TRUE) @ T_cad_body
        points_body = apply(np.linalg.inv(T_cad_body), seen_points(rng, np.asarray(xy, float)))
        placed = None if placed_T_cad_map is None else placed_T_cad_map @ T_map_body
        loc.add_keyframe(int(k * every_s * 1e9), T_map_body, [], UP, points_body=points_body,
                         T_cad_body_placed=placed)
    return loc


def test_a_keyframe_placed_in_a_stored_map_localizes_before_any_door(room_with_walls: SurfaceIndex) -> None:
    assert fly_placed(room_with_walls, NEAR_THE_PARTITION_END, None).status == "exploring"
    loc = fly_placed(room_with_walls, NEAR_THE_PARTITION_END[:1], T_TRUE)
    assert loc.status == "localized" and not loc.landmarks
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.01


def test_a_placement_the_walls_see_through_is_refused(room_with_walls: SurfaceIndex) -> None:
    """Placed half a turn off (a stored view matched in the room's twin): a third of the points would have been
    seen through the partition. Not anchored."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0])) @ T_TRUE
    loc = fly_placed(room_with_walls, NEAR_THE_PARTITION_END, half_turn)
    assert loc.status == "exploring" and loc.graph.T_cad_map() is None


def test_placements_hold_the_pose_and_keep_the_status_alive(room_with_walls: SurfaceIndex) -> None:
    """Placed keyframes are CAD-linked measurements: 12 s with no door leaves the status `localized`, where
    one placement only would let it degrade (after `degraded_after_s`)."""
    cameras = [np.array([6.5 + 0.1 * k, 6.0 - 0.1 * k]) for k in range(13)]
    params = LocalizerParams(surface_min_points=100, surface_fit=False)
    once = Localizer(corridor_model(), PoseGraph(), SilentRegistrar(), params, surfaces=room_with_walls)
    always = fly_placed(room_with_walls, cameras, T_TRUE, params)
    for k, xy in enumerate(cameras):
        T_map_body = np.linalg.inv(T_TRUE) @ make_T(np.eye(3), np.array([xy[0], xy[1], 1.4]))
        once.add_keyframe(int(k * 1e9), T_map_body, [], UP, T_cad_body_placed=T_TRUE @ T_map_body if k == 0 else None)
    assert once.status == "degraded" and always.status == "localized"
    T_cad_map = always.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.01


def test_doors_beyond_the_sighting_range_and_the_walls_localize(room_with_walls: SurfaceIndex) -> None:
    """No door within the sighting range (here 2 m), five of the fourteen alike doors beyond it: the far pairs'
    resection offers every pose that puts two of the model's doors along two bearings, the far sightings'
    bearings keep those explaining them, and the walls single out the true one, fitted to the bearings and
    held there (its height too) with no landmark at all. Without the resection it keeps exploring."""
    model = doors_on_the_room(FOURTEEN_DOORS)
    runs = {}
    for resect in (True, False):
        params = LocalizerParams(surface_min_points=100, max_range_m=2.0, far_resection=resect)
        registrar = ModelRegistrar(model, min_landmarks=4, candidates_from=1)
        loc = Localizer(model, PoseGraph(), registrar, params, surfaces=room_with_walls)
        rng = np.random.default_rng(3)
        for k in range(8):
            xy = np.array([2.0 + 0.15 * k, 3.5])
            T_cad_body = make_T(rot_z(0.05 * k), np.array([xy[0], xy[1], 1.4]))
            sightings = sightings_from(model, T_cad_body, max_range_m=20.0, rng=rng, sigma_m=0.02)
            points_body = apply(np.linalg.inv(T_cad_body), seen_points(rng, xy))
            loc.add_keyframe(k * 500_000_000, np.linalg.inv(T_TRUE) @ T_cad_body, sightings, UP,
                             points_body=points_body)
        runs[resect] = loc
    loc = runs[True]
    assert loc.status == "localized" and not loc.landmarks and not loc.links
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.1
    assert rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T) < 0.5
    assert runs[False].status == "exploring"

