"""The service's frame pipeline and stereo depth points for the surface check (service/frames.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import encode_image, pose_from_matrix


def textured_pair(disparity_px: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A fronto-parallel textured plane: the right image is the left shifted by the disparity."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (480, 640 + disparity_px)).astype(np.uint8), (5, 5), 1.2)
    left = texture[:, :640]
    right = texture[:, disparity_px:disparity_px + 640]
    return left, right


def _plane_frame() -> pb.StereoFrame:
    from macroloc.common.geometry import forward_stereo_T_body_cam

    left, right = textured_pair(24)
    info = pb.CameraInfo(width=640, height=480, fx=480.0, fy=480.0, cx=319.5, cy=239.5, baseline_m=0.12,
                         T_body_cam=pose_from_matrix(forward_stereo_T_body_cam()))
    return pb.StereoFrame(left=encode_image(left), right=encode_image(right), info=info)


def _plane_rig():  # noqa: ANN202 - StereoRig
    from macroloc.perception.calib import StereoRig

    return StereoRig(480.0, 480.0, 319.5, 239.5, 0.12, 640, 480)


def test_by_default_a_frame_s_depth_points_are_measured_only_when_asked_for() -> None:
    """[perception.depth] at_keyframes (the default): no frame measures depth points as it comes; each leaves a
    measurement, which the session calls where the frame becomes a keyframe, and which measures that frame's (not
    a later one's: the images are the frame's own)."""
    from macroloc.common.geometry import forward_stereo_T_body_cam
    from macroloc.perception.params import DepthPointsParams
    from macroloc.service.frames import StereoDepth

    depth, T_body_cam = StereoDepth.configured(DepthPointsParams()), forward_stereo_T_body_cam()
    near_left, near_right = textured_pair(24)
    far_left, far_right = textured_pair(12, seed=1)  # the plane twice as far
    assert depth(near_left, near_right, _plane_rig(), T_body_cam) is None
    first = depth.deferred(near_left, near_right, _plane_rig(), T_body_cam)
    assert depth(far_left, far_right, _plane_rig(), T_body_cam) is None
    second = depth.deferred(far_left, far_right, _plane_rig(), T_body_cam)
    assert first is not None and second is not None
    near_points, far_points = first(), second()
    assert len(near_points) > 500 and len(far_points) > 500
    assert np.median(near_points[:, 0]) == pytest.approx(2.5, abs=0.05)  # 2.4 m + the camera's 0.10 m
    assert np.median(far_points[:, 0]) == pytest.approx(4.9, abs=0.1)


def test_every_third_frame_measures_depth_points_of_the_plane() -> None:
    from macroloc.common.geometry import forward_stereo_T_body_cam
    from macroloc.perception.params import DepthPointsParams
    from macroloc.service.frames import StereoDepth

    depth = StereoDepth.configured(DepthPointsParams(at_keyframes=False))
    left, right = textured_pair(24)
    measured = []
    for _ in range(4):
        measured.append(depth(left, right, _plane_rig(), forward_stereo_T_body_cam()))
        assert depth.deferred(left, right, _plane_rig(), forward_stereo_T_body_cam()) is None
    assert measured[1] is None and measured[2] is None and measured[3] is not None
    points = measured[0]
    assert points is not None and len(points) > 500
    # the plane is z = fx b / d = 2.4 m ahead of the camera: body x (forward) = 2.4 + the camera's 0.10 m
    assert np.median(points[:, 0]) == pytest.approx(2.5, abs=0.05)


def test_depth_points_reach_a_wall_nearer_than_the_chains_search() -> None:
    """A wall 0.70 m ahead (82 px of disparity): the depth points' SGBM searches 128 disparities and finds it;
    searching the perception chain's 64 (down to 0.9 m) it would be matched at a wrong disparity, behind itself."""
    from macroloc.perception.calib import StereoRig
    from macroloc.service.frames import StereoDepth

    left, right = textured_pair(82)
    rig = StereoRig(480.0, 480.0, 319.5, 239.5, 0.12, 640, 480)
    z_m = {}
    for n in (128, 64):
        points = StereoDepth(every=1, num_disparities=n)(left, right, rig, np.eye(4))
        assert points is not None
        z_m[n] = points[:, 2]
    assert len(z_m[128]) > 500 and np.mean(np.abs(z_m[128] - 0.70) < 0.02) > 0.95
    assert np.mean(np.abs(z_m[64] - 0.70) < 0.1) < 0.05, "the chain's search range would have measured it too"


def test_the_configured_chain_parameters_reach_the_service_s_chain_and_odometry() -> None:
    """[perception.*] reach the components that use them: the frame's SGBM, the sides, the plausibility limits
    and the wall plane in the service's chain (the replay's too: it runs the service's front end), the depth
    points and the visual odometry's settings (gravity is the session's: test_session)."""
    pytest.importorskip("onnxruntime")
    from macroloc.service.config import load_config
    from macroloc.service.frames import make_perception_pipeline
    from macroloc.service.front_end import FrontEnd, FrontEndParams
    from macroloc.service.visual_odometry import VisualOdometry

    cfg = load_config(None, perception={"stereo": {"num_disparities": 64}, "lines": {"margin": 0.2},
                                        "plausibility": {"max_side_angle_deg": 9.0}, "wall_plane": {"iterations": 8},
                                        "odometry": {"tracker": "klt"}, "gravity": {"window_s": 2.0},
                                        "depth": {"every": 2, "stride_px": 8, "max_range_m": 6.0,
                                                  "at_keyframes": False},
                                        "inertial": {"calibrate_s": 2.0}})
    params = cfg.perception.to_params()
    pipeline = make_perception_pipeline(params=params)
    assert pipeline is not None
    import cv2

    assert cv2.getNumThreads() == 1  # the service keeps a core for its answers (perception.threads.SERVICE_THREADS)
    front_end = FrontEnd(None, None, pipeline=pipeline, params=FrontEndParams.configured(cfg))  # type: ignore[arg-type]
    depth = front_end.stereo_depth
    assert depth is not None and depth.every == 2 and depth.stride_px == 8 and depth.range_m == (0.3, 6.0)
    assert not depth.at_keyframes and depth.matcher is pipeline.disparity  # the chain's SGBM, shared
    chain = pipeline.perception
    assert chain.matcher.config.num_disparities == 64 and chain.lines.margin == 0.2
    assert chain.plausibility.max_side_angle_deg == 9.0 and chain.wall is not None and chain.wall.iterations == 8
    odometry = VisualOdometry(params=params)
    assert odometry._params.odometry.tracker == "klt"
    assert odometry._depth.every == 2 and odometry._depth.stride_px == 8 and not odometry._depth.at_keyframes
    assert odometry._inertial.params.calibrate_s == 2.0


def test_the_service_s_chain_is_told_which_way_is_down_by_the_session_s_up() -> None:
    """The service's pipeline hands the chain gravity in the camera frame from the up it is given (the session's,
    from the IMU), as a replay's chain has it; without one, none."""
    pytest.importorskip("onnxruntime")
    from macroloc.perception.pipeline import Perception
    from macroloc.service.frames import PerceptionPipeline

    chain = Perception.create(None)
    given = []
    process = chain.process
    chain.process = lambda pair: given.append(pair.gravity_cam) or process(pair)  # type: ignore[method-assign]
    pipeline = PerceptionPipeline(chain)
    pipeline(_plane_frame(), np.array([0.0, 0.0, 1.0]))
    pipeline(_plane_frame())
    assert given[0] is not None and np.allclose(given[0], [0.0, 1.0, 0.0])  # the optical frame's y points down
    assert given[1] is None
