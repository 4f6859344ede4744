"""The replay report's per-frame error decomposition (service/offline/replay_report.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from macroloc.service.offline.replay_report import _pose_error


@settings(max_examples=30, deadline=None)
@given(dx=st.floats(-1, 1), dy=st.floats(-1, 1), dz=st.floats(-1, 1), yaw_true=st.floats(-3.1, 3.1),
       dyaw_deg=st.floats(-20, 20), tilt_deg=st.floats(0, 10), tilt_axis=st.floats(-3.1, 3.1))
def test_the_error_splits_into_height_horizontal_tilt_and_yaw(dx: float, dy: float, dz: float, yaw_true: float,
                                                             dyaw_deg: float, tilt_deg: float,
                                                             tilt_axis: float) -> None:
    T_true = np.eye(4)
    T_true[:3, :3] = Rotation.from_euler("z", yaw_true).as_matrix()
    T_true[:3, 3] = [5.0, -2.0, 1.4]
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(tilt_axis), np.sin(tilt_axis), 0.0]))
    T_est = np.eye(4)
    T_est[:3, :3] = (tilt * Rotation.from_euler("z", yaw_true + np.radians(dyaw_deg))).as_matrix()
    T_est[:3, 3] = T_true[:3, 3] + [dx, dy, dz]
    position, horizontal, height, tilt_err, yaw_err = _pose_error(T_est, T_true)
    assert position == pytest.approx(np.linalg.norm([dx, dy, dz]), abs=1e-9)
    assert horizontal == pytest.approx(np.hypot(dx, dy), abs=1e-9) and height == pytest.approx(dz, abs=1e-9)
    assert tilt_err == pytest.approx(tilt_deg, abs=1e-6)
    assert yaw_err == pytest.approx(abs(dyaw_deg), abs=0.1 * tilt_deg + 1e-6)  # a tilt leaks a little into yaw
    assert np.isnan(_pose_error(None, T_true)).all()
