"""Visual place recognition in a saved map: a new flight placed where an earlier one flew, before it sees a door.

A stored keyframe keeps a `KeyframeView` (graph.mapstore): up to `stored_features` ORB features of its left image
with a reliable stereo depth (SGBM's sub-pixel disparity at the keypoint, perception.stereo.keypoint_points), as 3D
points in its body frame. To place a new keyframe, its ORB features are matched to every stored view at once (the
`vote_features` strongest against each view's `vote_per_view` strongest, in faiss' exact binary index: the two
nearest descriptors within `vote_distance` vote for their views); the `top_views` views with the most such matches
are matched again one by one with Lowe's ratio test (per view: across views, the same corner seen twice would fail
it), and PnP-RANSAC on their 3D points, in the saved map's frame, gives the camera's pose there. A pose is kept
only with `min_inliers` inliers and at most `max_tilt_deg` between its up and the IMU's: both frames are levelled by
gravity, so a pose tilted from it is a wrong one. And where the matches left over put the camera in a second place,
with half as many inliers or more (twin rooms that look alike), there is no answer: never a guess.

The answer is T_map_body in the saved map's frame; times the saved map's T_cad_map it is the body's pose in
the CAD frame (the localizer checks it against the walls before anchoring with it).

Frames: `map` = the stored flight's map frame (z up); `body` and `cam` as in graph.localizer / perception.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from macroloc.common.views import KeyframeView
from macroloc.perception.binary_match import BinaryIndex
from macroloc.perception.calib import StereoRig
from macroloc.perception.params import PlaceParams
from macroloc.perception.stereo import SgbmMatcher, SgbmParams, keypoint_points, to_gray


@dataclass(frozen=True)
class PlaceMatch:
    T_map_body: np.ndarray  # 4x4, the saved map's frame
    inliers: int
    view: int  # index (into the views given) of the view with the most inliers


class PlaceRecognizer:
    """Describes keyframes for a saved map and places new ones in it (see module doc)."""

    def __init__(self, rig: StereoRig, T_body_cam: np.ndarray, config: PlaceParams | None = None) -> None:
        self.rig = rig
        self.T_body_cam = np.asarray(T_body_cam, float)
        self.config = c = config or PlaceParams()
        self._orb = cv2.ORB_create(nfeatures=c.n_features, fastThreshold=c.fast_threshold)  # type: ignore[attr-defined]
        self._sgbm: SgbmMatcher | None = None
        self._views: list[tuple[np.ndarray, KeyframeView]] = []
        self._database = BinaryIndex(np.zeros((0, 32), np.uint8))  # every stored view's voting descriptors
        self._owner = np.zeros(0, np.int64)  # the view of each of its rows

    # --- storing ----------------------------------------------------------------------------------------------

    def describe(self, left: np.ndarray, right: np.ndarray) -> KeyframeView:
        """A keyframe's view: its strongest ORB features with a reliable stereo depth, body frame."""
        c = self.config
        kp, desc = self._orb.detectAndCompute(to_gray(left), None)
        if desc is None or not kp:
            return KeyframeView(np.zeros((0, 3)), np.zeros((0, 32), np.uint8))
        if self._sgbm is None:
            self._sgbm = SgbmMatcher(SgbmParams(num_disparities=c.num_disparities))
        points_cam = keypoint_points(self._sgbm.disparity_px(left, right), np.array([k.pt for k in kp]), self.rig,
                                     max_depth_m=c.max_depth_m)
        ok = np.flatnonzero(points_cam[:, 2] > 0)
        ok = ok[np.argsort([-kp[i].response for i in ok], kind="stable")][:c.stored_features]
        points_body = points_cam[ok] @ self.T_body_cam[:3, :3].T + self.T_body_cam[:3, 3]
        return KeyframeView(points_body, desc[ok])

    # --- placing ----------------------------------------------------------------------------------------------

    def use(self, views: list[tuple[np.ndarray, KeyframeView]]) -> None:
        """The stored views to place new keyframes among: (T_map_body, view) each (SavedMap.placed_views)."""
        self._views = [(np.asarray(T, float), v) for T, v in views if len(v.descriptors)]
        n = self.config.vote_per_view
        self._database = BinaryIndex(np.vstack([v.descriptors[:n] for _, v in self._views]) if self._views
                                      else np.zeros((0, 32), np.uint8))
        self._owner = np.repeat(np.arange(len(self._views)), [len(v.descriptors[:n]) for _, v in self._views])

    @property
    def has_views(self) -> bool:
        return bool(self._views)

    def place(self, left: np.ndarray, up_body: np.ndarray | None = None) -> PlaceMatch | None:
        """The body's pose in the saved map from its left image, or None (too few consistent matches, a pose tilted
        from gravity, or two places alike)."""
        c = self.config
        if not self._views:
            return None
        kp, desc = self._orb.detectAndCompute(to_gray(left), None)
        if desc is None or len(kp) < c.min_inliers:
            return None
        uv = np.array([k.pt for k in kp], np.float64)
        strongest = np.argsort([-k.response for k in kp], kind="stable")[:c.vote_features]
        distance, row = self._database.nearest(desc[strongest], k=2)  # a twin place a bit or two further gets its vote
        votes = np.bincount(self._owner[row[distance < c.vote_distance]], minlength=len(self._views))
        top = [int(v) for v in np.argsort(-votes, kind="stable")[:c.top_views] if votes[v] >= c.min_inliers // 2]
        obj, img, of_view = [], [], []
        for v in top:
            T_map_body, view = self._views[v]
            query, train = BinaryIndex(view.descriptors).ratio_matches(desc, c.ratio)
            obj += list(view.points_body[train] @ T_map_body[:3, :3].T + T_map_body[:3, 3])
            img += list(uv[query])
            of_view += [v] * len(query)
        if len(obj) < c.min_inliers:
            return None
        obj_a, img_a = np.array(obj, np.float64), np.array(img, np.float64)
        found = self._pnp(obj_a, img_a, c.min_inliers)
        if found is None:
            return None
        rvec, tvec, idx = found
        T_map_body = self._body_pose(*cv2.solvePnPRefineLM(obj_a[idx], img_a[idx], self.rig.K, None, rvec, tvec))
        if up_body is not None and _tilt_deg(T_map_body, up_body) > c.max_tilt_deg:
            return None
        if self._rival(obj_a, img_a, idx, T_map_body):
            return None
        return PlaceMatch(T_map_body, len(idx), int(np.bincount(np.array(of_view)[idx]).argmax()))

    def _pnp(self, obj: np.ndarray, img: np.ndarray,
             need: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """PnP-RANSAC of image points (N, 2) on map points (N, 3): (rvec, tvec, inlier indices), or None with fewer
        than `need` inliers."""
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, self.rig.K, None, iterationsCount=300,
                                                 reprojectionError=self.config.ransac_reprojection_px,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < need:
            return None
        return rvec, tvec, inl[:, 0]

    def _body_pose(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        T_cam_map = np.eye(4)
        T_cam_map[:3, :3], T_cam_map[:3, 3] = cv2.Rodrigues(rvec)[0], np.ravel(tvec)
        return np.linalg.inv(T_cam_map) @ np.linalg.inv(self.T_body_cam)

    def _rival(self, obj: np.ndarray, img: np.ndarray, inliers: np.ndarray, T_map_body: np.ndarray) -> bool:
        """Does a second place explain the matches left over, with `rival_ratio` as many inliers and at least
        `min_inliers`, `rival_apart_m` away? Two places that look alike (a symmetric building's twin rooms): no
        guess."""
        c = self.config
        rest = np.setdiff1d(np.arange(len(obj)), inliers)
        need = max(c.min_inliers, int(np.ceil(c.rival_ratio * len(inliers))))
        if len(rest) < need:
            return False
        found = self._pnp(obj[rest], img[rest], need)
        if found is None:
            return False
        other = self._body_pose(*found[:2])
        return bool(np.linalg.norm(other[:3, 3] - T_map_body[:3, 3]) > c.rival_apart_m)


def _tilt_deg(T_map_body: np.ndarray, up_body: np.ndarray) -> float:
    """Angle between the map's up seen from the body (the pose's) and the IMU's up, degrees."""
    up = np.asarray(up_body, float) / np.linalg.norm(up_body)
    return float(np.degrees(np.arccos(np.clip(T_map_body[2, :3] @ up, -1.0, 1.0))))  # row 2: the map's z, in body
