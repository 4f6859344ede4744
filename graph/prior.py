"""An operator's prior on where the vehicle is (Nav2's `/initialpose`, a storey's name): it chooses among poses the
registration and the walls could not tell apart, and does nothing else.

Rules:
- A prior never makes a pose: it picks one of the tied poses an attempt left (`tied`: the walls' tied candidates,
  or, without the walls, the registration's candidates that each explain as many landmarks as the best and at
  least the registrar's `min_landmarks`), and only where exactly one of them lies inside its gate. No tied pose
  inside the gate, or two: nothing is picked, the status stays `ambiguous`.
- A prior never overrides the evidence: a registration that is `localized` by itself is taken as it is, whatever
  the prior says; one that is `exploring` (nothing confirmed) stays so.
- The gate of a pose prior: the body's position under the tied pose within `max(gate_sigmas * sigma_xy_m,
  MIN_GATE_M)` horizontally and `GATE_Z_M` vertically of the prior's, its heading within `max(gate_sigmas *
  sigma_yaw_rad, MIN_GATE_RAD)`. The gate of a storey: the body's height between that storey's elevation and the
  next one's (less `STOREY_MARGIN_M` each). With both, both must hold.
- The search is the whole model's, as without a prior (the registration's verification and its ambiguity test run
  as they do), so a wrong prior (another storey, 10 m off) finds no tied pose in its gate and picks nothing.

Frames: cad (the model, z up), map (the flight's odometry frame, z up), body. A pose prior is held as T_cad_map: the
operator's T_cad_body at a stamp times the inverse of the odometry's T_map_body at that stamp (the map frame does
not move, so the prior holds for later keyframes). Metres, radians.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from macroloc.graph.features import BuildingModel

MIN_GATE_M = 1.0  # a pose prior's horizontal gate is never narrower (rviz's 2D Pose Estimate: sigma 0.5 m)
MIN_GATE_RAD = float(np.deg2rad(20.0))
GATE_Z_M = 1.5  # half a storey: a pose prior on another storey admits nothing of this one
STOREY_MARGIN_M = 0.5


def yaw_of(R: np.ndarray) -> float:
    """Heading (rad) of a rotation matrix's x axis about z."""
    return float(np.arctan2(R[1, 0], R[0, 0]))


def storey_band_m(model: BuildingModel, storey: str) -> tuple[float, float]:
    """(low, high) CAD height (m) of a body on `storey`: from its elevation to the next storey's (less
    STOREY_MARGIN_M each; no upper bound on the top storey). KeyError for a storey without an elevation."""
    elevations = sorted(model.storey_elevations_m.values())
    low = model.storey_elevations_m[storey]
    above = [e for e in elevations if e > low + 1e-6]
    return low - STOREY_MARGIN_M, (min(above) - STOREY_MARGIN_M) if above else np.inf


@dataclass(frozen=True)
class PosePrior:
    """A prior (module doc): `T_cad_map` (4x4) from a pose prior, with its horizontal sigma (m) and heading sigma
    (rad); `storey_band_m`: (low, high) CAD height of the body from a storey prior (`storey_band_m`). Either or
    both."""

    T_cad_map: np.ndarray | None = None
    sigma_xy_m: float = 0.5
    sigma_yaw_rad: float = float(np.deg2rad(15.0))
    storey: str | None = None
    storey_band_m: tuple[float, float] | None = None
    gate_sigmas: float = 3.0

    def admits(self, T_cad_map: np.ndarray, T_map_body: np.ndarray) -> bool:
        """Whether the body at T_map_body (4x4, map frame) under the candidate T_cad_map lies inside the gate."""
        T_cad_body = T_cad_map @ T_map_body
        if self.storey_band_m is not None:
            low, high = self.storey_band_m
            if not low <= T_cad_body[2, 3] < high:
                return False
        if self.T_cad_map is None:
            return True
        T_prior_body = self.T_cad_map @ T_map_body
        d = T_cad_body[:3, 3] - T_prior_body[:3, 3]
        turned = abs((yaw_of(T_cad_body[:3, :3]) - yaw_of(T_prior_body[:3, :3]) + np.pi) % (2 * np.pi) - np.pi)
        return float(np.hypot(d[0], d[1])) <= max(self.gate_sigmas * self.sigma_xy_m, MIN_GATE_M) and \
            abs(float(d[2])) <= GATE_Z_M and turned <= max(self.gate_sigmas * self.sigma_yaw_rad, MIN_GATE_RAD)

    def pick(self, tied: Sequence[np.ndarray], T_map_body: np.ndarray) -> np.ndarray | None:
        """The one tied T_cad_map inside the gate (module doc), else None (none inside, or two or more)."""
        inside = [T for T in tied if self.admits(T, T_map_body)]
        return inside[0] if len(inside) == 1 else None

    def describe(self) -> str:
        where = [] if self.T_cad_map is None else [f"pose (sigma {self.sigma_xy_m:.2f} m, "
                                                   f"{np.rad2deg(self.sigma_yaw_rad):.0f} deg)"]
        return " and ".join(where + ([f"storey {self.storey!r}"] if self.storey else [])) or "nothing"
