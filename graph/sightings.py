"""What the localizer is fed and keeps of each door and window: a sighting in one frame, a landmark of the flight.

Frames: body = x forward, y left, z up; map = the flight's odometry frame, z up. Metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Sighting:
    """A door/window seen in one frame: type and corners (4, 3) in the body frame (any order), metres.

    truncated: (sideways, vertically) cut by the image border; the corners on that side are the border's, not
    the opening's, so the position along that axis is known only roughly (see LocalizerParams.truncated_sigma_m).
    """

    type: str
    corners_body: np.ndarray
    truth_id: str | None = None  # ground truth (simulated flights), for scoring only: never used to match
    truncated: tuple[bool, bool] = (False, False)


@dataclass
class Landmark:
    """A door or window of this flight; its pose is the graph's (T_map_rect). Its size, which the registration
    compares with the model's (graph.robust, `size_tolerance_m`), is the median of its sightings' sides: the width
    over the sightings not cut by the image border sideways, the height over those not cut at the top or bottom
    (over all of them where every one is cut: a cut side is short). One sighting's is not enough: perception sees
    the doors of a corridor obliquely (65-75 deg off their normal) and with their frames, so a first sighting can be
    wider than the door by half a metre: the true door is then no candidate for it and the walls choose among wrong
    ones, while the median of a few sightings passes (docs/measurements.md, "Change by change")."""

    key: int
    type: str  # the type most of its sightings were called (`add_sighting`)
    sides_m: list[tuple[float, float, bool, bool]]  # each sighting's (width, height, cut sideways, cut vertically)
    truth_id: str | None = None  # scoring only
    keyframes: set[int] = field(default_factory=set)  # the keyframes that saw it
    votes: dict[str, int] = field(default_factory=dict)  # sightings per type called

    @classmethod
    def first_seen(cls, key: int, kind: str, corners: np.ndarray, truncated: tuple[bool, bool],
                   truth_id: str | None = None, keyframe: int | None = None) -> Landmark:
        landmark = cls(key, kind, [], truth_id)
        landmark.add_sighting(corners, truncated, keyframe, kind)
        return landmark

    @property
    def n_sightings(self) -> int:
        return len(self.sides_m)

    @property
    def n_keyframes(self) -> int:
        """The keyframes that saw it: the count registration asks for (`RegistrationParams.min_sightings_to_register`),
        since the frames carried into one keyframe saw it from one place within a fraction of a second (a false
        detection of something lasts as many frames as the camera takes then)."""
        return len(self.keyframes)

    def add_sighting(self, corners: np.ndarray, truncated: tuple[bool, bool], keyframe: int | None = None,
                     kind: str | None = None) -> None:
        """A sighting's corners (4, 3) in order around the rectangle, in a frame whose z is up (the map's), whether
        it was cut (sideways, vertically), the keyframe it entered the graph with, and the type it was called. The
        landmark's type is the one most of its sightings were called (the first on a tie): a detector calls one
        opening a door in some frames and a window in others, and it is one opening."""
        self.sides_m.append((*_sides_m(corners), bool(truncated[0]), bool(truncated[1])))
        if keyframe is not None:
            self.keyframes.add(keyframe)
        if kind is not None:
            self.votes[kind] = self.votes.get(kind, 0) + 1
            if self.votes[kind] > self.votes.get(self.type, 0):
                self.type = kind

    def size_m(self) -> tuple[float, float]:
        """(width, height), metres."""
        sides = np.array(self.sides_m, float)
        whole = sides[:, 2:] == 0
        width, height = (float(np.median(sides[whole[:, k], k] if whole[:, k].any() else sides[:, k])) for k in (0, 1))
        return width, height

    def cut(self) -> tuple[bool, bool]:
        """Whether every sighting was cut by the image border (sideways, vertically): the size along such an axis
        (`size_m`) is then a cut side's, short of the opening's."""
        sides = np.array(self.sides_m, float)
        return bool(sides[:, 2].all()), bool(sides[:, 3].all())

    def corners(self, T_x_rect: np.ndarray) -> np.ndarray:
        """The rectangle (4, 3) of `size_m` about the landmark's frame T_x_rect (axes u along the wall, n, z up)."""
        (w, h), u, z = self.size_m(), T_x_rect[:3, 0], T_x_rect[:3, 2]
        return T_x_rect[:3, 3] + np.array([-w * u + h * z, w * u + h * z, w * u - h * z, -w * u - h * z]) / 2.0


def _sides_m(corners: np.ndarray) -> tuple[float, float]:
    """(horizontal, vertical) side of a rectangle's corners (4, 3), in order around it, z up: the edge from the
    first corner to the second or to the fourth, whichever is more level, and the other."""
    p = np.asarray(corners, float)
    level, upright = p[1] - p[0], p[3] - p[0]
    if abs(level[2]) > abs(upright[2]):
        level, upright = upright, level
    return float(np.linalg.norm(level)), float(np.linalg.norm(upright))

