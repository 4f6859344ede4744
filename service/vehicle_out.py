"""Vehicle-facing outputs beside the protobuf keys: the seam the service publishes ROS 2 and PX4 messages through.

`VehicleOutput` is what `service.node` calls on every pose, plan and status; `NullVehicleOutput` is the one used
when neither `[ros]` nor `[px4]` is enabled (no flag in the hot loop); `VehicleOutputs` fans out to several.
`Motion` turns consecutive estimates into a velocity where it is known: from the odometry frame's poses (smooth
across re-localizations), rotated into the CAD frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from macroloc.graph.localizer import Estimate
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb

MAX_VELOCITY_GAP_NS = 500_000_000  # poses further apart than this give no velocity


class VehicleOutput(Protocol):
    def pose(self, est: Estimate) -> None:
        """A new estimate (stamps increase)."""

    def waypoints(self, msg: pb.Waypoints) -> None:
        """A new plan (CAD frame, with its yaws and the stamp of the pose it started from)."""

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        """The periodic status."""

    def close(self) -> None:
        """Undeclare publishers, stop timers (before the session closes)."""


class NullVehicleOutput:
    """Publishes nothing: neither ROS nor PX4 enabled."""

    def pose(self, est: Estimate) -> None:
        pass

    def waypoints(self, msg: pb.Waypoints) -> None:
        pass

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        pass

    def close(self) -> None:
        pass


class Closes(Protocol):
    def close(self) -> None: ...


class VehicleOutputs:
    """Several outputs as one (ROS and PX4 both on); `then_close`: closed after the outputs (their transport's
    announcements, service.ros_transport)."""

    def __init__(self, outputs: Sequence[VehicleOutput], then_close: Sequence[Closes] = ()) -> None:
        self.outputs = list(outputs)
        self.then_close = list(then_close)

    def pose(self, est: Estimate) -> None:
        for out in self.outputs:
            out.pose(est)

    def waypoints(self, msg: pb.Waypoints) -> None:
        for out in self.outputs:
            out.waypoints(msg)

    def status(self, diag: pb.Diagnostics, status: pb.ServiceStatus) -> None:
        for out in self.outputs:
            out.status(diag, status)

    def close(self) -> None:
        for out in self.outputs:
            out.close()
        for other in self.then_close:
            other.close()


class Motion:
    """Velocity of the body (m/s) from consecutive estimates: finite differences of T_map_body (the odometry
    frame, which re-localizations do not move), rotated into the CAD frame by the estimate's T_cad_map."""

    def __init__(self) -> None:
        self._last: tuple[int, np.ndarray] | None = None

    def velocity_cad(self, est: Estimate) -> np.ndarray | None:
        """(3,) m/s in the CAD frame, or None where unknown (first pose, a gap, no T_cad_map)."""
        last, self._last = self._last, (est.stamp_ns, est.T_map_body[:3, 3].copy())
        if last is None or est.T_cad_map is None:
            return None
        dt_ns = est.stamp_ns - last[0]
        if dt_ns <= 0 or dt_ns > MAX_VELOCITY_GAP_NS:
            return None
        v_map = (est.T_map_body[:3, 3] - last[1]) / (dt_ns * 1e-9)
        return np.asarray(est.T_cad_map[:3, :3] @ v_map, float)


def waypoints_arrays(msg: pb.Waypoints) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points and (N,) yaws of a Waypoints message (yaws 0 where an older sender gave none)."""
    points = np.array([[p.x, p.y, p.z] for p in msg.points_cad], float).reshape(-1, 3)
    yaws = np.array(msg.yaw_rad, float) if len(msg.yaw_rad) == len(points) else np.zeros(len(points))
    return points, yaws
