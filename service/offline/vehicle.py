"""A recorded flight as its vehicle sends it: per recorded frame, the messages on the service's input keys, in the
order a vehicle sends them (the IMU samples since the previous frame, the odometry, the doors and windows it saw
where it sends its own, the stereo frame). `replay --over-zenoh` puts them on Zenoh for a running `macroloc serve`;
the offline replay parses them with the service's own parser and hands the events to the service's front end
(service.front_end), so that both run one path and differ only in the transport.

The vehicle's odometry (`odometry`), chosen the same way on both sides:
- `recorded`: the recording's own (a vehicle's VIO, a demo flight's); a recording without one is refused.
- `simulated`: ground truth with the drift of a decent VIO (`TruthSource.odometry`: a scale error, a yaw bias, noise
  growing with motion), seeded; for simulated recordings.
- `auto`: `recorded` where the first frame carries odometry (and no sightings are sent), else `simulated` where it
  carries ground truth, else none (the service then takes the odometry from elsewhere, e.g. a ROS topic).

- `none` (of `auto` only) or `visual` where the caller lets the service's front end run its visual odometry.

Its doors and windows (`sightings`): none (the service perceives the stereo frames itself), or a `TruthSource`'s
(ground truth with realistic errors), sent as `ObservedFeatures` in the body frame.

An operator's prior (`prior`, a PoseEstimate in the CAD frame as Nav2's /initialpose becomes it): sent once on
`initialpose`, after the first frame's messages (the service takes a pose prior against the odometry it has).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from google.protobuf.message import Message

from macroloc.graph.errors import UserInputError
from macroloc.graph.localizer import Sighting
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame, pose_from_matrix, vector3
from macroloc.service.offline.replay_sources import TruthSource

ODOMETRY_CHOICES = ("auto", "recorded", "simulated", "visual")  # a user's (`--odometry`); `none` comes of auto only


@dataclass(frozen=True)
class VehicleMessage:
    """One message as the vehicle puts it: `key` is the input key's leaf (stereo, imu, odometry, observations,
    initialpose)."""

    key: str
    message: Message


class RecordedVehicle:
    """See module doc. Deterministic for a seed; one instance per flight (the simulated odometry drifts on)."""

    def __init__(self, odometry: str = "auto", sightings: TruthSource | None = None, seed: int = 0,
                 depth_camera: bool = False, prior: pb.PoseEstimate | None = None) -> None:
        """`depth_camera`: the stereo frames carry the recording's ground-truth depth image, as a vehicle with a
        depth camera sends it (the service then takes its points for the walls' checks: service.front_end).
        `prior`: the operator's prior, sent once after the first frame (module doc)."""
        if odometry not in ODOMETRY_CHOICES:
            raise UserInputError(f"--odometry must be one of {', '.join(ODOMETRY_CHOICES)}, not {odometry!r}")
        self.choice = odometry
        self.sightings = sightings
        self.depth_camera = depth_camera
        self._simulated = TruthSource(seed=seed)  # the vehicle's VIO, for a simulated recording without odometry
        self.odometry: str | None = None  # what it sends, once the first frame has told: recorded, simulated, none
        self.prior = prior  # sent with the first frame, then None

    def messages(self, frame: FlightFrame) -> Iterator[VehicleMessage]:
        """The frame's messages, in the order sent (module doc)."""
        for imu in frame.imu:
            yield VehicleMessage("imu", imu)
        if self.odometry is None:  # the first frame decides
            if self.choice == "recorded" and not frame.odometry:
                raise UserInputError("--odometry recorded: the recording's first frame carries no vehicle odometry; "
                                     "use --odometry simulated for a simulated recording")
            # with its own sightings, the source's drifted odometry goes with them unless `recorded` is asked for
            recorded = bool(frame.odometry) and (self.choice == "recorded" or
                                                 (self.choice == "auto" and self.sightings is None))
            self.odometry = "visual" if self.choice == "visual" else "recorded" if recorded else \
                "simulated" if frame.ground_truth is not None or self.choice == "simulated" else "none"
        inputs = self.sightings(frame) if self.sightings is not None else None
        if self.odometry == "recorded":
            yield from (VehicleMessage("odometry", odo) for odo in frame.odometry)
        elif self.odometry == "simulated":
            if frame.ground_truth is None:
                raise UserInputError("--odometry simulated needs a simulated recording with ground truth")
            # the sightings' source drifts its own odometry with its noise: the vehicle sends that one
            T_odom_body = inputs.T_odom_body if inputs is not None else self._simulated.odometry(frame)
            odo = pb.Odometry(T_map_body=pose_from_matrix(T_odom_body))
            odo.header.stamp_ns, odo.header.frame_id = frame.stamp_ns, "map"
            yield VehicleMessage("odometry", odo)
        if inputs is not None:
            yield VehicleMessage("observations", observed_features(frame.stamp_ns, inputs.sightings))
        if self.depth_camera and frame.ground_truth is not None and frame.ground_truth.HasField("depth"):
            stereo = pb.StereoFrame()
            stereo.CopyFrom(frame.stereo)
            stereo.depth.CopyFrom(frame.ground_truth.depth)
            yield VehicleMessage("stereo", stereo)
        else:
            yield VehicleMessage("stereo", frame.stereo)
        if self.prior is not None:
            prior, self.prior = self.prior, None
            yield VehicleMessage("initialpose", prior)


def observed_features(stamp_ns: int, sightings: list[Sighting]) -> pb.ObservedFeatures:
    """Sightings (corners in the body frame) as the vehicle sends them, with their ground-truth ids where known."""
    msg = pb.ObservedFeatures()
    msg.header.stamp_ns = stamp_ns
    msg.header.frame_id = "body"
    for s in sightings:
        # the ground truth's id where the sightings are the simulator's (for scoring the links only)
        msg.features.add(type=s.type, id=s.truth_id or "").corners.extend(vector3(c) for c in s.corners_body)
    return msg
