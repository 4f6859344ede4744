"""service.localizer_loop: the one loop around the localizer that the replay and the service both run."""

from __future__ import annotations

import numpy as np

from macroloc.graph.localizer import Localizer
from macroloc.service.front_end import FrontEnd
from macroloc.service.inputs import OdometryIn
from macroloc.service.localizer_loop import FrameIn, make_loop
from tests.graph.corridor_flight import model_registrar
from tests.graph.scenes import corridor_model, make_T


def _T(x_m: float) -> np.ndarray:
    return make_T(np.eye(3), np.array([x_m, 0.0, 1.4]))


def test_the_service_and_the_replay_make_the_same_keyframes() -> None:
    """The service's odometry events and the replay's frames go through one keyframe rule: the same frames
    become keyframes (here every 0.28 m: 0.04 m a frame, more than [graph.keyframes] translation_m = 0.25 m)."""
    model = corridor_model()
    backend = FrontEnd.fresh_or_restored(model, None)
    bare = make_loop(model)
    service, replay = [], []
    for k in range(40):
        stamp_ns = k * 33_000_000
        backend.odometry(OdometryIn(stamp_ns, _T(0.04 * k)))
        service.append(backend.loop.keyframe)
        bare.frame(FrameIn(stamp_ns, _T(0.04 * k)))
        replay.append(bare.keyframe)
    assert service == replay
    assert [k for k, is_kf in enumerate(replay) if is_kf] == list(range(0, 40, 7))


def test_dead_reckoned_seconds_add_up_until_the_next_keyframe(monkeypatch) -> None:  # noqa: ANN001
    session = make_loop(corridor_model())
    given: list[float] = []
    add_keyframe = Localizer.add_keyframe

    def spy(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        given.append(kwargs["dead_reckoned_s"])
        return add_keyframe(self, *args, **kwargs)

    monkeypatch.setattr(Localizer, "add_keyframe", spy)
    for k in range(14):  # 0.1 s apart, not moving: a keyframe every 0.34 s (4 frames)
        session.frame(FrameIn(k * 100_000_000, _T(0.0), dead_reckoned_s=0.1 if k >= 2 else 0.0))
    assert np.allclose(given, [0.0, 0.3, 0.4, 0.4])  # frames 0, 4, 8, 12


def test_a_frame_s_depth_is_measured_only_where_it_becomes_a_keyframe(monkeypatch) -> None:  # noqa: ANN001
    """`FrameIn.measure_depth` is called for the keyframes (every 0.28 m here, as above) and no other frame, and
    the keyframe takes what it measured."""
    session = make_loop(corridor_model())
    measured: list[int] = []
    taken: list[np.ndarray] = []
    depth_at = Localizer._depth_at

    def spy(self, T_odom_body, points_body):  # noqa: ANN001, ANN202
        out = depth_at(self, T_odom_body, points_body)
        taken.append(out)
        return out

    monkeypatch.setattr(Localizer, "_depth_at", spy)
    for k in range(22):
        points = np.array([[2.0 + k, 0.0, 0.0]])
        session.frame(FrameIn(k * 33_000_000, _T(0.04 * k),
                              measure_depth=lambda k=k, p=points: measured.append(k) or p))
    assert measured == [0, 7, 14, 21]
    assert [float(t[0, 0]) for t in taken] == [2.0, 9.0, 16.0, 23.0]


def test_a_fresh_graph_keeps_the_old_one_s_settings_and_camera() -> None:
    """Where the pose graph fails the session starts a new localizer: with the failed one's iSAM2 settings (its
    window, not the defaults) and camera position, whether the session was made by the factory or directly."""
    from macroloc.graph.posegraph import IsamSettings, PoseGraph
    from macroloc.service.localizer_loop import LocalizerLoop

    model = corridor_model()
    T_body_cam = np.eye(4)
    T_body_cam[:3, 3] = (0.1, 0.05, 0.02)
    settings = IsamSettings(window_keyframes=300, marginalise_landmarks=False)
    old = Localizer(model, PoseGraph(settings), model_registrar(model), T_body_cam=T_body_cam)  # the tests' registrar
    new = LocalizerLoop(old).fresh(old)
    assert new is not old and new.graph.settings == settings
    assert np.allclose(new.viewer_body, old.viewer_body) and new.registrar is old.registrar


def test_the_snapshot_gives_a_frame_between_keyframes_the_session_s_own_pose() -> None:
    """What the service answers a stereo frame with on its arrival (`PoseSnapshot.at`, from the newest keyframe,
    without the localizer) is what the session itself gives that frame between keyframes: pose, CAD pose, status."""
    from macroloc.graph.posegraph import PoseGraph
    from macroloc.service.localizer_loop import LocalizerLoop
    from tests.graph.scenes import drifting_odometry, sightings_from, straight_flight

    model = corridor_model()
    session = LocalizerLoop(Localizer(model, PoseGraph(), model_registrar(model)))
    truth = straight_flight(60, step_m=0.1)
    odometry = drifting_odometry(truth)
    compared = 0
    for k, (T_true, T_odom) in enumerate(zip(truth, odometry, strict=True)):
        stamp_ns = k * 33_000_000
        snapshot = session.snapshot
        est = session.frame(FrameIn(stamp_ns, T_odom, sightings_from(model, T_true) if k % 3 == 0 else []))
        if session.keyframe or snapshot is None:
            continue
        answer = snapshot.at(stamp_ns, T_odom)
        assert answer.status == est.status
        np.testing.assert_allclose(answer.T_map_body, est.T_map_body, atol=1e-9)
        assert (answer.T_cad_body is None) == (est.T_cad_body is None)
        if est.T_cad_body is not None:
            np.testing.assert_allclose(answer.T_cad_body, est.T_cad_body, atol=1e-9)
            compared += 1
    assert compared >= 10 and session.status == "localized"


def test_the_service_gives_the_keyframes_gravity_s_up_from_the_imu_less_the_odometry_s_acceleration(
        monkeypatch) -> None:  # noqa: ANN001
    """The IMU is the session's input (the replay runs the same front end): the service's IMU and odometry events
    (service.front_end) give every keyframe the up of the specific force less the odometry's acceleration (here a
    vehicle accelerating along x at 1 m/s^2, rolled 5 degrees: the specific force alone leans 5.8 degrees off up)."""
    from scipy.spatial.transform import Rotation

    from macroloc.service.inputs import ImuIn

    given: list[np.ndarray | None] = []
    add_keyframe = Localizer.add_keyframe

    def spy(self, stamp_ns, T_map_body, sightings, up_body=None, **kwargs):  # noqa: ANN001, ANN003, ANN202
        given.append(None if up_body is None else np.array(up_body))
        return add_keyframe(self, stamp_ns, T_map_body, sightings, up_body, **kwargs)

    monkeypatch.setattr(Localizer, "add_keyframe", spy)
    R = Rotation.from_euler("x", 5, degrees=True).as_matrix()
    accel_odom = np.array([1.0, 0.0, 0.0])

    def T_at(t_s: float) -> np.ndarray:
        T = _T(0.5 * t_s * t_s)
        T[:3, :3] = R
        return T

    backend = FrontEnd.fresh_or_restored(corridor_model(), None)
    f_body = R.T @ (accel_odom + [0.0, 0.0, 9.81])
    for k in range(45):
        stamp_ns = k * 33_000_000
        for s in [stamp_ns - 33_000_000 + 5_000_000 * (j + 1) for j in range(6)] if k else [stamp_ns]:
            backend.imu(ImuIn(s, tuple(f_body), (0.0, 0.0, 0.0)))
        backend.odometry(OdometryIn(stamp_ns, T_at(stamp_ns * 1e-9)))
    true_up = R.T @ [0.0, 0.0, 1.0]

    def off_deg(up: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip(up @ true_up / np.linalg.norm(up), -1, 1))))

    assert off_deg(f_body) > 5.0  # the specific force alone
    ups = [up for up in given if up is not None]
    assert len(given) >= 4 and ups and ups[-1] is given[-1]
    assert off_deg(ups[-1]) < 0.5


def test_a_frame_s_own_up_is_used_instead_of_the_session_s() -> None:
    """A driver that knows up otherwise (the simulator's truth) hands it with the frame; the session's from the
    IMU is used only where the frame brings none."""
    from unittest import mock

    session = make_loop(corridor_model())
    session.imu(np.array([[0.0, 0.0, 9.81]]))
    session.odometry(0, _T(0.0))
    own = np.array([0.0, 0.1, 1.0]) / np.linalg.norm([0.0, 0.1, 1.0])
    with mock.patch.object(Localizer, "add_keyframe", autospec=True, side_effect=Localizer.add_keyframe) as spy:
        session.frame(FrameIn(0, _T(0.0), up_body=own))
        session.frame(FrameIn(400_000_000, _T(0.0)))
    assert np.allclose(spy.call_args_list[0].args[4], own)
    assert np.allclose(spy.call_args_list[1].args[4], [0.0, 0.0, 1.0])


def test_the_configured_gravity_reaches_the_session() -> None:
    from macroloc.service.config import load_config
    from macroloc.service.localizer_loop import loop_from_config

    cfg = load_config(None, perception={"gravity": {"window_s": 2.0}})
    assert loop_from_config(cfg, corridor_model()).gravity.params.window_s == 2.0


def test_a_keyframe_older_than_the_newest_pose_moves_it() -> None:
    """In the service a stereo frame is perceived after newer odometry samples were handled: its keyframe (the
    older stamp) may localize the graph, and the newest pose (`last`: the plan's start, the saved map's pose) is
    then tracked again on that graph instead of staying as it was computed before."""
    from tests.graph.scenes import sightings_from, straight_flight

    model = corridor_model()
    session = make_loop(model, registrar=model_registrar(model))
    poses = straight_flight(30)
    localized_at = None
    for k, T in enumerate(poses):
        T_next = poses[min(k + 1, len(poses) - 1)]
        session.frame(FrameIn(k * 100_000_000 + 50_000_000, T_next))  # the newer odometry, handled first
        est = session.frame(FrameIn(k * 100_000_000, T, sightings_from(model, T)))  # the older frame's sightings
        if est.status == "localized":
            localized_at = k
            break
    assert localized_at is not None and session.keyframe
    last = session.last
    assert last is not None and last.stamp_ns == localized_at * 100_000_000 + 50_000_000
    assert last.status == "localized" and last.T_cad_body is not None
    expected = est.T_cad_body @ np.linalg.inv(poses[localized_at]) @ poses[min(localized_at + 1, len(poses) - 1)]
    assert np.allclose(last.T_cad_body, expected, atol=1e-6)  # moved on by the odometry since the keyframe
