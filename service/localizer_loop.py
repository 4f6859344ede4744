"""The localizer loop: the per-frame loop around `graph.localizer.Localizer` that `serve`, `replay`, `demo`
and the benchmarks all run, and the one factory that builds it from the config.

Its inputs, in the order they come: `imu(accel)` (the IMU's specific forces), `odometry(stamp, T_odom_body)` (each
odometry pose: with the IMU samples since the previous one it gives gravity's up, `up_body`, by one rule:
perception.gravity.ImuGravity) and `frame(FrameIn)` (one frame: odometry pose, sightings, depth points,
seconds dead-reckoned, a place-recognition result), which returns the `Estimate`. It owns what makes the figures:
gravity's up, the keyframe rule (`graph.keyframes.KeyframeRule`), the depth hand-over to the next keyframe, the
dead-reckoned seconds summed until a keyframe takes them, the hand-off of a frame placed in a saved map (or whose
view is kept: always a keyframe), and a fresh graph where an update fails. Its one caller is the per-frame front
end (service.front_end), which `serve` and `replay` both run: it assembles the frames from the vehicle's events
(odometry by stamp, sightings waiting for their odometry, stereo frames perceived) and reads `up_body` for the
perception chain and place recognition, which run before the frame is handed in. ("Session" is Zenoh's word here.)

Frames: odom = the vehicle's odometry frame (the localizer's map frame), body, cad. Metres, nanoseconds.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.keyframes import KeyframeRule
from macroloc.graph.localizer import Estimate, Localizer, LocalizerParams, Sighting, model_registrar
from macroloc.graph.posegraph import IsamSettings, PoseGraph
from macroloc.graph.registrar import Registrar
from macroloc.graph.surfaces import SurfaceIndex
from macroloc.perception.gravity import ImuGravity
from macroloc.perception.params import GravityParams
from macroloc.service.places import Placed

if TYPE_CHECKING:
    from macroloc.service.config import GraphConfig, MacrolocConfig
    from macroloc.service.saved_map import SavedMap

log = logging.getLogger(__name__)


@dataclass
class FrameIn:
    """One frame's inputs. T_odom_body: 4x4 odometry pose at `stamp_ns`; sightings: corners in the body frame;
    points_body: (N, 3) depth points, body frame, measured at this frame; up_body: gravity's up, body frame, where
    the driver knows it otherwise than from the IMU (the simulator's truth), else None: the loop's own
    (`LocalizerLoop.up_body`); dead_reckoned_s: seconds since the previous frame the odometry only
    extrapolated; placed: the frame's pose in a saved map and/or its view to keep (service.places); measure_depth:
    this frame's depth points (N, 3, body frame), measured when called: called only where the frame becomes a
    keyframe."""

    stamp_ns: int
    T_odom_body: np.ndarray
    sightings: list[Sighting] = field(default_factory=list)
    up_body: np.ndarray | None = None
    points_body: np.ndarray | None = None
    dead_reckoned_s: float = 0.0
    placed: Placed | None = None
    measure_depth: Callable[[], np.ndarray] | None = None


@dataclass(frozen=True)
class PoseSnapshot:
    """The newest keyframe's estimate and odometry pose, replaced whole after each keyframe: `at` gives what
    `LocalizerLoop.frame` gives a frame between keyframes, from any thread, without the localizer."""

    estimate: Estimate  # the localizer's track() at the keyframe itself
    T_odom_kf: np.ndarray  # the keyframe's odometry pose
    covariance: np.ndarray | None  # the keyframe's (what a tracked pose carries)

    def at(self, stamp_ns: int, T_odom_body: np.ndarray) -> Estimate:
        e = self.estimate
        T_map_body = e.T_map_body @ np.linalg.inv(self.T_odom_kf) @ T_odom_body
        return Estimate(stamp_ns, e.status, T_map_body, None if e.T_cad_map is None else e.T_cad_map @ T_map_body,
                        e.T_cad_map, self.covariance, e.inliers, e.keyframe, matches=e.matches)


@dataclass(frozen=True)
class LoopSettings:
    """Typed arguments of a localizer loop's components, read from the config by `settings_from_config`."""

    localizer: LocalizerParams = field(default_factory=LocalizerParams)
    rule: KeyframeRule = field(default_factory=KeyframeRule)
    isam: IsamSettings = field(default_factory=IsamSettings)
    storey_hint: str | None = None  # register against this storey's doors and windows only
    method: str = "robust"  # the registration's search (graph.registration)
    covariance: bool = False  # each keyframe's marginal covariance (iSAM2), carried by the poses until the next
    gravity: GravityParams = field(default_factory=GravityParams)  # gravity's up from the IMU ([perception.gravity])


class LocalizerLoop:
    """See module doc. One thread only."""

    def __init__(self, localizer: Localizer, rule: KeyframeRule | None = None, covariance: bool = False,
                 fresh: Callable[[Localizer], Localizer] | None = None, gravity: GravityParams | None = None) -> None:
        """`fresh`: a new localizer like the failed one given (its registrar kept), where the graph fails;
        `gravity`: the IMU's up estimate's parameters."""
        self.localizer = localizer
        self.gravity = ImuGravity(gravity)
        self.fresh = fresh or _fresh
        self.rule = rule or KeyframeRule()
        self.covariance = covariance
        self.last: Estimate | None = None  # the newest estimate by stamp (a late keyframe moves it: `_remember`)
        self._T_odom_last: np.ndarray | None = None  # its odometry pose
        self.keyframe = False  # whether the last frame became a keyframe
        self.restarts = 0  # times the pose graph failed (indeterminate, non-finite) and started afresh
        self._T_kf: np.ndarray | None = None  # the last keyframe's odometry pose
        self._stamp_kf_ns: int | None = None
        self._dead_reckoned_s = 0.0  # since the last keyframe
        self._kf_covariance: np.ndarray | None = None  # 6x6 [rot; trans], body tangent (graph.posegraph)
        self.snapshot: PoseSnapshot | None = None  # after each keyframe (None before the first, after a restart)

    @property
    def status(self) -> str:
        return self.localizer.status

    @property
    def up_body(self) -> np.ndarray | None:
        """Gravity's up (unit, body frame) at the newest odometry pose, from the IMU; None where unknown."""
        return self.gravity.up_body

    def imu(self, accel_body_mps2: np.ndarray) -> None:
        """IMU specific forces ((3,) or (K, 3), body frame, m/s^2) measured since the last odometry pose."""
        self.gravity.imu(accel_body_mps2)

    def odometry(self, stamp_ns: int, T_odom_body: np.ndarray) -> np.ndarray | None:
        """An odometry pose (4x4, odometry frame), before the frames at it: with the IMU samples since the previous
        one it gives gravity's up (perception.gravity.ImuGravity's rule), returned."""
        return self.gravity.odometry(stamp_ns, T_odom_body)

    def frame(self, f: FrameIn) -> Estimate:
        """The frame's estimate: a keyframe where the rule says so (or the frame was placed, or keeps a view),
        else the last keyframe's estimate moved by the odometry (its sightings and depth wait for the next)."""
        if f.points_body is not None:
            self.add_depth(f.T_odom_body, f.points_body)  # given with the next keyframe
        self._dead_reckoned_s += f.dead_reckoned_s
        if self.keyframe_due(f.stamp_ns, f.T_odom_body, bool(f.sightings), f.placed):
            if f.measure_depth is not None:  # only now: a keyframe takes the newest depth, no other frame's is used
                self.add_depth(f.T_odom_body, f.measure_depth())
            return self._keyframe(f)
        return self._track(f.stamp_ns, f.T_odom_body, f.sightings)

    def keyframe_due(self, stamp_ns: int, T_odom_body: np.ndarray, has_sightings: bool,
                     placed: Placed | None = None) -> bool:
        """Whether a frame at T_odom_body (4x4, odometry frame) and stamp_ns is a keyframe (see `frame`)."""
        if placed is not None and (placed.T_cad_body is not None or placed.view is not None):
            return True
        dt_s = np.inf if self._stamp_kf_ns is None else (stamp_ns - self._stamp_kf_ns) * 1e-9
        return self.rule.is_keyframe(self._T_kf, T_odom_body, dt_s, has_sightings, self.status == "localized")

    def pose_at(self, stamp_ns: int, T_odom_body: np.ndarray) -> Estimate:
        """The pose at an odometry pose, never a keyframe (but the first)."""
        if self.localizer.graph.n_keyframes == 0:
            return self._keyframe(FrameIn(stamp_ns, T_odom_body))
        return self._track(stamp_ns, T_odom_body, [])

    def add_depth(self, T_odom_body: np.ndarray, points_body: np.ndarray) -> None:
        """Depth points (N, 3, body frame) measured at T_odom_body, for the next keyframe (graph.surfaces)."""
        if len(points_body):
            self.localizer.add_depth(T_odom_body, points_body)

    def new_time_base(self) -> None:
        """The clock was reset: the keyframe timer and gravity's history start again (the graph and its poses
        stay)."""
        self._stamp_kf_ns = None
        self.gravity.new_time_base()

    def _keyframe(self, f: FrameIn) -> Estimate:
        self.keyframe = True
        self._T_kf, self._stamp_kf_ns = f.T_odom_body, f.stamp_ns
        dead_reckoned_s, self._dead_reckoned_s = self._dead_reckoned_s, 0.0
        placed = f.placed or Placed(None, None)
        try:
            up_body = f.up_body if f.up_body is not None else self.up_body
            est = self.localizer.add_keyframe(f.stamp_ns, f.T_odom_body, f.sightings, up_body,
                                              with_covariance=self.covariance, T_cad_body_placed=placed.T_cad_body,
                                              view=placed.view, dead_reckoned_s=dead_reckoned_s)
        except RuntimeError as exc:  # GTSAM's IndeterminantLinearSystemException and its kin
            return self._restart(f.stamp_ns, f"the update failed ({str(exc).splitlines()[0][:120]})")
        if not _finite(est):
            return self._restart(f.stamp_ns, "the estimate is not finite")
        self._kf_covariance = est.covariance
        self.snapshot = PoseSnapshot(self.localizer.track(f.stamp_ns, f.T_odom_body), f.T_odom_body, est.covariance)
        return self._remember(est, f.T_odom_body, graph_changed=True)

    def _track(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting]) -> Estimate:
        self.keyframe = False
        est = self._tracked(stamp_ns, T_odom_body, sightings)
        if not _finite(est):
            return self._restart(stamp_ns, "the tracked pose is not finite")
        return self._remember(est, T_odom_body)

    def _tracked(self, stamp_ns: int, T_odom_body: np.ndarray, sightings: list[Sighting]) -> Estimate:
        """The last keyframe's estimate moved by the odometry to T_odom_body, with the keyframe's covariance where
        the localizer gives none (the odometry since adds little over a keyframe interval)."""
        est = self.localizer.track(stamp_ns, T_odom_body, sightings)
        if est.covariance is None:
            est.covariance = self._kf_covariance
        return est

    def _restart(self, stamp_ns: int, why: str) -> Estimate:
        """The pose graph cannot go on: a fresh one (this flight's landmarks are lost; a saved map's place
        recognition stays), LOST for this stamp, localized again from what comes next."""
        self.restarts += 1
        log.error("pose graph restarted (%d so far): %s", self.restarts, why)
        self.localizer = self.fresh(self.localizer)
        self._T_kf, self._stamp_kf_ns, self._kf_covariance, self._dead_reckoned_s = None, None, None, 0.0
        self.snapshot = None
        self.last, self._T_odom_last = Estimate(stamp_ns, "lost", np.eye(4)), None
        return self.last

    def _remember(self, est: Estimate, T_odom_body: np.ndarray, graph_changed: bool = False) -> Estimate:
        """`last` is the newest estimate by stamp. A keyframe older than it (a stereo frame perceived after newer
        odometry came) does not replace it, but moves it: the newest pose is tracked again on the graph the
        keyframe changed, so that what is read of `last` (the plan's start, the saved map's pose) is localized as
        soon as the graph is."""
        if self.last is None or est.stamp_ns >= self.last.stamp_ns:
            self.last, self._T_odom_last = est, T_odom_body
        elif graph_changed and self._T_odom_last is not None:
            newest = self._tracked(self.last.stamp_ns, self._T_odom_last, [])
            if _finite(newest):
                self.last = newest
        return est


def _fresh(old: Localizer) -> Localizer:
    """A new localizer like `old`: its model, registrar, parameters, iSAM2 settings, camera position and walls."""
    T_body_cam = np.eye(4)
    T_body_cam[:3, 3] = old.viewer_body
    new = Localizer(old.model, PoseGraph(old.graph.settings), old.registrar, old.params, T_body_cam, old.surfaces)
    new.set_prior(old.anchoring.prior)  # the operator's prior outlives a failed graph
    return new


def _finite(est: Estimate) -> bool:
    return all(m is None or bool(np.isfinite(m).all()) for m in (est.T_map_body, est.T_cad_body, est.T_cad_map))


# --- the factory ------------------------------------------------------------------------------------------------


def settings_from_config(graph: GraphConfig, *, storey_hint: str | None = None, method: str = "robust",
                         covariance: bool = False) -> LoopSettings:
    """The factory's half that reads the config's [graph] section: typed arguments for the components, each
    [graph.<part>] table its part of `LocalizerParams`, [graph.keyframes] the `KeyframeRule`, [graph.isam] the
    `IsamSettings`. `storey_hint`: a checked one (BuildingModel.checked_storey), else the section's own."""
    return LoopSettings(graph.localizer_params(), graph.keyframes, graph.isam,
                           storey_hint if storey_hint is not None else graph.storey_hint, method, covariance)


def make_localizer(model: BuildingModel, storey_hint: str | None = None, T_body_cam: np.ndarray | None = None,
                   params: LocalizerParams | None = None, isam: IsamSettings | None = None,
                   surfaces: SurfaceIndex | None = None, registrar: Registrar | None = None,
                   method: str = "robust") -> Localizer:
    """Registration against the whole model (or `registrar`); with the model's surfaces, registrations are checked
    against the depth points (graph.surfaces)."""
    p = params or LocalizerParams()
    if registrar is None:
        registrar = model_registrar(model, p.registration, storey_hint, surfaces is not None, method)
    return Localizer(model, PoseGraph(isam), registrar, params, T_body_cam=T_body_cam, surfaces=surfaces)


def make_loop(model: BuildingModel, settings: LoopSettings | None = None, *,
                 surfaces: SurfaceIndex | None = None, T_body_cam: np.ndarray | None = None,
                 registrar: Registrar | None = None) -> LocalizerLoop:
    """A localizer loop from typed settings (`loop_from_config` reads them from the config). `registrar`: instead
    of the whole model's (e.g. service.front_end's after a restart from a saved map)."""
    s = settings or LoopSettings()
    localizer = make_localizer(model, s.storey_hint, T_body_cam, s.localizer, s.isam, surfaces, registrar,
                               s.method)

    def fresh(old: Localizer) -> Localizer:
        return Localizer(model, PoseGraph(s.isam), old.registrar, s.localizer, T_body_cam, surfaces)

    return LocalizerLoop(localizer, s.rule, s.covariance, fresh, s.gravity)


def loop_from_config(cfg: MacrolocConfig, model: BuildingModel, *,
                        saved: SavedMap | None = None, surfaces: SurfaceIndex | None = None,
                        T_body_cam: np.ndarray | None = None,
                        registrar: Callable[[LoopSettings], Registrar] | None = None,
                        storey_hint: str | None = None, method: str | None = None,
                        covariance: bool = False) -> LocalizerLoop:
    """THE factory: a localizer loop from the whole config in `model`, what `serve`, `replay`, `demo` and the benchmarks
    run ([graph] for the localizer, [perception.gravity] for gravity's up from the IMU, [localize] method for the
    registration's search). `saved`: the saved map to start from (service.saved_map); `surfaces`: the model's
    walls, for the surface check; `T_body_cam`: the left camera in the body frame; `registrar`: makes the
    registrar from the settings instead of the model's (or the saved map's); `storey_hint`: instead of
    graph.storey_hint (checked against the model: UserInputError where it has no such storey); `method`: instead
    of localize.method."""
    storey = model.checked_storey(storey_hint or cfg.graph.storey_hint)
    settings = settings_from_config(cfg.graph, storey_hint=storey, method=method or cfg.localize.method,
                                    covariance=covariance)
    settings = replace(settings, gravity=cfg.perception.gravity)
    if saved is not None:
        registrar = saved.registrar(model, with_surfaces=surfaces is not None)
    return make_loop(model, settings, surfaces=surfaces, T_body_cam=T_body_cam,
                        registrar=None if registrar is None else registrar(settings))
