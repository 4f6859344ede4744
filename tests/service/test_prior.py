"""Issue 57 item 3: the operator's prior (Nav2's /initialpose, a storey's name) is taken as a prior the registration
must still confirm: in the half-turn symmetric duplex a right one localizes a flight that stays ambiguous without it,
a wrong one (10 m off, on the other storey) never makes a wrong `localized`; the wire and ROS forms are checked as
every input is."""

from __future__ import annotations

import numpy as np
import pytest

from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose, pose_from_matrix


@pytest.fixture(scope="module")
def duplex_flight(duplex_path, tmp_path_factory):
    from macroloc.sim.truth_flight import write_truth_flight

    return write_truth_flight(duplex_path, tmp_path_factory.mktemp("flight") / "duplex.mcap", seed=1,
                              duration_s=12.0, storey="Level 2")


def _replay(flight, building, make_prior=None):  # noqa: ANN001, ANN202
    """The flight replayed as the service runs it (service.offline.run.replay_flight); `make_prior`: the operator's
    prior (a PoseEstimate, as on `initialpose`) from the first frame's true pose, sent after that frame (an operator
    after take-off)."""
    from macroloc.proto.recording import read_flight
    from macroloc.service.config import load_config
    from macroloc.service.offline.run import ReplayOptions, replay_flight

    prior = None
    if make_prior is not None:
        first = next(iter(read_flight(flight)))
        prior = make_prior(matrix_from_pose(first.ground_truth.T_cad_body), first.stamp_ns)
    return replay_flight(flight, building, load_config(None), ReplayOptions(seed=1), prior=prior)


def _pose_estimate(T_cad_body: np.ndarray, stamp_ns: int, storey: str = "") -> pb.PoseEstimate:
    m = pb.PoseEstimate(storey=storey, T_cad_body=pose_from_matrix(T_cad_body))
    m.header.frame_id, m.header.stamp_ns = "cad", stamp_ns
    return m


def test_a_right_prior_settles_the_symmetric_duplex_and_a_wrong_one_never_localizes_wrongly(duplex_flight,
                                                                                          duplex_path) -> None:
    def right(T_cad_body, stamp_ns):  # noqa: ANN001, ANN202
        return _pose_estimate(T_cad_body, stamp_ns)

    def wrong(T_cad_body, stamp_ns):  # noqa: ANN001, ANN202 - 10 m sideways, on the storey below
        T = T_cad_body.copy()
        T[:3, 3] += (10.0 * np.cos(0.3), 10.0 * np.sin(0.3), -3.1)
        return _pose_estimate(T, stamp_ns, storey="Level 1")

    none = _replay(duplex_flight, duplex_path)
    assert not none.result.localized and none.result.status_final == "ambiguous"  # its halves look alike
    taken = _replay(duplex_flight, duplex_path, right)
    assert taken.front_end.localizer.anchoring.prior is not None  # the service took the message
    assert taken.result.localized and taken.result.wrong_localizations == 0
    assert taken.front_end.localizer.anchoring.by_prior
    assert taken.result.ape.max is not None and taken.result.ape.max < 0.5
    refused = _replay(duplex_flight, duplex_path, wrong)
    assert refused.front_end.localizer.anchoring.prior is not None
    assert refused.result.wrong_localizations == 0 and not refused.front_end.localizer.anchoring.by_prior
    assert refused.result.status_final == "ambiguous"


def _parser():  # noqa: ANN202
    from macroloc.service.health import DropCounter
    from macroloc.service.inputs import InputLimits, InputParser

    parser = InputParser(["front"], DropCounter(), InputLimits(bounds_cad=(np.full(3, -10.0), np.full(3, 30.0))))
    parser.stamps.now_ns = lambda: 1_800_000_000 * 10**9
    return parser


def _prior_msg(xyz=(5.0, 1.0, 1.4), storey: str = "", stamp_ns: int = 0, cov=None) -> bytes:  # noqa: ANN001
    T = np.eye(4)
    T[:3, 3] = xyz
    m = pb.PoseEstimate(storey=storey)
    if xyz is not None:
        m.T_cad_body.CopyFrom(pose_from_matrix(T))
    if cov is not None:
        m.covariance.extend(np.asarray(cov, float).ravel())
    m.header.frame_id, m.header.stamp_ns = "cad", stamp_ns
    return m.SerializeToString()


def test_the_wire_prior_is_checked_as_every_input_is() -> None:
    parser = _parser()
    assert parser.prior(_prior_msg(stamp_ns=2**64 - 1)) is None
    assert parser.prior(_prior_msg((1e300, 0.0, 0.0))) is None
    assert parser.prior(_prior_msg((float("nan"), 0.0, 0.0))) is None
    assert parser.prior(_prior_msg(None)) is None  # neither pose nor storey
    assert parser.prior(_prior_msg(cov=np.full((6, 6), np.nan))) is None
    dropped = parser.drops.counts()
    assert {"initialpose/future_stamp", "initialpose/out_of_bounds", "initialpose/nan",
            "initialpose/empty"} <= set(dropped), dropped
    storey_only = parser.prior(_prior_msg(None, storey="Level 2"))
    assert storey_only is not None and storey_only.T_cad_body is None and storey_only.storey == "Level 2"
    cov = np.diag([0.0, 0.0, 0.04, 1.0, 0.25, 0.01])  # [rot; trans]: yaw sigma 0.2 rad, x sigma 1 m
    taken = parser.prior(_prior_msg(cov=cov, stamp_ns=1_800_000_000 * 10**9))
    assert taken is not None and np.allclose(taken.T_cad_body[:3, 3], (5.0, 1.0, 1.4))
    assert taken.sigma_xy_m == pytest.approx(1.0) and taken.sigma_yaw_rad == pytest.approx(0.2)


def test_rviz_initialpose_and_a_storey_name_become_priors() -> None:
    from macroloc.proto.ros_types import msg, to_cdr
    from macroloc.service.ros_out import RosKeys, RosPriorInputs

    parser = _parser()
    inputs = RosPriorInputs(RosKeys("t1"))
    intakes = inputs.intakes(parser)
    assert set(intakes) == {"initialpose", "t1/macroloc/storey"}

    def initialpose(frame: str = "map") -> bytes:
        cov = np.zeros((6, 6))
        cov[0, 0] = cov[1, 1] = 0.25  # rviz's 2D Pose Estimate: x, y 0.25 m^2, yaw 0.0685 rad^2
        cov[5, 5] = 0.06853891909122467
        yaw = 0.7
        m = msg("geometry_msgs/msg/PoseWithCovarianceStamped")(
            header=msg("std_msgs/msg/Header")(stamp=msg("builtin_interfaces/msg/Time")(sec=0, nanosec=0),
                                              frame_id=frame),
            pose=msg("geometry_msgs/msg/PoseWithCovariance")(
                pose=msg("geometry_msgs/msg/Pose")(
                    position=msg("geometry_msgs/msg/Point")(x=4.0, y=2.0, z=0.0),
                    orientation=msg("geometry_msgs/msg/Quaternion")(x=0, y=0, z=np.sin(yaw / 2), w=np.cos(yaw / 2))),
                covariance=cov.ravel()))
        return to_cdr(m, "geometry_msgs/msg/PoseWithCovarianceStamped")

    parse = intakes["initialpose"][0]
    assert parse(initialpose("odom")) is None
    assert parser.drops.counts().get("ros_initialpose/wrong_frame") == 1
    prior = parse(initialpose())
    assert prior is not None and prior.sigma_xy_m == pytest.approx(0.5)
    assert prior.sigma_yaw_rad == pytest.approx(np.sqrt(0.06853891909122467))
    assert np.allclose(prior.T_cad_body[:3, 3], (4.0, 2.0, 0.0))
    assert np.arctan2(prior.T_cad_body[1, 0], prior.T_cad_body[0, 0]) == pytest.approx(0.7)
    storey = intakes["t1/macroloc/storey"][0](to_cdr(msg("std_msgs/msg/String")(data="Level 2"), "std_msgs/msg/String"))
    assert storey is not None and storey.storey == "Level 2" and storey.T_cad_body is None


def test_tf_holds_map_to_odom_only_unless_odom_tf_is_configured() -> None:
    from macroloc.graph.localizer import Estimate
    from macroloc.service.ros_out import RosMessages

    T_cad_map, T_map_body = np.eye(4), np.eye(4)
    T_cad_map[:3, 3] = (1.0, 2.0, 0.0)
    est = Estimate(5, "localized", T_map_body, T_cad_map @ T_map_body, T_cad_map)
    pairs = {(t.header.frame_id, t.child_frame_id) for t in RosMessages("t1").tf(est).transforms}
    assert pairs == {("map", "odom")}
    pairs = {(t.header.frame_id, t.child_frame_id) for t in RosMessages("t1", odom_tf=True).tf(est).transforms}
    assert pairs == {("map", "odom"), ("odom", "base_link")}
    assert RosMessages("t1").tf(Estimate(5, "exploring", T_map_body)) is None  # nothing to say before localizing
