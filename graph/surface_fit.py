"""Once the map is anchored to the model, each keyframe's depth points fitted to the model's walls and floor
(point-to-plane, graph.surfaces.align_to_surfaces) enter the pose graph as a measured T_cad_body with the fit's
information: the walls hold the pose where the doors' corners are coarse, the floor holds its height.

A fit that moves the pose more than `surface_fit_max_correction_m` or turns it more than
`surface_fit_max_turn_deg` is a fit to a wrong wall and is refused; in the first `surface_fit_settling_keyframes`
after localizing the turn may reach `surface_fit_settling_turn_deg`, while the pose still carries the orientation
error of the few doors it was found by.

The keyframe that anchors the graph is fitted before the registration's doors are linked (linked first, the pose
is where their coarse positions put it, and the fit from there may be refused as too large), to the walls alone
with its height held (the candidate's height is the registration's), and by the window's points, those the pose
was chosen and fitted by (`SurfaceJudge.refined`), not the keyframe's alone
(docs/measurements.md, "The anchoring keyframe is fitted by the window's points").

Frames: body (x forward, y left, z up), map (the flight's odometry frame, z up), cad (the model's). Metres.
"""

from __future__ import annotations

import numpy as np

from macroloc.graph.depth_window import DepthWindow
from macroloc.graph.params import SurfaceFitParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.rigid import apply, rotation_angle_deg
from macroloc.graph.surfaces import SurfaceIndex, align_to_surfaces


class SurfaceFitter:
    """Fits the newest keyframe to the model's surfaces, once each (see module doc)."""

    def __init__(self, params: SurfaceFitParams, graph: PoseGraph, depth: DepthWindow, surfaces: SurfaceIndex) -> None:
        self.params = params
        self.graph = graph
        self.depth = depth
        self.surfaces = surfaces
        self.fits = 0  # keyframes whose depth was fitted to the walls (and floor)
        self._tried_at = -1  # the newest keyframe whose depth points a fit to the walls was tried with
        self._anchored_at: int | None = None  # the keyframe at which the graph was anchored to the model

    def anchored_at(self, i: int) -> None:
        """The graph was anchored at keyframe i: the fits of the keyframes after it settle the pose's heading."""
        self._anchored_at = i

    def fit_newest(self, anchoring: bool = False) -> None:
        """The newest keyframe fitted to the surfaces, once, where it has depth points and the graph is anchored;
        `anchoring`: it is the keyframe that anchors the graph (see module doc)."""
        i = self.graph.n_keyframes - 1
        if not self.graph.has_anchor or not self.depth or self.depth.newest[0] != i or self._tried_at == i:
            return
        self._tried_at = i
        _, points_body, floor_body = self.depth.newest
        if anchoring:  # the window's points, as the candidate was chosen and fitted by (`SurfaceJudge.refined`)
            points_body = apply(np.linalg.inv(self.graph.T_map_body(i)), self.depth.points_map()[0])
        self._fit(i, points_body, floor_body if not anchoring else None)

    def _fit(self, i: int, points_body: np.ndarray, floor_body: np.ndarray | None) -> None:
        """Keyframe i's points (N, 3, body frame) fitted to the walls and, with `floor_body`, the floors; without
        floor points the height is held as it is."""
        T_cad_map = self.graph.T_cad_map()
        if not self.params.surface_fit or T_cad_map is None:
            return
        T_guess = T_cad_map @ self.graph.T_map_body(i)
        fit = align_to_surfaces(self.surfaces, points_body, T_guess, floor_body,
                                sigma_m=self.params.surface_fit_sigma_m, hold_height=floor_body is None)
        if fit is None:
            return
        step = np.linalg.inv(T_guess) @ fit.T_cad_body
        if np.linalg.norm(step[:3, 3]) > self.params.surface_fit_max_correction_m or \
                rotation_angle_deg(step[:3, :3]) > self._max_turn_deg(i):
            return
        self.graph.add_cad_pose(i, fit.T_cad_body, fit.information)
        self.graph.update()
        self.fits += 1

    def _max_turn_deg(self, i: int) -> float:
        """How far a fit may turn keyframe i's pose: further while the pose settles after localizing (a pose found
        by one door carries that door's orientation error, a few degrees, until the walls turn it back), less once
        it is held by the walls and more doors (a larger turn is then a fit to a wrong wall)."""
        p = self.params
        settling = self._anchored_at is not None and i - self._anchored_at < p.surface_fit_settling_keyframes
        return p.surface_fit_settling_turn_deg if settling else p.surface_fit_max_turn_deg


class NullFitter:
    """No model surfaces: no fits."""

    fits = 0

    def anchored_at(self, i: int) -> None:
        pass

    def fit_newest(self, anchoring: bool = False) -> None:
        pass
