"""graph.localizer with the walls: one door and the walls localize, turned doors are turned back, far doors'
bearings and placements in a stored map decide where the walls cannot (the test room: tests/graph/rooms.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from macroloc.graph.features import BuildingModel
from macroloc.graph.localizer import Estimate, Localizer, LocalizerParams
from macroloc.graph.params import JudgeParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import ModelRegistrar
from macroloc.graph.relocalize import Alignment
from macroloc.graph.rigid import apply, rotation_angle_deg
from macroloc.graph.surfaces import (
    SurfaceIndex,
    SurfaceParams,
    WallVoxels,
)
from tests.graph.helpers import localizer_params
from tests.graph.rooms import (
    NEAR_THE_PARTITION_END,
    T_TRUE,
    UP,
    WALL_SEGMENTS,
    CandidatesRegistrar,
    fly_seeing,
    room_mesh,
    seen_points,
    wall_points,
)
from tests.graph.scenes import corridor_model, door, make_T, rot_z, sightings_from


def test_the_check_is_retried_as_the_walls_come_into_view(room: SurfaceIndex) -> None:
    """Two doors and the outer walls only: the half-turn about the room's centre fits as well, and the status
    stays ambiguous; once the partition comes into view the same two doors settle it, with no new landmark."""
    half_turn = make_T(rot_z(np.pi), np.array([12.0, 7.0, 0.0]))
    registrar = CandidatesRegistrar([half_turn @ T_TRUE, T_TRUE])
    model = corridor_model()
    rng = np.random.default_rng(5)
    loc = Localizer(model, PoseGraph(), registrar, localizer_params(surface_min_points=100), surfaces=room)
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
    params = params or localizer_params(surface_min_points=100)
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
    base = localizer_params(surface_min_points=100)
    loc = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2, base, seen_turn_deg=15.0,
                              keyframes=12)
    assert loc.status == "localized" and loc.links == {0: "D03"}
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.1
    assert rotation_angle_deg(T_cad_map[:3, :3] @ T_TRUE[:3, :3].T) < 1.0
    not_turned = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2,
                                  localizer_params(base, surface_turn_deg=0.0), seen_turn_deg=15.0, keyframes=12)
    assert not_turned.status != "localized" and not_turned.graph.T_cad_map() is None
    for surface_fit, turned_deg in ((False, (5.0, 90.0)), (True, (0.0, 1.0))):
        oriented = fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2,
                                    localizer_params(base, cad_link_max_turn_deg=180.0, surface_fit=surface_fit),
                                    seen_turn_deg=15.0, keyframes=12)
        T_oriented = oriented.graph.T_cad_map()
        # without the walls' fits, the one door 3.5 m away holds the pose to 0.27 m: not held, degraded
        assert oriented.status == ("localized" if surface_fit else "degraded") and T_oriented is not None
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
    base = localizer_params(surface_min_points=100)
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
    # without the best candidate's images under the room's self-maps (JudgeParams.surface_self_map_images), which
    # may land a candidate's image on the true place, where the wall fit takes it
    one_door_only = fly_facing_doors(model, room_with_walls, seen, (9.0, 3.5), -np.pi / 2,
                                     localizer_params(base, surface_turn_max_inliers=1, surface_self_map_images=0),
                                     seen_turn_deg=8.0, keyframes=6)
    assert one_door_only.status == "ambiguous" and one_door_only.graph.T_cad_map() is None


def test_the_keyframe_that_localizes_is_fitted_by_the_window_s_points(room_with_walls: SurfaceIndex) -> None:
    """The keyframe that localizes sees its walls 0.25 m off (its depth biased: clutter the model lacks, a poor
    stereo frame); the keyframes before it saw them right. Fitted to the walls by the window's points, as the
    pose was chosen, it stays within 0.08 m; by its own points alone (a one-keyframe window), the fit moves it
    0.24 m (`truth`, Office_A seed 5: such a fit moved a pose from 0.13 to 0.50 m off, too far for its door to be
    linked)."""
    model = doors_on_the_room(FOURTEEN_DOORS)

    def first_pose_error_m(window_keyframes: int, own_wall_m: float = JudgeParams().surface_own_wall_m) -> float:
        params = localizer_params(surface_min_points=100, min_sightings_to_register=4,
                                  surface_window_keyframes=window_keyframes, surface_own_wall_m=own_wall_m)
        estimates: list[Estimate] = []
        fly_facing_doors(model, room_with_walls, ("D03",), (9.0, 3.5), -np.pi / 2, params, keyframes=6,
                         estimates=estimates, depth_offset=(3, np.array([0.25, 0.0, 0.0])))
        k, T_first = next((k, e.T_cad_body) for k, e in enumerate(estimates) if e.T_cad_body is not None)
        assert k == 3  # the fourth sighting of the door: the biased keyframe localizes
        return float(np.linalg.norm(T_first[:3, 3] - np.array([9.0 + 0.1 * k, 3.5, 1.4])))

    assert first_pose_error_m(60) < 0.08
    # one keyframe facing the door's wall sees little off it, so the walls would not choose from its points at
    # all (SurfaceJudge.choose): the comparison of the fits needs that rule off
    assert first_pose_error_m(1, own_wall_m=0.0) > 0.2


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


def test_an_ambiguous_localizer_names_the_poses_the_walls_fit_alike() -> None:
    """The half-turned twin room above: the localizer's rivals are the two poses the walls fit as well (the door
    matched to each of the two model doors, half a turn apart), not every candidate of the one landmark (four);
    the demo draws them (sim.demo)."""
    v, f = room_mesh()
    box = SurfaceIndex.from_mesh(v, f[:8], SurfaceParams(spacing_m=0.05))
    box.walls = WallVoxels.from_mesh(v, f[:8])
    model = doors_on_the_room([((9.0, 0.0), (0, 1)), ((3.0, 7.0), (0, -1))])
    loc = fly_facing_doors(model, box, ("D00",), (9.0, 3.5), -np.pi / 2)
    assert loc.status == "ambiguous" and len(loc.rivals) == 2
    A, B = loc.rivals
    assert np.allclose(A[:3, :3] @ B[:3, :3].T, np.diag([-1.0, -1.0, 1.0]), atol=1e-3)  # half a turn apart
    assert np.linalg.norm((A[:3, 3] + B[:3, 3]) / 2 - [6.0, 3.5, 0.0]) < 0.1  # about the room's centre


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
    params = localizer_params(surface_min_points=100)
    loc = fly_seeing_a_far_door(model, box, params)
    assert loc.status == "localized" and len(loc.landmarks) == 1
    T_cad_map = loc.graph.T_cad_map()
    assert T_cad_map is not None and np.linalg.norm(T_cad_map[:3, 3] - T_TRUE[:3, 3]) < 0.1
    assert loc.links == {0: "D00"}
    newest = loc.graph.T_map_body(loc.graph.n_keyframes - 1)
    assert loc.far.explained(T_cad_map, loc.far.in_map(), newest) == 1.0
    second, best = sorted(loc.judge.checks[-1][1])[-2:]
    assert best - second < 0.05  # the walls alone fit the half-turn as well
    without_far = fly_seeing_a_far_door(model, box, localizer_params(params, far_range_m=params.landmarks.max_range_m))
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
    params = localizer_params(surface_min_points=100)
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
    loc.far.params = replace(params.far, far_turn_deg=0.0)
    assert loc.far.explained(T_off, far, newest) == 0.0
    assert loc.far.explained(T_cad_map, far, newest) == 1.0
    loc.far.params = params.far
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
    base = localizer_params(surface_min_points=100, surface_refine_m=0.0)
    errors = []
    never_settling = localizer_params(base, surface_fit_settling_keyframes=0)
    for params in (base, localizer_params(base, surface_fit_settling_turn_deg=5.0), never_settling):
        loc = fly_seeing(room_with_walls, CandidatesRegistrar([T_off], localized=True), cameras, params)
        T_cad_map = loc.graph.T_cad_map()
        # every fit refused, nothing holds the pose (no door is linked here): not held, degraded
        assert loc.status == ("localized" if params is base else "degraded") and T_cad_map is not None
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
    params = params or localizer_params(surface_min_points=100)
    loc = Localizer(corridor_model(), PoseGraph(), SilentRegistrar(), params, surfaces=room)
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
    params = localizer_params(surface_min_points=100, surface_fit=False)
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
        params = localizer_params(surface_min_points=100, max_range_m=2.0, far_resection=resect)
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
