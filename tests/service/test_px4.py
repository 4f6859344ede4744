"""PX4 messages in a geo-referenced building (FZK-Haus: true north 40 deg from +x): the CAD pose through NED,
and setpoint yaws from the path's direction."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from macroloc.graph.geo import read_geo_reference
from macroloc.graph.localizer import Estimate
from macroloc.service.ned import quat_wxyz_from_matrix
from macroloc.service.px4 import Px4Messages


@pytest.fixture(scope="module")
def fzk_geo(fzk_path):  # noqa: ANN201
    return read_geo_reference(fzk_path)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
       st.lists(st.floats(-30, 30), min_size=3, max_size=3))
def test_visual_odometry_is_the_cad_pose_in_ned(fzk_geo, q: list[float], t: list[float]) -> None:
    geo = fzk_geo
    assert geo is not None
    T_cad_body = np.eye(4)
    T_cad_body[:3, :3], T_cad_body[:3, 3] = Rotation.from_quat(q).as_matrix(), t
    est = Estimate(5_000_000, "localized", np.eye(4), T_cad_body, np.eye(4), np.diag([1e-4] * 3 + [4e-4] * 3))
    msgs = Px4Messages(geo.T_enu_cad())
    # by hand: north and east unit vectors in the CAD plane, NED rows (north, east, down)
    north = np.r_[geo.north_cad, 0.0]
    east = np.array([geo.north_cad[1], -geo.north_cad[0], 0.0])
    R_ned_cad = np.vstack([north, east, [0.0, 0.0, -1.0]])
    p_ned = R_ned_cad @ (T_cad_body[:3, 3] - geo.origin_cad)
    R_ned_frd = R_ned_cad @ T_cad_body[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    T = msgs.T_ned_frd(T_cad_body)
    assert np.abs(T[:3, 3] - p_ned).max() < 1e-9
    assert np.abs(quat_wxyz_from_matrix(T[:3, :3]) - quat_wxyz_from_matrix(R_ned_frd)).max() < 1e-9
    m = msgs.odometry(est, None)
    assert m.pose_frame == m.POSE_FRAME_NED
    assert np.abs(m.position - p_ned).max() < 1e-3  # float32 on the wire
    assert np.allclose(m.position_variance, 4e-4) and np.allclose(m.orientation_variance, 1e-4)
    assert m.timestamp_sample == 5000 and m.reset_counter == 0


def test_setpoint_yaw_follows_true_north(fzk_geo) -> None:
    """A waypoint heading along true north has NED yaw 0, along east +90 deg (clockwise from north)."""
    msgs = Px4Messages(fzk_geo.T_enu_cad())
    north_yaw_cad = float(np.arctan2(fzk_geo.north_cad[1], fzk_geo.north_cad[0]))  # 40 deg in FZK-Haus
    assert np.degrees(north_yaw_cad) == pytest.approx(40.0, abs=1e-6)
    assert msgs.setpoint(np.zeros(3), north_yaw_cad, 0).yaw == pytest.approx(0.0, abs=1e-6)
    assert msgs.setpoint(np.zeros(3), north_yaw_cad - np.pi / 2, 0).yaw == pytest.approx(np.pi / 2, abs=1e-6)
    sp = msgs.setpoint(np.r_[10 * fzk_geo.north_cad, 2.0], 0.0, 7)
    assert np.allclose(sp.position, [10.0, 0.0, -2.0], atol=1e-5) and sp.timestamp == 7
