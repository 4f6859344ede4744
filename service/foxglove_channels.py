"""Foxglove's channels of a flight, in Foxglove's own protobuf schemas (foxglove_schemas_protobuf): one class that
both the live view (`service.foxglove_live`) and the MCAP writer of a replay or a simulated flight
(`service.offline.foxglove_out`) write through. The channels and frames are listed in `service.offline.foxglove_out`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from scipy.spatial.transform import Rotation

from macroloc.graph.features import BuildingModel
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import decode_image

log = logging.getLogger(__name__)

TYPE_COLOUR = {"door": (0.85, 0.2, 0.2), "window": (0.2, 0.45, 0.95)}
OTHER_COLOUR = (0.6, 0.6, 0.6)
MATCHED_ALPHA, UNMATCHED_ALPHA = 0.9, 0.25
STATUS_LEVEL = {"localized": 2, "exploring": 2, "ambiguous": 3, "degraded": 3, "lost": 4}  # foxglove.Log levels


def _stamp(stamp_ns: int) -> Any:
    ts = Timestamp()
    ts.FromNanoseconds(int(stamp_ns))
    return ts


def _pose(T: np.ndarray) -> Any:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # scipy: x, y, z, w
    return Pose(position=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), orientation=Quaternion(x=q[0], y=q[1], z=q[2],
                                                                                            w=q[3]))


def _colour(rgb: tuple[float, float, float], alpha: float) -> Any:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)


class FoxgloveChannels:
    """The channels of the module doc, written through `write(topic, message, stamp_ns)` (an MCAP protobuf
    writer's: a FoxgloveWriter's own file, or a flight recording's, beside its macroloc channels)."""

    def __init__(self, write: Callable[[str, Any, int], None]) -> None:
        self.write = write

    def image(self, frame: pb.StereoFrame, stamp_ns: int) -> None:
        """The left image (JPEG: the recorded bytes where they are JPEG) and its camera."""
        left = frame.left
        data = left.data if left.encoding == pb.Image.JPEG else \
            cv2.imencode(".jpg", decode_image(left), [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes()
        self.write("/camera/left/image", CompressedImage(timestamp=_stamp(stamp_ns), frame_id="cam", data=data,
                                                         format="jpeg"), stamp_ns)
        i = frame.info
        K = [i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0]
        self.write("/camera/left/calibration", CameraCalibration(
            timestamp=_stamp(stamp_ns), frame_id="cam", width=i.width, height=i.height, distortion_model="plumb_bob",
            D=[0.0] * 5, K=K, R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], P=[i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0,
                                                                     0.0, 1.0, 0.0]), stamp_ns)

    def transforms(self, stamp_ns: int, T_map_body: np.ndarray | None, T_body_cam: np.ndarray,
                   T_cad_map: np.ndarray | None = None, T_cad_body: np.ndarray | None = None) -> None:
        """cad -> map (when known), map -> body, body -> cam; where there is no map (a simulated flight), cad ->
        body (`T_cad_body`, its truth)."""
        def tf(parent: str, child: str, T: np.ndarray) -> Any:
            p = _pose(T)
            return FrameTransform(timestamp=_stamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
                                  translation=p.position, rotation=p.orientation)

        links = [("body", "cam", T_body_cam)]
        if T_map_body is not None:
            links.append(("map", "body", T_map_body))
            if T_cad_map is not None:
                links.append(("cad", "map", T_cad_map))
        elif T_cad_body is not None:
            links.append(("cad", "body", T_cad_body))
        self.write("/tf", FrameTransforms(transforms=[tf(*link) for link in links]), stamp_ns)

    def pose(self, topic: str, stamp_ns: int, T_cad_body: np.ndarray) -> None:
        self.write(topic, PoseInFrame(timestamp=_stamp(stamp_ns), frame_id="cad", pose=_pose(T_cad_body)), stamp_ns)

    def model(self, stamp_ns: int, model: BuildingModel, matched: set[str] | None = None,
              wall_segments_xy: np.ndarray | None = None, wall_z_m: float = 0.0) -> None:
        """The doors and windows as boxes (their corners' rectangle, 5 cm thick), matched ones opaque; the walls as
        lines cut at `wall_z_m` (`wall_segments_xy`: (S, 2, 2), CAD frame)."""
        matched = matched or set()
        entities = []
        for f in model.features:
            T, size = _box(f.corners_cad)
            alpha = MATCHED_ALPHA if f.id in matched else UNMATCHED_ALPHA
            cube = CubePrimitive(pose=_pose(T), size=Vector3(x=size[0], y=size[1], z=size[2]),
                                 color=_colour(TYPE_COLOUR.get(f.type, OTHER_COLOUR), alpha))
            entities.append(SceneEntity(timestamp=_stamp(stamp_ns), frame_id="cad", id=f"{f.type}/{f.id}",
                                        cubes=[cube]))
        if wall_segments_xy is not None and len(wall_segments_xy):
            points = [Point3(x=float(x), y=float(y), z=wall_z_m) for seg in wall_segments_xy for x, y in seg]
            line = LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose(np.eye(4)), thickness=0.05, points=points,
                                 color=_colour((0.4, 0.4, 0.4), 1.0))
            entities.append(SceneEntity(timestamp=_stamp(stamp_ns), frame_id="cad", id="walls", lines=[line]))
        self.write("/model", SceneUpdate(entities=entities), stamp_ns)

    def landmarks(self, stamp_ns: int, positions_cad: list[tuple[str, str, np.ndarray]], frame_id: str = "cad"
                  ) -> None:
        """(key, type, position) of each landmark, as spheres; positions in `frame_id` (the CAD frame, or "map"
        before the flight is localized)."""
        entities = []
        for key, kind, p in positions_cad:
            T = np.eye(4)
            T[:3, 3] = p
            sphere = SpherePrimitive(pose=_pose(T), size=Vector3(x=0.25, y=0.25, z=0.25),
                                     color=_colour(TYPE_COLOUR.get(kind, OTHER_COLOUR), 1.0))
            entities.append(SceneEntity(timestamp=_stamp(stamp_ns), frame_id=frame_id, id=f"landmark/{key}",
                                        spheres=[sphere]))
        self.write("/landmarks", SceneUpdate(entities=entities), stamp_ns)

    def links(self, stamp_ns: int, pairs_cad: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """(landmark position, linked model feature's centroid), both (3,) in the CAD frame: one line each."""
        points = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for pair in pairs_cad for p in pair]
        line = LinePrimitive(type=LinePrimitive.LINE_LIST, pose=_pose(np.eye(4)), thickness=0.04, points=points,
                             color=_colour((0.1, 0.7, 0.3), 1.0))
        self.write("/landmarks/links", SceneUpdate(entities=[SceneEntity(
            timestamp=_stamp(stamp_ns), frame_id="cad", id="links", lines=[line] if points else [])]), stamp_ns)

    def covariance(self, stamp_ns: int, T_cad_body: np.ndarray, covariance: np.ndarray) -> None:
        """The position covariance of a pose as an ellipsoid of 2 sigma along each principal axis (diameter 4
        sigma). `covariance`: 6x6 [rot; trans] in the body's tangent space (graph.localizer.Estimate's), so the
        position block is rotated into the CAD frame: R_cad_body C_tt R_cad_body^T."""
        R = T_cad_body[:3, :3]
        C_cad = R @ np.asarray(covariance, float)[3:, 3:] @ R.T
        variances, axes = np.linalg.eigh(0.5 * (C_cad + C_cad.T))
        if np.linalg.det(axes) < 0:  # a rotation, not a reflection
            axes[:, 0] = -axes[:, 0]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = axes, T_cad_body[:3, 3]
        d = 4.0 * np.sqrt(np.clip(variances, 0.0, None))
        sphere = SpherePrimitive(pose=_pose(T), size=Vector3(x=d[0], y=d[1], z=d[2]),
                                 color=_colour((1.0, 0.62, 0.1), 0.35))
        self.write("/pose/covariance", SceneUpdate(entities=[SceneEntity(
            timestamp=_stamp(stamp_ns), frame_id="cad", id="covariance", spheres=[sphere])]), stamp_ns)

    def poses(self, topic: str, stamp_ns: int, Ts_cad: list[np.ndarray]) -> None:
        """Several 4x4 poses in the CAD frame as one PosesInFrame (the plan's waypoints, the rival hypotheses)."""
        self.write(topic, PosesInFrame(timestamp=_stamp(stamp_ns), frame_id="cad", poses=[_pose(T) for T in Ts_cad]),
                   stamp_ns)

    def detections(self, stamp_ns: int, info: pb.CameraInfo, corners_cam: list[tuple[str, np.ndarray]]) -> None:
        """Each sighting's corners (4, 3) in the left camera frame, projected as a closed outline."""
        outlines = []
        for kind, c in corners_cam:
            if np.any(c[:, 2] <= 0.05):
                continue
            uv = np.c_[info.fx * c[:, 0] / c[:, 2] + info.cx, info.fy * c[:, 1] / c[:, 2] + info.cy]
            outlines.append(PointsAnnotation(timestamp=_stamp(stamp_ns), type=PointsAnnotation.LINE_LOOP,
                                             points=[Point2(x=float(u), y=float(v)) for u, v in uv],
                                             outline_color=_colour(TYPE_COLOUR.get(kind, OTHER_COLOUR), 1.0),
                                             thickness=3.0))
        self.write("/camera/left/detections", ImageAnnotations(points=outlines), stamp_ns)

    def status(self, stamp_ns: int, status: str) -> None:
        self.write("/status", Log(timestamp=_stamp(stamp_ns), level=STATUS_LEVEL.get(status, 2),  # type: ignore[arg-type]
                                  message=f"status: {status}", name="macroloc"), stamp_ns)


def _box(corners_cad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T_cad_box, size xyz) of a rectangle's 4 corners in order around it: x along its first side, y along its
    second, z its normal; 5 cm thick."""
    c = np.asarray(corners_cad, float)
    u, v = c[1] - c[0], c[3] - c[0]
    x = u / max(np.linalg.norm(u), 1e-9)
    z = np.cross(u, v)
    z = z / max(np.linalg.norm(z), 1e-9)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.c_[x, y, z]
    T[:3, 3] = c.mean(axis=0)
    return T, np.array([np.linalg.norm(u), abs(float(v @ y)), 0.05])
