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
- `perception`: the vehicle sends the IMU, its odometry (`auto`: the recording's where it has some, else the
  ground truth's with a VIO's drift, else none and the service runs its visual odometry) and the stereo frames;
  the service perceives them (`[perception] detect_every`).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from macroloc.graph.bim import load_building
from macroloc.graph.errors import UserInputError
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame, read_flight
from macroloc.service.assets import prepare_building
from macroloc.service.config import MacrolocConfig
from macroloc.service.front_end import FrontEnd, make_front_end
from macroloc.service.inputs import limits_from_config
from macroloc.service.offline.foxglove_out import FoxgloveWriter, ReplayRecorder
from macroloc.service.offline.plots import load_wall_mesh
from macroloc.service.offline.replay import FrameRecorder, FrameSink, ReplayResult, null_sink, replay_as_service
from macroloc.service.offline.replay_report import write_report
from macroloc.service.offline.replay_sources import TruthSource
from macroloc.service.offline.vehicle import ODOMETRY_CHOICES, RecordedVehicle
from macroloc.service.saved_map import read_saved_map, write_saved_map

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
    """A replay's result and the front end it ran (its localizer and newest estimate, what a saved map is written
    from: `save_map`)."""

    result: ReplayResult
    front_end: FrontEnd

    def save_map(self, path: Path, building: Path, replaces: Path | None = None) -> Path | None:
        """This run's saved map at `path`, as the service saves its own (service.saved_map.write_saved_map; None
        where it keeps the map it started from, `replaces`, because it did not localize)."""
        f = self.front_end
        return write_saved_map(path, f.localizer, f.last, f.restored, building.name, replaces=replaces)


def service_config_for(cfg: MacrolocConfig, options: ReplayOptions, odometry: str) -> MacrolocConfig:
    """The service's config for a replay: `cfg`, with the perception chain on only for perception observations,
    the visual odometry where the vehicle sends no odometry, and the storey asked for."""
    service = cfg.service.model_copy(update={"perception": options.observations == "perception",
                                             "odometry": "visual" if odometry == "visual" else "vehicle"})
    graph = cfg.graph if options.storey is None else cfg.graph.model_copy(update={"storey_hint": options.storey})
    return cfg.model_copy(update={"service": service, "graph": graph})


def vehicle_for(options: ReplayOptions, first: FlightFrame | None, visual_if_none: bool = True,
                prior: pb.PoseEstimate | None = None) -> RecordedVehicle:
    """The recorded vehicle of a replay (module doc), from the recording's `first` frame: `auto` odometry is the
    recording's own where it has some, else the ground truth's with a VIO's drift where it has ground truth, else
    (`visual_if_none`: offline, where the service is configured here) the service's visual odometry. `prior`: an
    operator's prior the vehicle sends after the first frame (service.offline.vehicle)."""
    truth = options.observations in ("truth", "truth-vo")
    odometry = options.odometry
    nothing_recorded = first is not None and not first.odometry and first.ground_truth is None
    if options.observations == "truth-vo" or (odometry == "auto" and visual_if_none and nothing_recorded):
        odometry = "visual"
    sightings = TruthSource(seed=options.seed) if truth else None
    return RecordedVehicle(odometry, sightings, options.seed, depth_camera=options.observations == "truth",
                           prior=prior)


def replay_flight(flight: Path | Iterable[FlightFrame], building: Path, cfg: MacrolocConfig,
                  options: ReplayOptions | None = None, saved_map: Path | None = None,
                  sink: FrameSink = null_sink, recorder: FrameRecorder | None = None,
                  prior: pb.PoseEstimate | None = None) -> Replayed:
    """Replay `flight` (a macroloc MCAP, or frames from any reader: service.offline.ros_bag.open_flight) in
    `building` as `macroloc serve` with `cfg` would run it (module doc), started from the saved map at `saved_map`
    where given (service.saved_map: a replay's `--save-map` or a service's `map.pb`); `sink` sees every frame's
    estimate, `recorder` every frame (e.g. service.offline.foxglove_out.ReplayRecorder); `prior`: an operator's
    prior (a PoseEstimate, frame cad, as on `initialpose`) the vehicle sends after the first frame."""
    options = (options or ReplayOptions()).checked()
    frames = iter(_frames(flight))
    first = next(frames, None)
    if first is None:
        raise UserInputError(f"recording {flight if isinstance(flight, Path) else 'given'} holds no stereo frames")
    vehicle = vehicle_for(options, first, prior=prior)
    run_cfg = service_config_for(cfg, options, vehicle.choice)
    prepared = prepare_building(building, run_cfg.graph, run_cfg.planning)
    model = prepared.model
    saved = read_saved_map(saved_map, model) if saved_map is not None else None
    front_end = make_front_end(run_cfg, model, prepared.surfaces, saved)
    log.info("replay: %s observations, odometry %s", options.observations, vehicle.choice)
    result = replay_as_service(itertools.chain([first], frames), front_end, vehicle,
                               limits_from_config(run_cfg.inputs, model), run_cfg.service.cameras, sink, recorder)
    return Replayed(result, front_end)


def _frames(flight: Path | Iterable[FlightFrame]) -> Iterable[FlightFrame]:
    return read_flight(flight) if isinstance(flight, Path) else flight


def replay_offline(flight: Path | Iterable[FlightFrame], building: Path, cfg: MacrolocConfig,
                   options: ReplayOptions | None = None, saved_map: Path | None = None,
                   save_map: Path | None = None, out: Path | None = None, report: Path | None = None) -> ReplayResult:
    """`macroloc replay` without --over-zenoh: `replay_flight`, then what the files ask for: `save_map` (this
    run's saved map), `out` (the replay for Foxglove, written as it runs: service.offline.foxglove_out) and
    `report` (a top-down picture, per-frame figures and result.json: service.offline.replay_report)."""
    recorder = None
    with contextlib.ExitStack() as stack:
        if out is not None:
            recorder = ReplayRecorder(stack.enter_context(FoxgloveWriter(out)), load_building(building),
                                      load_wall_mesh(building))
        replayed = replay_flight(flight, building, cfg, options, saved_map, recorder=recorder)
    if save_map is not None:
        replayed.save_map(save_map, building, replaces=saved_map)
    if report is not None:
        f = replayed.front_end
        write_report(replayed.result, f.model, report, load_wall_mesh(building), f.restored,
                     config=cfg.model_dump(mode="json"))
    return replayed.result
