"""The map's landmarks: the doors and windows seen within the sighting range, each a Pose3 landmark of the pose
graph (graph.landmarks), with the sighting factors that hold them to the keyframes.

A sighting re-observes the landmark nearest to it within `associate_m`, facing alike, or starts a new one,
whatever type each was called (one opening is one landmark: the detector calls a door a window in some frames, and
the landmark's type is the one most of its sightings were called, graph.sightings.Landmark.add_sighting); beyond
`max_range_m` it makes none (its corners are too coarse), and up to `far_range_m` it is handed back as a far
sighting (graph.far_window). A frame sees a door once: a second detection of the same landmark in one frame
(overlapping boxes of one door) is dropped, so that it neither counts as a second sighting nor doubles the weight of
its factor. A keyframe holds a landmark by one factor (`LandmarkParams.one_factor_per_keyframe`): the
frames carried into it saw the door from nearly one viewpoint within a fraction of a second, so their errors (the
detector's box on that door's look, the stereo's bias at that range) are shared, not independent; their mean is
one sighting's measurement, with one sighting's sigmas. The graph's weight of a door then follows the keyframes
that saw it, not the camera's frame rate or the perception cadence.

Frames: body (x forward, y left, z up), map (the flight's odometry frame, z up). Metres.
"""

from __future__ import annotations

import numpy as np

from macroloc.graph.landmarks import closer_flip, is_vertical, observed_frame
from macroloc.graph.params import LandmarkParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.relocalize import ObservedRect
from macroloc.graph.rigid import apply
from macroloc.graph.sightings import Landmark, Sighting


class LandmarkMap:
    """The landmarks by key, in the pose graph `graph` (see module doc)."""

    def __init__(self, params: LandmarkParams, graph: PoseGraph, viewer_body: np.ndarray) -> None:
        """`viewer_body` (3,): the camera's position in the body frame (sightings' ranges are from it)."""
        self.params = params
        self.graph = graph
        self.viewer_body = viewer_body
        self.landmarks: dict[int, Landmark] = {}
        self.duplicates = 0  # sightings dropped: their landmark was seen in the same frame already

    def add_frames(self, i: int, T_map_body: np.ndarray, frames: list[list[Sighting]], up_body: np.ndarray
                   ) -> tuple[list[Sighting], set[int]]:
        """The sightings of keyframe i (at T_map_body) and of the frames carried into it, frame by frame, into
        the graph; returns the far sightings (beyond `max_range_m`, up to `far_range_m`) and the keys of the
        landmarks re-observed."""
        far: list[Sighting] = []
        reobserved: set[int] = set()
        measured: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}  # landmark -> (T_body_rect, sigmas) per frame
        for sightings in frames:
            seen: set[int] = set()
            for s in sightings:
                j = self._add(i, T_map_body, s, up_body, seen, far, reobserved, measured)
                if j is not None:
                    seen.add(j)
        for j, measurements in measured.items():
            if self.params.one_factor_per_keyframe:
                measurements = [_mean_measurement(measurements)]
            for T_body_rect, sigmas in measurements:
                self.graph.add_sighting(i, j, T_body_rect, sigmas)
        return far, reobserved

    def _add(self, i: int, T_map_body: np.ndarray, s: Sighting, up_body: np.ndarray, seen: set[int],
             far: list[Sighting], reobserved: set[int], measured: dict[int, list[tuple[np.ndarray, np.ndarray]]]
             ) -> int | None:
        """One sighting into the landmark map (a new landmark or a re-observation), its measurement into
        `measured`; its landmark's key, or None where it was not taken (not upright, out of range: then into `far`
        up to `far_range_m`, or its landmark `seen` in the same frame already)."""
        p = self.params
        if not is_vertical(s.corners_body, up_body):
            return None
        T_body_rect = observed_frame(s.corners_body, up_body, self.viewer_body)
        rng = float(np.linalg.norm(T_body_rect[:3, 3] - self.viewer_body))
        if rng > p.max_range_m:
            if rng <= p.far_range_m:
                far.append(s)
            return None
        T_map_rect = T_map_body @ T_body_rect
        j = self._associate(T_map_rect)
        corners_map = apply(T_map_body, s.corners_body)
        if j is None:
            j = len(self.landmarks)
            self.landmarks[j] = Landmark.first_seen(j, s.type, corners_map, s.truncated, s.truth_id, i)
            self.graph.add_landmark(j, T_map_rect)
        elif j in seen:
            self.duplicates += 1
            return None
        else:
            self.landmarks[j].add_sighting(corners_map, s.truncated, i, s.type)
            T_body_rect = np.linalg.inv(T_map_body) @ closer_flip(T_map_rect, self.graph.T_map_rect(j))
            reobserved.add(j)
        measured.setdefault(j, []).append((T_body_rect, self._sigmas(s, rng)))
        return j

    def _sigmas(self, s: Sighting, range_m: float) -> np.ndarray:
        """[rot; trans] sigmas of a sighting, the translation along the rectangle's own axes (u along the wall,
        n its normal, z up): stereo noise grows with range squared; a side cut by the image border is loose."""
        p = self.params
        sigma_m = p.position_sigma_m(range_m)
        trans = np.full(3, sigma_m)
        if s.truncated[0]:
            trans[0] = max(sigma_m, p.truncated_sigma_m)
        if s.truncated[1]:
            trans[2] = max(sigma_m, p.truncated_sigma_m)
        return np.r_[np.full(3, p.sighting_sigma_rad[0] + p.sighting_sigma_rad[1] * range_m**2), trans]

    def _associate(self, T_map_rect: np.ndarray) -> int | None:
        """The landmark nearest to the sighting within `associate_m`, facing alike, or None (a new landmark)."""
        best, best_d = None, self.params.associate_m
        for j in self.landmarks:
            T_j = self.graph.T_map_rect(j)
            d = float(np.linalg.norm(T_j[:3, 3] - T_map_rect[:3, 3]))
            if d < best_d and abs(float(np.dot(T_j[:3, 1], T_map_rect[:3, 1]))) > 0.8:
                best, best_d = j, d
        return best

    def confirmed(self, min_keyframes: int) -> list[int]:
        """The keys of the landmarks seen from at least `min_keyframes` keyframes (`Landmark.n_keyframes`), in key
        order."""
        return [j for j, lm in sorted(self.landmarks.items()) if lm.n_keyframes >= min_keyframes]

    def observed(self, keys: list[int]) -> tuple[list[ObservedRect], list[np.ndarray]]:
        """The landmarks `keys` as the registrar takes them: their rectangles' frames and corners (4, 3), map
        frame, at the graph's current estimates."""
        observed = [ObservedRect(j, self.landmarks[j].type, self.graph.T_map_rect(j), self.landmarks[j].cut())
                    for j in keys]
        return observed, [self.landmarks[o.key].corners(o.T_map_rect) for o in observed]

    def centres_map(self, keys: list[int]) -> list[tuple[str, np.ndarray]]:
        """The landmarks `keys` as (type, centre (3,) in the map frame)."""
        return [(self.landmarks[j].type, self.graph.T_map_rect(j)[:3, 3]) for j in keys]

    def walls_map(self, keys: list[int]) -> list[tuple[np.ndarray, np.ndarray]]:
        """The planes of the landmarks `keys` (the walls they sit in) as (centre (3,), unit normal (3,)), map frame."""
        return [(T[:3, 3], T[:3, 1]) for T in (self.graph.T_map_rect(j) for j in keys)]


def _mean_measurement(measurements: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One keyframe's sightings of one landmark (T_body_rect 4x4, each flipped alike, and [rot; trans] sigmas) as
    one: the mean position, the chordal mean rotation (the nearest rotation to the matrices' mean) and the mean
    sigmas, those of one sighting (see the module doc)."""
    if len(measurements) == 1:
        return measurements[0]
    Ts = np.array([T for T, _ in measurements])
    u, _, vt = np.linalg.svd(Ts[:, :3, :3].sum(axis=0))
    T = np.eye(4)
    T[:3, :3] = u @ np.diag([1.0, 1.0, float(np.linalg.det(u @ vt))]) @ vt
    T[:3, 3] = Ts[:, :3, 3].mean(axis=0)
    return T, np.mean([sigmas for _, sigmas in measurements], axis=0)
