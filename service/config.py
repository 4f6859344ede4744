"""The one typed configuration of macroloc: defaults here, overridable by a JSON/TOML file, environment
variables (MACROLOC_<SECTION>__<KEY>, e.g. MACROLOC_ZENOH__MODE=client) and command-line flags.

A component's parameters are declared once, as the fields of its frozen dataclass (graph/params.py,
perception/params.py, graph/keyframes.py: each with its default, bounds and description, `common.parameters.param`),
and that dataclass IS its config table: `[graph.judge]` is a `JudgeParams`, `[perception.odometry]` a
`VisualOdometryParams`; pydantic checks a table's keys against the fields' bounds and refuses any other key. The
keys declared here are the service's own (its process, transports, the simulator) and the choices no component
takes as a parameter (`[localize] method`, `[graph] storey_hint`). Components never read this object: factories
in `service/` hand each component its own parameters. `macroloc dump-config` prints the resolved configuration.
"""

from __future__ import annotations

import json
import logging
import tomllib
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from macroloc.common.parameters import param
from macroloc.graph.errors import UserInputError
from macroloc.graph.keyframes import KeyframeRule
from macroloc.graph.params import (
    AnchorParams,
    DepthWindowParams,
    FarParams,
    IsamSettings,
    JudgeParams,
    LandmarkParams,
    LocalizerParams,
    OdometryFactorParams,
    RecoveryParams,
    RegistrationParams,
    RobustParams,
    StatusParams,
    SurfaceFitParams,
)
from macroloc.perception.image_header import DEFAULT_MAX_PIXELS
from macroloc.perception.params import (
    DepthPointsParams,
    GravityParams,
    InertialParams,
    LineParams,
    PerceptionParams,
    PlaceParams,
    PlausibilityParams,
    ProposalParams,
    SgbmParams,
    SizeTolerance,
    VisualOdometryParams,
    WallPlaneParams,
)

log = logging.getLogger(__name__)


def _over_default(default: object, values: object) -> object:
    """`values` (a table's keys, a dict) over `default` (a parameter dataclass): the default's other fields kept,
    nested tables likewise; anything else as given (pydantic checks it)."""
    if not (is_dataclass(default) and isinstance(values, dict)):
        return values
    out: dict[str, object] = {f.name: getattr(default, f.name) for f in fields(default)}
    for key, value in values.items():
        out[key] = _over_default(out[key], value) if key in out else value
    return out


class _Section(BaseModel):
    """A config section: a misspelt key is refused with its name, never silently ignored. A table that is a
    component's parameter dataclass, given in part, keeps its default's other values (the section's default, which
    may differ from the dataclass's own: `[perception.stereo]` searches 128 disparities, `SgbmParams()` 64)."""

    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="before")
    @classmethod
    def _tables_over_their_defaults(cls, data: Any) -> Any:  # noqa: ANN401
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for key, f in cls.model_fields.items():
            if isinstance(out.get(key), dict) and is_dataclass(f.annotation):
                out[key] = _over_default(f.get_default(call_default_factory=True), out[key])
        return out


@dataclass(frozen=True)
class LocalizeConfig(RobustParams):
    """One-shot registration of observed macro-features to the CAD model (graph/registration): `macroloc localize
    --config FILE` reads the robust method's keys (graph.params.RobustParams, whose fields they are); `macroloc
    serve` reads `method` (its pose graph registers with the [graph.registration] keys)."""

    method: Literal["robust", "paper"] = param("robust", "'paper' = the paper's algorithm exactly")

    def robust_params(self) -> RobustParams:
        """The robust method's parameters (graph.registration.register(method='robust', params=...)): this
        section's keys but `method`."""
        return RobustParams(**{f.name: getattr(self, f.name) for f in fields(RobustParams)})


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
    odometry: Literal["vehicle", "visual"] = Field(
        "vehicle", description="where the odometry comes from: 'vehicle' (its odometry key, or the ROS/PX4 topic of "
        "[ros]/[px4]) or 'visual' (the stereo visual odometry on the frames and the IMU: service.visual_odometry)")
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


_PERCEPTION, _LOCALIZER = PerceptionParams(), LocalizerParams()  # the components' defaults, the tables' defaults


class PerceptionConfig(_Section):
    """The perception chain (perception/): which door/window detector, on which frames it runs, and one table per
    component, each its part of perception.params.PerceptionParams (`[perception.lines]` is `LineParams`)."""

    detector_model: Path | None = Field(None, description="detector ONNX file with its JSON sidecar beside it; "
                                        "default: the shipped perception/models/detector.onnx (trained on real "
                                        "photos). A detector adapted to one building is trained on renders of its "
                                        "model: python -m macroloc.perception.train --sim FOLDER --out DIR")
    detect_every: int = Field(1, ge=1, description="serve and replay: the chain runs on every n-th stereo "
                              "frame (service.front_end)")
    stereo: SgbmParams = Field(default_factory=lambda: _PERCEPTION.stereo,
                               description="[perception.stereo]: the frame's stereo matching")
    lines: LineParams = Field(default_factory=lambda: _PERCEPTION.lines,
                              description="[perception.lines]: the openings' sides from line segments")
    plausibility: PlausibilityParams = Field(default_factory=lambda: _PERCEPTION.plausibility,
                                             description="[perception.plausibility]: a door's or window's limits")
    wall_plane: WallPlaneParams = Field(default_factory=lambda: _PERCEPTION.wall_plane,
                                        description="[perception.wall_plane]: the wall an opening sits in")
    odometry: VisualOdometryParams = Field(default_factory=lambda: _PERCEPTION.odometry,
                                           description="[perception.odometry]: the stereo visual odometry, where "
                                           "[service] odometry = visual")
    gravity: GravityParams = Field(default_factory=lambda: _PERCEPTION.gravity,
                                   description="[perception.gravity]: gravity's up from the IMU, in the service and a "
                                   "replay alike")
    depth: DepthPointsParams = Field(default_factory=lambda: _PERCEPTION.depth,
                                     description="[perception.depth]: the depth points for the walls' checks")
    place: PlaceParams = Field(default_factory=lambda: _PERCEPTION.place,
                               description="[perception.place]: keyframes placed in a saved map's views")
    inertial: InertialParams = Field(default_factory=lambda: _PERCEPTION.inertial,
                                     description="[perception.inertial]: the visual odometry's dead reckoning on "
                                     "the IMU where it loses track")
    proposals: ProposalParams = Field(default_factory=lambda: _PERCEPTION.proposals,
                                      description="[perception.proposals]: doors proposed from geometry (perceive)")
    size_check: SizeTolerance = Field(default_factory=lambda: _PERCEPTION.size_check,
                                      description="[perception.size_check]: an opening's size against the "
                                      "model's (perceive)")

    def to_params(self) -> PerceptionParams:
        """The chain's parameters: each table is its part of `PerceptionParams`."""
        return PerceptionParams(**{f.name: getattr(self, f.name) for f in fields(PerceptionParams)})


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
    table per component, its part of graph.params.LocalizerParams (`[graph.judge]` is `JudgeParams`), with the
    keyframe rule (graph.keyframes.KeyframeRule) and the pose graph's iSAM2 (graph.params.IsamSettings)."""

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
    keyframes: KeyframeRule = Field(default_factory=KeyframeRule,
                                    description="[graph.keyframes]: which frames become keyframes, the service and "
                                    "replay alike (service/localizer_loop.py)")
    odometry: OdometryFactorParams = Field(default_factory=lambda: _LOCALIZER.odometry,
                                           description="[graph.odometry]: the odometry between keyframes")
    landmarks: LandmarkParams = Field(default_factory=lambda: _LOCALIZER.landmarks,
                                      description="[graph.landmarks]: sightings into landmarks")
    registration: RegistrationParams = Field(default_factory=lambda: _LOCALIZER.registration,
                                             description="[graph.registration]: the map registered to the model")
    anchor: AnchorParams = Field(default_factory=lambda: _LOCALIZER.anchor,
                                 description="[graph.anchor]: landmarks linked to the model once localized")
    judge: JudgeParams = Field(default_factory=lambda: _LOCALIZER.judge,
                               description="[graph.judge]: the surface check's judgement of candidate poses")
    depth: DepthWindowParams = Field(default_factory=lambda: _LOCALIZER.depth,
                                     description="[graph.depth]: the recent keyframes' depth points kept")
    far: FarParams = Field(default_factory=lambda: _LOCALIZER.far,
                           description="[graph.far]: doors and windows beyond the sighting range")
    fit: SurfaceFitParams = Field(default_factory=lambda: _LOCALIZER.fit,
                                  description="[graph.fit]: each keyframe fitted to the walls once localized")
    status: StatusParams = Field(default_factory=lambda: _LOCALIZER.status,
                                 description="[graph.status]: the localized status decaying")
    recovery: RecoveryParams = Field(default_factory=lambda: _LOCALIZER.recovery,
                                     description="[graph.recovery]: a pose no longer held found again by the walls or "
                                     "the doors")
    isam: IsamSettings = Field(default_factory=IsamSettings, description="[graph.isam]: the pose graph's iSAM2")

    def localizer_params(self) -> LocalizerParams:
        """The localizer's parameters: each of its parts is the table of the same name."""
        return LocalizerParams(**{f.name: getattr(self, f.name) for f in fields(LocalizerParams)})

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
            if is_dataclass(current):
                current = {f.name: getattr(current, f.name) for f in fields(current)}
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

    localize: LocalizeConfig = Field(default_factory=LocalizeConfig)
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
            adapter: TypeAdapter[Any] = TypeAdapter(type(getattr(cfg, section)))
            setattr(cfg, section, adapter.validate_python(_merged(adapter.dump_python(getattr(cfg, section)), values)))
        return cfg
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        # a parameter dataclass's unknown key reads as a section's
        msg = "Extra inputs are not permitted" if first["type"] == "unexpected_keyword_argument" else first["msg"]
        raise UserInputError(f"config: {where}: {msg}") from None
