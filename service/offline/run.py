"""A replay as one library call: `replay_flight` builds what `macroloc serve` builds from the config (the building's
prepared assets, service.assets; the front end through the service's one factory, service.front_end.make_front_end)
and runs a recording through it as its vehicle sends it (service.offline.vehicle), then scores the poses against
the recording's ground truth. `macroloc replay` and the benchmarks call it.

What a replay's `observations` mean, as settings of the vehicle and the service:
- `truth`: the vehicle sends the IMU, its odometry (`odometry`: by default the ground truth with a VIO's drift),
  the doors and windows in view (ground truth with realistic errors: service.offline.replay_sources.TruthSource)
  and stereo frames with its depth camera's image; the service perceives nothing.
- `truth-vo`: the same without odometry and depth image; the service runs its stereo visual odometry
  (`[service] odometry = "visual"`) and measures stereo depth with it.
- `perception`: the vehicle sends the IMU, its odometry where the recording has it (`auto`; else the service runs
  its visual odometry) and the stereo frames; the service perceives them (`[perception] detect_every`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from macroloc.graph.errors import UserInputError
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame
from macroloc.service.assets import prepare_building
from macroloc.service.config import MacrolocConfig
from macroloc.service.front_end import FrontEnd, make_front_end
from macroloc.service.inputs import limits_from_config
from macroloc.service.offline.replay import FrameSink, ReplayResult, null_sink, replay_as_service
from macroloc.service.offline.replay_sources import TruthSource
from macroloc.service.offline.vehicle import ODOMETRY_CHOICES, RecordedVehicle

log = logging.getLogger(__name__)

OBSERVATIONS = ("truth", "truth-vo", "perception")


@dataclass(frozen=True)
class ReplayOptions:
    """How a recording is replayed (module doc): `observations`; `odometry` (service.offline.vehicle: auto,
    recorded, simulated, visual); `seed` of the truth's noise and of the simulated odometry's drift; `storey`: the
    storey to register against (instead of [graph] storey_hint)."""

    observations: str = "truth"
    odometry: str = "auto"
    seed: int = 0
    storey: str | None = None

    def checked(self) -> ReplayOptions:
        if self.observations not in OBSERVATIONS:
            raise UserInputError(f"--observations must be one of {', '.join(OBSERVATIONS)}, "
                                 f"not {self.observations!r}")
        if self.odometry not in ODOMETRY_CHOICES:
            raise UserInputError(f"--odometry must be one of {', '.join(ODOMETRY_CHOICES)}, not {self.odometry!r}")
        if self.observations == "truth-vo" and self.odometry not in ("auto", "visual"):
            raise UserInputError("--observations truth-vo is the truth's doors with the visual odometry: "
                                 "leave --odometry out")
        return self


@dataclass
class Replayed:
    """A replay's result and the front end it ran (its localizer, what a saved map is written from)."""

    result: ReplayResult
    front_end: FrontEnd


def service_config_for(cfg: MacrolocConfig, options: ReplayOptions, odometry: str) -> MacrolocConfig:
    """The service's config for a replay: `cfg`, with the perception chain on only for perception observations,
    the visual odometry where the vehicle sends no odometry, and the storey asked for."""
    service = cfg.service.model_copy(update={"perception": options.observations == "perception",
                                             "odometry": "visual" if odometry == "visual" else "vehicle"})
    graph = cfg.graph if options.storey is None else cfg.graph.model_copy(update={"storey_hint": options.storey})
    return cfg.model_copy(update={"service": service, "graph": graph})


def vehicle_for(options: ReplayOptions, has_odometry: bool) -> RecordedVehicle:
    """The recorded vehicle of a replay (module doc); `has_odometry`: whether the recording carries the vehicle's."""
    truth = options.observations in ("truth", "truth-vo")
    odometry = options.odometry
    if options.observations == "truth-vo" or (options.observations == "perception" and odometry == "auto"
                                              and not has_odometry):
        odometry = "visual"
    sightings = TruthSource(seed=options.seed) if truth else None
    return RecordedVehicle(odometry, sightings, options.seed, depth_camera=options.observations == "truth")


def replay_flight(flight: Path | Iterable[FlightFrame], building: Path, cfg: MacrolocConfig,
                  options: ReplayOptions | None = None, saved: pb.MapSnapshot | None = None,
                  sink: FrameSink = null_sink) -> Replayed:
    """Replay `flight` (a macroloc MCAP, or frames from any reader: service.offline.ros_bag.open_flight) in
    `building` as `macroloc serve` with `cfg` would run it (module doc), started from the `saved` map where given;
    `sink` sees every frame's estimate."""
    options = (options or ReplayOptions()).checked()
    frames = iter(_frames(flight))
    first = next(frames, None)
    if first is None:
        raise UserInputError(f"recording {flight if isinstance(flight, Path) else 'given'} holds no stereo frames")
    vehicle = vehicle_for(options, bool(first.odometry))
    run_cfg = service_config_for(cfg, options, vehicle.choice)
    prepared = prepare_building(building, run_cfg.graph, run_cfg.planning)
    model = prepared.model
    front_end = make_front_end(run_cfg, model, prepared.surfaces, saved)
    log.info("replay: %s observations, odometry %s", options.observations, vehicle.choice)
    result = replay_as_service(_chain(first, frames), front_end, vehicle, limits_from_config(run_cfg.inputs, model),
                               run_cfg.service.cameras, sink)
    return Replayed(result, front_end)


def _frames(flight: Path | Iterable[FlightFrame]) -> Iterable[FlightFrame]:
    from macroloc.proto.recording import read_flight

    return read_flight(flight) if isinstance(flight, Path) else flight


def _chain(first: FlightFrame, rest: Iterable[FlightFrame]) -> Iterable[FlightFrame]:
    yield first
    yield from rest
