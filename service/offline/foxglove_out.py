"""Flights for Foxglove: MCAP channels of Foxglove's own protobuf schemas (foxglove_schemas_protobuf), so a replay
or a simulated flight plays in Foxglove's Image and 3D panels with nothing else to install.

Channels (log time = the flight's stamp of each message):
  /camera/left/image        foxglove.CompressedImage    left image (JPEG), frame "cam"
  /camera/left/calibration  foxglove.CameraCalibration  the rectified left camera (K, P; no distortion)
  /camera/left/detections   foxglove.ImageAnnotations   the frame's doors/windows seen, corners projected (replay)
  /tf                       foxglove.FrameTransforms    cad -> map (once localized), map -> body, body -> cam
  /pose/estimate            foxglove.PoseInFrame        the body in the CAD frame (replay, once localized)
  /pose/truth               foxglove.PoseInFrame        the body in the CAD frame, ground truth (where known)
  /model                    foxglove.SceneUpdate        doors (red) and windows (blue) as boxes, matched ones opaque,
                                                        the others faint; the walls cut at the flight's height
  /landmarks                foxglove.SceneUpdate        the flight's landmarks in the CAD frame (end of a replay)
  /status                   foxglove.Log                the localizer's status, at each change (replay)
The live view (service.foxglove_live) adds, through the same class:
  /pose/covariance          foxglove.SceneUpdate        the pose's position covariance as a 2-sigma ellipsoid (cad)
  /landmarks/links          foxglove.SceneUpdate        a line from each landmark to the model feature it is linked to
  /hypotheses               foxglove.PosesInFrame       the rival body poses an 'ambiguous' registration left (cad)
  /plan                     foxglove.PosesInFrame       the waypoints with their yaws (cad)
A simulated flight (`macroloc simulate`) carries the image, calibration, transform (cad -> body -> cam, its
truth), truth pose and model channels beside its macroloc ones.
Frames: "cad" (the model's, the 3D panel's fixed frame), "map" (the flight's odometry frame; its transform from
"cad" appears once localized), "body", "cam" (optical, x right, y down, z forward).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from mcap.writer import CompressionType
from mcap_protobuf.writer import Writer

from macroloc.graph.features import BuildingModel
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import FlightFrame, matrix_from_pose
from macroloc.service.foxglove_channels import FoxgloveChannels
from macroloc.service.offline.plots import wall_segments_xy

log = logging.getLogger(__name__)


class FoxgloveWriter(FoxgloveChannels):
    """An MCAP file of Foxglove messages (see module doc). Use as a context manager."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file = open(path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self.counts: dict[str, int] = {}
        super().__init__(self._write)

    def _write(self, topic: str, message: Any, stamp_ns: int) -> None:
        seq = self.counts.get(topic, 0)
        self._writer.write_message(topic, message, log_time=int(stamp_ns), publish_time=int(stamp_ns), sequence=seq)
        self.counts[topic] = seq + 1

    def close(self) -> None:
        if not self._file.closed:
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> FoxgloveWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class SimulationChannels:
    """A simulated flight's Foxglove channels, written into its recording (service.recording.FlightWriter)."""

    def __init__(self, write: Callable[[str, Any, int], None], model: BuildingModel, wall_mesh: Any = None) -> None:
        self.channels = FoxgloveChannels(write)
        self.model, self.wall_mesh = model, wall_mesh
        self._first = True

    def frame(self, stereo: pb.StereoFrame, T_cad_body: np.ndarray, T_body_cam: np.ndarray) -> None:
        c, s = self.channels, stereo.header.stamp_ns
        if self._first:
            z = float(T_cad_body[2, 3])
            walls = wall_segments_xy(self.wall_mesh, z) if self.wall_mesh is not None else None
            c.model(s, self.model, set(), walls, z)
            self._first = False
        c.image(stereo, s)
        c.transforms(s, None, T_body_cam, T_cad_body=T_cad_body)
        c.pose("/pose/truth", s, T_cad_body)


class ReplayRecorder:
    """Writes a replay's frames to a FoxgloveWriter as they run (service.offline.replay's `recorder`)."""

    def __init__(self, writer: FoxgloveChannels, model: BuildingModel, wall_mesh: Any = None) -> None:
        self.writer, self.model, self.wall_mesh = writer, model, wall_mesh
        self._status: str | None = None
        self._first = True
        self._wall_z: float | None = None
        self.last_stamp_ns = 0

    def frame(self, frame: FlightFrame, inputs: Any, estimate: Any) -> None:
        """One frame: image, detections, transforms, poses, status (`inputs`: service.offline.replay.FrameSeen,
        `estimate`: graph.localizer.Estimate)."""
        w, s = self.writer, frame.stamp_ns
        T_body_cam = inputs.T_body_cam
        truth = matrix_from_pose(frame.ground_truth.T_cad_body) if frame.ground_truth is not None else None
        if self._first:
            self._model(s, set(), truth)
            self._first = False
        w.image(frame.stereo, s)
        T_cam_body = np.linalg.inv(T_body_cam)
        w.detections(s, frame.stereo.info, [(x.type, (T_cam_body[:3, :3] @ x.corners_body.T).T + T_cam_body[:3, 3])
                                            for x in inputs.sightings])
        w.transforms(s, estimate.T_map_body, T_body_cam, estimate.T_cad_map)
        if estimate.T_cad_body is not None:
            w.pose("/pose/estimate", s, estimate.T_cad_body)
        if truth is not None:
            w.pose("/pose/truth", s, truth)
        if estimate.status != self._status:
            w.status(s, estimate.status)
            self._status = estimate.status
        self.last_stamp_ns = s

    def _model(self, stamp_ns: int, matched: set[str], T_cad_body: np.ndarray | None) -> None:
        if self._wall_z is None:  # the flight's height at its start, else the doors' and windows' middle height
            self._wall_z = float(T_cad_body[2, 3]) if T_cad_body is not None else \
                float(np.median([f.centroid_cad[2] for f in self.model.features]))
        walls = wall_segments_xy(self.wall_mesh, self._wall_z) if self.wall_mesh is not None else None
        self.writer.model(stamp_ns, self.model, matched, walls, self._wall_z)

    def finish(self, localizer: Any) -> None:
        """The matched features and the landmarks at the end (`localizer`: graph.localizer.Localizer)."""
        s = self.last_stamp_ns
        self._model(s, set(localizer.links.values()), None)
        T_cad_map = localizer.graph.T_cad_map()
        if T_cad_map is not None:
            self.writer.landmarks(s, [(str(j), lm.type, (T_cad_map @ localizer.graph.T_map_rect(j))[:3, 3])
                                      for j, lm in localizer.landmarks.items()])
