"""The one typed configuration of macroloc: defaults here, overridable by a JSON/TOML file, environment
variables (MACROLOC_<SECTION>__<KEY>, e.g. MACROLOC_ZENOH__MODE=client) and command-line flags.

Components never read this object: factories in `service/` turn its sections into typed constructor
arguments. `macroloc dump-config` prints the resolved configuration.
"""

from __future__ import annotations

import json
import logging
import tomllib
from dataclasses import fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from macroloc.graph.errors import UserInputError
from macroloc.graph.keyframes import KeyframeRule
from macroloc.graph.params import (
    AnchorParams,
    DepthParams,
    FarParams,
    IsamSettings,
    JudgeParams,
    LandmarkParams,
    OdometryParams,
    RecoveryParams,
    RegistrationParams,
    RobustParams,
    StatusParams,
    SurfaceFitParams,
    VerifyParams,
)
from macroloc.perception.image_header import DEFAULT_MAX_PIXELS
from macroloc.perception.params import PerceptionParams

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

log = logging.getLogger(__name__)
P = TypeVar("P", bound="DataclassInstance")  # a parameter dataclass


class _Section(BaseModel):
    """A config section: a misspelt key is refused with its name, never silently ignored."""

    model_config = ConfigDict(extra="forbid")


def _replaced(defaults: P, section: BaseModel) -> P:
    """`defaults` (a parameter dataclass) with the section's keys that are its fields (of the same names)."""
    names = {f.name for f in fields(defaults)}
    return replace(defaults, **{k: getattr(section, k) for k in type(section).model_fields if k in names})


_ROBUST, _VERIFY = RobustParams(), VerifyParams()  # the one-shot registration's defaults (graph.params), written once


class VerifyConfig(_Section):
    """How the one-shot registration verifies a pose's matches (graph.params.VerifyParams, graph.verify)."""

    gate_sigmas: float = Field(
        _VERIFY.gate_sigmas, gt=0,
        description="a residual beyond this many sigmas of its noise model is no match (wall normal, sides)")
    position_gate_chi2: float = Field(
        _VERIFY.position_gate_chi2, gt=0, description="... and a centroid beyond this chi-square (3 dof)")
    false_detection_rate: float = Field(
        _VERIFY.false_detection_rate, gt=0, lt=1, description="the prior of a false detection (the outlier process)")
    normal_floor_deg: float = Field(
        _VERIFY.normal_floor_deg, ge=0, description="the wall normal is never trusted better than this, deg")
    size_floor_m: float = Field(_VERIFY.size_floor_m, ge=0, description="nor a side length better than this, m")
    neighbours: int = Field(
        _VERIFY.neighbours, ge=1, description="CAD features within the position gate considered per observation")


class LocalizeConfig(_Section):
    """One-shot registration of observed macro-features to the CAD model (graph/registration): `macroloc localize
    --config FILE` reads the robust method's keys (graph.robust.RobustParams' fields of the same names); `macroloc
    serve` reads `method` (its pose graph registers with the [graph.registration] keys)."""

    method: Literal["robust", "paper"] = Field("robust", description="'paper' = the paper's algorithm exactly")
    inlier_threshold_m: float = Field(
        _ROBUST.inlier_threshold_m,
        description="an observation this close to a same-type CAD feature (centroids) supports the pose, m (as "
        "[graph.registration] inlier_threshold_m is the pose graph's, for perception's coarser landmarks)")
    landing_alpha: float = Field(
        _ROBUST.landing_alpha,
        description="a different pose within the rival margin of the best makes the answer 'ambiguous'; the margin "
        "covers the false detections' chance landings on features but this often")
    min_inliers: int = Field(
        _ROBUST.min_inliers, description="fewer explained observations than this (4 without gravity): not_localized")
    seed: int = Field(_ROBUST.seed, description="random seed of the hypothesis order (deterministic answers)")
    size_tolerance_m: float = Field(
        _ROBUST.size_tolerance_m, gt=0,
        description="an observed rectangle's sides match a CAD feature's within this, m")
    coarse_base_m: float = Field(
        _ROBUST.coarse_base_m, gt=0,
        description="the coarse check's tolerance: this plus coarse_slope times the distance from the seed, m")
    coarse_slope: float = Field(
        _ROBUST.coarse_slope, ge=0, description="... its growth with the distance from the seed, m/m")
    max_seeds: int = Field(
        _ROBUST.max_seeds, ge=1, description="observed rectangles that seed hypotheses, at most")
    min_seeds: int = Field(
        _ROBUST.min_seeds, ge=1, description="seeds added per round (the refinement runs after each round)")
    early_stop_fraction: float = Field(
        _ROBUST.early_stop_fraction, gt=0, le=1,
        description="seeding stops once a refined pose explains this fraction of the observations")
    refine_top: int = Field(
        _ROBUST.refine_top, ge=1, description="distinct coarse hypotheses refined")
    scan_top: int = Field(
        _ROBUST.scan_top, ge=1, description="coarse hypotheses scanned for distinct ones")
    refine_iterations: int = Field(
        _ROBUST.refine_iterations, ge=1, description="refinement iterations of each pose")
    gravity_tolerance_deg: float = Field(
        _ROBUST.gravity_tolerance_deg, ge=0,
        description="with gravity given, a hypothesis may tilt the map this much, deg")
    ambiguity_tau_m: float = Field(
        _ROBUST.ambiguity_tau_m, gt=0,
        description="an observation farther than this from any CAD feature explains nothing, m")
    rival_self_maps: int = Field(
        _ROBUST.rival_self_maps, ge=0,
        description="the best pose's images under the building's self-maps refined and scored as rivals")
    seed_rivals: int = Field(
        _ROBUST.seed_rivals, ge=0,
        description="per seed observation, its best distinct coarse hypotheses verified as rivals")
    noise_floor_m: float = Field(
        _ROBUST.noise_floor_m, gt=0, description="the residuals' noise scale is never taken below this, m")
    distinct_m: float = Field(
        _ROBUST.distinct_m, gt=0,
        description="poses that move the matched observations by more than this are different, m ...")
    distinct_deg: float = Field(
        _ROBUST.distinct_deg, gt=0, description="... and so are poses whose rotations differ by more than this, deg")
    pair_min_baseline_m: float = Field(
        _ROBUST.pair_min_baseline_m, ge=0,
        description="pair hypotheses (gravity given) need observations this far apart, m ...")
    pair_max_baseline_m: float = Field(
        _ROBUST.pair_max_baseline_m, gt=0, description="... and consider CAD pairs up to this far apart, m")
    pair_tolerance_m: float = Field(
        _ROBUST.pair_tolerance_m, gt=0,
        description="a pair's horizontal distance and height difference agree within this, m")
    coarse_observations: int = Field(
        _ROBUST.coarse_observations, ge=1, description="observations nearest the seed that rank its hypotheses")
    polish_tau_m: float = Field(
        _ROBUST.polish_tau_m, gt=0, description="the ranking's tolerance after the polishing step, m")
    rival_candidates: int = Field(
        _ROBUST.rival_candidates, ge=0,
        description="best-supported distinct hypotheses refined when looking for a rival")
    min_inlier_fraction: float = Field(
        _ROBUST.min_inlier_fraction, ge=0, le=1,
        description="a pose explaining fewer of the observations than this fraction is not trusted")
    cross_type_weight: float = Field(
        _ROBUST.cross_type_weight, ge=0, le=1,
        description="an observation on a feature of the other type (door/window confusion) counts this much")
    min_inliers_without_gravity: int = Field(
        _ROBUST.min_inliers_without_gravity, ge=1,
        description="without gravity, fewer explained observations than this: not_localized (unless every one is a "
        "rectangle: min_inliers)")
    complete_below: int = Field(
        _ROBUST.complete_below, ge=0,
        description="below this many inliers the answer is every distinct hypothesis explaining as many observations "
        "as the best or one fewer, for other evidence to choose among (0: the refined few)")
    prune_top: int = Field(
        _ROBUST.prune_top, ge=0,
        description="per seed rectangle (gravity given), the CAD candidates kept, best layout score first (0: every "
        "one)")
    image_anchors: int = Field(
        _ROBUST.image_anchors, ge=1,
        description="matched features of the best pose whose alike features propose its images (rivals)")
    image_anchor_gap_m: float = Field(
        _ROBUST.image_anchor_gap_m, ge=0, description="... at least this far apart, m")
    image_alike_fraction: float = Field(
        _ROBUST.image_alike_fraction, gt=0, le=1,
        description="alike: a feature whose layout explains this fraction of the anchor's relations")
    image_landing_m: float = Field(
        _ROBUST.image_landing_m, gt=0,
        description="an image maps a matched feature onto one of its type this close, m ...")
    image_min_fraction: float = Field(
        _ROBUST.image_min_fraction, gt=0, le=1, description="... for this fraction of them (at least 2) ...")
    image_check: int = Field(
        _ROBUST.image_check, ge=1, description="... of this many, spread over the footprint")
    image_slack: float = Field(
        _ROBUST.image_slack, ge=0,
        description="images short of the best by the rival margin and this many observations more are not judged")
    verify: VerifyConfig = Field(default_factory=lambda: VerifyConfig(),
                                 description="[localize.verify]: how a pose's matches are verified")

    def robust_params(self) -> RobustParams:
        """The robust method's parameters (graph.registration.register(method='robust', params=...)): its
        defaults but for this section's keys of the same names."""
        return replace(_replaced(RobustParams(), self), verify=_replaced(VerifyParams(), self.verify))


class CameraConfig(_Section):
    """The rectified stereo camera (simulator defaults; a real vehicle sends its own CameraInfo)."""

    width: int = Field(640, description="image width of the simulated camera (macroloc simulate), px")
    height: int = Field(480, description="image height of the simulated camera, px")
    fx: float = Field(480.0, description="focal length along x of the simulated (rectified) camera, px")
    fy: float = Field(480.0, description="focal length along y, px")
    cx: float = Field(319.5, description="principal point x, px")
    cy: float = Field(239.5, description="principal point y, px")
    baseline_m: float = Field(0.12, description="stereo baseline of the simulated camera, m")
    rate_hz: float = Field(30.0, description="stereo frame rate of a simulated flight, Hz")
    T_body_cam: list[list[float]] | None = Field(
        None, description="the left camera's optical frame in the body frame (4x4, rows), for ROS 2 bags without "
        "/tf_static (base_link -> the camera's frame); None: looking forward along body x, 0.10 m ahead, the left "
        "camera baseline/2 to the left (the simulator's mounting)")


class ZenohConfig(_Section):
    """Zenoh session: peer mode on loopback with multicast scouting off is the embedded default."""

    mode: Literal["peer", "client", "router"] = Field("peer", description="Zenoh session mode")
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.2:7447")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="endpoints to listen on (the service's default: loopback, Zenoh's port)")
    config_file: Path | None = Field(None, description="a zenoh JSON5 config file, applied before the keys above")
    multicast_scouting: bool = Field(False, description="discover peers by UDP multicast (off: only the "
                                     "connect/listen endpoints)")
    gossip_scouting: bool = Field(False, description="off for fixed endpoints; on when peers meet through a router")


class ServiceConfig(_Section):
    """The long-running process."""

    vehicle: str = Field("drone1", description="key prefix: macroloc/<vehicle>/...")
    building: Path | None = Field(None, description="IFC or mesh file of the building")
    state_dir: Path = Field(Path("~/.local/state/macroloc").expanduser(), description="maps and logs")
    queue_size: int = Field(4, description="bounded queue between the frame ring and the heavy worker")
    ring_size: int = Field(2, description="latest stereo frames kept by the ring channel")
    cameras: list[str] = Field(default_factory=lambda: ["front"], description="accepted StereoFrame camera ids")
    status_period_s: float = Field(1.0, description="period of status and diagnostics messages, s")
    save_period_s: float = Field(5.0, description="period of saving the map to state_dir, s (and at exit)")
    perception: bool = Field(True, description="run the perception chain on stereo frames (else decode only)")
    log_json: bool = Field(False, description="structured logs: one JSON object per line on stderr")
    stall_after_s: float = Field(5.0, gt=0, description="a worker busy this long on one event is stalled: the "
                                 "liveliness token is withdrawn and systemd's watchdog no longer fed, s")
    drain_timeout_s: float = Field(15.0, gt=0, description="at stop, how long queued events are handled before the "
                                   "map is saved and the process exits (keep under the unit's TimeoutStopSec), s")
    lockstep: bool = Field(False, description="handle inputs in the order sent, none dropped, and replan before the "
                           "pose: for a simulated vehicle whose clock waits for the service (demo --lockstep, tests)")


class PlanningConfig(_Section):
    """Occupancy grid and A* (paper §3.3)."""

    cell_m: float = Field(0.20, description="occupancy grid cell size, m")
    vehicle_radius_m: float = Field(0.35, description="obstacles are inflated by this radius before A*, m")
    flight_height_m: float = Field(1.4, description="height above the storey's floor at which the model is cut "
                                   "into the occupancy grid and waypoints are placed, m")
    replan_period_s: float = Field(2.0, description="replan to the active goal from the current pose this often, s")


class SimConfig(_Section):
    """The camera simulator (`macroloc simulate`): flights through a building model and their recordings."""

    duration_s: float = Field(60.0, description="flight duration, s")
    speed_mps: float = Field(1.0, description="cruise speed, m/s")
    min_height_m: float = Field(1.0, description="lowest flight height above the storey's floor, m")
    max_height_m: float = Field(1.8, description="highest flight height above the storey's floor, m")
    imu_rate_hz: float = Field(200.0, description="IMU sample rate of a simulated flight, Hz")
    image_encoding: Literal["png", "jpeg", "raw"] = Field("jpeg", description="stereo images in the recording "
                                                          "(jpeg: quality 92, ~100 KB; png of a noisy image: ~450 KB)")
    depth: bool = Field(True, description="record the ground-truth depth (RAW_DEPTH_F32, m, 1 mm steps) per frame")
    facade_photos: Path | None = Field(None, description="folder of facade photos with YOLO labels (images/, "
                                       "labels/) to texture half the doors/windows with real crops; only photos "
                                       "numbered n % 5 != 0 are used (the rest is the detector's test split)")


# the localizer's defaults, written once (graph.params, graph.keyframes): the [graph] tables take theirs from these
_LANDMARKS, _ANCHOR, _STATUS, _RECOVERY = LandmarkParams(), AnchorParams(), StatusParams(), RecoveryParams()
_REGISTRATION, _JUDGE, _FAR = RegistrationParams(), JudgeParams(), FarParams()
_ODOMETRY, _DEPTH, _FIT = OdometryParams(), DepthParams(), SurfaceFitParams()
_RULE, _ISAM = KeyframeRule(), IsamSettings()


class _Params(_Section):
    """A table of the [graph] section: each key is the field of the same name of one of the localizer's parameter
    dataclasses (graph.params), its default that field's."""

    def to_params(self, defaults: P) -> P:
        """`defaults` (a parameter dataclass) with this table's keys that are its fields."""
        return _replaced(defaults, self)


_PERCEPTION = PerceptionParams()  # the chain's defaults (perception.params), written once


class StereoTable(_Params):
    """The frame's SGBM, shared by the depth points, the openings and the odometry's keyframes
    (perception.params.SgbmConfig)."""

    num_disparities: int = Field(
        _PERCEPTION.stereo.num_disparities, ge=16, multiple_of=16,
        description="disparities searched: depth down to fx * baseline / this (a wider baseline or a nearer wall wants "
        "more)")
    block_size: int = Field(_PERCEPTION.stereo.block_size, ge=1, description="matched block, px (odd)")
    uniqueness_ratio: int = Field(_PERCEPTION.stereo.uniqueness_ratio, ge=0, description="OpenCV's uniquenessRatio, %")
    speckle_window: int = Field(_PERCEPTION.stereo.speckle_window, ge=0, description="OpenCV's speckleWindowSize, px")
    speckle_range: int = Field(_PERCEPTION.stereo.speckle_range, ge=0, description="OpenCV's speckleRange")
    three_way: bool = Field(_PERCEPTION.stereo.three_way, description="OpenCV's 3-way mode (faster than the full mode)")
    scale: float = Field(
        _PERCEPTION.stereo.scale, gt=0, le=1,
        description="below 1: matched on the pair shrunk by this factor, the disparity brought back to full size")


class LinesTable(_Params):
    """The openings' sides from line segments (paper's LSD refinement; perception.params.LineConfig)."""

    join_angle_deg: float = Field(
        _PERCEPTION.lines.join_angle_deg, ge=0,
        description="segments joined where their slopes lie within this, deg (the paper's 2)")
    join_gap_px: float = Field(
        _PERCEPTION.lines.join_gap_px, ge=0, description="... and their close ends within this, px (the paper's 10)")
    join_offset_px: float = Field(
        _PERCEPTION.lines.join_offset_px, ge=0,
        description="... and they are collinear within this perpendicular offset, px")
    max_tilt_deg: float = Field(
        _PERCEPTION.lines.max_tilt_deg, ge=0,
        description="a side candidate's angle from the image vertical at most this, deg (a drone rolls)")
    margin: float = Field(
        _PERCEPTION.lines.margin, ge=0,
        description="the box grows by this fraction of its size on each side before LSD")
    side_band: float = Field(
        _PERCEPTION.lines.side_band, ge=0,
        description="a side candidate lies within this fraction of the box width inside its edge ...")
    side_band_out: float = Field(_PERCEPTION.lines.side_band_out, ge=0, description="... or this fraction outside it")
    min_length: float = Field(
        _PERCEPTION.lines.min_length, ge=0, description="... and is at least this fraction of the box height long")
    near_length: float = Field(
        _PERCEPTION.lines.near_length, ge=0,
        description="among candidates at least this fraction of the longest, the nearest to the edge wins")
    snap: float = Field(
        _PERCEPTION.lines.snap, ge=0,
        description="a side's end this close to the box's top or bottom (fraction of its height) goes onto it")


class PlausibilityTable(_Params):
    """Limits a reconstructed door or window must meet (perception.params.PlausibilityConfig)."""

    depth_range_m: tuple[float, float] = Field(
        _PERCEPTION.plausibility.depth_range_m, description="its depth, [near, far] m")
    door_width_m: tuple[float, float] = Field(
        _PERCEPTION.plausibility.door_width_m, description="a door's width, [min, max] m")
    door_height_m: tuple[float, float] = Field(
        _PERCEPTION.plausibility.door_height_m, description="a door's height, [min, max] m")
    window_width_m: tuple[float, float] = Field(
        _PERCEPTION.plausibility.window_width_m, description="a window's width, [min, max] m")
    window_height_m: tuple[float, float] = Field(
        _PERCEPTION.plausibility.window_height_m, description="a window's height, [min, max] m")
    max_tilt_deg: float = Field(
        _PERCEPTION.plausibility.max_tilt_deg, ge=0,
        description="its sides from gravity, when gravity is known, at most this, deg")
    max_tilt_no_gravity_deg: float = Field(
        _PERCEPTION.plausibility.max_tilt_no_gravity_deg, ge=0,
        description="... from the camera's y axis when it is not, deg")
    max_side_angle_deg: float = Field(
        _PERCEPTION.plausibility.max_side_angle_deg, ge=0,
        description="its two sides nearly parallel: within this, deg")


class WallPlaneTable(_Params):
    """The wall an opening sits in, from the depth beside its sides and above its top
    (perception.params.WallPlaneConfig)."""

    near_px: float = Field(
        _PERCEPTION.wall_plane.near_px, ge=0, description="the strips start this far outside the sides, px ...")
    far_px: float = Field(_PERCEPTION.wall_plane.far_px, ge=0, description="... and end this far, px")
    n_samples: int = Field(
        _PERCEPTION.wall_plane.n_samples, ge=1,
        description="points along each side (and the top) per column (row) of a strip")
    threshold_m: tuple[float, float] = Field(
        _PERCEPTION.wall_plane.threshold_m,
        description="a point lies on the plane within a + b * depth^2, [a m, b 1/m]")
    min_points: int = Field(
        _PERCEPTION.wall_plane.min_points, ge=1, description="points of a strip for it to count ...")
    min_strips: int = Field(
        _PERCEPTION.wall_plane.min_strips, ge=1, description="... and this many strips must lie on the plane")
    min_inlier_fraction: float = Field(
        _PERCEPTION.wall_plane.min_inlier_fraction, ge=0, le=1,
        description="of the points of the strips that count, on the plane")
    max_tilt_deg: float = Field(
        _PERCEPTION.wall_plane.max_tilt_deg, ge=0,
        description="the plane's normal from horizontal (gravity known) at most this, deg")
    min_incidence_deg: float = Field(
        _PERCEPTION.wall_plane.min_incidence_deg, ge=0,
        description="a corner's viewing ray meets the plane at least this steeply, deg")
    iterations: int = Field(_PERCEPTION.wall_plane.iterations, ge=1, description="RANSAC hypotheses (seeded)")


class VisualOdometryTable(_Params):
    """The stereo visual odometry of a replay (perception.params.OdometryConfig; the service takes the vehicle's
    odometry)."""

    n_features: int = Field(
        _PERCEPTION.odometry.n_features, ge=1, description="ORB features kept a frame, spread over the grid")
    detect_features: int = Field(
        _PERCEPTION.odometry.detect_features, ge=1, description="ORB's keypoints before the grid picks n_features")
    grid_cols: int = Field(_PERCEPTION.odometry.grid_cols, ge=1, description="the grid's columns ...")
    grid_rows: int = Field(
        _PERCEPTION.odometry.grid_rows, ge=1, description="... and rows (each cell keeps its strongest keypoints)")
    fast_threshold: int = Field(
        _PERCEPTION.odometry.fast_threshold, ge=1,
        description="ORB's FAST threshold (low-contrast walls want a lower one)")
    min_disparity_px: float = Field(
        _PERCEPTION.odometry.min_disparity_px, ge=0, description="a keypoint's disparity at least this, px")
    num_disparities: int = Field(
        _PERCEPTION.odometry.num_disparities, ge=16, multiple_of=16,
        description="SGBM's range at keyframes where the odometry matches on its own")
    edge_disparity_px: float = Field(
        _PERCEPTION.odometry.edge_disparity_px, ge=0,
        description="a keypoint whose 3 x 3 disparities spread more lies on a depth edge: dropped, px")
    max_depth_m: float = Field(_PERCEPTION.odometry.max_depth_m, gt=0, description="keypoints farther are dropped, m")
    ratio: float = Field(
        _PERCEPTION.odometry.ratio, gt=0, le=1, description="Lowe's ratio test for frame-to-keyframe matches")
    ransac_reprojection_px: float = Field(
        _PERCEPTION.odometry.ransac_reprojection_px, gt=0, description="PnP-RANSAC's reprojection threshold, px")
    min_inliers: int = Field(
        _PERCEPTION.odometry.min_inliers, ge=1, description="fewer PnP inliers: tracking lost for the frame")
    rekey_inliers: int = Field(
        _PERCEPTION.odometry.rekey_inliers, ge=1, description="fewer: the frame becomes the reference keyframe")
    rekey_translation_m: float = Field(
        _PERCEPTION.odometry.rekey_translation_m, gt=0, description="... or after this much motion, m")
    rekey_rotation_rad: float = Field(_PERCEPTION.odometry.rekey_rotation_rad, gt=0, description="... or rotation, rad")
    rekey_at_session_keyframes: bool = Field(
        _PERCEPTION.odometry.rekey_at_session_keyframes,
        description="the session's keyframes become the odometry's reference too, sharing their whole-frame SGBM "
        "(with [perception.depth] at_keyframes; less CPU, but off: held-out APE worse, docs/measurements.md)")
    max_step_m: float = Field(
        _PERCEPTION.odometry.max_step_m, gt=0,
        description="a frame-to-frame jump beyond this is a wrong PnP solution, m")
    max_step_rad: float = Field(_PERCEPTION.odometry.max_step_rad, gt=0, description="... or a turn beyond this, rad")
    max_step_change_m: float = Field(
        _PERCEPTION.odometry.max_step_change_m, gt=0,
        description="a pose from few inliers this far off the last step's velocity is wrong, m")
    gyro_tolerance_rad: float = Field(
        _PERCEPTION.odometry.gyro_tolerance_rad, gt=0,
        description="a PnP rotation this far from the gyro's is replaced by the gyro's, rad")
    pnp_rotation_gain: float = Field(
        _PERCEPTION.odometry.pnp_rotation_gain, ge=0, le=1,
        description="with a gyro: the share of PnP's rotation taken per frame")
    tracker: Literal["orb", "klt"] = Field(
        _PERCEPTION.odometry.tracker,
        description="orb: ORB matched to the keyframe every frame; klt: the keyframe's points followed by optical "
        "flow (a third of the CPU; it drifted more in one building: docs/measurements.md)")
    flow_points: int = Field(
        _PERCEPTION.odometry.flow_points, ge=1, description="klt: the keyframe's points followed, spread over the grid")
    flow_window_px: int = Field(_PERCEPTION.odometry.flow_window_px, ge=3, description="klt: Lucas-Kanade's window, px")
    flow_levels: int = Field(_PERCEPTION.odometry.flow_levels, ge=0, description="klt: its pyramid's levels")
    flow_from: Literal["last", "keyframe"] = Field(
        _PERCEPTION.odometry.flow_from,
        description="klt: each point followed from the last frame or from the keyframe's image")
    flow_min_eigen: float = Field(
        _PERCEPTION.odometry.flow_min_eigen, gt=0, description="klt: Lucas-Kanade's minEigThreshold")
    flow_round_trip_px: float = Field(
        _PERCEPTION.odometry.flow_round_trip_px, gt=0,
        description="klt: a point tracked forward then back further than this is lost, px")
    flow_border_px: float = Field(
        _PERCEPTION.odometry.flow_border_px, ge=0,
        description="klt: a point tracked this near the image's edge is lost, px")


class GravityTable(_Params):
    """Gravity's up from the IMU's specific force less the odometry's acceleration (perception.params.GravityParams),
    in the service and a replay alike."""

    window_s: float = Field(
        _PERCEPTION.gravity.window_s, gt=0,
        description="positions and specific forces of this long a span estimate the mean acceleration, s")
    min_span_s: float = Field(
        _PERCEPTION.gravity.min_span_s, gt=0,
        description="a shorter history gives the specific force alone (as at take-off), s")
    max_accel_mps2: float = Field(
        _PERCEPTION.gravity.max_accel_mps2, gt=0,
        description="a larger fitted acceleration is no flight's: no estimate for the frame, m/s^2")
    end_s: float = Field(
        _PERCEPTION.gravity.end_s, gt=0,
        description="the velocities at the window's ends: lines fitted to this long a part of it, s")
    min_specific_force_mps2: float = Field(
        _PERCEPTION.gravity.min_specific_force_mps2, ge=0,
        description="an IMU sample below this (a free fall) is left out, m/s^2 ...")
    max_specific_force_mps2: float = Field(
        _PERCEPTION.gravity.max_specific_force_mps2, gt=0, description="... and above this (a knock), m/s^2")


class DepthTable(_Params):
    """The depth points for the surface check and fit, from the frame's SGBM or a depth image the vehicle sends
    (perception.params.DepthPointsConfig)."""

    every: int = Field(_PERCEPTION.depth.every, ge=0, description="depth points on every this many stereo frames (the "
                       "localizer keeps the newest before each keyframe); 0: none")
    at_keyframes: bool = Field(_PERCEPTION.depth.at_keyframes, description="measure them only on the frames that "
                               "become keyframes (a keyframe takes the newest before it, the others are never used); "
                               "false: on every `every`-th frame")
    stride_px: int = Field(_PERCEPTION.depth.stride_px, ge=1, description="every this many pixels of the disparity, px")
    min_range_m: float = Field(_PERCEPTION.depth.min_range_m, ge=0, description="points nearer are dropped, m")
    max_range_m: float = Field(_PERCEPTION.depth.max_range_m, gt=0, description="points farther are dropped, m")
    depth_image_stride_px: int = Field(
        _PERCEPTION.depth.depth_image_stride_px, ge=1,
        description="a depth image the vehicle sends with its stereo frame: every this many pixels, px")


class PlaceTable(_Params):
    """Place recognition of keyframes in a stored map's views (perception.params.PlaceConfig)."""

    n_features: int = Field(_PERCEPTION.place.n_features, ge=1, description="ORB features of the image to place")
    stored_features: int = Field(
        _PERCEPTION.place.stored_features, ge=1,
        description="at most this many kept per stored view (those with a depth, strongest first)")
    fast_threshold: int = Field(_PERCEPTION.place.fast_threshold, ge=1, description="ORB's FAST threshold")
    num_disparities: int = Field(
        _PERCEPTION.place.num_disparities, ge=16, multiple_of=16,
        description="SGBM's search range for a stored view's depths")
    max_depth_m: float = Field(_PERCEPTION.place.max_depth_m, gt=0, description="a stored feature's depth at most, m")
    vote_features: int = Field(
        _PERCEPTION.place.vote_features, ge=1, description="the image's strongest features that vote for stored views")
    vote_per_view: int = Field(
        _PERCEPTION.place.vote_per_view, ge=1, description="... against each view's strongest this many")
    vote_distance: int = Field(
        _PERCEPTION.place.vote_distance, ge=0, le=256,
        description="Hamming distance (of 256 bits) under which a nearest descriptor votes for its view")
    top_views: int = Field(_PERCEPTION.place.top_views, ge=1, description="the best-voted views matched")
    ratio: float = Field(_PERCEPTION.place.ratio, gt=0, le=1, description="Lowe's ratio test of the matches")
    ransac_reprojection_px: float = Field(
        _PERCEPTION.place.ransac_reprojection_px, gt=0, description="PnP-RANSAC's reprojection threshold, px")
    min_inliers: int = Field(_PERCEPTION.place.min_inliers, ge=1, description="a place needs this many PnP inliers")
    max_tilt_deg: float = Field(
        _PERCEPTION.place.max_tilt_deg, ge=0, description="... and a pose this close to level, deg")
    rival_ratio: float = Field(
        _PERCEPTION.place.rival_ratio, ge=0, le=1,
        description="a second place explaining the leftover matches with this share of the inliers ...")
    rival_apart_m: float = Field(
        _PERCEPTION.place.rival_apart_m, ge=0, description="... this far from the first: the place is ambiguous, m")


class InertialTable(_Params):
    """The IMU's dead reckoning while a replay's visual odometry has lost track (perception.params.InertialParams)."""

    calibrate_s: float = Field(
        _PERCEPTION.inertial.calibrate_s, gt=0,
        description="gravity and the velocity are calibrated over this much tracked flight before the loss, s ...")
    min_calibrate_s: float = Field(
        _PERCEPTION.inertial.min_calibrate_s, gt=0,
        description="... at least this much, else the odometry coasts at constant velocity, s")
    end_s: float = Field(
        _PERCEPTION.inertial.end_s, gt=0, description="velocities: lines fitted to this long a span of positions, s")
    max_accel_mps2: float = Field(
        _PERCEPTION.inertial.max_accel_mps2, gt=0,
        description="a larger mean acceleration over the span is no flight's: no calibration, m/s^2")


class ProposalsTable(_Params):
    """Door candidates from geometry where the detector is blind; `macroloc perceive --building` only
    (perception.params.ProposalConfig, perception.door_proposals)."""

    scale: float = Field(_PERCEPTION.proposals.scale, gt=0, le=1,
                         description="LSD runs on the image shrunk by this factor")
    max_tilt_deg: float = Field(_PERCEPTION.proposals.max_tilt_deg, ge=0,
                                description="a door's side at most this far from vertical, deg")
    join_offset_px: float = Field(_PERCEPTION.proposals.join_offset_px, ge=0,
                                  description="collinear pieces of one side lie within this of each other's line, "
                                  "px ...")
    join_gap_px: float = Field(_PERCEPTION.proposals.join_gap_px, ge=0,
                               description="... and their ends within this, px")
    min_side_px: float = Field(_PERCEPTION.proposals.min_side_px, gt=0,
                               description="a side shorter than this is no door's, px")
    strip_px: tuple[float, float] = Field(_PERCEPTION.proposals.strip_px,
                                          description="the wall's depth is read between these distances outside a "
                                          "side, px")
    depth_tol_m: tuple[float, float] = Field(_PERCEPTION.proposals.depth_tol_m,
                                             description="stereo's depth noise a + b * depth^2, [a m, b 1/m]: what "
                                             "lies between the sides nearer than the wall by more stands in front")
    border_fraction: float = Field(_PERCEPTION.proposals.border_fraction, ge=0, lt=0.5,
                                   description="a side's end this near the border (share of the image height) runs "
                                   "on past it")
    max_proposals: int = Field(_PERCEPTION.proposals.max_proposals, ge=0,
                               description="proposals kept per frame, best fit first")
    check_wall: bool = Field(_PERCEPTION.proposals.check_wall,
                             description="the two sides must stand in one wall ([perception.wall_plane])")


class SizeCheckTable(_Params):
    """How far a reconstructed opening's width or height may lie from a model size and still fit it:
    floor_m + per_m * depth; `macroloc perceive --building` (perception.params.SizeTolerance)."""

    floor_m: float = Field(_PERCEPTION.size_check.floor_m, ge=0, description="at any depth, m ...")
    per_m: float = Field(_PERCEPTION.size_check.per_m, ge=0, description="... plus this per metre of depth")


class PerceptionConfig(_Section):
    """The perception chain (perception/): which door/window detector, on which frames it runs, and one table per
    component, named as its part of perception.params.PerceptionParams (`[perception.lines]` is `LineConfig`)."""

    detector_model: Path | None = Field(None, description="detector ONNX file with its JSON sidecar beside it; "
                                        "default: the shipped perception/models/detector.onnx (trained on real "
                                        "photos). A detector adapted to one building is trained on renders of its "
                                        "model: python -m macroloc.perception.train --sim FOLDER --out DIR")
    detect_every: int = Field(3, ge=1, description="replay: run the chain on every n-th stereo frame")
    stereo: StereoTable = Field(default_factory=lambda: StereoTable(),
                                description="[perception.stereo]: the frame's stereo matching")
    lines: LinesTable = Field(default_factory=lambda: LinesTable(),
                              description="[perception.lines]: the openings' sides from line segments")
    plausibility: PlausibilityTable = Field(default_factory=lambda: PlausibilityTable(),
                                            description="[perception.plausibility]: a door's or window's limits")
    wall_plane: WallPlaneTable = Field(default_factory=lambda: WallPlaneTable(),
                                       description="[perception.wall_plane]: the wall an opening sits in")
    odometry: VisualOdometryTable = Field(default_factory=lambda: VisualOdometryTable(),
                                          description="[perception.odometry]: a replay's stereo visual odometry")
    gravity: GravityTable = Field(default_factory=lambda: GravityTable(),
                                  description="[perception.gravity]: gravity's up from the IMU")
    depth: DepthTable = Field(default_factory=lambda: DepthTable(),
                              description="[perception.depth]: the depth points for the walls' checks")
    place: PlaceTable = Field(default_factory=lambda: PlaceTable(),
                              description="[perception.place]: keyframes placed in a stored map's views")
    inertial: InertialTable = Field(default_factory=lambda: InertialTable(),
                                    description="[perception.inertial]: the IMU's dead reckoning in a replay")
    proposals: ProposalsTable = Field(default_factory=lambda: ProposalsTable(),
                                      description="[perception.proposals]: doors proposed from geometry (perceive)")
    size_check: SizeCheckTable = Field(default_factory=lambda: SizeCheckTable(),
                                       description="[perception.size_check]: an opening's size against the "
                                       "model's (perceive)")

    def to_params(self) -> PerceptionParams:
        """The chain's parameters: each table onto its part of `PerceptionParams` (the rest at their defaults)."""
        d = _PERCEPTION
        return PerceptionParams(self.stereo.to_params(d.stereo), self.lines.to_params(d.lines),
                                self.plausibility.to_params(d.plausibility), self.wall_plane.to_params(d.wall_plane),
                                self.odometry.to_params(d.odometry), self.gravity.to_params(d.gravity),
                                self.depth.to_params(d.depth), self.place.to_params(d.place),
                                self.inertial.to_params(d.inertial), self.proposals.to_params(d.proposals),
                                self.size_check.to_params(d.size_check))


class KeyframesConfig(_Params):
    """Which frames become keyframes (graph.keyframes.KeyframeRule and its KeyframePolicy), the service and
    replay alike (service/session.py)."""

    translation_m: float = Field(_RULE.policy.translation_m, description="a new keyframe after this much motion, m")
    rotation_rad: float = Field(_RULE.policy.rotation_rad, description="... or this much rotation, rad")
    interval_s: float = Field(_RULE.policy.interval_s, description="... or this much time, s")
    while_exploring: bool = Field(
        _RULE.while_exploring, description="also every frame with sightings while not localized (slower to "
                                           "localize on 30 fps flights: docs/measurements.md, "
                                           "\"One keyframe rule for replay and service\")")
    without_sightings_m: float = Field(
        _RULE.without_sightings_m, description="a frame without sightings is a keyframe only after this much "
        "motion, m (0: the translation, rotation and interval above decide for it too)")

    def to_rule(self) -> KeyframeRule:
        return self.to_params(replace(_RULE, policy=self.to_params(_RULE.policy)))


class GraphOdometryConfig(_Params):
    """The odometry factor between consecutive keyframes (graph.params.OdometryParams)."""

    odometry_sigma_per_m: float = Field(
        _ODOMETRY.odometry_sigma_per_m, gt=0, description="the odometry's translation sigma per metre travelled "
        "(its drift), m/m")
    odometry_rot_sigma_per_m: float = Field(
        _ODOMETRY.odometry_rot_sigma_per_m, gt=0, description="its rotation sigma per metre travelled, rad/m")
    odometry_dead_reckoned_sigma_mps: float = Field(
        _ODOMETRY.odometry_dead_reckoned_sigma_mps, gt=0,
        description="translation sigma per second the odometry lost track and only extrapolated (a drone's speed "
        "it could not see change), m/s")


class LandmarksConfig(_Params):
    """Sightings into landmarks (graph.params.LandmarkParams)."""

    associate_m: float = Field(
        _LANDMARKS.associate_m, description="a sighting this close to a same-type landmark re-observes it, m")
    far_range_m: float = Field(
        _LANDMARKS.far_range_m, ge=0,
        description="doors and windows seen beyond the 7 m sighting range, up to this range, check "
        "candidate poses by their bearings and, before any door came within range, resect the pose, m "
        "(their stereo range is coarse, their bearing good to a fraction of a degree)")
    max_range_m: float = Field(
        _LANDMARKS.max_range_m, gt=0, description="sightings further away make no landmark: their corners are too "
        "coarse, m")
    sighting_sigma_m: tuple[float, float] = Field(
        _LANDMARKS.sighting_sigma_m, description="a sighting's position sigma is a + b * range^2 (stereo), [a m, b "
        "1/m]")
    sighting_sigma_rad: tuple[float, float] = Field(
        _LANDMARKS.sighting_sigma_rad, description="... its orientation's (the plane of noisy corners), [a rad, b "
        "rad/m^2]")
    truncated_sigma_m: float = Field(
        _LANDMARKS.truncated_sigma_m, gt=0, description="position sigma along an axis on which the sighting is cut by "
        "the image border, m")


class RegistrationConfig(_Params):
    """Registering the map's landmarks to the model (graph.params.RegistrationParams, graph.registrar)."""

    inlier_threshold_m: float = Field(
        _REGISTRATION.inlier_threshold_m, gt=0,
        description="an aligned landmark this close to a same-type CAD feature supports the pose (the "
        "registration's inlier and ambiguity tolerance, as [localize] inlier_threshold_m is the one-shot "
        "localize's), m (perception's landmarks lie 0.1-0.5 m off their feature: a tighter tolerance leaves the "
        "right pose too few inliers to beat its rivals)")
    registration_min_landmarks: int = Field(
        _REGISTRATION.registration_min_landmarks, ge=2,
        description="registration is tried once this many landmarks have been seen twice, and a pose "
        "must explain as many. With gravity two doors fix a pose, but at the tolerance above a building of a "
        "hundred alike doors offers chance fits of three landmarks "
        "(docs/measurements.md, \"Registration from three landmarks\")")
    verified_min_landmarks: int = Field(
        _REGISTRATION.verified_min_landmarks, ge=1,
        description="with the surface check ([graph] surface_check), candidate poses are weighed from this many "
        "landmarks. From one door or window (gravity known) they are every alike feature of the model, seen from "
        "either side; the walls must single one out")
    surface_retry_s: float = Field(
        _REGISTRATION.surface_retry_s, gt=0,
        description="while not localized and no new landmark came, the walls weigh the candidate poses "
        "again this often as more of them is seen, s (each check costs 0.1-0.4 s of CPU on a 2-core machine)")
    min_sightings_to_register: int = Field(
        _REGISTRATION.min_sightings_to_register, ge=1,
        description="a landmark takes part in registration once seen this often (one sighting may be a passing "
        "false detection)")
    registration_early_stop: float = Field(
        _REGISTRATION.registration_early_stop, gt=0, le=1,
        description="with the surface check, hypotheses stop being seeded once a pose explains this fraction of the "
        "landmarks (1: never)")


class AnchorConfig(_Params):
    """Holding the graph to the model once localized (graph.params.AnchorParams)."""

    cad_link_m: float = Field(
        _ANCHOR.cad_link_m, description="once localized, a landmark this close to a CAD feature is linked, m")
    cad_link_max_turn_deg: float = Field(
        _ANCHOR.cad_link_max_turn_deg, ge=0,
        description="... by its orientation too where that lies within this of the CAD feature's, deg "
        "(else by its position only: a door's plane from its corners can be far off on a door seen obliquely, and "
        "would turn the flight to fit it)")
    placed_sigma_m: float = Field(
        _ANCHOR.placed_sigma_m, gt=0, description="a keyframe placed in a stored map (place recognition): its "
        "position sigma in the model, m (the stored keyframe's error and PnP's together)")
    placed_sigma_deg: float = Field(_ANCHOR.placed_sigma_deg, gt=0, description="... its orientation sigma, deg")


class DepthConfig(_Params):
    """The recent keyframes whose depth points and far sightings are kept (graph.params.DepthParams)."""

    surface_window_keyframes: int = Field(
        _DEPTH.surface_window_keyframes, ge=1, description="the depth points of this many recent keyframes check a "
        "registration and find a pose again; [graph.isam] window_keyframes keeps at least as many")


class JudgeConfig(_Params):
    """The walls' judgement of candidate poses, the surface check ([graph] surface_check; graph.judge,
    graph.params.JudgeParams)."""

    surface_turn_deg: float = Field(
        _JUDGE.surface_turn_deg, ge=0,
        description="a candidate pose from one to three doors is first turned about one of them, within this, to "
        "the heading that fits the walls best while keeping its doors by theirs in the model, deg (from one door "
        "its heading is the door's plane: perception's is ~20 deg off on a door seen obliquely; from two or three "
        "a few metres apart 5-13 deg off); 0: not turned")
    surface_margin: float = Field(
        _JUDGE.surface_margin, ge=0, description="a candidate pose is taken only where every different candidate "
        "scores this much less (the fraction of the depth points on the model's surfaces and in sight); a smaller "
        "margin localizes sooner and risks a wrong pose where the building repeats itself")
    surface_margin_unfit: float = Field(
        _JUDGE.surface_margin_unfit, ge=0, description="... or this much less where that other pose does not fit the "
        "walls itself (candidates from two landmarks or more)")
    surface_min_points: int = Field(
        _JUDGE.surface_min_points, ge=1, description="fewer depth points than this: no check (the registration needs "
        "[graph.registration] registration_min_landmarks)")
    surface_min_support: float = Field(
        _JUDGE.surface_min_support, ge=0, le=1, description="a pose must put this fraction of the depth points on the "
        "model's surfaces")
    surface_max_seen_through: float = Field(
        _JUDGE.surface_max_seen_through, ge=0, le=1, description="... and let at most this fraction be seen through a "
        "wall ([graph] line_of_sight)")
    surface_refuse_seen_through: float = Field(
        _JUDGE.surface_refuse_seen_through, ge=0, le=1, description="a registrar's own answer is refused where more "
        "than this fraction is seen through a wall")
    surface_refine_m: float = Field(
        _JUDGE.surface_refine_m, ge=0, description="each candidate pose is first fitted to the walls, moving the "
        "points at most this, m")
    surface_screen_top: int = Field(
        _JUDGE.surface_screen_top, ge=1, description="of more candidates (one door: every alike door of the model, "
        "from both sides), only the best this many are fitted and checked ...")
    surface_screen_points: int = Field(
        _JUDGE.surface_screen_points, ge=1, description="... screened by this many depth points, unfitted")
    surface_turn_step_deg: float = Field(
        _JUDGE.surface_turn_step_deg, gt=0, description="the steps of surface_turn_deg's turns, deg")
    surface_turn_points: int = Field(
        _JUDGE.surface_turn_points, ge=1, description="the turns are judged by this many depth points")
    surface_turn_max_inliers: int = Field(
        _JUDGE.surface_turn_max_inliers, ge=1, description="where no candidate fits the walls unturned, candidates "
        "from up to this many doors are turned too (keeping as many by a CAD feature)")
    surface_own_wall_m: float = Field(
        _JUDGE.surface_own_wall_m, ge=0, description="candidates from one door are weighed by the depth points "
        "farther than this from its wall's plane (nearer, every candidate puts them on a wall), m")
    surface_self_map_images: int = Field(
        _JUDGE.surface_self_map_images, ge=0, description="before a candidate pose is taken, its images under up to "
        "this many of the building's near-self-maps that keep as many landmarks by a same-type CAD feature are "
        "weighed too (the doors cannot tell them apart); 0: none")


class FarConfig(_Params):
    """The doors and windows seen beyond the sighting range (graph.far_window, graph.params.FarParams)."""

    far_resection: bool = Field(
        _FAR.far_resection,
        description="before any door came within the sighting range, candidate poses from two far doors or "
        "windows seen at least 10 deg apart from one keyframe, for the walls to choose among")
    far_bearing_deg: float = Field(
        _FAR.far_bearing_deg, gt=0, description="a far sighting is explained where a same-type CAD feature lies within "
        "this horizontal bearing of it, seen from the keyframe's camera (and 3 sigmas of its range), deg")
    far_elevation_deg: float = Field(
        _FAR.far_elevation_deg, gt=0, description="... and within this of its elevation, deg")
    far_turn_deg: float = Field(
        _FAR.far_turn_deg, ge=0, description="... turning the candidate pose by up to this to do so, deg")
    far_turn_step_deg: float = Field(_FAR.far_turn_step_deg, gt=0, description="... in these steps, deg")
    far_min_sightings: int = Field(
        _FAR.far_min_sightings, ge=1, description="with this many far sightings in the window, a candidate pose "
        "explaining ...")
    far_min_explained: float = Field(
        _FAR.far_min_explained, ge=0, le=1, description="... at least this fraction of them is not rivalled by one "
        "explaining ...")
    far_margin: float = Field(_FAR.far_margin, ge=0, description="... this fraction less")
    far_pair_min_deg: float = Field(
        _FAR.far_pair_min_deg, gt=0, description="far_resection: the two far features at least this far apart in "
        "bearing, deg")
    far_pairs: int = Field(
        _FAR.far_pairs, ge=1, description="... from this many of the newest keyframes that saw such a pair (the "
        "widest pair of each)")
    far_resection_sightings: int = Field(
        _FAR.far_resection_sightings, ge=1, description="the resected candidates are judged by this many far "
        "sightings, evenly drawn")
    far_place_m: float = Field(
        _FAR.far_place_m, gt=0, description="one resected candidate per place this size; a pair whose ranges leave "
        "the camera more than this to move resects none, m")
    far_height_sigma_m: float = Field(
        _FAR.far_height_sigma_m, gt=0, description="the pose taken from far sightings holds the keyframe's height "
        "with this sigma, m ...")
    far_bearing_sigma_deg: float = Field(
        _FAR.far_bearing_sigma_deg, gt=0, description="... and is fitted to the far bearings with this one, deg")


class FitConfig(_Params):
    """Once localized, each keyframe's depth points fitted to the model's walls and floor
    (graph.params.SurfaceFitParams, graph.surface_fit)."""

    surface_fit: bool = Field(
        _FIT.surface_fit, description="once localized, each keyframe's depth points fitted to the walls join the "
        "graph as a measured pose in the model")
    surface_fit_max_correction_m: float = Field(
        _FIT.surface_fit_max_correction_m, gt=0, description="a fit that moves the pose further is not trusted (a "
        "wrong wall), m ...")
    surface_fit_max_turn_deg: float = Field(
        _FIT.surface_fit_max_turn_deg, gt=0, description="... nor one that turns it further, deg ...")
    surface_fit_settling_turn_deg: float = Field(
        _FIT.surface_fit_settling_turn_deg, gt=0, description="... but this far in the first keyframes after "
        "localizing, while the heading is the few doors' it was found by, deg")
    surface_fit_settling_keyframes: int = Field(
        _FIT.surface_fit_settling_keyframes, ge=0, description="those first keyframes")
    surface_fit_sigma_m: float = Field(
        _FIT.surface_fit_sigma_m, gt=0, description="a fitted point's distance to its wall, model against reality "
        "(the judge's fits of candidate poses use it too), m")


class StatusConfig(_Params):
    """The localized status decaying while no CAD-linked landmark is seen (graph.params.StatusParams)."""

    degraded_after_s: float = Field(
        _STATUS.degraded_after_s,
        description="localized, but no sighting of a CAD-linked landmark for this long: degraded")
    lost_after_s: float = Field(_STATUS.lost_after_s, description="... for this long: lost")
    held_sigma_m: float = Field(
        _STATUS.held_sigma_m, gt=0,
        description="the pose is held to the model while its horizontal sigma (the pose graph's) is within this: "
        "only then is it localized, fitted to the walls and are new doors linked by proximity. Beyond (the "
        "odometry lost track and extrapolated), the walls and the doors look for it again ([graph.recovery])")


class RecoveryConfig(_Params):
    """A pose no longer held to the model found again by the walls or the doors (graph.params.RecoveryParams)."""

    recovery: bool = Field(
        _RECOVERY.recovery,
        description="look for a pose that is no longer held among shifts of it within 3 sigma, by the walls seen "
        "since the odometry tracks again (taken only where no other shift fits them as well: [graph.judge]), else "
        "by the doors and windows mapped since it was held (taken where it puts two or more on the model's, and "
        "no shift recovery_apart_m from it as many)")
    recovery_step_m: float = Field(_RECOVERY.recovery_step_m, gt=0, description="the shifts' grid spacing")
    recovery_max_m: float = Field(_RECOVERY.recovery_max_m, gt=0, description="the largest shift")
    recovery_candidates: int = Field(
        _RECOVERY.recovery_candidates, ge=1, description="the shifts that put most depth points on the walls, this "
        "many ...")
    recovery_apart_m: float = Field(
        _RECOVERY.recovery_apart_m, ge=0, description="... at least this far apart, are fitted and judged, m")
    recovery_min_doors: int = Field(
        _RECOVERY.recovery_min_doors, ge=2, description="the doors' shift is taken where it puts this many doors and "
        "windows mapped since the pose was held on the model's (one alone may be a false detection by a model door)")
    recovery_sigma_m: float = Field(_RECOVERY.recovery_sigma_m, gt=0,
                                    description="the position sigma of a pose found again")
    recovery_sigma_deg: float = Field(_RECOVERY.recovery_sigma_deg, gt=0,
                                      description="... its orientation sigma, deg")


class IsamConfig(_Params):
    """The pose graph's iSAM2 (graph.posegraph.IsamSettings)."""

    relinearize_threshold: float = Field(_ISAM.relinearize_threshold, description="iSAM2 relinearization threshold")
    relinearize_skip: int = Field(_ISAM.relinearize_skip, ge=1,
                                  description="iSAM2 checks for relinearization every this many updates")
    window_keyframes: int = Field(
        _ISAM.window_keyframes, ge=0,
        description="keyframes kept as variables behind the newest; older ones are marginalised into a prior, so a "
        "keyframe's cost stays flat over a long mission (0: all kept, plain iSAM2). At least 60, the oldest keyframe "
        "the surface check reads back")
    marginalise_every: int = Field(
        _ISAM.marginalise_every, ge=1,
        description="with a window: keyframes are marginalised this many at a time (one re-factorisation each time)")
    marginalise_landmarks: bool = Field(
        _ISAM.marginalise_landmarks,
        description="with a window: a door or window no live keyframe sees leaves the graph with them, its CAD links "
        "set aside, and re-enters when seen again, at its last estimate with its links (unlinked: with a prior of its "
        "last covariance); the cost then follows the doors in view (false: every door mapped stays a variable)")


# The [graph] keys before its tables (issue 36), still read: each moves to its table, with a warning.
LEGACY_GRAPH_KEYS: dict[str, tuple[str, str]] = {
    "keyframe_translation_m": ("keyframes", "translation_m"),
    "keyframe_rotation_rad": ("keyframes", "rotation_rad"),
    "keyframe_interval_s": ("keyframes", "interval_s"),
    "keyframe_while_exploring": ("keyframes", "while_exploring"),
    "keyframe_without_sightings_m": ("keyframes", "without_sightings_m"),
    "associate_m": ("landmarks", "associate_m"),
    "far_range_m": ("landmarks", "far_range_m"),
    "registration_tolerance_m": ("registration", "inlier_threshold_m"),
    "registration_min_landmarks": ("registration", "registration_min_landmarks"),
    "verified_min_landmarks": ("registration", "verified_min_landmarks"),
    "surface_retry_s": ("registration", "surface_retry_s"),
    "cad_link_m": ("anchor", "cad_link_m"),
    "cad_link_max_turn_deg": ("anchor", "cad_link_max_turn_deg"),
    "surface_turn_deg": ("judge", "surface_turn_deg"),
    "surface_margin": ("judge", "surface_margin"),
    "far_resection": ("far", "far_resection"),
    "degraded_after_s": ("status", "degraded_after_s"),
    "lost_after_s": ("status", "lost_after_s"),
    "relinearize_threshold": ("isam", "relinearize_threshold"),
}


class GraphConfig(_Section):
    """The pose graph and the localizer (graph/posegraph, graph/localizer): the storey, the surface check, and one
    table per component, named as its part of graph.params.LocalizerParams (`[graph.judge]` is `JudgeParams`)."""

    storey_hint: str | None = Field(
        None, description="the storey the vehicle flies on, when the operator knows it (it took off there): "
        "registration then considers only that storey's doors and windows. Storeys built alike are otherwise "
        "told apart only by what differs between them, and the status stays ambiguous until that is seen")
    surface_check: bool = Field(
        True, description="check registrations against the walls: with depth points (stereo), a pose from as "
        "few as [graph.registration] verified_min_landmarks landmarks is taken when it puts most of the points on "
        "the model's surfaces, in sight of the camera, and no other candidate pose does (IFC models; "
        "[graph.judge])")
    line_of_sight: bool = Field(
        True, description="in that check, count against a pose the points it would have the camera see through "
        "a wall or column of the model; turn off for a model whose glass partitions are modelled as walls")
    keyframes: KeyframesConfig = Field(default_factory=lambda: KeyframesConfig(),
                                       description="[graph.keyframes]: which frames become keyframes")
    odometry: GraphOdometryConfig = Field(default_factory=lambda: GraphOdometryConfig(),
                                          description="[graph.odometry]: the odometry between keyframes")
    landmarks: LandmarksConfig = Field(default_factory=lambda: LandmarksConfig(),
                                       description="[graph.landmarks]: sightings into landmarks")
    registration: RegistrationConfig = Field(default_factory=lambda: RegistrationConfig(),
                                             description="[graph.registration]: the map registered to the model")
    anchor: AnchorConfig = Field(default_factory=lambda: AnchorConfig(),
                                 description="[graph.anchor]: landmarks linked to the model once localized")
    judge: JudgeConfig = Field(default_factory=lambda: JudgeConfig(),
                               description="[graph.judge]: the surface check's judgement of candidate poses")
    depth: DepthConfig = Field(default_factory=lambda: DepthConfig(),
                               description="[graph.depth]: the recent keyframes' depth points kept")
    far: FarConfig = Field(default_factory=lambda: FarConfig(),
                           description="[graph.far]: doors and windows beyond the sighting range")
    fit: FitConfig = Field(default_factory=lambda: FitConfig(),
                           description="[graph.fit]: each keyframe fitted to the walls once localized")
    status: StatusConfig = Field(default_factory=lambda: StatusConfig(),
                                 description="[graph.status]: the localized status decaying")
    recovery: RecoveryConfig = Field(default_factory=lambda: RecoveryConfig(),
                                     description="[graph.recovery]: a pose no longer held found again by the walls or "
                                     "the doors")
    isam: IsamConfig = Field(default_factory=lambda: IsamConfig(), description="[graph.isam]: the pose graph's iSAM2")

    @model_validator(mode="after")
    def _window_holds_the_depth_window(self) -> GraphConfig:
        least = self.depth.surface_window_keyframes
        if 0 < self.isam.window_keyframes < least:
            raise ValueError(f"[graph.isam] window_keyframes must be 0 (all kept) or at least {least}, the keyframes "
                             "the surface check reads back ([graph.depth] surface_window_keyframes)")
        return self

    @model_validator(mode="before")
    @classmethod
    def _nest_legacy_keys(cls, data: Any) -> Any:  # noqa: ANN401
        """A flat key of the [graph] section before its tables moves to its table, with one warning line each
        (where both are given, the flat key wins: it came from the environment over a file, or from a flag)."""
        if not isinstance(data, dict) or not LEGACY_GRAPH_KEYS.keys() & data.keys():
            return data
        out = dict(data)
        for old in [k for k in data if k in LEGACY_GRAPH_KEYS]:
            table, key = LEGACY_GRAPH_KEYS[old]
            log.warning("config: [graph] %s is now [graph.%s] %s", old, table, key)
            current = out.get(table) or {}
            if isinstance(current, BaseModel):
                current = current.model_dump()
            out[table] = {**current, key: out.pop(old)} if isinstance(current, dict) else current
        return out


class RosConfig(_Section):
    """ROS 2 through Zenoh (service/ros_out.py): CDR messages on the keys zenoh-bridge-ros2dds maps to ROS topics,
    or on rmw_zenoh's own keys (service/ros_transport.py)."""

    enabled: bool = Field(False, description="also publish ROS 2 messages (pose, odometry, path, tf, status) and take "
                          "a goal on <namespace>/<vehicle>/macroloc/goal; the protobuf keys stay on")
    middleware: Literal["bridge", "rmw_zenoh"] = Field(
        "bridge", description="how ROS topics (and PX4's) travel on Zenoh: 'bridge' on the keys zenoh-bridge-ros2dds "
        "maps (topic /a/b = key a/b); 'rmw_zenoh' as a node of ROS 2's rmw_zenoh_cpp: keys "
        "<domain_id>/a/b/<DDS type>/<RIHS01 hash>, the per-sample attachment and liveliness tokens, so that ROS 2 "
        "machines on the same Zenoh routers see the topics without a bridge")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the rmw_zenoh keys (middleware = rmw_zenoh)")
    namespace: str = Field("", description="ROS namespace before every topic: '' gives /<vehicle>/macroloc/pose and "
                           "/tf (Zenoh keys <vehicle>/macroloc/pose and tf)")
    frame_map: str = Field("map", description="REP-105 map frame id: macroloc's CAD frame")
    frame_odom: str = Field("odom", description="REP-105 odom frame id: macroloc's map (odometry) frame")
    frame_base_link: str = Field("base_link", description="the body frame id (FLU)")
    left_image: str = Field("", description="ROS topic of the left camera's sensor_msgs/Image (or CompressedImage, "
                            "see compressed), e.g. /cam0/image_raw, taken beside macroloc/<vehicle>/stereo; '' = none")
    right_image: str = Field("", description="ROS topic of the right camera's images, paired with the left by stamp")
    left_info: str = Field("", description="ROS topic of the left camera's sensor_msgs/CameraInfo")
    right_info: str = Field("", description="ROS topic of the right camera's CameraInfo (its P gives the baseline)")
    imu: str = Field("", description="ROS topic of sensor_msgs/Imu in the body frame, beside macroloc/<vehicle>/imu")
    odometry: str = Field("", description="ROS topic of the vehicle's nav_msgs/Odometry (a VIO: child base_link FLU in "
                          "its odom frame), taken as the service's odometry beside macroloc/<vehicle>/odometry "
                          "(service/odometry_in.py); '' = none")
    odometry_tf: bool = Field(False, description="take /tf's frame_odom -> frame_base_link (the vehicle's VIO, "
                              "REP-105) as the service's odometry (service/odometry_in.py); not with odom_tf, "
                              "which publishes that link itself")
    initialpose: str = Field("/initialpose", description="ROS topic of Nav2's initial pose (geometry_msgs/"
                             "PoseWithCovarianceStamped in map = CAD, rviz's 2D Pose Estimate), taken as a prior the "
                             "registration must still confirm (graph/prior.py; a storey's name as std_msgs/String on "
                             "<vehicle>/macroloc/storey likewise); '' = none")
    odom_tf: bool = Field(False, description="also publish odom -> base_link on /tf (the odometry's pose); off by "
                          "default as REP-105 asks of a localizer: the vehicle's VIO owns odom -> base_link, macroloc "
                          "publishes map -> odom")
    compressed: bool = Field(False, description="the image topics carry sensor_msgs/CompressedImage (jpeg, png)")
    rectified: bool = Field(False, description="the image topics carry rectified images (image_rect): not remapped")


class Px4Config(_Section):
    """PX4 through its uXRCE-DDS topics on Zenoh (service/px4.py): external vision odometry and offboard setpoints."""

    enabled: bool = Field(False, description="publish fmu/in/vehicle_visual_odometry, and fmu/in/trajectory_setpoint "
                          "with fmu/in/offboard_control_mode while a plan is active")
    namespace: str = Field("", description="PX4's topic namespace for this vehicle, e.g. px4_1 (keys "
                           "px4_1/fmu/in/...); '' for a single vehicle")
    offboard_rate_hz: float = Field(4.0, ge=2.0, description="offboard_control_mode and setpoint rate while a plan "
                                    "is active, Hz (PX4 leaves offboard below 2 Hz)")
    reset_jump_m: float = Field(0.10, gt=0, description="a change of T_cad_map by more than this (a re-localization or"
                                " a jump of the CAD anchor) increments reset_counter, m")
    reset_jump_deg: float = Field(2.0, gt=0, description="... or by more than this rotation, deg")
    reach_m: float = Field(0.5, gt=0, description="the setpoint moves to the next waypoint within this distance, m")
    take_odometry: bool = Field(False, description="take fmu/out/vehicle_odometry (NED/FRD, its reset_counter) as "
                                "the service's odometry (service/odometry_in.py; stamps on PX4's clock). Not while "
                                "EKF2 fuses macroloc's own pose (EKF2_EV_CTRL): its output then holds that pose")


class FoxgloveConfig(_Section):
    """The operator's live view (service/foxglove_live.py): Foxglove's WebSocket server beside the service, off by
    default. Its messages go through a bounded queue that drops the oldest, served by the view's own thread."""

    port: int = Field(0, ge=0, le=65535, description="TCP port of Foxglove's WebSocket server (open "
                      "ws://<host>:<port> in Foxglove with docs/foxglove_layout.json); 0 = no live view")
    host: str = Field("127.0.0.1", description="address the server binds to: loopback by default; 0.0.0.0 (or a "
                      "network interface's address) to watch from another machine")
    image_rate_hz: float = Field(2.0, ge=0, description="left camera images (with the detected boxes) sent at most "
                                 "this often, Hz; 0 = none")
    pose_rate_hz: float = Field(10.0, ge=0, description="poses (with /tf and the covariance) sent at most this often, "
                                "Hz; 0 = none")
    queue_size: int = Field(64, ge=1, description="messages waiting for the view's thread; beyond, the oldest is "
                            "dropped (the service never waits for the view)")


class InputsConfig(_Section):
    """Limits on what the service takes from the wire (service/inputs.py): anything beyond them is dropped,
    counted by key and kind in the diagnostics, and logged once per kind."""

    max_image_pixels: int = Field(
        DEFAULT_MAX_PIXELS, ge=1, le=DEFAULT_MAX_PIXELS, description="an image larger than this (width x height, "
        "read from the PNG/JPEG header before decoding, or declared for raw images) is refused; also caps images read "
        "from files. At most 4096 x 4096: the stereo matcher's and the decoder's own cap (larger pairs can crash "
        "OpenCV's SGBM: docs/measurements.md, \"The image size cap\")")
    max_stereo_bytes: int = Field(128 * 2**20, ge=1, description="largest StereoFrame payload taken, bytes")
    max_message_bytes: int = Field(2**20, ge=1, description="largest payload on the other input keys, bytes")
    max_features: int = Field(256, ge=1, description="most doors/windows in one ObservedFeatures message")
    position_margin_m: float = Field(
        20.0, ge=0, description="positions are plausible within the model's bounding box grown by this (goals, CAD "
        "frame), or within the box's diagonal plus this of the odometry's origin (odometry, map frame), m")
    max_observation_range_m: float = Field(50.0, gt=0, description="farthest sighting in the body/camera frame, m")
    max_accel_mps2: float = Field(160.0, gt=0, description="largest specific force an IMU sample may carry "
                                  "(16 g, a common accelerometer range), m/s^2")
    max_gyro_radps: float = Field(35.0, gt=0, description="largest angular rate (2000 deg/s, a common gyro range), "
                                  "rad/s")
    odometry_max_speed_mps: float = Field(10.0, gt=0, description="a ROS or PX4 odometry pose that moves further "
                                          "than this x dt + 0.25 m from the previous one is a reset of the vehicle's "
                                          "odometry: a new segment, chained at the last pose (service/odometry_in.py), "
                                          "m/s")
    odometry_max_rate_degps: float = Field(400.0, gt=0, description="... or that turns more than this x dt + 10 deg, "
                                           "deg/s")
    clock_reset_s: float = Field(
        2.0, gt=0, description="stamps on a key that go back (or jump ahead) by more than this, in several "
        "consecutive messages that agree among themselves, start a new time base (a vehicle clock reset), s")
    max_clock_ahead_s: float = Field(
        86400.0, gt=0, description="a stamp further than this ahead of this machine's clock is refused (it could "
        "otherwise hold its key shut until restart), s")


class MacrolocConfig(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="MACROLOC_", env_nested_delimiter="__", extra="forbid")

    localize: LocalizeConfig = Field(default_factory=lambda: LocalizeConfig())
    camera: CameraConfig = Field(default_factory=lambda: CameraConfig())
    zenoh: ZenohConfig = Field(default_factory=lambda: ZenohConfig())
    service: ServiceConfig = Field(default_factory=lambda: ServiceConfig())
    planning: PlanningConfig = Field(default_factory=lambda: PlanningConfig())
    sim: SimConfig = Field(default_factory=lambda: SimConfig())
    perception: PerceptionConfig = Field(default_factory=lambda: PerceptionConfig())
    graph: GraphConfig = Field(default_factory=lambda: GraphConfig())
    ros: RosConfig = Field(default_factory=lambda: RosConfig())
    px4: Px4Config = Field(default_factory=lambda: Px4Config())
    foxglove: FoxgloveConfig = Field(default_factory=lambda: FoxgloveConfig())
    inputs: InputsConfig = Field(default_factory=lambda: InputsConfig())

    @classmethod
    def settings_customise_sources(cls, settings_cls, init_settings, env_settings, dotenv_settings,  # noqa: ANN001, ANN206
                                   file_secret_settings):
        """The environment overrides the config file (passed as init values); flags are applied after both."""
        return env_settings, init_settings, dotenv_settings, file_secret_settings


def _merged(base: dict, values: dict) -> dict:
    """`base` with `values` over it, table by table (a [graph.judge] override keeps the table's other keys)."""
    out = dict(base)
    for key, value in values.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_config(path: Path | None = None, **overrides: dict) -> MacrolocConfig:
    """Defaults < file (JSON or TOML) < environment (MACROLOC_<SECTION>__<KEY>) < explicit overrides (one dict
    per section, e.g. from command-line flags)."""
    doc: dict = {}
    if path is not None:
        if not path.exists():
            raise UserInputError(f"config file not found: {path}")
        try:
            doc = tomllib.loads(path.read_text()) if path.suffix == ".toml" else json.loads(path.read_text())
        except (ValueError, tomllib.TOMLDecodeError) as exc:
            raise UserInputError(f"config file {path} is not valid {path.suffix[1:] or 'JSON'}: {exc}") from None
    try:
        cfg = MacrolocConfig(**doc)
        for section, values in overrides.items():
            current = getattr(cfg, section)
            setattr(cfg, section, type(current).model_validate(_merged(current.model_dump(), values)))
        return cfg
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise UserInputError(f"config: {where}: {first['msg']}") from None
