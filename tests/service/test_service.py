"""The service over real Zenoh sessions on loopback: poses, queries, liveliness, bad input, restart, router."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
import zenoh

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose
from macroloc.service.zenoh_io import session_config
from tests.service.helpers import (
    FakeFlight,
    client,
    free_port,
    loopback,
    running_service,
    service_config,
    wait_for,
    wait_subscribed,
    yaw_T,
)


@pytest.fixture(scope="module")
def start_pose(office_model) -> np.ndarray:
    door = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"][10]
    return yaw_T(0.3, door.centroid_cad + np.r_[door.normal_cad[:2] * 1.5, 0.4])


class Collector:
    """Messages of one type received on a key, kept in order."""

    def __init__(self, session: zenoh.Session, key: str, cls: Any) -> None:
        self.items: list = []
        self._sub = session.declare_subscriber(key, lambda s: self.items.append(cls.FromString(s.payload.to_bytes())))

    def last(self):  # noqa: ANN201
        return self.items[-1] if self.items else None


def fly(session: zenoh.Session, flight: FakeFlight, T_cad_body: np.ndarray, steps: int, first_stamp_ns: int = 0,
        vehicle: str = "t1", observe_every: int = 5) -> np.ndarray:
    """Publish odometry (and sightings every few steps) along a straight line, once the service subscribes;
    returns the final T_cad_body."""
    wait_subscribed(session, f"macroloc/{vehicle}/observations")
    T = T_cad_body.copy()
    for k in range(steps):
        stamp = first_stamp_ns + (k + 1) * 33_000_000
        session.put(f"macroloc/{vehicle}/imu", flight.imu(stamp, T).SerializeToString())
        session.put(f"macroloc/{vehicle}/odometry", flight.odometry(stamp, T).SerializeToString())
        if k % observe_every == 0:
            session.put(f"macroloc/{vehicle}/observations", flight.observations(stamp, T).SerializeToString())
        if k < steps - 1:
            T = T @ yaw_T(0.0, np.array([0.02, 0.0, 0.0]))
    return T


def _localized_at(poses: Collector, T: np.ndarray, tol_m: float = 0.3):  # noqa: ANN202
    p = poses.last()
    if p is None or p.status != pb.PoseEstimate.LOCALIZED:
        return False
    xyz = np.array([p.T_cad_body.position.x, p.T_cad_body.position.y, p.T_cad_body.position.z])
    return np.linalg.norm(xyz - T[:3, 3]) < tol_m


def _query(session: zenoh.Session, key: str, cls: Any, payload: bytes | None = None):  # noqa: ANN202
    replies = list(session.get(key, payload=payload, timeout=20.0))
    assert replies and replies[0].ok is not None, f"no reply on {key}"
    return cls.FromString(replies[0].ok.payload.to_bytes())


def test_localizes_answers_queries_and_holds_a_token(office_path, office_model, start_pose, tmp_path) -> None:
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)), client(port) as s:
        alive = list(s.liveliness().get("macroloc/t1/alive", timeout=10.0))
        assert [str(r.ok.key_expr) for r in alive if r.ok] == ["macroloc/t1/alive"]
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        waypoints = Collector(s, "macroloc/t1/waypoints", pb.Waypoints)
        status = Collector(s, "macroloc/t1/status", pb.ServiceStatus)
        features = Collector(s, "macroloc/t1/features", pb.ObservedFeatures)
        flight = FakeFlight(office_model, yaw_T(0.7, np.array([3.0, -2.0, 0.1])))
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="a localized pose near the truth")
        snap = _query(s, "macroloc/t1/map", pb.MapSnapshot)
        assert snap.status == pb.PoseEstimate.LOCALIZED and len(snap.landmarks_map) >= 4
        assert any(lm.id for lm in snap.landmarks_map)  # landmarks linked to CAD features
        plan = _query(s, "macroloc/t1/plan", pb.Waypoints, pb.Goal(space_name="121").SerializeToString())
        assert not plan.error and len(plan.points_cad) >= 2 and plan.path_length_m > 0
        s.put("macroloc/t1/goal", pb.Goal(space_name="MENS RR").SerializeToString())
        fly(s, flight, T, 3, first_stamp_ns=10**9)
        wait_for(lambda: waypoints.last() is not None and len(waypoints.last().points_cad) >= 2, what="waypoints")
        wait_for(lambda: status.last() is not None and status.last().status == pb.PoseEstimate.LOCALIZED,
                 what="a status message")
        wait_for(lambda: features.last() is not None and features.last().header.frame_id == "cad"
                 and any(f.id for f in features.last().features), what="reconstructed features in the CAD frame")


def _bad_inputs() -> dict[str, list[bytes]]:
    nan_odo = pb.Odometry()
    nan_odo.header.stamp_ns = 5
    nan_odo.T_map_body.position.x = float("nan")
    nan_odo.T_map_body.qw = 1.0
    stereo = pb.StereoFrame(camera_id="mystery")
    stereo.header.stamp_ns = 1
    wrong_size = pb.StereoFrame(camera_id="front")
    wrong_size.header.stamp_ns = 2
    wrong_size.left.CopyFrom(pb.Image(width=640, height=480, encoding=pb.Image.RAW_MONO8, data=b"x" * 100))
    wrong_size.right.CopyFrom(wrong_size.left)
    obs = pb.ObservedFeatures()
    obs.header.frame_id = "body"
    obs.features.add(type="door").corners.add(x=1.0)  # one corner, not four
    return {
        "odometry": [b"\xff\xff\xff not protobuf", nan_odo.SerializeToString()],
        "stereo": [b"\x00\x01garbage", stereo.SerializeToString(), wrong_size.SerializeToString()],
        "imu": [b"\xffjunk"],
        "observations": [obs.SerializeToString(), b"\xfe\xfe"],
        "goal": [pb.Goal().SerializeToString()],
    }


def test_malformed_input_is_counted_and_dropped(office_path, office_model, start_pose, tmp_path) -> None:
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)) as service, client(port) as s:
        diagnostics = Collector(s, "macroloc/t1/diagnostics", pb.Diagnostics)
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        flight = FakeFlight(office_model, np.eye(4))
        T = fly(s, flight, start_pose, 3, first_stamp_ns=10**9)
        def taken() -> int:
            return sum(service.drops.counts().values())  # type: ignore[attr-defined]

        for key, payloads in _bad_inputs().items():
            for payload in payloads:
                n_before = taken()
                s.put(f"macroloc/t1/{key}", payload)
                if key == "stereo":  # a ring channel keeps only the latest frames: one at a time
                    wait_for(lambda: taken() > n_before, what="the frame taken in")  # noqa: B023 - called at once
        s.put("macroloc/t1/odometry", flight.odometry(10, T).SerializeToString())  # a stamp from the past
        expected = {"odometry/not_protobuf", "odometry/nan", "odometry/out_of_order", "stereo/not_protobuf",
                    "stereo/unknown_camera", "stereo/bad_image", "imu/not_protobuf", "observations/bad_shape",
                    "observations/not_protobuf", "goal/empty"}

        def counted() -> set[str]:
            last = diagnostics.last()
            return set() if last is None else {k for k, v in last.dropped.items() if v > 0}

        try:
            wait_for(lambda: expected <= counted(), what="every drop counted")
        except AssertionError:
            raise AssertionError(f"missing drops: {expected - counted()}") from None
        n = len(poses.items)
        fly(s, flight, T, 2, first_stamp_ns=2 * 10**9)  # still serving
        wait_for(lambda: len(poses.items) >= n + 2, what="poses after the bad input")


def test_restart_from_the_saved_map_relocalizes_at_once(office_path, office_model, start_pose, tmp_path) -> None:
    flight = FakeFlight(office_model, yaw_T(-1.1, np.array([-4.0, 7.0, 0.0])))
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)), client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="localized before the restart")
    assert (tmp_path / "t1" / "map.pb").exists()
    # the restarted service sees a few doors: too few to register against the whole building
    port = free_port()
    flight.range_m = 2.5
    with running_service(service_config(office_path, tmp_path, port)), client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        # 0.8 s: past two keyframe intervals (a landmark takes part once seen from two keyframes)
        T = fly(s, flight, T, 24, first_stamp_ns=5 * 10**9, observe_every=1)
        assert len(flight.observations(0, T).features) < 4  # the whole-model registration needs 4
        wait_for(lambda: _localized_at(poses, T), what="re-localized from the saved map")


def test_a_restart_stopped_before_localizing_keeps_the_saved_map(office_path, office_model, start_pose,
                                                                 tmp_path) -> None:
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)), client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        T = fly(s, FakeFlight(office_model, np.eye(4)), start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="localized before the restart")
    saved = (tmp_path / "t1" / "map.pb").read_bytes()
    assert pb.MapSnapshot.FromString(saved).status == pb.PoseEstimate.LOCALIZED
    with running_service(service_config(office_path, tmp_path, free_port())):
        pass  # stopped before it saw anything
    assert (tmp_path / "t1" / "map.pb").read_bytes() == saved


def test_through_a_router(office_path, office_model, start_pose, tmp_path) -> None:
    """Service and vehicle both connect to a router (a Python session in router mode), never to each other."""
    from macroloc.service.zenoh_io import session_config

    router_port = free_port()
    router_conf = session_config(loopback(mode="router", listen=[f"tcp/127.0.0.1:{router_port}"]))
    with zenoh.open(router_conf):
        cfg = service_config(office_path, tmp_path, free_port())
        cfg.zenoh = loopback(mode="peer", listen=[], connect=[f"tcp/127.0.0.1:{router_port}"])
        with running_service(cfg), client(router_port, mode="client") as s:
            poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
            flight = FakeFlight(office_model, np.eye(4))
            wait_for(lambda: list(s.liveliness().get("macroloc/t1/alive", timeout=2.0)), what="token via router")
            T = fly(s, flight, start_pose, 40)
            wait_for(lambda: _localized_at(poses, T), what="poses through the router")


def test_stop_event_drains_and_saves(office_path, office_model, start_pose, tmp_path) -> None:
    """Stopping (what SIGTERM does) handles every queued input before the map is written."""
    port = free_port()
    cfg = service_config(office_path, tmp_path, port)
    with running_service(cfg) as service, client(port) as s:
        fly(s, FakeFlight(office_model, np.eye(4)), start_pose, 40)
        wait_for(lambda: service.rates["odometry"].total == 40, what="all odometry taken in")  # type: ignore
    snap = pb.MapSnapshot.FromString((tmp_path / "t1" / "map.pb").read_bytes())
    assert snap.status == pb.PoseEstimate.LOCALIZED
    assert snap.header.stamp_ns == 40 * 33_000_000  # the last odometry was handled before saving
    assert threading.active_count() < 50


def test_obstacles_seen_in_depth_enter_the_planner(office_path, office_model, start_pose, tmp_path) -> None:
    """A wall the model does not have, 1.5 m ahead in a frame's depth image, marks the planner's grid there."""
    from macroloc.common.geometry import forward_stereo_T_body_cam
    from macroloc.proto.recording import pose_from_matrix

    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)) as service, client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        T = fly(s, FakeFlight(office_model, np.eye(4)), start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="localized")
        image = pb.Image(width=64, height=48, encoding=pb.Image.RAW_MONO8, data=bytes(64 * 48))  # as CameraInfo says
        depth = np.full((48, 64), 1.5, "<f4")
        frame = pb.StereoFrame(camera_id="front", left=image, right=image,
                               depth=pb.Image(width=64, height=48, encoding=pb.Image.RAW_DEPTH_F32,
                                              data=depth.tobytes()),
                               info=pb.CameraInfo(width=64, height=48, fx=48, fy=48, cx=31.5, cy=23.5,
                                                  baseline_m=0.12,
                                                  T_body_cam=pose_from_matrix(forward_stereo_T_body_cam())))
        frame.header.stamp_ns = 41 * 33_000_000
        s.put("macroloc/t1/stereo", frame.SerializeToString())
        ahead_cad = T[:3, 3] + T[:3, 0] * 1.6  # body x is forward; the wall is 1.5 m ahead of the camera
        grid, layer = service.planner.grid(T[2, 3])  # type: ignore[attr-defined]
        r, c = grid.cell_of(ahead_cad)
        wait_for(lambda: layer.occupied()[r - 1:r + 2, c - 1:c + 2].any(), what="the seen wall in the obstacle layer")
        assert not layer.occupied()[grid.cell_of(T[:3, 3])], "nothing seen where the vehicle is"


def test_a_stereo_frame_is_answered_while_the_worker_is_busy(office_path, office_model, start_pose, tmp_path) -> None:
    """A frame's pose goes out on its arrival, from the newest keyframe's estimate moved by the odometry at its
    stamp, while the worker cannot touch the localizer (here: its lock held, as by a long registration)."""
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)) as service, client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        flight = FakeFlight(office_model, np.eye(4))
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="localized")
        image = pb.Image(width=64, height=48, encoding=pb.Image.RAW_MONO8, data=bytes(64 * 48))
        frame = pb.StereoFrame(camera_id="front", left=image, right=image,
                               info=pb.CameraInfo(width=64, height=48, fx=48, fy=48, cx=31.5, cy=23.5, baseline_m=0.12))
        stamp = 45 * 33_000_000
        T_moved = T @ yaw_T(0.0, np.array([0.3, 0.0, 0.0]))
        with service._lock:  # type: ignore[attr-defined]
            s.put("macroloc/t1/odometry", flight.odometry(stamp, T_moved).SerializeToString())
            # its own intake thread: else the frame may come first and take the newest odometry before it
            wait_for(lambda: stamp in service._odometry, what="the odometry taken")  # type: ignore[attr-defined]
            frame.header.stamp_ns = stamp
            s.put("macroloc/t1/stereo", frame.SerializeToString())
            wait_for(lambda: any(p.header.stamp_ns == stamp for p in poses.items), what="the frame's pose")
        p = next(p for p in poses.items if p.header.stamp_ns == stamp)
        assert p.status == pb.PoseEstimate.LOCALIZED
        xyz = np.array([p.T_cad_body.position.x, p.T_cad_body.position.y, p.T_cad_body.position.z])
        assert np.linalg.norm(xyz - T_moved[:3, 3]) < 0.1  # the odometry's 0.3 m since the last keyframe


def test_a_storey_hint_that_is_not_in_the_building_is_refused_at_start(office_path, tmp_path) -> None:
    from macroloc.graph.errors import UserInputError
    from macroloc.service.serve import build_service

    cfg = service_config(office_path, tmp_path, free_port())
    cfg = cfg.model_copy(update={"graph": cfg.graph.model_copy(update={"storey_hint": "Level 9"})})
    with pytest.raises(UserInputError, match="storey 'Level 9' has no doors or windows.*Level 1, Level 2"):
        build_service(cfg, session=None)
    cfg = cfg.model_copy(update={"graph": cfg.graph.model_copy(update={"storey_hint": "Level 2"})})
    with zenoh.open(session_config(loopback())) as session:
        service = build_service(cfg, session)
    assert service.front_end.localizer.registrar.storey_hint == "Level 2"  # type: ignore[attr-defined]


def test_the_service_takes_the_configured_perception_parameters(office_path, tmp_path) -> None:
    """[perception.*] reach the running service's front end: its depth images' sampling, its place recognition,
    its gravity, the chain's cadence; [service] odometry its odometry."""
    from macroloc.service.serve import build_service

    cfg = service_config(office_path, tmp_path, free_port())
    perception = cfg.perception.model_validate({"place": {"min_inliers": 55}, "depth": {"depth_image_stride_px": 12},
                                               "gravity": {"window_s": 1.5}, "detect_every": 2})
    cfg = cfg.model_copy(update={"perception": perception,
                                 "service": cfg.service.model_copy(update={"odometry": "visual"})})
    with zenoh.open(session_config(loopback())) as session:
        service = build_service(cfg, session)
    front_end = service.front_end
    assert front_end.params.place is not None and front_end.params.place.min_inliers == 55
    assert front_end.places.config == front_end.params.place
    assert front_end.params.depth.depth_image_stride_px == 12 and front_end.params.perceive_every == 2
    assert front_end.loop.gravity.params.window_s == 1.5
    assert front_end.visual is not None


def test_maps_accumulate_across_restarts(office_path, office_model, start_pose, tmp_path) -> None:
    """A restart that flies elsewhere keeps the earlier flight's landmarks in its saved map (merged, no duplicate)."""
    flight = FakeFlight(office_model, yaw_T(0.4, np.array([2.0, -3.0, 0.0])))
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)), client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        T = fly(s, flight, start_pose, 40)
        wait_for(lambda: _localized_at(poses, T), what="localized in the first flight")
    first = pb.MapSnapshot.FromString((tmp_path / "t1" / "map.pb").read_bytes())
    first_ids = {lm.id for lm in first.landmarks_map if lm.id}
    assert first_ids
    by_id = {f.id: f for f in office_model.features}
    # the second flight starts 8 m away along another corridor: doors the first never saw
    elsewhere = [f for f in office_model.features if f.type == "door" and f.storey == "Level 1"
                 and min(np.linalg.norm(f.centroid_cad - by_id[i].centroid_cad)
                         for i in first_ids) > 8.0][0]
    start2 = yaw_T(1.2, elsewhere.centroid_cad + np.r_[elsewhere.normal_cad[:2] * 1.5, 0.4])
    port = free_port()
    with running_service(service_config(office_path, tmp_path, port)), client(port) as s:
        poses = Collector(s, "macroloc/t1/pose", pb.PoseEstimate)
        T = fly(s, FakeFlight(office_model, yaw_T(-0.5, np.array([1.0, 4.0, 0.0]))), start2, 40,
                first_stamp_ns=10**10)
        wait_for(lambda: _localized_at(poses, T), what="localized in the second flight")
    second = pb.MapSnapshot.FromString((tmp_path / "t1" / "map.pb").read_bytes())
    ids = [lm.id for lm in second.landmarks_map if lm.id]
    assert first_ids <= set(ids), "the first flight's landmarks were lost"
    assert set(ids) - first_ids, "the second flight added none"
    assert len(ids) == len(set(ids)), "a landmark was kept twice"
    # carried landmarks sit where the model has them, in the second flight's map frame
    T_cad_map = matrix_from_pose(second.T_cad_map)
    for lm in second.landmarks_map:
        if lm.id in first_ids:
            corners = np.array([[c.x, c.y, c.z] for c in lm.corners]) @ T_cad_map[:3, :3].T + T_cad_map[:3, 3]
            assert np.linalg.norm(corners.mean(axis=0) - by_id[lm.id].centroid_cad) < 0.3
