"""Registration strategies for the localizer: the map's landmarks -> T_cad_map and matches.

`ModelRegistrar` asks the registration (`graph.registration.register`: the robust method's rectangle-seeded
hypotheses, or the paper's descriptor matching + RANSAC) to place the map's landmarks in the whole building
model, with the method's typed parameters (`RobustParams`, `PaperParams`).
`SavedMapRegistrar` re-localizes into a saved map: only the landmarks a previous flight linked to the
model are candidates, so a couple of sightings settle it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Protocol

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.landmarks import feature_frame_cad
from macroloc.graph.model_index import index_for
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.registration import PaperParams, register
from macroloc.graph.relocalize import Alignment, KnownRect, ObservedRect, align_rectangles
from macroloc.graph.robust import RobustParams, single_rectangle_poses
from macroloc.graph.robust import prepare as prepare_robust

log = logging.getLogger(__name__)


class Registrar(Protocol):
    """Places the map's landmarks in the CAD frame. Input: landmarks with T_map_rect and their corners
    (4, 3) in the map frame (or None); the map frame's z is up (gravity). `min_landmarks`: the fewest landmarks
    it answers 'localized' from; `candidates_from` (<= min_landmarks): the fewest it is asked with at all, below
    `min_landmarks` answering with candidate poses for other evidence to choose among."""

    min_landmarks: int
    candidates_from: int

    def __call__(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment: ...


class ModelRegistrar:
    """Registration against the whole building model (see module doc)."""

    def __init__(self, model: BuildingModel, method: str = "robust", storey_hint: str | None = None,
                 min_landmarks: int = 3, inlier_threshold_m: float | None = None,
                 candidates_from: int | None = None, early_stop_fraction: float | None = None) -> None:
        """`min_landmarks`: registration is tried from this many landmarks on (the robust method then also
        accepts a pose with as many inliers: with gravity, two rectangles fix a pose, and its ambiguity test
        answers 'ambiguous' where the building repeats them); `inlier_threshold_m`: how far (m) an aligned
        landmark may lie from its CAD feature and still support a pose (the method's inlier tolerance, and the
        robust method's ambiguity tolerance; None: the method's defaults); `candidates_from`: with fewer landmarks
        than `min_landmarks` but at least this many (robust method), the candidate poses come back as
        'ambiguous', for other evidence to decide (the localizer's surface check); None: `min_landmarks`;
        `early_stop_fraction`: the robust method's (None: its default)."""
        self.model = model
        self.method = method
        self.storey_hint = storey_hint
        self.min_landmarks = min_landmarks
        self.candidates_from = min(min_landmarks, candidates_from or min_landmarks) if method == "robust" \
            else min_landmarks
        self.params = self._method_params(inlier_threshold_m, early_stop_fraction)
        self._known = [KnownRect(f.id, f.type, feature_frame_cad(f)) for f in model.features
                       if f.orientation == "vertical" and (storey_hint is None or f.storey == storey_hint)]
        index = index_for(model)  # the per-building preprocessing (cached): done here, before the first frame
        if isinstance(self.params, RobustParams) and (storey_hint is None or storey_hint in set(index.storeys)):
            prepare_robust(index.for_storey(storey_hint), self.params)  # the robust method's own (pairs, ...)

    def _method_params(self, inlier_threshold_m: float | None, early_stop_fraction: float | None
                       ) -> RobustParams | PaperParams:
        """The registration method's parameters: its defaults but for the tolerance and, robust, the seeding."""
        if self.method != "robust":
            return PaperParams() if inlier_threshold_m is None else PaperParams(inlier_threshold_m=inlier_threshold_m)
        params = RobustParams(min_inliers=max(2, self.candidates_from))  # from one landmark: `_one_landmark`
        if self.candidates_from < self.min_landmarks:  # below min_landmarks the walls choose: offer them every pose
            params = replace(params, complete_below=self.min_landmarks)
        if early_stop_fraction is not None:
            params = replace(params, early_stop_fraction=early_stop_fraction)
        if inlier_threshold_m is not None:
            params = replace(params, inlier_threshold_m=inlier_threshold_m, ambiguity_tau_m=inlier_threshold_m)
        return params

    def __call__(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        if len(landmarks) == 1:
            return self._one_landmark(landmarks[0], corners_map[0])
        obs = [Observation(type=lm.type, centroid_map=lm.T_map_rect[:3, 3], corners_map=c)
               for lm, c in zip(landmarks, corners_map, strict=True)]
        gravity_map = np.array([0.0, 0.0, -1.0])  # the map frame's z is up
        result = register(self.model, ObservationSet(obs, gravity_map, self.storey_hint), method=self.method,
                          params=self.params)
        matches = [(landmarks[i].key, fid) for i, fid in result.matches]
        status = result.status
        if status == "localized" and result.inliers < self.min_landmarks:  # a candidate, not an answer
            status, matches = "ambiguous", []
        return Alignment(status, result.T_cad_map, matches, int(result.inliers), result.candidates)

    def _one_landmark(self, landmark: ObservedRect, corners_map: np.ndarray | None) -> Alignment:
        """One door or window: a candidate pose for every alike feature of the model (`_one_rectangle`)."""
        robust = self.params if isinstance(self.params, RobustParams) else RobustParams()
        return _one_rectangle(self.model, landmark, corners_map, self.storey_hint, robust.size_tolerance_m)


class SavedMapRegistrar:
    """Re-localization against the CAD-linked landmarks of a saved map (T_cad_rect of each). With
    `candidates_from` below `min_landmarks` (the localizer checks poses against the walls), fewer landmarks, or
    more that the saved map explains more than one way (a nearly symmetric building), come back as candidate
    poses: one per saved feature a landmark may be, from either side (one landmark: only features of its size,
    with `model`). The saved map holds a few of the building's doors, so the walls choose among a few poses, not
    among every alike door of the building."""

    def __init__(self, known: list[KnownRect], min_landmarks: int = 3, candidates_from: int | None = None,
                 model: BuildingModel | None = None) -> None:
        self.known = known
        self.min_landmarks = min_landmarks
        self.candidates_from = min(min_landmarks, candidates_from or min_landmarks)
        self._offer = candidates_from is not None
        self._model = model

    def __call__(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        if len(landmarks) == 1 and self._offer and self._model is not None:
            return self._one_landmark(landmarks[0], corners_map[0])
        return align_rectangles(landmarks, self.known, min_inliers=self.min_landmarks,
                                candidates_from=self.candidates_from if self._offer else None)

    def _one_landmark(self, landmark: ObservedRect, corners_map: np.ndarray | None) -> Alignment:
        """As `ModelRegistrar._one_landmark`, among the saved features only."""
        assert self._model is not None
        return _one_rectangle(self._model, landmark, corners_map, among={k.id for k in self.known})


class FirstOfRegistrar:
    """Tries each registrar in turn (when the map holds enough landmarks for it); the first 'localized' answer
    wins. A saved map first, the whole model after: re-localization falls back to a fresh localization when
    the new flight starts outside the saved map, or when the saved map's few landmarks leave it ambiguous.
    A 'localized' answer, or an 'ambiguous' one with candidate poses, is returned with the later registrars'
    answer as its `fallback`: the localizer asks for that only where the walls refuse the answer or confirm none
    of the candidates, so a saved map's few candidates are checked first and the whole model is searched only
    when they fail. Without candidates, the first 'ambiguous' answer is returned."""

    def __init__(self, registrars: list[Registrar]) -> None:
        self.registrars = registrars
        self.min_landmarks = min(r.min_landmarks for r in registrars)
        self.candidates_from = min(r.candidates_from for r in registrars)

    def __call__(self, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        return self._from(0, landmarks, corners_map)

    def _from(self, first: int, landmarks: list[ObservedRect], corners_map: Sequence[np.ndarray | None]) -> Alignment:
        ambiguous: list[Alignment] = []
        for k in range(first, len(self.registrars)):
            registrar = self.registrars[k]
            if len(landmarks) < registrar.candidates_from:
                continue
            result = registrar(landmarks, corners_map)
            if result.status == "localized" or result.candidates:
                later = self.registrars[k + 1:]
                if later:  # asked for where the walls refuse this answer or confirm none of these candidates
                    result.fallback = lambda k=k: self._from(k + 1, landmarks, corners_map)
                    # every candidate explains every landmark, and too few landmarks for a later registrar's own
                    # answer: a later one's candidates (all poses explaining as many) hold these
                    result.fallback_holds_these = result.status != "localized" and \
                        all(n == len(landmarks) for _, n in result.candidates) and \
                        all(len(landmarks) < r.min_landmarks for r in later)
                return result
            if result.status == "ambiguous":
                ambiguous.append(result)
        return (ambiguous or [Alignment("not_localized", None)])[0]


def _one_rectangle(model: BuildingModel, landmark: ObservedRect, corners_map: np.ndarray | None,
                   storey_hint: str | None = None, size_tolerance_m: float | None = None,
                   among: set[str] | None = None) -> Alignment:
    """One door or window: a candidate pose for every feature of the model alike to it (of `storey_hint`; among
    the ids `among`), from either side (`graph.robust.single_rectangle_poses`), for the walls to choose among;
    never an answer by itself."""
    if corners_map is None:
        return Alignment("not_localized", None)
    index = index_for(model).for_storey(storey_hint)
    params = RobustParams() if size_tolerance_m is None else RobustParams(size_tolerance_m=size_tolerance_m)
    poses = single_rectangle_poses(index, landmark.type, corners_map, params, among=among, cut=landmark.cut)
    if not poses:
        return Alignment("not_localized", None)
    return Alignment("ambiguous", None, [], 1, [(T, 1) for T in poses])
