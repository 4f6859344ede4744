"""The localizer's parameters: one small frozen dataclass per component, composed in `LocalizerParams`. Each
component receives its own (the judge `JudgeParams`, the far sightings `FarParams`, ...), never the whole set.

Each parameter is declared here once, as a field with its default, bounds and description
(`common.parameters.param`), and each dataclass is a config table of the service's (service/config.py) as it
is: `[graph.judge] surface_margin` is `JudgeParams.surface_margin`, in the [graph] section's table named as the
`LocalizerParams` field; `[localize]` is `RobustParams`. A new parameter is one line here; its key, its check,
docs/configuration.md and `macroloc dump-config` follow. They live in this one leaf module (numpy only) so that
the config takes them without importing the components (graph.judge pulls in scipy); the components re-export
theirs (`from macroloc.graph.judge import JudgeParams`). Metres, seconds, degrees where named so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, TypeVar

import numpy as np

from macroloc.common.parameters import Parameters, param, table

Ranges = TypeVar("Ranges", float, np.ndarray)


@dataclass(frozen=True)
class OdometryFactorParams(Parameters):
    """The odometry factor between consecutive keyframes (the localizer's prediction)."""

    odometry_sigma_per_m: float = param(
        0.03, "the odometry's translation sigma per metre travelled (its drift), m/m", gt=0)
    odometry_rot_sigma_per_m: float = param(0.01, "its rotation sigma per metre travelled, rad/m", gt=0)
    odometry_dead_reckoned_sigma_mps: float = param(
        0.5, "translation sigma per second the odometry lost track and only extrapolated (a drone's speed it could not "
        "see change), m/s", gt=0)


@dataclass(frozen=True)
class LandmarkParams(Parameters):
    """Sightings into landmarks (graph.landmarks): association, range, and the sighting factor's sigmas."""

    associate_m: float = param(
        0.6, "a sighting this close to a landmark facing alike re-observes it, whatever type it was called, m")
    sighting_sigma_m: tuple[float, float] = param(
        (0.03, 0.004), "a sighting's position sigma is a + b * range^2 (stereo), [a m, b 1/m]")
    sighting_sigma_rad: tuple[float, float] = param(
        (0.03, 0.012), "... its orientation's (the plane of noisy corners), [a rad, b rad/m^2]")
    truncated_sigma_m: float = param(
        0.5, "position sigma along an axis on which the sighting is cut by the image border, m", gt=0)
    max_range_m: float = param(7.0, "sightings further away make no landmark: their corners are too coarse, m", gt=0)
    one_factor_per_keyframe: bool = param(
        True, "the frames carried into a keyframe add one factor per landmark, their mean (graph.landmark_map): their "
        "errors are shared, so a factor per frame makes the graph as much surer of a door as the camera's frame rate "
        "is high (docs/measurements.md, \"Issue 56: the service's accuracy mended\")")
    far_range_m: float = param(
        20.0, "doors and windows seen beyond the 7 m sighting range, up to this range, check candidate poses by their "
        "bearings and, before any door came within range, resect the pose, m (their stereo range is coarse, their "
        "bearing good to a fraction of a degree)", ge=0)

    def position_sigma_m(self, range_m: Ranges) -> Ranges:
        """A sighting's position sigma at a range (stereo: it grows with range squared, `sighting_sigma_m`),
        metres; of each of an array of ranges too."""
        a, b = self.sighting_sigma_m
        return a + b * range_m**2


@dataclass(frozen=True)
class RegistrationParams(Parameters):
    """When and how the map's landmarks are registered to the model (the registrar, graph.registrar)."""

    min_sightings_to_register: int = param(
        2, "a landmark takes part in registration once seen from this many keyframes (one sighting may be a passing "
        "false detection, and the frames of one keyframe see it from one place: graph.sightings.Landmark.n_keyframes)",
        ge=1)
    # an aligned landmark this close to a same-type CAD feature supports a pose: the registrar's inlier and ambiguity
    # tolerance (RobustParams.inlier_threshold_m and ambiguity_tau_m), the judge's turns' too
    inlier_threshold_m: float = param(
        0.6, "an aligned landmark this close to a same-type CAD feature supports the pose (the registration's inlier "
        "and ambiguity tolerance, as [localize] inlier_threshold_m is the one-shot localize's), m (perception's "
        "landmarks lie 0.1-0.5 m off their feature: a tighter tolerance leaves the right pose too few inliers to beat "
        "its rivals)", gt=0)
    registration_min_landmarks: int = param(  # the model registrar answers 'localized' from this many landmarks ...
        4, "registration is tried once this many landmarks have been seen twice, and a pose must explain as many. With "
        "gravity two doors fix a pose, but at the tolerance above a building of a hundred alike doors offers chance "
        "fits of three landmarks (docs/measurements.md, \"Registration from three landmarks\")", ge=2)
    verified_min_landmarks: int = param(
        1, "with the surface check ([graph] surface_check), candidate poses are weighed from this many landmarks. From "
        "one door or window (gravity known) they are every alike feature of the model, seen from either side; the "
        "walls must single one out", ge=1)
    registration_early_stop: float = param(
        1.0, "with the surface check, hypotheses stop being seeded once a pose explains this fraction of the landmarks "
        "(1: never)", gt=0, le=1)
    surface_retry_s: float = param(  # with no new landmark, the check is retried this often as the walls come in view
        1.0, "while not localized and no new landmark came, the walls weigh the candidate poses again this often as "
        "more of them is seen, s (each check costs 0.1-0.4 s of CPU on a 2-core machine)", gt=0)


@dataclass(frozen=True)
class AnchorParams(Parameters):
    """Holding the graph to the model once localized: landmarks linked to CAD features, keyframes placed in a
    saved map."""

    cad_link_m: float = param(0.5, "once localized, a landmark this close to a CAD feature is linked, m")
    cad_link_max_turn_deg: float = param(
        8.0, "... by its orientation too where that lies within this of the CAD feature's, deg (else by its position "
        "only: a door's plane from its corners can be far off on a door seen obliquely, and would turn the flight to "
        "fit it)", ge=0)
    placed_sigma_m: float = param(
        0.15, "a keyframe placed in a saved map (place recognition): its position sigma in the model, m (the saved "
        "keyframe's error and PnP's together)", gt=0)
    placed_sigma_deg: float = param(  # the CAD frame, the saved keyframe's error and PnP's together
        2.0, "... its orientation sigma, deg", gt=0)


@dataclass(frozen=True)
class DepthWindowParams(Parameters):
    """How many recent keyframes' depth points (graph.depth_window) and far sightings (graph.far_window) are kept."""

    surface_window_keyframes: int = param(
        60, "the depth points of this many recent keyframes check a registration and find a pose again; [graph.isam] "
        "window_keyframes keeps at least as many", ge=1)


@dataclass(frozen=True)
class FarParams(Parameters):
    """The doors and windows seen beyond the sighting range (graph.far_window.FarSightings)."""

    far_bearing_deg: float = param(
        3.0, "a far sighting is explained where a same-type CAD feature lies within this horizontal bearing of it, "
        "seen from the keyframe's camera (and 3 sigmas of its range), deg", gt=0)
    far_elevation_deg: float = param(  # ... and within this of its elevation (a one-door candidate's height is coarse)
        5.0, "... and within this of its elevation, deg", gt=0)
    far_turn_deg: float = param(2.0, "... turning the candidate pose by up to this to do so, deg", ge=0)
    far_turn_step_deg: float = param(  # (its heading, from a door or two and the walls, is ~2 deg off)
        0.5, "... in these steps, deg", gt=0)
    far_min_sightings: int = param(
        10, "with this many far sightings in the window, a candidate pose explaining ...", ge=1)
    far_min_explained: float = param(
        0.8, "... at least this fraction of them is not rivalled by one explaining ...", ge=0, le=1)
    far_margin: float = param(  # this much less (the surfaces' margin aside)
        0.4, "... this fraction less", ge=0)
    far_resection: bool = param(
        True, "before any door came within the sighting range, candidate poses from two far doors or windows seen at "
        "least 10 deg apart from one keyframe, for the walls to choose among")
    far_pair_min_deg: float = param(
        10.0, "far_resection: the two far features at least this far apart in bearing, deg", gt=0)
    far_pairs: int = param(
        3, "... from this many of the newest keyframes that saw such a pair (the widest pair of each)", ge=1)
    far_resection_sightings: int = param(
        60, "the resected candidates are judged by this many far sightings, evenly drawn", ge=1)
    far_place_m: float = param(
        1.0, "one resected candidate per place this size; a pair whose ranges leave the camera more than this to move "
        "resects none, m", gt=0)
    far_height_sigma_m: float = param(
        0.2, "the pose taken from far sightings holds the keyframe's height with this sigma, m ...", gt=0)
    far_bearing_sigma_deg: float = param(0.5, "... and is fitted to the far bearings with this one, deg", gt=0)


@dataclass(frozen=True)
class JudgeParams(Parameters):
    """The walls' judgement of candidate poses (graph.judge.SurfaceJudge)."""

    surface_min_points: int = param(
        200, "fewer depth points than this: no check (the registration needs [graph.registration] "
        "registration_min_landmarks)", ge=1)
    surface_min_support: float = param(
        0.9, "a pose must put this fraction of the depth points on the model's surfaces", ge=0, le=1)
    # ... and every other candidate pose this much less (of points on surfaces and in sight, with the model's walls:
    # SurfaceCheck.score) ...
    surface_margin: float = param(
        0.3, "a candidate pose is taken only where every different candidate scores this much less (the fraction of "
        "the depth points on the model's surfaces and in sight); a smaller margin localizes sooner and risks a wrong "
        "pose where the building repeats itself", ge=0)
    surface_margin_unfit: float = param(
        0.15, "... or this much less where that other pose does not fit the walls itself (candidates from two "
        "landmarks or more)", ge=0)
    surface_max_seen_through: float = param(
        0.1, "... and let at most this fraction be seen through a wall ([graph] line_of_sight)", ge=0, le=1)
    surface_refuse_seen_through: float = param(
        0.25, "a registrar's own answer is refused where more than this fraction is seen through a wall", ge=0, le=1)
    surface_refine_m: float = param(
        0.6, "each candidate pose is first fitted to the walls, moving the points at most this, m", ge=0)
    surface_screen_top: int = param(
        8, "of more candidates (one door: every alike door of the model, from both sides), only the best this many are "
        "fitted and checked ...", ge=1)
    surface_screen_points: int = param(
        200, "... screened by this many depth points, unfitted", ge=1)
    surface_turn_deg: float = param(
        24.0, "a candidate pose from one to three doors is first turned about one of them, within this, to the heading "
        "that fits the walls best while keeping its doors by theirs in the model, deg (from one door its heading is "
        "the door's plane: perception's is ~20 deg off on a door seen obliquely; from two or three a few metres apart "
        "5-13 deg off); 0: not turned", ge=0)
    surface_turn_step_deg: float = param(  # these steps, to the heading that puts most points on the walls (`turned`)
        3.0, "the steps of surface_turn_deg's turns, deg", gt=0)
    surface_turn_points: int = param(  # ... judged by this many points; where no candidate then fits the walls, so is
        100, "the turns are judged by this many depth points", ge=1)
    surface_turn_max_inliers: int = param(
        3, "where no candidate fits the walls unturned, candidates from up to this many doors are turned too (keeping "
        "as many by a CAD feature)", ge=1)
    # candidates from one door are weighed by the points farther than this from its wall's plane (both faces of the
    # thickest walls, the reveals): nearer, every candidate puts them on a wall (`SurfaceJudge.choose`)
    surface_own_wall_m: float = param(
        1.0, "candidates from one door are weighed by the depth points farther than this from its wall's plane "
        "(nearer, every candidate puts them on a wall), m", ge=0)
    # before a candidate is taken, its images under up to this many of the building's near-self-maps (graph.self_maps,
    # most voted first) that keep as many landmarks by a same-type CAD feature are fitted and weighed too: the doors
    # cannot tell them apart, and the registrar offers them for its own best pose only (RobustParams.rival_self_maps,
    # the same count; 0: none)
    surface_self_map_images: int = param(
        8, "before a candidate pose is taken, its images under up to this many of the building's near-self-maps that "
        "keep as many landmarks by a same-type CAD feature are weighed too (the doors cannot tell them apart); 0: none",
        ge=0)
    # a candidate from two landmarks or more, one of which differs in size from the CAD feature it puts it by, is
    # taken only where no pose from one of them alone, different from it, scores within the margins: a false
    # detection that lands on a model door under a wrong pose makes that pose explain two, while the true pose
    # explains one and is never offered (docs/measurements.md, "A false door that lands on a model door")
    surface_one_landmark_rivals: bool = param(
        True, "a candidate pose from two landmarks or more, one of them unlike its CAD feature in size, is taken only "
        "where no different pose from one of them alone scores within the margins (a false detection may land on a "
        "model door)")


@dataclass(frozen=True)
class SurfaceFitParams(Parameters):
    """Once localized, each keyframe's depth points fitted to the model's walls and floor (graph.surfaces)."""

    surface_fit: bool = param(
        True, "once localized, each keyframe's depth points fitted to the walls join the graph as a measured pose in "
        "the model")
    surface_fit_max_correction_m: float = param(
        0.5, "a fit that moves the pose further is not trusted (a wrong wall), m ...", gt=0)
    surface_fit_max_turn_deg: float = param(5.0, "... nor one that turns it further, deg ...", gt=0)
    surface_fit_settling_turn_deg: float = param(
        10.0, "... but this far in the first keyframes after localizing, while the heading is the few doors' it was "
        "found by, deg", gt=0)
    surface_fit_settling_keyframes: int = param(  # pose's heading is the few doors' it was found by
        10, "those first keyframes", ge=0)
    surface_fit_sigma_m: float = param(
        0.05, "a fitted point's distance to its wall, model against reality (the judge's fits of candidate poses use "
        "it too), m", gt=0)


@dataclass(frozen=True)
class StatusParams(Parameters):
    """The localized status: decaying while no CAD-linked landmark is seen, and while the pose is not held."""

    degraded_after_s: float = param(10.0, "localized, but no sighting of a CAD-linked landmark for this long: degraded")
    lost_after_s: float = param(30.0, "... for this long: lost")
    # the pose is held to the model while its horizontal sigma (the graph's marginal, worst direction) is within this: 3
    # sigma inside the 0.5 m a wall fit may move it and a link may reach (surface_fit_max_correction_m, cad_link_m).
    # Only then is it `localized` and are the keyframe's wall fit and new links made (graph.anchoring)
    held_sigma_m: float = param(
        0.17, "the pose is held to the model while its horizontal sigma (the pose graph's) is within this: only then "
        "is it localized, fitted to the walls and are new doors linked by proximity. Beyond (the odometry lost track "
        "and extrapolated), the walls and the doors look for it again ([graph.recovery])", gt=0)


@dataclass(frozen=True)
class RecoveryParams(Parameters):
    """A pose no longer held to the model found again by the walls or the doors (graph.recovery)."""

    recovery: bool = param(
        True, "look for a pose that is no longer held among shifts of it within 3 sigma, by the walls seen since the "
        "odometry tracks again (taken only where no other shift fits them as well: [graph.judge]), else by the doors "
        "and windows mapped since it was held (taken where it puts two or more on the model's, and no shift "
        "recovery_apart_m from it as many)")
    # candidate shifts on a grid this fine, within 3 sigma of the pose: the walls' fit of each candidate
    # (JudgeParams.surface_refine_m, 0.6) reaches the truth from the nearest grid point (at most 0.35 m away)
    recovery_step_m: float = param(0.5, "the shifts' grid spacing", gt=0)
    recovery_max_m: float = param(  # ... and within this
        4.0, "the largest shift", gt=0)
    recovery_candidates: int = param(  # the shifts that put most points on the walls, recovery_apart_m apart, are
        8, "the shifts that put most depth points on the walls, this many ...", ge=1)
    # fitted and judged (JudgeParams.surface_screen_top, the judge's own cut); the doors' shift is refused where one
    # this far from it puts as many on the model
    recovery_apart_m: float = param(1.0, "... at least this far apart, are fitted and judged, m", ge=0)
    # the doors' shift puts this many landmarks on the model's features, or is not taken: one is the false door by a
    # model door that holding keeps out
    recovery_min_doors: int = param(
        2, "the doors' shift is taken where it puts this many doors and windows mapped since the pose was held on the "
        "model's (one alone may be a false detection by a model door)", ge=2)
    recovery_sigma_m: float = param(  # the pose found: its sigmas in the CAD frame (a placement's, AnchorParams)
        0.15, "the position sigma of a pose found again", gt=0)
    recovery_sigma_deg: float = param(2.0, "... its orientation sigma, deg", gt=0)


@dataclass(frozen=True)
class IsamSettings(Parameters):
    """The pose graph's iSAM2 (graph.posegraph, which re-exports it)."""

    relinearize_threshold: float = param(0.01, "iSAM2 relinearization threshold")
    relinearize_skip: int = param(1, "iSAM2 checks for relinearization every this many updates", ge=1)
    # Keyframes kept as variables behind the newest (0: all, plain iSAM2; see graph.posegraph's doc): >= the
    # localizer's `surface_window_keyframes` (60), the oldest keyframe whose estimate it reads back.
    window_keyframes: int = param(
        100, "keyframes kept as variables behind the newest; older ones are marginalised into a prior, so a keyframe's "
        "cost stays flat over a long mission (0: all kept, plain iSAM2). At least 60, the oldest keyframe the surface "
        "check reads back", ge=0)
    marginalise_every: int = param(
        100, "with a window: keyframes are marginalised this many at a time (one re-factorisation each time)", ge=1)
    marginalise_landmarks: bool = param(
        True, "with a window: a door or window no live keyframe sees leaves the graph with them, its CAD links set "
        "aside, and re-enters when seen again, at its last estimate with its links (unlinked: with a prior of its last "
        "covariance); the cost then follows the doors in view (false: every door mapped stays a variable)")


@dataclass(frozen=True)
class LocalizerParams(Parameters):
    """The localizer's parameters, one part per component (see module doc)."""

    odometry: OdometryFactorParams = field(default_factory=OdometryFactorParams)
    landmarks: LandmarkParams = field(default_factory=LandmarkParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    anchor: AnchorParams = field(default_factory=AnchorParams)
    depth: DepthWindowParams = field(default_factory=DepthWindowParams)
    far: FarParams = field(default_factory=FarParams)
    judge: JudgeParams = field(default_factory=JudgeParams)
    fit: SurfaceFitParams = field(default_factory=SurfaceFitParams)
    status: StatusParams = field(default_factory=StatusParams)
    recovery: RecoveryParams = field(default_factory=RecoveryParams)


@dataclass(frozen=True)
class VerifyParams(Parameters):
    """How a pose's matches are verified (graph.verify)."""

    gate_sigmas: float = param(
        3.0, "a residual beyond this many sigmas of its noise model is no match (wall normal, sides)", gt=0)
    position_gate_chi2: float = param(14.16, "... and a centroid beyond this chi-square (3 dof)", gt=0)
    false_detection_rate: float = param(0.2, "the prior of a false detection (the outlier process)", gt=0, lt=1)
    normal_floor_deg: float = param(  # the wall normal is never trusted better than this (CAD and detector frames)
        3.0, "the wall normal is never trusted better than this, deg", ge=0)
    size_floor_m: float = param(  # nor a side length better than this (opening vs frame of a door)
        0.10, "nor a side length better than this, m", ge=0)
    neighbours: int = param(4, "CAD features within the position gate considered per observation", ge=1)


@dataclass(frozen=True)
class ObservationModel(Parameters):
    """The generative model of observations (graph.posterior, issue 58); where each value comes from in its
    description (docs/measurements.md, "Issue 58: the posterior", has the measurements)."""

    corner_sigma_floor_m: float = param(
        0.05, "a corner's noise per axis at least (the shared scoring harness's default: N(0, 0.05^2) per "
        "coordinate); where the rectangles' own closure shows more (the hard noise: 0.10) that is taken, m", gt=0)
    cad_sigma_m: float = param(
        0.03, "the model's centroid vs the built one, per axis, beside the noise: the registration's noise floor "
        "(noise_floor_m, 0.05 m 3-D, 0.029 m per axis); on the harness's scenarios the IFC reading and the truth agree "
        "exactly (measured: docs/measurements.md, issue 58), so there it is margin, m", ge=0)
    size_sigma_floor_m: float = param(
        0.10, "a side length's sigma at least (opening vs frame; as [localize.verify] size_floor_m), m", gt=0)
    normal_sigma_floor_deg: float = param(
        3.0, "a wall normal's sigma at least (as [localize.verify] normal_floor_deg), deg", gt=0)
    miss_probability: float = param(
        0.15, "a door or window in view is not reported (the harness's drop, p = 0.15)", gt=0, lt=1)
    swap_probability: float = param(
        0.05, "a detection reports the other type, door <-> window (the harness's flip, p = 0.05)", gt=0, lt=1)
    false_detection_fraction: float = param(
        0.10, "false detections expected per observation (the harness: fp K of (1 - drop) K + fp K = 0.105)", gt=0)
    wall_per_feature_m: float = param(
        0.0, "metres of wall per observation over which false detections fall (0: the building's own, the median "
        "distance from a door or window to the next on its wall line: graph.posterior.wall_per_feature_m), m", ge=0)
    false_alike_fraction: float = param(
        0.5, "the share of false detections that look like one of the building's own doors and windows (height and "
        "sides drawn from theirs; the rest any height and size below): a prior, not measured: half either way", gt=0,
        lt=1)
    false_band_m: float = param(2.0, "heights a false detection's centre spreads over, m", gt=0)
    false_size_area_m2: float = param(
        4.4, "the sizes a false detection takes, uniformly: widths 0.4-2.4 m x heights 0.4-2.6 m, m^2", gt=0)
    gate_sigmas: float = param(4.0, "a residual beyond this many sigmas matches nothing", gt=0)
    view_margin_m: float = param(
        0.5, "in view: within this of the hull of the matched observations (plan), m ...", ge=0)
    view_band_m: float = param(1.0, "... and of their heights, m", ge=0)
    epsilon: float = param(0.01, "localized when the best pose holds 1 - epsilon of the posterior", gt=0, lt=1)
    neighbours: int = param(4, "CAD features within the gate considered per observation", ge=1)


@dataclass(frozen=True)
class RobustParams(Parameters):
    """The one-shot registration's parameters (graph.robust; `[localize]` sets some of them)."""

    inlier_threshold_m: float = param(  # a refined pose explains an observation within this distance
        0.30, "an observation this close to a same-type CAD feature (centroids) supports the pose, m (as "
        "[graph.registration] inlier_threshold_m is the pose graph's, for perception's coarser landmarks)")
    size_tolerance_m: float = param(0.35, "an observed rectangle's sides match a CAD feature's within this, m", gt=0)
    coarse_base_m: float = param(
        0.45, "the coarse check's tolerance: this plus coarse_slope times the distance from the seed, m", gt=0)
    coarse_slope: float = param(0.12, "... its growth with the distance from the seed, m/m", ge=0)
    max_seeds: int = param(  # observed rectangles used to generate hypotheses, at most
        8, "observed rectangles that seed hypotheses, at most", ge=1)
    min_seeds: int = param(2, "seeds added per round (the refinement runs after each round)", ge=1)
    early_stop_fraction: float = param(
        0.5, "seeding stops once a refined pose explains this fraction of the observations", gt=0, le=1)
    refine_top: int = param(  # distinct coarse hypotheses refined (a symmetric rival scores like the best: it is kept)
        6, "distinct coarse hypotheses refined", ge=1)
    scan_top: int = param(300, "coarse hypotheses scanned for distinct ones", ge=1)
    refine_iterations: int = param(2, "refinement iterations of each pose", ge=1)
    gravity_tolerance_deg: float = param(15.0, "with gravity given, a hypothesis may tilt the map this much, deg", ge=0)
    ambiguity_tau_m: float = param(
        0.30, "an observation farther than this from any CAD feature explains nothing, m", gt=0)
    rival_self_maps: int = param(
        8, "the best pose's images under the building's self-maps refined and scored as rivals", ge=0)
    landing_alpha: float = param(
        0.1, "a different pose within the rival margin of the best makes the answer 'ambiguous'; the margin covers the "
        "false detections' chance landings on features but this often")
    seed_rivals: int = param(3, "per seed observation, its best distinct coarse hypotheses verified as rivals", ge=0)
    noise_floor_m: float = param(  # lower bound of the 3-D residual RMS used as the noise scale
        0.05, "the residuals' noise scale is never taken below this, m", gt=0)
    distinct_m: float = param(
        0.5, "poses that move the matched observations by more than this are different, m ...", gt=0)
    distinct_deg: float = param(5.0, "... and so are poses whose rotations differ by more than this, deg", gt=0)
    pair_min_baseline_m: float = param(
        2.0, "pair hypotheses (gravity given) need observations this far apart, m ...", ge=0)
    pair_max_baseline_m: float = param(30.0, "... and consider CAD pairs up to this far apart, m", gt=0)
    pair_tolerance_m: float = param(
        0.35, "a pair's horizontal distance and height difference agree within this, m", gt=0)
    coarse_observations: int = param(12, "observations nearest the seed that rank its hypotheses", ge=1)
    polish_tau_m: float = param(0.45, "the ranking's tolerance after the polishing step, m", gt=0)
    rival_candidates: int = param(4, "best-supported distinct hypotheses refined when looking for a rival", ge=0)
    min_inlier_fraction: float = param(
        0.35, "a pose explaining fewer of the observations than this fraction is not trusted", ge=0, le=1)
    cross_type_weight: float = param(
        0.5, "an observation on a feature of the other type (door/window confusion) counts this much", ge=0, le=1)
    min_inliers: int = param(3, "fewer explained observations than this (4 without gravity): not_localized")
    min_inliers_without_gravity: int = param(  # 6 DoF: three centroids fit some pose anywhere; ask for more support ...
        4, "without gravity, fewer explained observations than this: not_localized (unless every one is a rectangle: "
        "min_inliers)", ge=1)
    # ... unless every inlier is a rectangle, verified by its wall normal and sides (graph.verify): then min_inliers
    # Below this many inliers the answer is only candidates for other evidence (the walls) to choose among: then
    # they are every distinct hypothesis that explains as many observations as the best, or one fewer (down to
    # two), not the refined few (a building with many alike door pairs offers dozens, and the truth must be among
    # them, also where one observation is a false detection that a wrong pose happens to explain: the truth then
    # explains one fewer than the best, and the walls, offered no true pose, may take a wrong one that fits them;
    # docs/measurements.md, "Registration's candidates below four landmarks"). 0: the refined few.
    complete_below: int = param(
        0, "below this many inliers the answer is every distinct hypothesis explaining as many observations as the "
        "best or one fewer, for other evidence to choose among (0: the refined few)", ge=0)
    # Issue 37: candidates ranked by the layout descriptor (graph.layout), and rivals found by it.
    prune_top: int = param(
        64, "per seed rectangle (gravity given), the CAD candidates kept, best layout score first (0: every one)", ge=0)
    # every one); 64 keeps the true one for nearly every seed rectangle (bench.bench_scale; docs/measurements.md,
    # "Issue 37: registration that scales")
    image_anchors: int = param(
        3, "matched features of the best pose whose alike features propose its images (rivals)", ge=1)
    image_anchor_gap_m: float = param(  # anchors: the matched features with most matched ones around, this far apart
        3.0, "... at least this far apart, m", ge=0)
    image_alike_fraction: float = param(
        0.7, "alike: a feature whose layout explains this fraction of the anchor's relations", gt=0, le=1)
    image_landing_m: float = param(0.45, "an image maps a matched feature onto one of its type this close, m ...", gt=0)
    image_min_fraction: float = param(0.5, "... for this fraction of them (at least 2) ...", gt=0, le=1)
    image_check: int = param(8, "... of this many, spread over the footprint", ge=1)
    image_slack: float = param(  # images explaining fewer observations than the best less the rival margin (in
        2.0, "images short of the best by the rival margin and this many observations more are not judged", ge=0)
    # observations) and this many more cannot come within the margin: they are not judged
    verify: VerifyParams = table(VerifyParams, "[localize.verify]: how a pose's matches are verified")
    seed: int = param(0, "random seed of the hypothesis order (deterministic answers)")
    # Issue 58: the posterior over the poses found (graph.posterior) is computed and reported either way
    decision: Literal["margin", "posterior"] = param(
        "margin", "the rule of the answer: 'margin' (the rival margin) or 'posterior' (localized when the best pose "
        "holds 1 - observation.epsilon of the posterior over the poses found, graph.posterior)")
    observation: ObservationModel = table(
        ObservationModel, "[localize.observation]: the generative model of observations behind the posterior")
