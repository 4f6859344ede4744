"""graph.prior: an operator's prior picks among tied poses only, never one outside its gate, never one of two."""

from __future__ import annotations

import numpy as np

from macroloc.graph.prior import PosePrior, storey_band_m
from macroloc.graph.rigid import make_T, rot_z


def _tied() -> tuple[np.ndarray, np.ndarray]:
    """A half-turn symmetric building's two images of one pose (T_cad_map): about the point (10, 5)."""
    T_true = make_T(rot_z(0.4), np.array([3.0, 2.0, 0.0]))
    half_turn = make_T(rot_z(np.pi), np.array([20.0, 10.0, 0.0]))
    return T_true, half_turn @ T_true


def test_a_right_prior_picks_the_true_pose_and_a_wrong_one_picks_nothing() -> None:
    T_true, T_rival = _tied()
    T_map_body = make_T(rot_z(0.1), np.array([1.0, 1.0, 1.4]))
    right = PosePrior(T_cad_map=make_T(rot_z(0.5), np.array([3.3, 1.8, 0.0])))  # 0.36 m, 6 deg off
    assert right.pick([T_rival, T_true], T_map_body) is T_true
    off = make_T(rot_z(0.4), np.array([3.0 + 10 * np.cos(0.3), 2.0 + 10 * np.sin(0.3), 3.1]))  # 10 m, storey above
    assert PosePrior(T_cad_map=off).pick([T_rival, T_true], T_map_body) is None
    # a prior so loose that both poses are inside its gate chooses neither
    assert PosePrior(T_cad_map=right.T_cad_map, sigma_xy_m=10.0, sigma_yaw_rad=np.pi).pick(
        [T_true, T_rival], T_map_body) is None
    # the true place, the wrong heading (the rival's): nothing
    turned = PosePrior(T_cad_map=make_T(rot_z(0.4 + np.pi / 2), np.array([3.0, 2.0, 0.0])))
    assert turned.pick([T_true, T_rival], T_map_body) is None


def test_a_storey_prior_gates_by_height(duplex_model) -> None:
    low, high = storey_band_m(duplex_model, "Level 1")
    assert low < 1.4 < high < 3.1
    assert storey_band_m(duplex_model, "Roof")[1] == np.inf
    T_ground = make_T(np.eye(3), np.zeros(3))
    T_upper = make_T(np.eye(3), np.array([0.0, 0.0, 3.1]))
    T_map_body = make_T(np.eye(3), np.array([0.0, 0.0, 1.4]))
    by_storey = PosePrior(storey="Level 2", storey_band_m=storey_band_m(duplex_model, "Level 2"))
    assert by_storey.pick([T_ground, T_upper], T_map_body) is T_upper
    assert by_storey.pick([T_ground], T_map_body) is None
