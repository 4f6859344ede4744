"""The saved map: what a run leaves for the next one to start from, one format and one restore path for
`serve --state-dir` (its periodic saves and a restart) and `replay --save-map` / `replay --map`.

Its format is the `MapSnapshot` message (the same one the service's `macroloc/<vehicle>/map` query answers) in one
file, with its keyframe views in a view log beside it (service.state.SavedMapFile): the service's is
`<state_dir>/<vehicle>/map.pb`; a replay's is the path given to `--save-map`. A file written by either loads in
the other: `replay --map <state_dir>/<vehicle>/map.pb`, or a replay's map (and its view log) copied to
`<state_dir>/<vehicle>/map.pb` before `serve` starts.

What is saved (`map_snapshot`, `saved_views`): the run's landmarks (map frame) with their CAD links, T_cad_map
and the status, the last pose, and the keyframe views kept for place recognition; where the run started from a
saved map, that map's landmarks and views this run has none near, moved into this run's map frame (a map grows
flight after flight without piling up copies of the same places). A run that started from a localized saved map
does not replace it before it is localized itself (`supersedes`).

What a run starts from (`SavedMap`, `SavedMap.registrar`): where the saved map was localized and holds views, its
frames are placed in them by place recognition (service.places) from the first frame on, before any door is
seen. Otherwise `RestoredRegistrar` first checks the saved T_cad_map against the first sightings (the vehicle's
odometry usually outlives a service restart), then the landmarks the saved map linked to the model
(`SavedMapRegistrar`), then the whole model.

Other "maps" of the code, not this one: the localizer's `LandmarkMap` (this run's landmarks, in memory) and the
map frame (the odometry's frame, "map" in `T_map_body`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.localizer import Estimate, Localizer, LocalizerParams, model_registrar, stored_registrar
from macroloc.graph.mapstore import PlacedView, carried_views
from macroloc.graph.registrar import FirstOfRegistrar, Registrar
from macroloc.graph.relocalize import Alignment, KnownRect, ObservedRect
from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
from macroloc.proto.recording import matrix_from_pose, pose_from_matrix, vector3
from macroloc.service.localizer_loop import LoopSettings
from macroloc.service.state import SavedMapFile, view_from_wire, view_to_wire

log = logging.getLogger(__name__)

STATUS_TO_WIRE = {"exploring": pb.PoseEstimate.EXPLORING, "localized": pb.PoseEstimate.LOCALIZED,
                  "ambiguous": pb.PoseEstimate.AMBIGUOUS, "degraded": pb.PoseEstimate.DEGRADED,
                  "lost": pb.PoseEstimate.LOST}
SAME_LANDMARK_M = 0.5  # two doors or windows of one building are a frame width apart at least (> 0.6 m)


@dataclass(frozen=True)
class SavedLandmark:
    """A landmark of a saved map: type, linked CAD feature id ("" if none), corners (4, 3) in the CAD frame."""

    type: str
    id: str
    corners_cad: np.ndarray


@dataclass
class SavedMap:
    """A saved map as a run starts from it (see module doc). `T_cad_map`: where the saving run was localized, else
    None (its landmarks and views cannot be placed in the CAD frame then, and are not used); `linked`: the model's
    frames of the vertical features its landmarks were linked to; `landmarks`: its landmarks (CAD frame);
    `views`: its keyframe views (T_map_body in the saved map's frame, view)."""

    building_sha256: str
    T_cad_map: np.ndarray | None
    linked: list[KnownRect] = field(default_factory=list)
    landmarks: list[SavedLandmark] = field(default_factory=list)
    views: list[PlacedView] = field(default_factory=list)

    @classmethod
    def from_snapshot(cls, snapshot: pb.MapSnapshot, model: BuildingModel) -> SavedMap:
        """The saved map of `snapshot` (views inline, as `SavedMapFile.read` gives them) in `model`."""
        features = {f.id: f for f in model.features}
        linked = [KnownRect(lm.id, features[lm.id].type, feature_frame_cad(features[lm.id]))
                  for lm in snapshot.landmarks_map if lm.id in features and features[lm.id].orientation == "vertical"]
        T_cad_map = matrix_from_pose(snapshot.T_cad_map) if snapshot.status == pb.PoseEstimate.LOCALIZED else None
        if T_cad_map is None:  # in an unlocalized map's frame its landmarks and views cannot be placed: dropped
            return cls(snapshot.building_sha256, None, linked)
        landmarks = [SavedLandmark(lm.type, lm.id, np.array([[c.x, c.y, c.z] for c in lm.corners])
                                   @ T_cad_map[:3, :3].T + T_cad_map[:3, 3])
                     for lm in snapshot.landmarks_map if len(lm.corners) == 4]
        return cls(snapshot.building_sha256, T_cad_map, linked, landmarks, [view_from_wire(v) for v in snapshot.views])

    def placed_views(self) -> list[PlacedView]:
        """(T_map_body, view) of its keyframe views: what place recognition places a new run's frames in."""
        return self.views

    def registrar(self, model: BuildingModel,
                  with_surfaces: bool = False) -> Callable[[LoopSettings], Registrar]:
        """The registrar of a run started from this map, from the session's settings (for
        service.localizer_loop.loop_from_config): `RestoredRegistrar`."""
        log.info("starting from a saved map: %d linked landmarks, %d keyframe views, T_cad_map %s", len(self.linked),
                 len(self.views), "saved" if self.T_cad_map is not None else "absent")

        def restored(s: LoopSettings) -> Registrar:
            fallback = model_registrar(model, s.localizer.registration, s.storey_hint, with_surfaces, s.method)
            return RestoredRegistrar(model, self.T_cad_map, self.linked, fallback, params=s.localizer,
                                     with_surfaces=with_surfaces)

        return restored


class RestoredRegistrar:
    """Re-localization into a saved map: its T_cad_map, then its CAD-linked landmarks, then the model."""

    min_landmarks = 1
    candidates_from = 1

    def __init__(self, model: BuildingModel, T_cad_map_saved: np.ndarray | None, linked: list[KnownRect],
                 fallback: Registrar, agree_m: float = 0.4, params: LocalizerParams | None = None,
                 with_surfaces: bool = False) -> None:
        self.T_cad_map_saved = T_cad_map_saved
        stored = stored_registrar(model, linked, (params or LocalizerParams()).registration, with_surfaces) \
            if linked else None
        # the saved landmarks' few poses first (checked by the walls), the whole model's where they fail
        self.chain: Registrar = FirstOfRegistrar([stored, fallback]) if stored is not None else fallback
        self.agree_m = agree_m
        self._known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features
                       if f.orientation == "vertical"]
        self._known_xyz = np.array([k.T_cad_rect[:3, 3] for k in self._known]).reshape(-1, 3)

    def __call__(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        if self.T_cad_map_saved is not None:
            matches = self._agreeing(landmarks)
            if len(matches) >= max(1, int(np.ceil(0.6 * len(landmarks)))):
                saved = Alignment("localized", self.T_cad_map_saved, matches, len(matches))
                saved.fallback = lambda: self._registered(landmarks, corners_map)  # where the walls refuse it
                return saved
        return self._registered(landmarks, corners_map)

    def _registered(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        if len(landmarks) >= self.chain.candidates_from:
            return self.chain(landmarks, corners_map)
        return Alignment("not_localized", None)

    def _agreeing(self, landmarks: list[ObservedRect]) -> list[tuple[int, str]]:
        assert self.T_cad_map_saved is not None
        matches = []
        for lm in landmarks:
            xyz_cad = (self.T_cad_map_saved @ lm.T_map_rect)[:3, 3]
            d = np.linalg.norm(self._known_xyz - xyz_cad, axis=1)
            for k in np.argsort(d)[:3]:
                if d[k] < self.agree_m and self._known[k].type == lm.type:
                    matches.append((lm.key, self._known[k].id))
                    break
        return matches


# --- saving -----------------------------------------------------------------------------------------------------


def map_snapshot(localizer: Localizer, last: Estimate | None, started_from: SavedMap | None, building: str,
                 building_sha256: str | None = None) -> pb.MapSnapshot:
    """The map as saved and served (the map query's reply): this run's landmarks (map frame) with their CAD links
    and those of the saved map it started from that it has not seen, T_cad_map, the status, the last pose
    (`last`: the newest estimate); `building`: the model's file name, `building_sha256`: its hash (default: the
    localizer's model's). Its views are added on saving (`saved_views`, SavedMapFile.save)."""
    model = localizer.model
    snap = pb.MapSnapshot(building=building, building_sha256=building_sha256 or model.sha256,
                          status=STATUS_TO_WIRE[localizer.status], keyframes=localizer.graph.n_keyframes)
    snap.header.frame_id = "map"
    T_cad_map = localizer.graph.T_cad_map()
    if T_cad_map is not None:
        snap.T_cad_map.CopyFrom(pose_from_matrix(T_cad_map))
    if last is not None:
        snap.header.stamp_ns = last.stamp_ns
        snap.T_map_body.CopyFrom(pose_from_matrix(last.T_map_body))
        snap.storey = _storey_of(model, last.matches)
    own = []
    for j, lm in localizer.landmarks.items():
        f = snap.landmarks_map.add(type=lm.type, id=localizer.links.get(j, ""), source_id=lm.truth_id or "")
        corners = lm.corners(localizer.graph.T_map_rect(j))
        f.corners.extend(vector3(c) for c in corners)
        own.append((lm.type, f.id, np.asarray(corners).mean(axis=0)))
    if T_cad_map is not None and started_from is not None:
        for kind, feature_id, corners_map in carried_landmarks(started_from.landmarks, own, np.linalg.inv(T_cad_map)):
            snap.landmarks_map.add(type=kind, id=feature_id).corners.extend(vector3(c) for c in corners_map)
    return snap


def saved_views(localizer: Localizer, started_from: SavedMap | None) -> list[PlacedView]:
    """The keyframe views a saved map keeps for place recognition, (T_map_body, view): this run's, and those of the
    saved map it started from where this run has none near, in this run's map frame, once it is localized."""
    own = [(localizer.graph.T_map_body(i), v) for i, v in sorted(localizer.views.items())]
    T_cad_map = localizer.graph.T_cad_map()
    if started_from is not None and T_cad_map is not None:  # what a later run can be placed by
        return own + carried_views(own, T_cad_map, started_from.T_cad_map, started_from.placed_views())
    return own


def supersedes(localizer: Localizer, started_from: SavedMap | None) -> bool:
    """Whether this run's map should replace the saved one it started from: not before this run is localized,
    where that one was (a run stopped before it finds itself would otherwise lose the saved map, its links to the
    model and its views)."""
    return started_from is None or started_from.T_cad_map is None or localizer.graph.has_anchor


def carried_landmarks(carried: list[SavedLandmark], own: list[tuple[str, str, np.ndarray]],
                      T_map_cad: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """The saved map's landmarks this run has not seen, as (type, id, corners_map (4, 3)) in this run's map
    frame: one linked to a CAD feature this run also links, or of the same type with its centroid within
    SAME_LANDMARK_M of one of this run's (`own`: type, id, centroid_map), is the same one."""
    out = []
    own_ids = {i for _, i, _ in own if i}
    for lm in carried:
        corners_map = lm.corners_cad @ T_map_cad[:3, :3].T + T_map_cad[:3, 3]
        centroid = corners_map.mean(axis=0)
        if (lm.id and lm.id in own_ids) or any(t == lm.type and np.linalg.norm(c - centroid) < SAME_LANDMARK_M
                                               for t, _, c in own):
            continue
        out.append((lm.type, lm.id, corners_map))
    return out


def _storey_of(model: BuildingModel, matches: dict[int, str]) -> str:
    storeys = {f.id: f.storey for f in model.features}
    names = [str(storeys[fid]) for fid in matches.values() if storeys.get(fid)]
    return max(set(names), key=names.count) if names else ""


# --- files: `replay --map` / `--save-map` (the service keeps its own SavedMapFile under state_dir) ------------


def read_saved_map(path: Path, model: BuildingModel) -> SavedMap:
    """The saved map at `path` (a service's `<state_dir>/<vehicle>/map.pb` or a replay's `--save-map`), for a run
    in `model`. UserInputError where there is none, where it is not a saved map (a JSON map of macroloc before
    issue 56 included: it is refused, to be saved again) or was made in another building."""
    snapshot = SavedMapFile.at(path).read()
    if snapshot.building_sha256 != model.sha256:
        raise UserInputError(f"saved map {path} was made in another building")
    return SavedMap.from_snapshot(snapshot, model)


def write_saved_map(path: Path, localizer: Localizer, last: Estimate | None, started_from: SavedMap | None,
                    building: str, replaces: Path | None = None) -> Path | None:
    """Save a run's map at `path` (with its view log beside it), as the service saves its own; `last`: its newest
    estimate (`LastEstimate`), `building`: the model's file name. Where `path` is the saved map the run started
    from (`replaces`) and the run does not supersede it (`supersedes`), that map is kept and nothing is written
    (None), as the service keeps its own."""
    if replaces is not None and Path(path).resolve() == Path(replaces).resolve() \
            and not supersedes(localizer, started_from):
        log.warning("not localized: the saved map %s this run started from is kept as it was", path)
        return None
    return SavedMapFile.at(path).save(map_snapshot(localizer, last, started_from, building),
                                      saved_views(localizer, started_from))


class LastEstimate:
    """A replay's sink (service.offline.replay) that keeps its newest estimate, for `write_saved_map`'s last pose
    (a late keyframe for an older stamp does not replace a newer pose, as in the session's `last`)."""

    def __init__(self) -> None:
        self.estimate: Estimate | None = None

    def __call__(self, estimate: Estimate) -> None:
        if self.estimate is None or estimate.stamp_ns >= self.estimate.stamp_ns:
            self.estimate = estimate


def saved_map_of(localizer: Localizer, started_from: SavedMap | None = None) -> SavedMap:
    """A run's saved map as a later run reads it back (`write_saved_map`, then `read_saved_map`), without the file."""
    snapshot = map_snapshot(localizer, None, started_from, "")
    snapshot.views.extend(view_to_wire(v, T) for T, v in saved_views(localizer, started_from))
    return SavedMap.from_snapshot(snapshot, localizer.model)
