"""The perception chain's parameters: one small frozen dataclass per component, composed in `PerceptionParams`
(the frame's stereo, the sides' line segments, the plausibility limits, the wall plane, the visual odometry,
gravity). They live in this leaf module (no OpenCV) so that the service's config (service/config.py,
`[perception.*]`) can take its defaults from them; the components re-export theirs. Pixels, metres, degrees,
seconds where named so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

JOIN_ANGLE_DEG = 2.0  # paper: slopes within 2 degrees
JOIN_GAP_PX = 10.0  # paper: close endpoints within 10 pixels


@dataclass(frozen=True)
class SgbmConfig:
    """SGBM parameters: disparities searched (multiple of 16), block size (odd, px), 3-way mode."""

    num_disparities: int = 64
    block_size: int = 5
    uniqueness_ratio: int = 5
    speckle_window: int = 100
    speckle_range: int = 2
    three_way: bool = True
    scale: float = 1.0  # < 1: matched on the pair shrunk by this factor (disparities and block too), then the
    #                     disparity brought back to full size (nearest pixel, values / scale): 0.5 costs ~1/4


@dataclass(frozen=True)
class LineConfig:
    join_angle_deg: float = JOIN_ANGLE_DEG
    join_gap_px: float = JOIN_GAP_PX
    join_offset_px: float = 3.0  # our addition: the joined pieces must also be collinear (perpendicular offset)
    max_tilt_deg: float = 25.0  # |angle from the image vertical| for a side candidate (drone roll up to ~20 deg)
    margin: float = 0.10  # the box grows by this fraction of its size on each side before LSD
    side_band: float = 0.30  # a side candidate lies within this fraction of the box width inside that edge
    side_band_out: float = 0.08  # ... or this fraction outside it (strong edges beside a feature are not its side)
    min_length: float = 0.35  # ... and is at least this fraction of the box height long
    near_length: float = 0.6  # among candidates at least this fraction of the longest, the nearest wins
    snap: float = 0.04  # a side's end this close (fraction of box height) to the box's top/bottom goes onto it


@dataclass(frozen=True)
class PlausibilityConfig:
    """Limits a reconstructed door/window must meet (m, degrees)."""

    depth_range_m: tuple[float, float] = (0.5, 12.0)
    door_width_m: tuple[float, float] = (0.5, 2.6)
    door_height_m: tuple[float, float] = (1.5, 3.2)
    window_width_m: tuple[float, float] = (0.25, 4.0)
    window_height_m: tuple[float, float] = (0.25, 3.5)
    max_tilt_deg: float = 15.0  # side direction vs gravity, when gravity is known
    max_tilt_no_gravity_deg: float = 30.0  # vs the camera's y axis when it is not (drone roll up to ~20 deg)
    max_side_angle_deg: float = 15.0  # the two sides must be nearly parallel


@dataclass(frozen=True)
class WallPlaneConfig:
    """The wall an opening sits in, from the depth beside its sides and above its top (`wall_plane`)."""

    near_px: float = 6.0  # the strips start this far outside the sides (past the frame's edge) ...
    far_px: float = 24.0  # ... and end this far
    n_samples: int = 16  # points along each side (and the top) per column (row) of a strip
    threshold_m: tuple[float, float] = (0.03, 0.0125)  # a point lies on the plane within a + b * depth^2 (stereo)
    min_points: int = 6  # of a strip (left, right, top) for it to count ...
    min_strips: int = 2  # ... and this many must lie on the plane (one strip leaves it free to turn about it)
    min_inlier_fraction: float = 0.8  # of the points of the strips that count (0.6 let more wrong walls through)
    max_tilt_deg: float = 15.0  # the plane's normal from horizontal (with gravity known): a wall stands
    min_incidence_deg: float = 10.0  # a corner's viewing ray must meet the plane at least this steeply
    iterations: int = 64  # RANSAC hypotheses (seeded: the same frame gives the same plane)


@dataclass(frozen=True)
class OdometryConfig:
    n_features: int = 1000  # kept a frame, spread over the grid below (2000 before issue 37, unspread)
    detect_features: int = 2000  # ORB's keypoints before the grid picks `n_features` (only those are described)
    grid_cols: int = 8  # the image is cut into grid_cols x grid_rows cells; each keeps its strongest keypoints
    grid_rows: int = 6
    fast_threshold: int = 7  # rendered walls are low in contrast: a lower FAST threshold keeps features
    min_disparity_px: float = 1.0
    num_disparities: int = 128  # SGBM's search range at keyframes: depth down to fx * baseline / 128 (0.45 m)
    edge_disparity_px: float = 1.0  # a keypoint whose 3 x 3 disparities spread more lies on a depth edge
    max_depth_m: float = 15.0
    ratio: float = 0.8  # Lowe's ratio test for frame-to-keyframe matches
    ransac_reprojection_px: float = 2.0
    min_inliers: int = 15  # fewer: tracking lost for this frame
    rekey_inliers: int = 80  # fewer: the current frame becomes the reference keyframe
    rekey_translation_m: float = 0.3
    rekey_rotation_rad: float = 0.35
    rekey_at_session_keyframes: bool = False  # the session's keyframes become the odometry's too, sharing their
    #   SGBM (where the depth points are measured at keyframes: StereoOdometry.rekey); 12 % less replay CPU, but
    #   off: APE worse on held-out Office_A flights (docs/measurements.md, "The odometry re-keyed on the session's
    #   keyframes")
    max_step_m: float = 0.15  # a frame-to-frame jump beyond this (4.5 m/s at 30 Hz) is a wrong PnP solution
    max_step_rad: float = 0.25
    max_step_change_m: float = 0.03  # a pose from fewer than rekey_inliers this far off the last step's velocity
    #                                  (27 m/s^2 at 30 Hz) is a wrong PnP solution (a wall filling the view)
    gyro_tolerance_rad: float = 0.035  # a PnP rotation this far from the gyro's is replaced by the gyro's
    pnp_rotation_gain: float = 0.2  # with a gyro: the share of PnP's rotation taken per frame (see _agree_with_gyro)
    # "orb": ORB detected, described and matched to the keyframe every frame; "klt": the keyframe's points followed
    # by optical flow between keyframes (a third of the CPU; not the default: it drifted more than ORB in one of the
    # two buildings measured: docs/measurements.md, "Visual odometry by optical flow")
    tracker: Literal["orb", "klt"] = "orb"
    flow_points: int = 300  # the keyframe's points followed by the flow, spread over the grid (cost grows with them)
    flow_window_px: int = 15  # Lucas-Kanade's window
    flow_levels: int = 2  # its pyramid's levels above the image (the gyro's prediction leaves little to search)
    flow_from: Literal["last", "keyframe"] = "last"  # each point followed from the last frame, or the keyframe's image
    flow_min_eigen: float = 1e-4  # LK's minEigThreshold (OpenCV's): a point whose window's gradients are weaker is
    #                               lost (higher: fewer points on edges, which slide along them)
    flow_round_trip_px: float = 1.0  # a point tracked forward then back further than this from where it was: lost
    flow_border_px: float = 8.0  # a point tracked this near the image's edge or nearer: lost


@dataclass(frozen=True)
class GravityParams:
    window_s: float = 1.0  # positions and specific forces of this long a span estimate the mean acceleration
    min_span_s: float = 0.5  # a shorter history gives the specific force alone (as at take-off)
    max_accel_mps2: float = 4.0  # a larger fitted acceleration is not a flight's: no estimate for this frame
    end_s: float = 0.25  # the velocities at the window's ends: lines fitted to this long a part of it
    min_specific_force_mps2: float = 5.0  # an IMU sample outside these is no flight's: a free fall or a knock,
    max_specific_force_mps2: float = 15.0  # left out (in the service and a replay alike)


@dataclass(frozen=True)
class DepthPointsConfig:
    """The depth points for the surface check and fit (service.frames.StereoDepth), from the frame's SGBM or from
    a depth image the vehicle sends."""

    every: int = 3  # every this many stereo frames (the localizer keeps the newest before each keyframe); 0: none
    at_keyframes: bool = True  # measured only on the frames that become keyframes (what the localizer uses: a
    #                            keyframe takes the newest before it), not on every `every`-th frame
    stride_px: int = 16  # every this many pixels of the disparity image ...
    min_range_m: float = 0.3  # ... at this range ...
    max_range_m: float = 8.0  # ... to this one
    depth_image_stride_px: int = 20  # a depth image the vehicle sends: every this many pixels, to max_range_m


@dataclass(frozen=True)
class PlaceConfig:
    """Place recognition of keyframes in a stored map's views (perception.place)."""

    n_features: int = 1000  # ORB features of the image to place
    stored_features: int = 400  # ... and at most this many kept per stored view (those with a depth, strongest)
    fast_threshold: int = 7  # as the visual odometry's: rendered walls are low in contrast
    num_disparities: int = 128  # SGBM's search range for a stored view's depths (down to 0.45 m)
    max_depth_m: float = 12.0
    vote_features: int = 300  # the image's strongest features that vote for stored views ...
    vote_per_view: int = 150  # ... against each view's strongest (a view's features are stored strongest first)
    vote_distance: int = 40  # Hamming distance (of 256 bits) under which a nearest descriptor votes for its view
    top_views: int = 4
    ratio: float = 0.8
    ransac_reprojection_px: float = 3.0
    min_inliers: int = 40
    max_tilt_deg: float = 5.0
    rival_ratio: float = 0.5  # a second place explaining the leftover matches with this share of the inliers ...
    rival_apart_m: float = 1.0  # ... this far from the first: the place is ambiguous (no answer)


@dataclass(frozen=True)
class InertialParams:
    """The IMU's dead reckoning while the visual odometry has lost track (perception.inertial)."""

    calibrate_s: float = 3.0  # gravity is calibrated over this much tracked flight before the loss ...
    min_calibrate_s: float = 1.0  # ... at least this much, else the odometry coasts at constant velocity
    end_s: float = 0.25  # velocities: lines fitted to this long a span of positions
    max_accel_mps2: float = 4.0  # a larger mean acceleration over the span is not a flight's: no calibration


@dataclass(frozen=True)
class ProposalConfig:
    """Limits of the door proposals; every one is derived from elsewhere (see the notes)."""

    scale: float = 0.5  # LSD on the image at this scale: a door side a proposal needs is >= 2 x min_side_px long
    max_tilt_deg: float = LineConfig.max_tilt_deg  # from vertical: the drone rolls up to ~20 deg (perception.lines)
    join_offset_px: float = LineConfig.join_offset_px  # collinear pieces of one side (perception.lines) ...
    join_gap_px: float = JOIN_GAP_PX  # ... whose ends lie within the paper's joining distance
    min_side_px: float = 40.0  # px: a 1.52 m door at 18 m, f = 480: past the 12 m range (1.52 m: a short door,
    # docs/measurements.md, "Door proposals' shortest side")
    strip_px: tuple[float, float] = (6.0, 24.0)  # the wall's depth from this far outside a side (WallPlaneConfig)
    depth_tol_m: tuple[float, float] = (0.03, 0.0125)  # stereo's noise, a + b z^2 (WallPlaneConfig.threshold_m)
    border_fraction: float = 40 / 480  # a side's end this near the border runs on past it (pipeline's margin)
    max_proposals: int = 4  # per frame, best fit first: each costs an LSD refine and a 3D fit (~3 ms)
    check_wall: bool = True  # the sides must stand in one wall (the chain's WallPlaneConfig; False: not checked)


@dataclass(frozen=True)
class SizeTolerance:
    """How far a reconstructed width or height may lie from the true one: `floor_m + per_m * depth_m`, from the
    chain's error measured on rendered frames with known truth (`bench.bench_size_check --measure`, the detector's
    boxes matched to the truth): it holds nearly all widths and heights not cut by the border (docs/measurements.md,
    "The detector's kind and the size tolerance").
    Stereo's depth error grows as depth squared, but a width or height is a difference of two corners at the
    same depth, so its error grows with depth (the pixel error of a side times depth / f) plus a constant part
    (the box and the LSD side missing the frame by a few centimetres)."""

    floor_m: float = 0.10
    per_m: float = 0.03

    def at(self, depth_m: float) -> float:
        return self.floor_m + self.per_m * max(depth_m, 0.0)


@dataclass(frozen=True)
class PerceptionParams:
    """The chain's parameters, one part per component: `stereo` is the frame's SGBM (shared by the depth points,
    the openings and the odometry's keyframes: 128 disparities, depth down to fx * baseline / 128)."""

    stereo: SgbmConfig = field(default_factory=lambda: SgbmConfig(num_disparities=128))
    lines: LineConfig = field(default_factory=LineConfig)
    plausibility: PlausibilityConfig = field(default_factory=PlausibilityConfig)
    wall_plane: WallPlaneConfig = field(default_factory=WallPlaneConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    gravity: GravityParams = field(default_factory=GravityParams)
    depth: DepthPointsConfig = field(default_factory=DepthPointsConfig)
    place: PlaceConfig = field(default_factory=PlaceConfig)
    inertial: InertialParams = field(default_factory=InertialParams)
    proposals: ProposalConfig = field(default_factory=ProposalConfig)
    size_check: SizeTolerance = field(default_factory=SizeTolerance)
