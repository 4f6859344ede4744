"""Landmarks linked to the building model's features once the map is anchored to it: each link is a factor
holding the landmark at its CAD feature, and the links' sightings keep the status localized.

A landmark is linked by its position, and by its orientation too only where that lies within
`cad_link_max_turn_deg` of the feature's: a door's orientation is its corners' plane, which a door seen obliquely
through another doorway (one side hidden by its jamb) has far off, nearly always the same way; linked by that
orientation it would turn the flight to fit it, by its position only the walls and the odometry keep the heading
(docs/measurements.md, "A door seen obliquely is linked by its position only").

Frames: map (the flight's odometry frame, z up), cad (the model's); T_cad_map maps map points into the CAD frame.
"""

from __future__ import annotations

import logging

import numpy as np

from macroloc.graph.features import MacroFeature
from macroloc.graph.landmarks import closer_flip, feature_frame_cad
from macroloc.graph.params import AnchorParams
from macroloc.graph.posegraph import CAD_LINK_POSITION_SIGMAS, CAD_LINK_SIGMAS, PoseGraph
from macroloc.graph.rigid import rotation_angle_deg
from macroloc.graph.sightings import Landmark

log = logging.getLogger(__name__)


class CadLinks:
    """Landmark key -> CAD feature id, and when a linked landmark was last seen (see module doc)."""

    def __init__(self, params: AnchorParams, graph: PoseGraph, features: dict[str, MacroFeature]) -> None:
        """`features`: the model's features by id."""
        self.params = params
        self.graph = graph
        self.features = features
        self.links: dict[int, str] = {}
        self.last_link_ns: int | None = None  # the newest keyframe that saw a linked landmark (or linked one)

    def seen(self, keys: set[int], stamp_ns: int) -> None:
        """The landmarks `keys` were re-observed at `stamp_ns`: where one of them is linked, the model was seen."""
        if any(j in self.links for j in keys):
            self.last_link_ns = stamp_ns

    def link(self, j: int, fid: str, T_cad_map: np.ndarray) -> None:
        """Landmark j is CAD feature `fid`: its position, and its orientation where the landmark's lies within
        `cad_link_max_turn_deg` of the feature's (see module doc)."""
        feature = self.features.get(fid)
        if feature is None or feature.orientation != "vertical":
            return
        T_cad_pred = T_cad_map @ self.graph.T_map_rect(j)
        T_cad_rect = closer_flip(feature_frame_cad(feature), T_cad_pred)
        turn_deg = rotation_angle_deg(T_cad_rect[:3, :3].T @ T_cad_pred[:3, :3])
        oriented = turn_deg <= self.params.cad_link_max_turn_deg
        if not oriented:
            log.info("landmark %d linked to %s by its position only: its orientation is %.1f deg off", j, fid,
                     turn_deg)
        self.graph.add_cad_link(j, T_cad_rect, CAD_LINK_SIGMAS if oriented else CAD_LINK_POSITION_SIGMAS)
        self.links[j] = fid

    def link_new(self, landmarks: dict[int, Landmark], stamp_ns: int) -> None:
        """The landmarks not yet linked that lie within `cad_link_m` of a same-type CAD feature no other landmark
        is linked to are linked (the graph anchored)."""
        T_cad_map = self.graph.T_cad_map()
        assert T_cad_map is not None
        linked = set(self.links.values())
        added = False
        for j, lm in landmarks.items():
            if j in self.links:
                continue
            T_cad_rect = T_cad_map @ self.graph.T_map_rect(j)
            fid = self._nearest_feature(lm.type, T_cad_rect[:3, 3], exclude=linked)
            if fid is not None:
                self.link(j, fid, T_cad_map)
                linked.add(fid)
                added = True
                self.last_link_ns = stamp_ns
        if added:
            self.graph.update()

    def _nearest_feature(self, kind: str, xyz_cad: np.ndarray, exclude: set[str]) -> str | None:
        """The vertical `kind` feature nearest to `xyz_cad` (3,) within `cad_link_m`, not among `exclude`."""
        best, best_d = None, self.params.cad_link_m
        for f in self.features.values():
            if f.type != kind or f.orientation != "vertical" or f.id in exclude:
                continue
            d = float(np.linalg.norm(f.centroid_cad - xyz_cad))
            if d < best_d:
                best, best_d = f.id, d
        return best
