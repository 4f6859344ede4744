"""APE and RPE with evo's definitions (translation part, unaligned APE)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from macroloc.graph.trajectory_metrics import ErrorStats, ape_translation, rpe_translation
from tests.graph.scenes import make_T, rot_z, straight_flight


def test_ape_of_a_shifted_trajectory_is_the_shift() -> None:
    ref = np.array(straight_flight(20))
    est = ref.copy()
    est[:, :3, 3] += [0.3, 0.4, 0.0]
    assert np.allclose(ape_translation(ref, est), 0.5)
    assert np.allclose(rpe_translation(ref, est), 0.0, atol=1e-12)
    stats = ErrorStats.of(ape_translation(ref, est))
    assert np.isclose(stats.rmse, 0.5) and stats.n == 20


@given(yaw=st.floats(-3.1, 3.1), tx=st.floats(-20, 20), ty=st.floats(-20, 20))
@settings(max_examples=30)
def test_rpe_ignores_a_rigid_transform_of_the_estimate_but_ape_does_not(yaw: float, tx: float, ty: float) -> None:
    ref = np.array(straight_flight(15))
    G = make_T(rot_z(yaw), np.array([tx, ty, 0.0]))
    est = np.einsum("ij,njk->nik", G, ref)
    assert np.allclose(rpe_translation(ref, est, delta=3), 0.0, atol=1e-9)
    if abs(tx) + abs(ty) > 1.0 and abs(yaw) < 0.01:
        assert ape_translation(ref, est).min() > 0.5


def test_empty_trajectories_give_nan_stats() -> None:
    assert np.isnan(ErrorStats.of(np.zeros(0)).rmse)
