"""Stereo visual odometry: ORB matches (or optical flow between keyframes), SGBM depth at keyframes, PnP-RANSAC
against the last keyframe.

Each frame with `VisualOdometryParams.tracker` "klt": up to `flow_points` of the reference keyframe's 3D-pointed
keypoints, spread over the grid, are followed from the last frame into this one by pyramidal Lucas-Kanade, each
starting where the last pose moved on at the last velocity and turned by the gyro's rotation puts it; a point that
does not come back to within `flow_round_trip_px` when followed back, or nears the image's edge, is dropped
(`flow_from` "keyframe": followed from the keyframe's image instead, their positions there kept).
`cv2.solvePnPRansac` (then Levenberg-Marquardt on the inliers) on the followed points against their keyframe 3D
points gives the camera's motion since that keyframe, and only PnP's inliers are followed on. ORB is detected and
described only for a new keyframe, and on a frame where the flow fails (too few points, PnP failing, or a pose no
drone could reach): that frame is matched as with "orb", and the flow goes on from the matches PnP kept. With
"orb" (the default), every frame: ORB on the left image, matched to the reference keyframe's descriptors
(Lowe's ratio test, in faiss' exact binary index: perception.binary_match). The figures, ORB against flow:
docs/measurements.md, "Visual odometry by optical flow (issue 37, item 1)".

A frame becomes the reference when tracking thins out or the camera has moved far from it, or where the caller
makes it one (`rekey`: a session keyframe, whose depth points match the pair anyway); only then is the stereo
pair matched: OpenCV SGBM's sub-pixel disparity at each keypoint gives its 3D point by eq. 2
(z = fx * baseline / disparity), kept where the disparity is consistent over the 3 x 3 pixels around it (not
on a depth edge); 128 disparities reach down to 0.45 m, for a wall close by. With a gyroscope, a PnP rotation
more than 2 deg from the gyro's since the keyframe is replaced by the gyro's and the translation refitted: a wall
filling the view lets PnP take a turn for a slide. Sub-pixel SGBM depth and the gyro's check drift several times
less than ORB matched along rows (integer disparities, wrong matches on horizontal edges), which can miss a turn
facing a wall entirely. SGBM runs only at keyframes. Chosen over dense RGB-D odometry (Open3D) for cost, and it
does not import open3d (which needs libusb here).

With a gyroscope, each frame's rotation is the gyro's since the last frame, pulled a fifth of the way towards
PnP's (a complementary filter, `pnp_rotation_gain`), and the translation refitted to PnP's inliers for it. PnP's
own rotation is noisy by tenths of a degree a frame, and a rotation error is taken for a sideways slide: the pose
jitters by centimetres a frame, and each new reference keyframe keeps its error. The filter trades that jitter for
the gyro's bias, which leaks in as drift: the graph's landmarks and walls correct drift, not jitter. A lower gain
jitters less but drifts more (docs/measurements.md, "Visual odometry: the gyro prior and keyframes").

Frames: `odom` = the first frame's left camera (optical: x right, y down, z forward); `T_odom_cam` 4x4, metres.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.common.geometry import rotation_angle_rad
from macroloc.perception.binary_match import BinaryIndex
from macroloc.perception.calib import StereoRig
from macroloc.perception.params import VisualOdometryParams
from macroloc.perception.stereo import FrameDisparity, SgbmMatcher, SgbmParams, keypoint_points, to_gray

log = logging.getLogger(__name__)


@dataclass
class OdometryResult:
    T_odom_cam: np.ndarray  # 4x4
    inliers: int
    tracked: bool  # False: PnP failed; the pose is dead-reckoned (`track`'s lost_position) or at the last velocity


@dataclass
class _Keyframe:
    T_odom_cam: np.ndarray
    descriptors: np.ndarray  # (N, 32) uint8
    points_cam: np.ndarray  # (N, 3) metres, in this keyframe's camera frame
    uv: np.ndarray  # (N, 2) pixels: where the points are in this keyframe's left image
    response: np.ndarray  # (N,) their ORB keypoints' corner response
    index: BinaryIndex  # of the descriptors, for the frames' matches


@dataclass
class _Tracks:
    """The keyframe's points followed by optical flow: `index` into its points, `uv` in the last frame."""

    index: np.ndarray  # (M,) int
    uv: np.ndarray  # (M, 2) float32
    gray: np.ndarray  # the last frame's left image, grey


class StereoOdometry:
    """Frame-to-keyframe stereo odometry (see module doc). Feed frames in time order."""

    def __init__(self, rig: StereoRig, config: VisualOdometryParams | None = None,
                 disparity: SgbmMatcher | FrameDisparity | None = None) -> None:
        """`disparity`: the frame's shared SGBM (FrameDisparity) where other consumers match the same frames;
        None: its own, with `config.num_disparities`."""
        self.rig = rig
        self.config = config or VisualOdometryParams()
        self.orb = cv2.ORB_create(  # type: ignore[attr-defined]
            nfeatures=self.config.detect_features, fastThreshold=self.config.fast_threshold)
        self.sgbm = disparity or SgbmMatcher(SgbmParams(num_disparities=self.config.num_disparities))
        if self.config.tracker not in ("klt", "orb") or self.config.flow_from not in ("last", "keyframe"):
            raise ValueError(f"VisualOdometryParams.tracker {self.config.tracker!r}: 'klt' or 'orb'; flow_from "
                             f"{self.config.flow_from!r}: 'last' or 'keyframe'")
        self.K = rig.K
        self._ref: _Keyframe | None = None
        self._tracks: _Tracks | None = None  # tracker "klt" only
        self._ref_gray = np.zeros((0, 0), np.uint8)  # the keyframe's left image, grey (tracker "klt")
        self._T_last = np.eye(4)
        self._T_prev = np.eye(4)
        self._inliers: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 3)), np.zeros((0, 2)))  # of the last PnP
        self._inlier_rows: np.ndarray = np.zeros(0, np.int64)  # their rows in its input
        self._inlier_index: np.ndarray = np.zeros(0, np.int64)  # their keyframe points (ORB's matches)
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list | None, np.ndarray] | None = None  # type: ignore[type-arg]
        self._ref_left: np.ndarray | None = None  # the reference keyframe's left image (the same array)

    def track(self, left: np.ndarray, right: np.ndarray, R_prev_cur: np.ndarray | None = None,
              lost_position: Callable[[np.ndarray], np.ndarray | None] | None = None) -> OdometryResult:
        """The left camera's pose in the odometry frame after this stereo pair (uint8 grey or BGR).

        R_prev_cur: the camera's rotation since the previous frame from a gyroscope (3x3, previous camera frame
        <- this one), when there is one. A plane filling the view (a wall close by) leaves PnP unable to tell a
        turn from a slide: where its rotation departs from the gyro's, the gyro's is kept and the translation
        refitted to the same matches. lost_position: where tracking is lost, called with the pose coasted at the
        last velocity (T_odom_cam, the gyro's rotation) for the camera's position to take instead (e.g. with the
        height dead-reckoned on the IMU, perception.inertial); None from it, or no callable: the coasted pose."""
        gray = to_gray(left)
        klt = self.config.tracker == "klt"
        if self._ref is None:
            first = self._new_keyframe(np.eye(4), left, right, *self._features(gray), gray)
            self._last = None
            return OdometryResult(np.eye(4), len(first.points_cam), True)
        ref = self._ref
        R_ref_cam_gyro = None if R_prev_cur is None else ref.T_odom_cam[:3, :3].T @ self._T_last[:3, :3] @ R_prev_cur
        kp: list | None = None  # type: ignore[type-arg]
        desc = np.zeros((0, 32), np.uint8)
        T_ref_cam: np.ndarray | None = None
        inliers = 0
        if klt and self._tracks is not None:
            T_ref_cam, inliers, tracked = self._flow(gray, R_prev_cur)
            T_ref_cam = self._checked(T_ref_cam, inliers, R_ref_cam_gyro)
            if T_ref_cam is not None:
                self._tracks = tracked
        if T_ref_cam is None:  # ORB against the keyframe: every frame ("orb"), or where the flow lost its points
            kp, desc = self._features(gray)
            T_ref_cam, inliers = self._pnp(kp, desc)
            T_ref_cam = self._checked(T_ref_cam, inliers, R_ref_cam_gyro)
            if T_ref_cam is not None and klt:  # the flow goes on from the matches PnP kept
                self._tracks = (_Tracks(self._inlier_index, self._inliers[1].astype(np.float32), gray)
                                if self.config.flow_from == "last" else
                                _Tracks(self._inlier_index, ref.uv[self._inlier_index].astype(np.float32),
                                        self._ref_gray))
        if T_ref_cam is None:
            T = self._T_last @ (np.linalg.inv(self._T_prev) @ self._T_last)  # constant velocity
            if R_prev_cur is not None:
                T[:3, :3] = self._T_last[:3, :3] @ R_prev_cur
            position = None if lost_position is None else lost_position(T)
            if position is not None:
                T[:3, 3] = position
            self._advance(T)
            assert kp is not None
            self._new_keyframe(T, left, right, kp, desc, gray)
            self._last = None
            return OdometryResult(T, inliers, False)
        T = ref.T_odom_cam @ T_ref_cam
        self._advance(T)
        if self._should_rekey(T_ref_cam, inliers):
            if kp is None:
                kp, desc = self._features(gray)
            self._new_keyframe(T, left, right, kp, desc, gray)
        self._last = (T, left, right, gray, kp, desc)
        return OdometryResult(T, inliers, True)

    def rekey(self) -> None:
        """Make the last frame tracked the reference keyframe, where it is not already and its tracking held.
        Called where the session makes it a keyframe, whose whole-frame SGBM the depth points measure anyway
        (a shared FrameDisparity): the odometry's own re-keying rule then rarely needs an SGBM of its own."""
        if self._last is None:
            return
        T, left, right, gray, kp, desc = self._last
        self._last = None
        if left is self._ref_left:
            return
        if kp is None:
            kp, desc = self._features(gray)
        self._new_keyframe(T, left, right, kp, desc, gray)

    def _features(self, gray: np.ndarray) -> tuple[list, np.ndarray]:  # type: ignore[type-arg]
        """ORB keypoints, spread (`_spread`), and their descriptors."""
        kp, desc = self.orb.compute(gray, self._spread(self.orb.detect(gray, None), gray.shape))
        return list(kp), desc if desc is not None else np.zeros((0, 32), np.uint8)

    def _checked(self, T_ref_cam: np.ndarray | None, inliers: int,
                 R_ref_cam_gyro: np.ndarray | None) -> np.ndarray | None:
        """PnP's T_ref_cam agreed with the gyro (where there is one); None where it is None or not plausible."""
        if T_ref_cam is None:
            return None
        if R_ref_cam_gyro is not None:
            T_ref_cam = self._agree_with_gyro(T_ref_cam, R_ref_cam_gyro)
        assert self._ref is not None
        return T_ref_cam if self._plausible(self._ref.T_odom_cam @ T_ref_cam, inliers) else None

    def _new_keyframe(self, T_odom_cam: np.ndarray, left: np.ndarray, right: np.ndarray, kp: list,  # type: ignore[type-arg]
                      desc: np.ndarray, gray: np.ndarray) -> _Keyframe:
        self._ref = self._keyframe(T_odom_cam, left, right, kp, desc)
        self._ref_left = left
        if self.config.tracker == "klt":
            keep = self._spread_index(self._ref.uv, self._ref.response, self.config.flow_points, gray.shape)
            self._tracks = _Tracks(keep, self._ref.uv[keep].astype(np.float32), gray)
            self._ref_gray = gray
        return self._ref

    def _flow(self, gray: np.ndarray, R_prev_cur: np.ndarray | None) -> tuple[np.ndarray | None, int, _Tracks]:
        """T_ref_cam from the keyframe's points followed from the last frame into this one by pyramidal
        Lucas-Kanade, the inlier count, and the points kept (PnP's inliers). Each point starts where the last
        frame's pose moved on at the last velocity, turned by the gyro's rotation, puts it; a point that does
        not come back to within `flow_round_trip_px` of where it was when followed back is dropped."""
        c, ref, tracks = self.config, self._ref, self._tracks
        assert ref is not None and tracks is not None
        lost: tuple[np.ndarray | None, int, _Tracks] = (None, 0, tracks)
        if len(tracks.index) < c.min_inliers:
            return lost
        T_pred = self._T_last @ (np.linalg.inv(self._T_prev) @ self._T_last)  # this frame at the last velocity
        if R_prev_cur is not None:
            T_pred[:3, :3] = self._T_last[:3, :3] @ R_prev_cur
        T_cam_ref = np.linalg.inv(T_pred) @ ref.T_odom_cam
        x = ref.points_cam[tracks.index] @ T_cam_ref[:3, :3].T + T_cam_ref[:3, 3]
        guess = tracks.uv.copy()
        ahead = x[:, 2] > 0.05
        guess[ahead] = np.column_stack([self.rig.fx_px * x[ahead, 0] / x[ahead, 2] + self.rig.cx_px,
                                        self.rig.fy_px * x[ahead, 1] / x[ahead, 2] + self.rig.cy_px])
        win = (c.flow_window_px, c.flow_window_px)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)
        prev = tracks.uv.reshape(-1, 1, 2)
        cur, ok, _ = cv2.calcOpticalFlowPyrLK(tracks.gray, gray, prev, guess.reshape(-1, 1, 2).copy(),
                                              winSize=win, maxLevel=c.flow_levels, criteria=criteria, flags=flags,
                                              minEigThreshold=c.flow_min_eigen)
        back, ok_back, _ = cv2.calcOpticalFlowPyrLK(gray, tracks.gray, cur, prev.copy(), winSize=win,
                                                    maxLevel=c.flow_levels, criteria=criteria, flags=flags,
                                                    minEigThreshold=c.flow_min_eigen)
        cur, back = cur.reshape(-1, 2), back.reshape(-1, 2)
        h, w = self.rig.height_px, self.rig.width_px
        b = c.flow_border_px
        keep = ((ok.ravel() == 1) & (ok_back.ravel() == 1)
                & (np.linalg.norm(back - tracks.uv, axis=1) <= c.flow_round_trip_px)
                & (cur[:, 0] >= b) & (cur[:, 0] <= w - 1 - b) & (cur[:, 1] >= b) & (cur[:, 1] <= h - 1 - b))
        index, uv = tracks.index[keep], cur[keep]
        if len(index) < c.min_inliers:
            return lost
        T_ref_cam, inl = self._solve(ref.points_cam[index].astype(np.float64), uv.astype(np.float64))
        if T_ref_cam is None:
            return None, inl, tracks
        rows = self._inlier_rows
        if c.flow_from == "last":
            return T_ref_cam, inl, _Tracks(index[rows], uv[rows], gray)
        return T_ref_cam, inl, _Tracks(index[rows], tracks.uv[keep][rows], tracks.gray)

    def _spread(self, keypoints: tuple, shape: tuple[int, ...]) -> list:  # type: ignore[type-arg]
        """At most `n_features` keypoints spread over the image: each grid cell keeps its strongest, as many as
        an equal share, and what cells with fewer leave goes to the strongest of the rest. Matching cost grows
        with the count squared (2000 a frame: 24 ms of OpenCV's brute-force matching here), and features bunched on one
        textured patch constrain the pose less than the same number spread."""
        if len(keypoints) <= self.config.n_features:
            return list(keypoints)
        uv = cv2.KeyPoint_convert(keypoints).astype(np.float64)  # type: ignore[attr-defined]
        keep = self._spread_index(uv, np.array([k.response for k in keypoints]), self.config.n_features, shape)
        return [keypoints[i] for i in keep]

    def _spread_index(self, uv: np.ndarray, response: np.ndarray, n: int, shape: tuple[int, ...]) -> np.ndarray:
        """The rows of at most `n` of the points `uv` spread over the grid (see `_spread`)."""
        c = self.config
        if len(uv) <= n:
            return np.arange(len(uv))
        h, w = shape[:2]
        cell = (np.minimum(uv[:, 1] * c.grid_rows // h, c.grid_rows - 1) * c.grid_cols
                + np.minimum(uv[:, 0] * c.grid_cols // w, c.grid_cols - 1)).astype(np.int64)
        order = np.lexsort((-response, cell))  # by cell, strongest first within each
        first = np.searchsorted(cell[order], cell[order], side="left")
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order)) - first  # 0 for a cell's strongest
        share = n // (c.grid_cols * c.grid_rows)
        return np.lexsort((-response, rank >= share, ))[:n]  # the cells' shares first, then the strongest

    def _agree_with_gyro(self, T_ref_cam: np.ndarray, R_ref_cam_gyro: np.ndarray) -> np.ndarray:
        """T_ref_cam with the gyro's rotation where they disagree by more than `gyro_tolerance_rad` (PnP took a
        turn for a slide), else with the gyro's moved `pnp_rotation_gain` of the way towards PnP's (1: PnP's
        pose as it is); the translation refitted to PnP's inliers for that rotation."""
        d = T_ref_cam[:3, :3].T @ R_ref_cam_gyro
        gain = self.config.pnp_rotation_gain
        if rotation_angle_rad(d) <= self.config.gyro_tolerance_rad:
            if gain >= 1.0:
                return T_ref_cam
            step = Rotation.from_matrix(R_ref_cam_gyro.T @ T_ref_cam[:3, :3]).as_rotvec()
            R_ref_cam_gyro = R_ref_cam_gyro @ Rotation.from_rotvec(gain * step).as_matrix()
        obj, img = self._inliers
        R_cam_ref = R_ref_cam_gyro.T
        # x_cam = R X + t, seen along the ray m: m x (R X + t) = 0, linear in t (3 rows per point, rank 2)
        m = np.column_stack([(img[:, 0] - self.rig.cx_px) / self.rig.fx_px,
                             (img[:, 1] - self.rig.cy_px) / self.rig.fy_px, np.ones(len(img))])
        mx = np.zeros((len(m), 3, 3))
        mx[:, 0, 1], mx[:, 0, 2], mx[:, 1, 2] = -m[:, 2], m[:, 1], -m[:, 0]
        mx -= mx.transpose(0, 2, 1)
        rx = obj @ R_cam_ref.T
        t_cam_ref = np.linalg.lstsq(mx.reshape(-1, 3), -np.einsum("nij,nj->ni", mx, rx).reshape(-1), rcond=None)[0]
        T_cam_ref = np.eye(4)
        T_cam_ref[:3, :3], T_cam_ref[:3, 3] = R_cam_ref, t_cam_ref
        return np.linalg.inv(T_cam_ref)

    def _keyframe(self, T_odom_cam: np.ndarray, left: np.ndarray, right: np.ndarray, kp: list,
                  desc: np.ndarray) -> _Keyframe:
        """A reference keyframe: the keypoints with a reliable stereo depth, their 3D points and descriptors."""
        points = self._keypoint_points(left, right, kp)
        valid = points[:, 2] > 0
        uv = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
        response = np.array([k.response for k in kp], np.float64)
        return _Keyframe(T_odom_cam, desc[valid], points[valid], uv[valid], response[valid], BinaryIndex(desc[valid]))

    def _plausible(self, T: np.ndarray, inliers: int) -> bool:
        """Is the motion since the last frame one a drone can make? Few inliers (a textureless view) also have
        to keep the velocity about as it was: their PnP solutions stray by centimetres a frame."""
        c = self.config
        step = np.linalg.inv(self._T_last) @ T
        if inliers < c.rekey_inliers and c.max_step_change_m > 0:
            predicted = 2.0 * self._T_last[:3, 3] - self._T_prev[:3, 3]  # at the last step's velocity
            if np.linalg.norm(T[:3, 3] - predicted) > c.max_step_change_m:
                return False
        return bool(np.linalg.norm(step[:3, 3]) <= c.max_step_m and rotation_angle_rad(step[:3, :3]) <= c.max_step_rad)

    def _advance(self, T: np.ndarray) -> None:
        self._T_prev, self._T_last = self._T_last, T

    def _keypoint_points(self, left: np.ndarray, right: np.ndarray, kp: list) -> np.ndarray:
        """(N, 3) points in the camera frame of the keypoints (z = 0: no reliable depth)."""
        c = self.config
        if not kp:
            return np.zeros((0, 3))
        return keypoint_points(self.sgbm.disparity_px(left, right), np.array([k.pt for k in kp]), self.rig,
                               c.min_disparity_px, c.edge_disparity_px, c.max_depth_m)

    def _pnp(self, kp: list, desc: np.ndarray) -> tuple[np.ndarray | None, int]:
        """T_ref_cam from matches of this frame's keypoints to the reference's 3D points, and the inlier count."""
        ref = self._ref
        assert ref is not None
        if len(desc) < 2 or len(ref.descriptors) < 2:
            return None, 0
        query, train = ref.index.ratio_matches(desc, self.config.ratio)
        if len(query) < self.config.min_inliers:
            return None, len(query)
        obj = ref.points_cam[train].astype(np.float64)
        img = cv2.KeyPoint_convert([kp[i] for i in query]).astype(np.float64)  # type: ignore[attr-defined]
        T_ref_cam, inliers = self._solve(obj, img)
        if T_ref_cam is not None:
            self._inlier_index = train[self._inlier_rows]
        return T_ref_cam, inliers

    def _solve(self, obj: np.ndarray, img: np.ndarray) -> tuple[np.ndarray | None, int]:
        """T_ref_cam from the keyframe's 3D points `obj` seen at pixels `img`: RANSAC (EPnP), then
        Levenberg-Marquardt on the inliers, which are kept (`_inliers`, and their rows `_inlier_rows`)."""
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, self.K, None, iterationsCount=200,
                                                 reprojectionError=self.config.ransac_reprojection_px,
                                                 flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < self.config.min_inliers:
            return None, 0 if inl is None else len(inl)
        idx = inl[:, 0]
        self._inliers = (obj[idx], img[idx])
        self._inlier_rows = idx
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], self.K, None, rvec, tvec)
        T_cam_ref = np.eye(4)
        T_cam_ref[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_cam_ref[:3, 3] = tvec.ravel()
        return np.linalg.inv(T_cam_ref), len(idx)

    def _should_rekey(self, T_ref_cam: np.ndarray, inliers: int) -> bool:
        c = self.config
        angle = rotation_angle_rad(T_ref_cam[:3, :3])
        return bool(inliers < c.rekey_inliers or np.linalg.norm(T_ref_cam[:3, 3]) > c.rekey_translation_m
                    or angle > c.rekey_rotation_rad)
