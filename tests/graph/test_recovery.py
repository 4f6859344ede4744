"""graph.recovery: a pose the odometry carried alone (not held) found again by the walls, and left where the walls
cannot single it out (the test room: tests/graph/rooms.py)."""

from __future__ import annotations

import numpy as np

from macroloc.graph.localizer import Localizer, LocalizerParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import ModelRegistrar
from macroloc.graph.rigid import apply
from macroloc.graph.surfaces import SurfaceIndex
from tests.graph.helpers import localizer_params
from tests.graph.rooms import T_TRUE, UP, WALL_SEGMENTS, seen_points
from tests.graph.scenes import make_T, rot_z, sightings_from
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
