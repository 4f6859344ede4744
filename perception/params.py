"""The perception chain's parameters: one small frozen dataclass per component, composed in `PerceptionParams`
(the frame's stereo, the sides' line segments, the plausibility limits, the wall plane, the visual odometry,
gravity, ...). Each parameter is declared here once, as a field with its default, bounds and description
(`common.parameters.param`), and each part is the service's config table of its name as it is
(`[perception.odometry]` is `VisualOdometryParams`; service/config.py). They live in this leaf module (no OpenCV)
so that the config takes them without importing the components; the components re-export theirs. Pixels,
metres, degrees, seconds where named so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from macroloc.common.parameters import Parameters, param

JOIN_ANGLE_DEG = 2.0  # paper: slopes within 2 degrees
JOIN_GAP_PX = 10.0  # paper: close endpoints within 10 pixels


@dataclass(frozen=True)
class SgbmParams(Parameters):
    """SGBM parameters: disparities searched (multiple of 16), block size (odd, px), 3-way mode."""

    num_disparities: int = param(
        64, "disparities searched: depth down to fx * baseline / this (a wider baseline or a nearer wall wants more)",
        ge=16, multiple_of=16)
    block_size: int = param(5, "matched block, px (odd)", ge=1)
    uniqueness_ratio: int = param(5, "OpenCV's uniquenessRatio, %", ge=0)
    speckle_window: int = param(100, "OpenCV's speckleWindowSize, px", ge=0)
    speckle_range: int = param(2, "OpenCV's speckleRange", ge=0)
    three_way: bool = param(True, "OpenCV's 3-way mode (faster than the full mode)")
    # < 1: matched on the pair shrunk by this factor (disparities and block too), then the disparity brought back to
    # full size (nearest pixel, values / scale): 0.5 costs ~1/4
    scale: float = param(
        1.0, "below 1: matched on the pair shrunk by this factor, the disparity brought back to full size", gt=0, le=1)


@dataclass(frozen=True)
class LineParams(Parameters):
    join_angle_deg: float = param(
        JOIN_ANGLE_DEG, "segments joined where their slopes lie within this, deg (the paper's 2)", ge=0)
    join_gap_px: float = param(JOIN_GAP_PX, "... and their close ends within this, px (the paper's 10)", ge=0)
    join_offset_px: float = param(  # our addition: the joined pieces must also be collinear (perpendicular offset)
        3.0, "... and they are collinear within this perpendicular offset, px", ge=0)
    max_tilt_deg: float = param(
        25.0, "a side candidate's angle from the image vertical at most this, deg (a drone rolls)", ge=0)
    margin: float = param(0.10, "the box grows by this fraction of its size on each side before LSD", ge=0)
    side_band: float = param(
        0.30, "a side candidate lies within this fraction of the box width inside its edge ...", ge=0)
    side_band_out: float = param(  # ... or this fraction outside it (strong edges beside a feature are not its side)
        0.08, "... or this fraction outside it", ge=0)
    min_length: float = param(0.35, "... and is at least this fraction of the box height long", ge=0)
    near_length: float = param(
        0.6, "among candidates at least this fraction of the longest, the nearest to the edge wins", ge=0)
    snap: float = param(
        0.04, "a side's end this close to the box's top or bottom (fraction of its height) goes onto it", ge=0)


@dataclass(frozen=True)
class PlausibilityParams(Parameters):
    """Limits a reconstructed door/window must meet (m, degrees)."""

    depth_range_m: tuple[float, float] = param((0.5, 12.0), "its depth, [near, far] m")
    door_width_m: tuple[float, float] = param((0.5, 2.6), "a door's width, [min, max] m")
    door_height_m: tuple[float, float] = param((1.5, 3.2), "a door's height, [min, max] m")
    window_width_m: tuple[float, float] = param((0.25, 4.0), "a window's width, [min, max] m")
    window_height_m: tuple[float, float] = param((0.25, 3.5), "a window's height, [min, max] m")
    max_tilt_deg: float = param(15.0, "its sides from gravity, when gravity is known, at most this, deg", ge=0)
    max_tilt_no_gravity_deg: float = param(30.0, "... from the camera's y axis when it is not, deg", ge=0)
    max_side_angle_deg: float = param(  # the two sides must be nearly parallel
        15.0, "its two sides nearly parallel: within this, deg", ge=0)


@dataclass(frozen=True)
class WallPlaneParams(Parameters):
    """The wall an opening sits in, from the depth beside its sides and above its top (`wall_plane`)."""

    near_px: float = param(6.0, "the strips start this far outside the sides, px ...", ge=0)
    far_px: float = param(24.0, "... and end this far, px", ge=0)
    n_samples: int = param(16, "points along each side (and the top) per column (row) of a strip", ge=1)
    threshold_m: tuple[float, float] = param(
        (0.03, 0.0125), "a point lies on the plane within a + b * depth^2, [a m, b 1/m]")
    min_points: int = param(  # of a strip (left, right, top) for it to count ...
        6, "points of a strip for it to count ...", ge=1)
    min_strips: int = param(  # ... and this many must lie on the plane (one strip leaves it free to turn about it)
        2, "... and this many strips must lie on the plane", ge=1)
    min_inlier_fraction: float = param(  # of the points of the strips that count (0.6 let more wrong walls through)
        0.8, "of the points of the strips that count, on the plane", ge=0, le=1)
    max_tilt_deg: float = param(15.0, "the plane's normal from horizontal (gravity known) at most this, deg", ge=0)
    min_incidence_deg: float = param(10.0, "a corner's viewing ray meets the plane at least this steeply, deg", ge=0)
    iterations: int = param(  # RANSAC hypotheses (seeded: the same frame gives the same plane)
        64, "RANSAC hypotheses (seeded)", ge=1)


@dataclass(frozen=True)
class VisualOdometryParams(Parameters):
    n_features: int = param(  # kept a frame, spread over the grid below (2000 before issue 37, unspread)
        1000, "ORB features kept a frame, spread over the grid", ge=1)
    detect_features: int = param(  # ORB's keypoints before the grid picks `n_features` (only those are described)
        2000, "ORB's keypoints before the grid picks n_features", ge=1)
    grid_cols: int = param(  # the image is cut into grid_cols x grid_rows cells; each keeps its strongest keypoints
        8, "the grid's columns ...", ge=1)
    grid_rows: int = param(6, "... and rows (each cell keeps its strongest keypoints)", ge=1)
    fast_threshold: int = param(  # rendered walls are low in contrast: a lower FAST threshold keeps features
        7, "ORB's FAST threshold (low-contrast walls want a lower one)", ge=1)
    min_disparity_px: float = param(1.0, "a keypoint's disparity at least this, px", ge=0)
    num_disparities: int = param(  # SGBM's search range at keyframes: depth down to fx * baseline / 128 (0.45 m)
        128, "SGBM's range at keyframes where the odometry matches on its own", ge=16, multiple_of=16)
    edge_disparity_px: float = param(
        1.0, "a keypoint whose 3 x 3 disparities spread more lies on a depth edge: dropped, px", ge=0)
    max_depth_m: float = param(15.0, "keypoints farther are dropped, m", gt=0)
    ratio: float = param(0.8, "Lowe's ratio test for frame-to-keyframe matches", gt=0, le=1)
    ransac_reprojection_px: float = param(2.0, "PnP-RANSAC's reprojection threshold, px", gt=0)
    min_inliers: int = param(15, "fewer PnP inliers: tracking lost for the frame", ge=1)
    rekey_inliers: int = param(80, "fewer: the frame becomes the reference keyframe", ge=1)
    rekey_translation_m: float = param(0.3, "... or after this much motion, m", gt=0)
    rekey_rotation_rad: float = param(0.35, "... or rotation, rad", gt=0)
    # the session's keyframes become the odometry's too, sharing their SGBM (where the depth points are measured at
    # keyframes: StereoOdometry.rekey); 12 % less replay CPU, but off: APE worse on held-out Office_A flights
    # (docs/measurements.md, "The odometry re-keyed on the session's keyframes")
    rekey_at_session_keyframes: bool = param(
        False, "the session's keyframes become the odometry's reference too, sharing their whole-frame SGBM (with "
        "[perception.depth] at_keyframes; less CPU, but off: held-out APE worse, docs/measurements.md)")
    max_step_m: float = param(0.15, "a frame-to-frame jump beyond this is a wrong PnP solution, m", gt=0)
    max_step_rad: float = param(0.25, "... or a turn beyond this, rad", gt=0)
    # a pose from fewer than rekey_inliers this far off the last step's velocity (27 m/s^2 at 30 Hz) is a wrong PnP
    # solution (a wall filling the view)
    max_step_change_m: float = param(
        0.03, "a pose from few inliers this far off the last step's velocity is wrong, m", gt=0)
    gyro_tolerance_rad: float = param(
        0.035, "a PnP rotation this far from the gyro's is replaced by the gyro's, rad", gt=0)
    pnp_rotation_gain: float = param(0.2, "with a gyro: the share of PnP's rotation taken per frame", ge=0, le=1)
    # "orb": ORB detected, described and matched to the keyframe every frame; "klt": the keyframe's points followed
    # by optical flow between keyframes (a third of the CPU; not the default: it drifted more than ORB in one of the
    # two buildings measured: docs/measurements.md, "Visual odometry by optical flow")
    tracker: Literal["orb", "klt"] = param(
        "orb", "orb: ORB matched to the keyframe every frame; klt: the keyframe's points followed by optical flow (a "
        "third of the CPU; it drifted more in one building: docs/measurements.md)")
    flow_points: int = param(  # the keyframe's points followed by the flow, spread over the grid (cost grows with them)
        300, "klt: the keyframe's points followed, spread over the grid", ge=1)
    flow_window_px: int = param(15, "klt: Lucas-Kanade's window, px", ge=3)
    flow_levels: int = param(  # its pyramid's levels above the image (the gyro's prediction leaves little to search)
        2, "klt: its pyramid's levels", ge=0)
    flow_from: Literal["last", "keyframe"] = param(
        "last", "klt: each point followed from the last frame or from the keyframe's image")
    # LK's minEigThreshold (OpenCV's): a point whose window's gradients are weaker is lost (higher: fewer points on
    # edges, which slide along them)
    flow_min_eigen: float = param(1e-4, "klt: Lucas-Kanade's minEigThreshold", gt=0)
    flow_round_trip_px: float = param(1.0, "klt: a point tracked forward then back further than this is lost, px", gt=0)
    flow_border_px: float = param(8.0, "klt: a point tracked this near the image's edge is lost, px", ge=0)


@dataclass(frozen=True)
class GravityParams(Parameters):
    window_s: float = param(
        1.0, "positions and specific forces of this long a span estimate the mean acceleration, s", gt=0)
    min_span_s: float = param(0.5, "a shorter history gives the specific force alone (as at take-off), s", gt=0)
    max_accel_mps2: float = param(
        4.0, "a larger fitted acceleration is no flight's: no estimate for the frame, m/s^2", gt=0)
    end_s: float = param(0.25, "the velocities at the window's ends: lines fitted to this long a part of it, s", gt=0)
    min_specific_force_mps2: float = param(  # an IMU sample outside these is no flight's: a free fall or a knock,
        5.0, "an IMU sample below this (a free fall) is left out, m/s^2 ...", ge=0)
    max_specific_force_mps2: float = param(  # left out (in the service and a replay alike)
        15.0, "... and above this (a knock), m/s^2", gt=0)


@dataclass(frozen=True)
class DepthPointsParams(Parameters):
    """The depth points for the surface check and fit (service.frames.StereoDepth), from the frame's SGBM or from
    a depth image the vehicle sends."""

    every: int = param(
        3, "depth points on every this many stereo frames (the localizer keeps the newest before each keyframe); 0: "
        "none", ge=0)
    # measured only on the frames that become keyframes (what the localizer uses: a keyframe takes the newest before
    # it), not on every `every`-th frame
    at_keyframes: bool = param(
        True, "measure them only on the frames that become keyframes (a keyframe takes the newest before it, the "
        "others are never used); false: on every `every`-th frame")
    stride_px: int = param(16, "every this many pixels of the disparity, px", ge=1)
    min_range_m: float = param(  # ... at this range ...
        0.3, "points nearer are dropped, m", ge=0)
    max_range_m: float = param(  # ... to this one
        8.0, "points farther are dropped, m", gt=0)
    depth_image_stride_px: int = param(
        20, "a depth image the vehicle sends with its stereo frame: every this many pixels, px", ge=1)


@dataclass(frozen=True)
class PlaceParams(Parameters):
    """Place recognition of keyframes in a saved map's views (perception.place)."""

    n_features: int = param(1000, "ORB features of the image to place", ge=1)
    stored_features: int = param(
        400, "at most this many kept per stored view (those with a depth, strongest first)", ge=1)
    fast_threshold: int = param(  # as the visual odometry's: rendered walls are low in contrast
        7, "ORB's FAST threshold", ge=1)
    num_disparities: int = param(128, "SGBM's search range for a stored view's depths", ge=16, multiple_of=16)
    max_depth_m: float = param(12.0, "a stored feature's depth at most, m", gt=0)
    vote_features: int = param(300, "the image's strongest features that vote for stored views", ge=1)
    vote_per_view: int = param(  # ... against each view's strongest (a view's features are stored strongest first)
        150, "... against each view's strongest this many", ge=1)
    vote_distance: int = param(
        40, "Hamming distance (of 256 bits) under which a nearest descriptor votes for its view", ge=0, le=256)
    top_views: int = param(4, "the best-voted views matched", ge=1)
    ratio: float = param(0.8, "Lowe's ratio test of the matches", gt=0, le=1)
    ransac_reprojection_px: float = param(3.0, "PnP-RANSAC's reprojection threshold, px", gt=0)
    min_inliers: int = param(40, "a place needs this many PnP inliers", ge=1)
    max_tilt_deg: float = param(5.0, "... and a pose this close to level, deg", ge=0)
    rival_ratio: float = param(
        0.5, "a second place explaining the leftover matches with this share of the inliers ...", ge=0, le=1)
    rival_apart_m: float = param(1.0, "... this far from the first: the place is ambiguous, m", ge=0)


@dataclass(frozen=True)
class InertialParams(Parameters):
    """The IMU's dead reckoning while the visual odometry has lost track (perception.inertial)."""

    calibrate_s: float = param(
        3.0, "gravity and the velocity are calibrated over this much tracked flight before the loss, s ...", gt=0)
    min_calibrate_s: float = param(
        1.0, "... at least this much, else the odometry coasts at constant velocity, s", gt=0)
    end_s: float = param(0.25, "velocities: lines fitted to this long a span of positions, s", gt=0)
    max_accel_mps2: float = param(
        4.0, "a larger mean acceleration over the span is no flight's: no calibration, m/s^2", gt=0)


@dataclass(frozen=True)
class ProposalParams(Parameters):
    """Limits of the door proposals; every one is derived from elsewhere (see the notes)."""

    scale: float = param(  # LSD on the image at this scale: a door side a proposal needs is >= 2 x min_side_px long
        0.5, "LSD runs on the image shrunk by this factor", gt=0, le=1)
    max_tilt_deg: float = param(  # from vertical: the drone rolls up to ~20 deg (perception.lines)
        LineParams.max_tilt_deg, "a door's side at most this far from vertical, deg", ge=0)
    join_offset_px: float = param(  # collinear pieces of one side (perception.lines) ...
        LineParams.join_offset_px, "collinear pieces of one side lie within this of each other's line, px ...", ge=0)
    join_gap_px: float = param(  # ... whose ends lie within the paper's joining distance
        JOIN_GAP_PX, "... and their ends within this, px", ge=0)
    min_side_px: float = param(  # px: a 1.52 m door at 18 m, f = 480: past the 12 m range (1.52 m: a short door,
        40.0, "a side shorter than this is no door's, px", gt=0)
    # docs/measurements.md, "Door proposals' shortest side")
    strip_px: tuple[float, float] = param(  # the wall's depth from this far outside a side (WallPlaneParams)
        (6.0, 24.0), "the wall's depth is read between these distances outside a side, px")
    depth_tol_m: tuple[float, float] = param(  # stereo's noise, a + b z^2 (WallPlaneParams.threshold_m)
        (0.03, 0.0125), "stereo's depth noise a + b * depth^2, [a m, b 1/m]: what lies between the sides nearer than "
        "the wall by more stands in front")
    border_fraction: float = param(
        40 / 480, "a side's end this near the border (share of the image height) runs on past it", ge=0, lt=0.5)
    max_proposals: int = param(  # per frame, best fit first: each costs an LSD refine and a 3D fit (~3 ms)
        4, "proposals kept per frame, best fit first", ge=0)
    check_wall: bool = param(  # the sides must stand in one wall (the chain's WallPlaneParams; False: not checked)
        True, "the two sides must stand in one wall ([perception.wall_plane])")


@dataclass(frozen=True)
class SizeTolerance(Parameters):
    """How far a reconstructed width or height may lie from the true one: `floor_m + per_m * depth_m`, from the
    chain's error measured on rendered frames with known truth (`bench.bench_size_check --measure`, the detector's
    boxes matched to the truth): it holds nearly all widths and heights not cut by the border (docs/measurements.md,
    "The detector's kind and the size tolerance").
    Stereo's depth error grows as depth squared, but a width or height is a difference of two corners at the
    same depth, so its error grows with depth (the pixel error of a side times depth / f) plus a constant part
    (the box and the LSD side missing the frame by a few centimetres)."""

    floor_m: float = param(0.10, "at any depth, m ...", ge=0)
    per_m: float = param(0.03, "... plus this per metre of depth", ge=0)

    def at(self, depth_m: float) -> float:
        return self.floor_m + self.per_m * max(depth_m, 0.0)


@dataclass(frozen=True)
class PerceptionParams(Parameters):
    """The chain's parameters, one part per component: `stereo` is the frame's SGBM (shared by the depth points,
    the openings and the odometry's keyframes: 128 disparities, depth down to fx * baseline / 128)."""

    stereo: SgbmParams = field(default_factory=lambda: SgbmParams(num_disparities=128))
    lines: LineParams = field(default_factory=LineParams)
    plausibility: PlausibilityParams = field(default_factory=PlausibilityParams)
    wall_plane: WallPlaneParams = field(default_factory=WallPlaneParams)
    odometry: VisualOdometryParams = field(default_factory=VisualOdometryParams)
    gravity: GravityParams = field(default_factory=GravityParams)
    depth: DepthPointsParams = field(default_factory=DepthPointsParams)
    place: PlaceParams = field(default_factory=PlaceParams)
    inertial: InertialParams = field(default_factory=InertialParams)
    proposals: ProposalParams = field(default_factory=ProposalParams)
    size_check: SizeTolerance = field(default_factory=SizeTolerance)
