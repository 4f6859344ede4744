"""graph.recovery: a pose the odometry carried alone (not held) found again by the walls (the test room:
tests/graph/rooms.py) or by the doors mapped since (a corridor: tests/graph/scenes.py), and left where they cannot
single it out."""

from __future__ import annotations

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.localizer import Localizer, LocalizerParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import ModelRegistrar
from macroloc.graph.rigid import apply
from macroloc.graph.surfaces import SurfaceIndex
from tests.graph.corridor_flight import fly, position_error
from tests.graph.helpers import localizer_params
from tests.graph.rooms import T_TRUE, UP, WALL_SEGMENTS, seen_points
from tests.graph.scenes import door, make_T, rot_z, sightings_from, straight_flight
from tests.graph.test_localizer_walls import FOURTEEN_DOORS, doors_on_the_room


def fly_through_a_gap_in_the_odometry(room: SurfaceIndex, params: LocalizerParams, keyframes: int = 16,
                                      jump_at: int = 6, jump_m: tuple[float, float] = (0.0, 1.0),
                                      seen_after: np.ndarray = WALL_SEGMENTS) -> tuple[Localizer, list[np.ndarray]]:
    """Localized by D03 and the walls from (9, 3.5) facing -y, the flight goes on along x with the walls in view
    and no door; at keyframe `jump_at` the odometry has extrapolated for 3 s and is `jump_m` (CAD x, y) off,
    then tracks again, measuring the walls `seen_after` (segments as `WALL_SEGMENTS`). Returns the localizer and
    the true T_cad_body of each keyframe."""
    model = doors_on_the_room(FOURTEEN_DOORS)
    loc = Localizer(model, PoseGraph(), ModelRegistrar(model, min_landmarks=4, candidates_from=1), params,
                    surfaces=room)
    rng = np.random.default_rng(8)
    truth = []
    for k in range(keyframes):
        xy = np.array([9.0 - 0.25 * k, 3.5])
        T_cad_body = make_T(rot_z(-np.pi / 2), np.array([xy[0], xy[1], 1.4]))
        truth.append(T_cad_body)
        sightings = [s for s in sightings_from(model, T_cad_body) if s.truth_id == "D03"] if k < 3 else []
        T_cad_odom = T_cad_body if k < jump_at else make_T(np.eye(3), np.array([*jump_m, 0.0])) @ T_cad_body
        loc.add_keyframe(k * 500_000_000, np.linalg.inv(T_TRUE) @ T_cad_odom, sightings, UP,
                         points_body=apply(np.linalg.inv(T_cad_body),
                                           seen_points(rng, xy, n=300, segments=WALL_SEGMENTS if k < jump_at
                                                       else seen_after)),
                         dead_reckoned_s=3.0 if k == jump_at else 0.0)
    return loc, truth


def test_the_walls_find_a_pose_the_odometry_carried_alone_again(room_with_walls: SurfaceIndex) -> None:
    """The odometry extrapolates 1 m wrong (across the room, toward the partition's free end): not held, no fit
    is made from there, and the pose would stay 1 m off; the walls seen since, tried at shifts within 3 sigma of
    it, single out the true one, and the pose is held again."""
    base = localizer_params(surface_min_points=100)
    for recovery, error_m in ((True, (0.0, 0.1)), (False, (0.9, 1.1))):
        loc, truth = fly_through_a_gap_in_the_odometry(room_with_walls, localizer_params(base, recovery=recovery))
        i = loc.graph.n_keyframes - 1
        T_cad_body = loc.graph.T_cad_map() @ loc.graph.T_map_body(i)
        assert error_m[0] <= np.linalg.norm(T_cad_body[:2, 3] - truth[i][:2, 3]) < error_m[1]
        assert loc.anchoring.held() == recovery
        assert len(loc.recovery.recoveries) == recovery


def test_the_walls_leave_a_pose_they_cannot_single_out(room_with_walls: SurfaceIndex) -> None:
    """The same gap, 1 m along the room, with only the long walls in view after it (as in a corridor): shifts
    along them fit alike, and the pose is left as the odometry carried it, not held."""
    long_walls = np.array([[6, 0, 12, 0], [12, 7, 6, 7]], float)
    loc, truth = fly_through_a_gap_in_the_odometry(room_with_walls, localizer_params(surface_min_points=100),
                                                   jump_m=(1.0, 0.0), seen_after=long_walls)
    assert not loc.recovery.recoveries and not loc.anchoring.held()
    recovered, _ = fly_through_a_gap_in_the_odometry(room_with_walls, localizer_params(surface_min_points=100),
                                                     jump_m=(1.0, 0.0))
    assert len(recovered.recovery.recoveries) == 1  # with the end walls in view, the same gap is found


def fly_on_after_a_gap(model: BuildingModel, params: LocalizerParams | None = None, keyframes: int = 60,
                       jump_at: int = 30, jump_m: float = 1.0) -> tuple[Localizer, list[np.ndarray]]:
    """Localized by the doors along the corridor (no depth: nothing for the walls), then at keyframe `jump_at`
    the odometry has extrapolated for 3 s and is `jump_m` too far along it; from there only doors never seen
    before are in view (the mapped ones, linked, would hold the pose by themselves). Returns the localizer and
    the true T_cad_body of each keyframe."""
    poses = straight_flight(keyframes)
    jump = make_T(np.eye(3), np.array([jump_m, 0.0, 0.0]))
    loc = fly(model, poses[:jump_at], poses[:jump_at], params=params)
    assert loc.status == "localized" and loc.anchoring.held()
    seen = {lm.truth_id for lm in loc.landmarks.values()}
    for k in range(jump_at, keyframes):
        new = [s for s in sightings_from(model, poses[k]) if s.truth_id not in seen] if k > jump_at else []
        loc.add_keyframe(k * 100_000_000, jump @ poses[k], new, UP, dead_reckoned_s=3.0 if k == jump_at else 0.0)
    return loc, poses


def test_the_doors_mapped_since_find_a_pose_the_odometry_carried_alone_again(corridor) -> None:
    """The odometry extrapolates 1 m too far along the corridor: not held, nothing is linked from there, and the
    pose would stay 1 m off; the doors mapped since, put on the model's by one shift of the pose within 3 sigma,
    single out the true one, the pose is held again and the new doors are linked to theirs."""
    for recovery, error_m in ((True, (0.0, 0.1)), (False, (0.9, 1.1))):
        loc, poses = fly_on_after_a_gap(corridor, localizer_params(recovery=recovery))
        i = loc.graph.n_keyframes - 1
        assert error_m[0] <= position_error(loc, poses, i) < error_m[1]
        assert loc.anchoring.held() == recovery
        assert len(loc.door_recovery.recoveries) == recovery
        truth = {lm.key: lm.truth_id for lm in loc.landmarks.values()}
        assert all(truth[j] == fid for j, fid in loc.links.items())


def test_the_doors_leave_a_pose_that_a_row_of_alike_doors_cannot_single_out(corridor) -> None:
    """Beyond the corridor's first 10 m, alike doors every 2 m along one wall: the doors mapped since the gap fit a
    shift of the pose to the truth and shifts 2 m from it alike, so none is taken; the same gap before a row
    spaced irregularly is found."""
    def corridor_then_row(jitter_m: float) -> BuildingModel:
        rng = np.random.default_rng(4)
        first = [f for f in corridor.features if f.centroid_cad[0] < 10.0]
        row = [door(f"R{k:02d}", (12.0 + 2.0 * k + rng.uniform(-jitter_m, jitter_m), 1.5), (0.0, -1.0))
               for k in range(10)]
        return BuildingModel(source="row", sha256=f"row{jitter_m}", storeys=["L1"], features=[*first, *row])

    loc, poses = fly_on_after_a_gap(corridor_then_row(0.0))
    assert not loc.door_recovery.recoveries and not loc.anchoring.held()
    assert position_error(loc, poses, loc.graph.n_keyframes - 1) > 0.9
    found, poses = fly_on_after_a_gap(corridor_then_row(0.6))
    assert len(found.door_recovery.recoveries) == 1
    assert position_error(found, poses, found.graph.n_keyframes - 1) < 0.1
