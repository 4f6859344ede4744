"""The replay is the service: a recording replayed offline through the service's front end and the same recording
played into a lock-step `macroloc serve` over Zenoh give the same keyframes and the same estimates."""

from __future__ import annotations

import numpy as np
import pytest

from tests.service.helpers import free_port, loopback, running_service, service_config


def _offline(cfg, flight, odometry: str, truth_sightings: bool):  # noqa: ANN001, ANN202 - ReplayResult
    from macroloc.service.assets import prepare_building
    from macroloc.service.front_end import make_front_end
    from macroloc.service.inputs import limits_from_config
    from macroloc.service.offline.replay import replay_as_service
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.vehicle import RecordedVehicle

    prepared = prepare_building(cfg.service.building, cfg.graph, cfg.planning)
    front_end = make_front_end(cfg, prepared.model, prepared.surfaces)
    sightings = TruthSource(seed=3) if truth_sightings else None
    return replay_as_service(flight, front_end, RecordedVehicle(odometry, sightings, seed=3),
                             limits_from_config(cfg.inputs, prepared.model), cfg.service.cameras)


def _over_zenoh(cfg, flight, odometry: str, truth_sightings: bool):  # noqa: ANN001, ANN202 - ZenohReplayResult
    from macroloc.service.offline.replay_sources import TruthSource
    from macroloc.service.offline.replay_zenoh import replay_over_zenoh

    sightings = TruthSource(seed=3) if truth_sightings else None
    with running_service(cfg):
        return replay_over_zenoh(flight, loopback(connect=cfg.zenoh.listen), cfg.service.vehicle, sightings,
                                 speed=0.0, seed=3, answered=True, odometry=odometry)


@pytest.mark.timeout(600)
def test_a_perceived_flight_gives_the_same_estimates_offline_and_through_the_service(
        rendered_office_flight, office_path, tmp_path) -> None:
    """Every input on the path: the IMU, the vehicle's (simulated) odometry, the doors it sends itself (ground truth
    with noise: the 7 s flight localizes) and the stereo frames, which the service perceives (every third: the
    cadence holds on both sides) and measures depth and views in."""
    cfg = service_config(office_path, tmp_path, free_port())
    cfg.service.perception = True
    cfg.service.lockstep = True
    cfg.perception.detect_every = 3
    offline = _offline(cfg, rendered_office_flight, "simulated", truth_sightings=True)
    served = _over_zenoh(cfg, rendered_office_flight, "simulated", truth_sightings=True)

    assert served.frames == offline.frames and served.odometry == "source"
    assert served.keyframes == offline.keyframes
    assert served.wrong_localizations == offline.wrong_localizations
    compared = 0
    for stamp, status, T_est in zip(offline.trace.stamp_ns, offline.trace.status, offline.trace.T_est, strict=True):
        served_status, served_T = served.poses_cad[stamp]
        assert served_status == status, stamp
        assert (served_T is None) == (T_est is None), stamp
        if T_est is not None:
            assert np.abs(served_T - T_est).max() < 1e-9, stamp
            compared += 1
    assert served.localized and offline.localized and compared > 20
    assert served.time_to_localize_s == pytest.approx(offline.time_to_localize_s, abs=1e-3)
    # the over-Zenoh JSON carries the offline one's figures, scored alike
    ours, theirs = offline.to_json(), served.to_json()
    for key in ("ape_rmse_m", "ape_max_m", "rpe_1s_rmse_m", "wrong_while_localized_s", "position_sigma_final_m"):
        assert theirs[key] == pytest.approx(ours[key], abs=1e-3), key
    for key in ("localized", "wrong_localizations", "keyframes", "landmarks", "cad_links", "wrong_links",
                "status_final", "dropped"):
        assert theirs[key] == ours[key], key
    assert set(ours) <= set(theirs), set(ours) - set(theirs)  # every figure, the timings included
    assert theirs["isam_update_ms_mean"] > 0 and theirs["processing_to_localize_s"] > 0
