"""service.front_end: the pose graph defends itself against an update it cannot survive."""

from __future__ import annotations

import numpy as np

from macroloc.service.front_end import FrontEnd
from macroloc.service.inputs import OdometryIn
from tests.service.helpers import yaw_T


def test_an_absurd_odometry_restarts_the_graph_and_poses_stay_finite(duplex_model) -> None:
    """One odometry sample at x = 1e300 (what an unchecked peer sent) makes GTSAM's system indeterminate: the
    backend answers LOST for it, starts a fresh graph, and the next samples give finite poses again."""
    backend = FrontEnd.fresh_or_restored(duplex_model, None)
    stamp = 0
    for k in range(10):
        stamp += 100_000_000
        backend.odometry(OdometryIn(stamp, yaw_T(0.05 * k, np.array([0.1 * k, 0.0, 1.4]))))
    stamp += 100_000_000
    bad = backend.odometry(OdometryIn(stamp, yaw_T(0.0, np.array([1e300, 0.0, 1.4]))))
    assert backend.graph_restarts == 1 and bad.status == "lost"
    for k in range(10):
        stamp += 100_000_000
        est = backend.odometry(OdometryIn(stamp, yaw_T(0.05 * k, np.array([2.0 + 0.1 * k, 0.0, 1.4]))))
        assert np.isfinite(est.T_map_body).all() and est.status != "lost"
    assert backend.graph_restarts == 1


def test_the_configured_gravity_estimate_is_the_backend_s_also_after_a_new_time_base(duplex_model) -> None:
    """[perception.gravity] reaches the service's up estimate (its session's), and a clock reset keeps it."""
    from macroloc.service.config import load_config

    cfg = load_config(None, perception={"gravity": {"window_s": 2.0, "max_specific_force_mps2": 12.0}})
    backend = FrontEnd.fresh_or_restored(duplex_model, None, cfg)
    gravity = backend.loop.gravity
    assert gravity.params.window_s == 2.0 and gravity.params.max_specific_force_mps2 == 12.0
    backend.new_time_base()
    assert backend.loop.gravity._estimator.params.window_s == 2.0
