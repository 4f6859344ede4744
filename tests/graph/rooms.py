"""The test room of the surface-check tests: a 12 x 7 m box with a 4 m partition from one wall, walls 3 m tall,
floor and ceiling; what a camera in it measures; a registrar that answers with given candidate poses and a
short flight that sees two doors and the walls."""

from __future__ import annotations

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.localizer import Localizer, LocalizerParams
from macroloc.graph.posegraph import PoseGraph
from macroloc.graph.registrar import Registrar
from macroloc.graph.relocalize import Alignment
from macroloc.graph.rigid import apply
from macroloc.graph.surfaces import (
    SurfaceIndex,
)
from tests.graph.helpers import localizer_params
from tests.graph.scenes import corridor_model, make_T, rot_z, sightings_from

UP = np.array([0.0, 0.0, 1.0])


def quad(a, b, c, d) -> tuple[np.ndarray, np.ndarray]:
    return np.array([a, b, c, d], float), np.array([[0, 1, 2], [0, 2, 3]])


def wall(x0, y0, x1, y1, h=3.0):  # noqa: ANN001, ANN201
    return quad((x0, y0, 0), (x1, y1, 0), (x1, y1, h), (x0, y0, h))


def room_mesh() -> tuple[np.ndarray, np.ndarray]:
    parts = [wall(0, 0, 12, 0), wall(12, 0, 12, 7), wall(12, 7, 0, 7), wall(0, 7, 0, 0), wall(5, 0, 5, 4),
             quad((0, 0, 0), (12, 0, 0), (12, 7, 0), (0, 7, 0)), quad((0, 0, 3), (12, 0, 3), (12, 7, 3), (0, 7, 3))]
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.vstack(vertices), np.vstack(faces)


WALL_SEGMENTS = np.array([[0, 0, 12, 0], [12, 0, 12, 7], [12, 7, 0, 7], [0, 7, 0, 0], [5, 0, 5, 4]], float)



def seen_points(rng: np.random.Generator, camera_xy: np.ndarray, n: int = 150, z: float = 1.4,
                segments: np.ndarray = WALL_SEGMENTS) -> np.ndarray:
    """What a camera at `camera_xy` in the room (or the walls `segments`) measures around it (CAD): the nearest
    wall along random horizontal directions, at heights about its own."""
    a = rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.cos(a), np.sin(a)])
    nearest = np.full(n, np.inf)
    for x0, y0, x1, y1 in segments:
        e, w = np.array([x1 - x0, y1 - y0]), np.array([x0, y0]) - camera_xy
        den = d[:, 0] * e[1] - d[:, 1] * e[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[0] * e[1] - w[1] * e[0]) / den  # along the line of sight
            s = (w[0] * d[:, 1] - w[1] * d[:, 0]) / den  # along the wall
        hit = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1) & (t < nearest)
        nearest[hit] = t[hit]
    xy = camera_xy + d * nearest[:, None]
    return np.column_stack([xy, z + rng.uniform(-0.4, 0.4, n)])[np.isfinite(nearest)]  # where a wall was hit


def wall_points(rng: np.random.Generator, n: int = 400, z: float = 1.4, n_walls: int = 5) -> np.ndarray:
    """Points on the walls at about camera height (CAD), as a camera turning in the room would measure them."""
    v, f = room_mesh()
    walls = v[f[: 2 * n_walls]]  # the walls' triangles (2 each)
    k = rng.integers(0, len(walls), n)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    p = (1 - s)[:, None] * walls[k, 0] + (s * (1 - r2))[:, None] * walls[k, 1] + (s * r2)[:, None] * walls[k, 2]
    p[:, 2] = z + rng.uniform(-0.4, 0.4, n)
    return p


class CandidatesRegistrar:
    """Answers every registration with the given candidate poses (T_cad_map, inliers), as 'ambiguous' or, for
    `localized`, naming the first one; tries from 2 landmarks, trusts from 4."""

    min_landmarks = 4
    candidates_from = 2

    def __init__(self, candidates: list[np.ndarray], localized: bool = False) -> None:
        self.candidates = candidates
        self.localized = localized
        self.calls = 0

    def __call__(self, landmarks, corners_map) -> Alignment:  # noqa: ANN001
        self.calls += 1
        status = "localized" if self.localized else "ambiguous"
        return Alignment(status, self.candidates[0], [], len(landmarks), [(T, len(landmarks))
                                                                           for T in self.candidates])


T_TRUE = make_T(np.eye(3), np.array([2.0, 3.5, 0.0]))  # T_cad_map: the flight starts 2 m into the room
T_WRONG = make_T(rot_z(0.35), np.array([3.0, 2.0, 0.0]))  # 20 degrees and a metre or so off


def fly_in_room(room: SurfaceIndex | None, registrar: Registrar, with_points: bool = True,
                n_walls: int = 5, model: BuildingModel | None = None, **params: float) -> Localizer:
    """Three keyframes that see two doors of a corridor model (`model`: it, or a model whose first features are
    its; the registrar ignores where they are) and the room's walls around the flight; `params`: LocalizerParams
    beside the defaults."""
    model = model or corridor_model()
    rng = np.random.default_rng(3)
    loc = Localizer(model, PoseGraph(), registrar, localizer_params(surface_min_points=100, **params),  # type: ignore[arg-type]
                    surfaces=room)
    T_cad_body_doors = make_T(np.eye(3), np.array([1.0, 0.0, 1.4]))  # where two doors are in view
    for k in range(3):
        T_map_body = make_T(np.eye(3), np.array([0.1 * k, 0.0, 1.4]))
        T_cad_body = T_TRUE @ T_map_body
        points_cad = wall_points(rng, 150, n_walls=n_walls)
        points_body = apply(np.linalg.inv(T_cad_body), points_cad) if with_points else None
        sightings = sightings_from(model, T_cad_body_doors)[:2]
        loc.add_keyframe(k * 100_000_000, T_map_body, sightings, UP, points_body=points_body)
    return loc


def fly_seeing(room: SurfaceIndex, registrar: CandidatesRegistrar, cameras_cad: list[np.ndarray],
               params: LocalizerParams | None = None) -> Localizer:
    """Keyframes at `cameras_cad` (x, y; the map frame is T_TRUE's) with what a camera there sees of the room,
    and two door sightings for the registrar (which ignores where they are)."""
    model = corridor_model()
    rng = np.random.default_rng(6)
    loc = Localizer(model, PoseGraph(), registrar, params or localizer_params(surface_min_points=100), surfaces=room)
    sightings = sightings_from(model, make_T(np.eye(3), np.array([1.0, 0.0, 1.4])))[:2]
    for k, xy in enumerate(cameras_cad):
        T_cad_body = make_T(np.eye(3), np.array([xy[0], xy[1], 1.4]))
        T_map_body = np.linalg.inv(T_TRUE) @ T_cad_body
        points_body = apply(np.linalg.inv(T_cad_body), seen_points(rng, np.asarray(xy, float)))
        loc.add_keyframe(k * 100_000_000, T_map_body, sightings, UP, points_body=points_body)
    return loc


NEAR_THE_PARTITION_END = [np.array([6.5, 6.0]), np.array([6.8, 5.7]), np.array([7.1, 5.4])]
