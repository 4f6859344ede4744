"""Flights: collision-free, inside, 1.0-1.8 m above the floor, smooth, seeded, looking ahead."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from macroloc.sim.flight import FlightParams, doors_crossed, plan_flight
from macroloc.sim.scene import load_scene
from macroloc.sim.simulator import choose_storey, storey_levels


@pytest.fixture(scope="module")
def duplex_flight(duplex_path: Path, duplex_model):
    storey = choose_storey(duplex_model, None)
    z0, ceiling = storey_levels(duplex_model, storey)
    params = FlightParams(duration_s=30.0, speed_mps=1.0)
    traj, space = plan_flight(load_scene(duplex_path), z0, params, seed=5, ceiling_z_m=ceiling,
                              features=duplex_model.features)
    return traj, space, params, z0


def test_default_storey_has_most_features(duplex_model) -> None:
    counts = {k: len(v) for k, v in duplex_model.by_storey().items() if k}
    assert choose_storey(duplex_model, None) == max(counts, key=lambda k: counts[k])


def test_unknown_storey_is_a_user_error(duplex_model) -> None:
    from macroloc.graph.errors import UserInputError

    with pytest.raises(UserInputError, match="storeys"):
        choose_storey(duplex_model, "Level 99")


def test_flight_stays_in_free_space_and_height_band(duplex_flight) -> None:
    traj, space, params, z0 = duplex_flight
    assert traj.duration_s == pytest.approx(params.duration_s, abs=0.01)
    assert space.is_safe(traj.positions_cad[:, :2]).all()
    h = traj.positions_cad[:, 2] - z0
    assert h.min() >= params.min_height_m - 1e-6 and h.max() <= params.max_height_m + 1e-6


def test_flight_is_smooth(duplex_flight) -> None:
    traj, _, params, _ = duplex_flight
    dt = 1.0 / params.rate_hz
    vel = np.diff(traj.positions_cad, axis=0) / dt
    speed = np.linalg.norm(vel[:, :2], axis=1)
    assert speed.max() <= params.speed_mps * 1.1
    assert np.abs(np.diff(vel, axis=0)).max() / dt < 3.0  # no jumps in velocity: bounded acceleration
    assert np.linalg.norm(vel[0]) < 0.05  # starts from rest
    R = traj.R_cad_body
    step = np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1))
    assert step.max() / dt < 1.5  # rad/s: no attitude jumps


def test_flight_looks_mostly_ahead(duplex_flight) -> None:
    traj, _, _, _ = duplex_flight
    vel = np.gradient(traj.positions_cad[:, :2], axis=0)
    moving = np.linalg.norm(vel, axis=1) * 200 > 0.4
    forward = traj.R_cad_body[:, :2, 0]  # body x in the CAD frame
    cos = np.einsum("ni,ni->n", forward[moving], vel[moving]) / (
        np.linalg.norm(forward[moving], axis=1) * np.linalg.norm(vel[moving], axis=1))
    assert np.median(cos) > np.cos(np.radians(35))
    tilt = np.degrees(np.arccos(np.clip(traj.R_cad_body[:, 2, 2], -1, 1)))
    assert tilt.max() < 10.0  # roll/pitch of a gently accelerating multirotor


def test_flight_is_seeded(duplex_path: Path, duplex_model) -> None:
    scene = load_scene(duplex_path)
    z0, _ = storey_levels(duplex_model, "Level 1")
    params = FlightParams(duration_s=5.0)
    a, _ = plan_flight(scene, z0, params, seed=1)
    b, _ = plan_flight(scene, z0, params, seed=1)
    c, _ = plan_flight(scene, z0, params, seed=2)
    assert np.array_equal(a.positions_cad, b.positions_cad)
    assert not np.array_equal(a.positions_cad, c.positions_cad)


def test_pose_interpolation_matches_samples(duplex_flight) -> None:
    traj, _, _, _ = duplex_flight
    k = 1234
    T = traj.T_cad_body(float(traj.stamps_s[k]))
    assert np.allclose(T[:3, 3], traj.positions_cad[k]) and np.allclose(T[:3, :3], traj.R_cad_body[k], atol=1e-9)


@pytest.mark.slow
def test_office_flight_passes_through_doors(office_path: Path, office_model) -> None:
    z0, ceiling = storey_levels(office_model, "Level 1")
    traj, space = plan_flight(load_scene(office_path), z0, FlightParams(duration_s=60.0), seed=2,
                              ceiling_z_m=ceiling, features=office_model.features)
    assert space.safe.sum() * space.cell_m**2 > 500  # m^2: the whole floor, rooms joined through doorways
    crossed = doors_crossed(traj, office_model.features)
    for k in crossed:  # under the door head when passing it
        f = office_model.features[k]
        near = np.linalg.norm(traj.positions_cad[:, :2] - f.centroid_cad[:2], axis=1) < 0.3
        assert (traj.positions_cad[near, 2] < f.corners_cad[:, 2].max() - 0.2).all()


def test_named_storey_is_flown_at_its_height(duplex_path: Path, duplex_model) -> None:
    from macroloc.sim.simulator import SimulationParams, plan_only

    traj, storey = plan_only(duplex_path, SimulationParams(seed=2, storey="Level 1",
                                                           flight=FlightParams(duration_s=5.0)))
    z0, _ = storey_levels(duplex_model, "Level 1")
    assert storey == "Level 1"
    h = traj.positions_cad[:, 2] - z0
    assert h.min() >= 1.0 - 1e-6 and h.max() <= 1.8 + 1e-6
