"""The localizer's parameters: one small frozen dataclass per component, composed in `LocalizerParams`. Each
component receives its own (the judge `JudgeParams`, the far sightings `FarParams`, ...), never the whole set.

They live in this one leaf module (numpy only) so that the service's config (service/config.py) can take its
defaults from them without importing the components (graph.judge pulls in scipy); the components re-export
theirs (`from macroloc.graph.judge import JudgeParams`). A field's name is its config key's where the config
sets it, in the [graph] section's table named as the `LocalizerParams` field (`[graph.judge] surface_margin` is
`JudgeParams.surface_margin`). Metres, seconds, degrees where named so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

Ranges = TypeVar("Ranges", float, np.ndarray)


@dataclass(frozen=True)
class OdometryParams:
    """The odometry factor between consecutive keyframes (the localizer's prediction)."""

    odometry_sigma_per_m: float = 0.03  # translation sigma per metre travelled (drift model of the odometry)
    odometry_rot_sigma_per_m: float = 0.01  # rad per metre travelled
    odometry_dead_reckoned_sigma_mps: float = 0.5  # translation sigma per second the odometry lost track and only
    #                                               extrapolated (a drone's speed it could not see change)


@dataclass(frozen=True)
class LandmarkParams:
    """Sightings into landmarks (graph.landmarks): association, range, and the sighting factor's sigmas."""

    associate_m: float = 0.6  # a sighting within this of a same-type landmark re-observes it
    sighting_sigma_m: tuple[float, float] = (0.03, 0.004)  # sigma = a + b * range^2 (stereo) of a sighting's position
    sighting_sigma_rad: tuple[float, float] = (0.03, 0.012)  # same for its orientation (plane of noisy corners)
    truncated_sigma_m: float = 0.5  # position sigma along an axis on which the sighting is cut by the image border
    max_range_m: float = 7.0  # sightings further away are no landmarks: their corners are too coarse ...
    far_range_m: float = 20.0  # ... but up to this range their bearings check candidate poses (`FarSightings`)

    def position_sigma_m(self, range_m: Ranges) -> Ranges:
        """A sighting's position sigma at a range (stereo: it grows with range squared, `sighting_sigma_m`),
        metres; of each of an array of ranges too."""
        a, b = self.sighting_sigma_m
        return a + b * range_m**2


@dataclass(frozen=True)
class RegistrationParams:
    """When and how the map's landmarks are registered to the model (the registrar, graph.registrar)."""

    min_sightings_to_register: int = 2  # a landmark seen once (a passing false detection?) waits
    inlier_threshold_m: float = 0.6  # an aligned landmark this close to a same-type CAD feature supports a pose:
    #                                  the registrar's inlier and ambiguity tolerance (RobustParams.inlier_threshold_m
    #                                  and ambiguity_tau_m), the judge's turns' too
    registration_min_landmarks: int = 4  # the model registrar answers 'localized' from this many landmarks ...
    verified_min_landmarks: int = 1  # ... and offers candidate poses from this many, for the surface check
    registration_early_stop: float = 1.0  # with the surface check, it stops seeding hypotheses once a pose explains
    #                                       this fraction of the landmarks (1.0: never; see `model_registrar`)
    surface_retry_s: float = 1.0  # with no new landmark, the check is retried this often as the walls come in view


@dataclass(frozen=True)
class AnchorParams:
    """Holding the graph to the model once localized: landmarks linked to CAD features, keyframes placed in a
    stored map."""

    cad_link_m: float = 0.5  # once localized: a landmark within this of a same-type CAD feature is linked ...
    cad_link_max_turn_deg: float = 8.0  # ... its orientation too where it lies within this of the feature's
    placed_sigma_m: float = 0.15  # a keyframe placed in a stored map (place recognition): its pose's sigmas in
    placed_sigma_deg: float = 2.0  # the CAD frame, the stored keyframe's error and PnP's together


@dataclass(frozen=True)
class DepthParams:
    """How many recent keyframes' depth points (graph.depth_window) and far sightings (graph.far_window) are kept."""

    surface_window_keyframes: int = 60  # the depth points of this many recent keyframes check a registration


@dataclass(frozen=True)
class FarParams:
    """The doors and windows seen beyond the sighting range (graph.far_window.FarSightings)."""

    far_bearing_deg: float = 3.0  # a far sighting is explained where a same-type CAD feature lies within this
    #                               horizontal bearing of it, seen from the keyframe's camera, and 3 sigmas of its range
    far_elevation_deg: float = 5.0  # ... and within this of its elevation (a one-door candidate's height is coarse)
    far_turn_deg: float = 2.0  # ... turning the candidate pose by up to this (`far_turn_step_deg` steps) to do so
    far_turn_step_deg: float = 0.5  # (its heading, from a door or two and the walls, is ~2 deg off)
    far_min_sightings: int = 10  # with this many far sightings in the window, a candidate pose explaining
    far_min_explained: float = 0.8  # at least this fraction of them is not rivalled by one explaining
    far_margin: float = 0.4  # this much less (the surfaces' margin aside)
    far_resection: bool = True  # with no landmark yet, candidate poses from two far doors seen from one camera
    far_pair_min_deg: float = 10.0  # ... at least this far apart in bearing (graph.far), in the newest
    far_pairs: int = 3  # ... this many keyframes that saw such a pair, the widest pair of each (`resected`)
    far_resection_sightings: int = 60  # the candidates are judged by this many of the far sightings, evenly drawn
    far_place_m: float = 1.0  # one candidate per place this size; a pair whose ranges leave the camera more than
    #                           this to move (within one sigma) resects none (`FarSightings.resected`)
    far_height_sigma_m: float = 0.2  # the pose taken holds the anchoring keyframe's height with this sigma ...
    far_bearing_sigma_deg: float = 0.5  # ... and is fitted to the far bearings with this one (`FarSightings.refined`)


@dataclass(frozen=True)
class JudgeParams:
    """The walls' judgement of candidate poses (graph.judge.SurfaceJudge)."""

    surface_min_points: int = 200  # fewer points than this: no check (the registration needs the landmarks above)
    surface_min_support: float = 0.9  # a pose must put this fraction of the points on the model's surfaces ...
    surface_margin: float = 0.3  # ... and every other candidate pose this much less (of points on surfaces and in
    #                               sight, with the model's walls: SurfaceCheck.score) ...
    surface_margin_unfit: float = 0.15  # ... or this much less where that pose does not fit the walls itself
    #                                     (candidates from two landmarks or more: `SurfaceJudge.choose`) ...
    surface_max_seen_through: float = 0.1  # ... and let at most this fraction be seen through a wall
    surface_refuse_seen_through: float = 0.25  # a registrar's own answer is refused where more are seen through one
    surface_refine_m: float = 0.6  # each candidate pose is first fitted to the walls, moving the points at most this
    surface_screen_top: int = 8  # of more candidates (one door: every alike door of the model, from both sides),
    surface_screen_points: int = 200  # only the best this many by these many points, unfitted, are fitted and checked
    surface_turn_deg: float = 24.0  # a candidate pose from one door is first turned about it, within this and by
    surface_turn_step_deg: float = 3.0  # these steps, to the heading that puts most points on the walls (`turned`)
    surface_turn_points: int = 100  # ... judged by this many points; where no candidate then fits the walls, so is
    surface_turn_max_inliers: int = 3  # one from up to this many doors, keeping as many by a CAD feature
    surface_own_wall_m: float = 1.0  # candidates from one door are weighed by the points farther than this from its
    #                                  wall's plane (both faces of the thickest walls, the reveals): nearer, every
    #                                  candidate puts them on a wall (`SurfaceJudge.choose`)
    surface_self_map_images: int = 8  # before a candidate is taken, its images under up to this many of the
    #                                   building's near-self-maps (graph.self_maps, most voted first) that keep as
    #                                   many landmarks by a same-type CAD feature are fitted and weighed too: the
    #                                   doors cannot tell them apart, and the registrar offers them for its own best
    #                                   pose only (RobustParams.rival_self_maps, the same count; 0: none)


@dataclass(frozen=True)
class SurfaceFitParams:
    """Once localized, each keyframe's depth points fitted to the model's walls and floor (graph.surfaces)."""

    surface_fit: bool = True  # once localized, each keyframe's depth points fitted to the walls join the graph
    surface_fit_max_correction_m: float = 0.5  # a fit that moves the pose further is not trusted (wrong wall) ...
    surface_fit_max_turn_deg: float = 5.0  # ... nor one that turns it further ...
    surface_fit_settling_turn_deg: float = 10.0  # ... but this far in the first keyframes after localizing, while the
    surface_fit_settling_keyframes: int = 10  # pose's heading is the few doors' it was found by
    surface_fit_sigma_m: float = 0.05  # a fitted point's distance to its wall, model against reality (m); the
    #                                    judge's fits of candidate poses use it too


@dataclass(frozen=True)
class StatusParams:
    """The localized status: decaying while no CAD-linked landmark is seen, and while the pose is not held."""

    degraded_after_s: float = 10.0  # localized but no CAD-linked sighting for this long
    lost_after_s: float = 30.0
    held_sigma_m: float = 0.17  # the pose is held to the model while its horizontal sigma (the graph's marginal,
    #                             worst direction) is within this: 3 sigma inside the 0.5 m a wall fit may move it
    #                             and a link may reach (surface_fit_max_correction_m, cad_link_m). Only then is it
    #                             `localized` and are the keyframe's wall fit and new links made (graph.anchoring)


@dataclass(frozen=True)
class RecoveryParams:
    """A pose no longer held to the model found again by the walls or the doors (graph.recovery)."""

    recovery: bool = True
    recovery_step_m: float = 0.5  # candidate shifts on a grid this fine, within 3 sigma of the pose: the walls' fit
    #                               of each candidate (JudgeParams.surface_refine_m, 0.6) reaches the truth from the
    #                               nearest grid point (at most 0.35 m away)
    recovery_max_m: float = 4.0  # ... and within this
    recovery_candidates: int = 8  # the shifts that put most points on the walls, at least recovery_apart_m apart, are
    recovery_apart_m: float = 1.0  # fitted and judged (JudgeParams.surface_screen_top, the judge's own cut); the
    #                                doors' shift is refused where one this far from it puts as many on the model
    recovery_min_doors: int = 2  # the doors' shift puts this many landmarks on the model's features, or is not
    #                              taken: one is the false door by a model door that holding keeps out
    recovery_sigma_m: float = 0.15  # the pose found: its sigmas in the CAD frame (a placement's, AnchorParams)
    recovery_sigma_deg: float = 2.0


@dataclass(frozen=True)
class IsamSettings:
    """The pose graph's iSAM2 (graph.posegraph, which re-exports it)."""

    relinearize_threshold: float = 0.01
    relinearize_skip: int = 1
    # Keyframes kept as variables behind the newest (0: all, plain iSAM2; see graph.posegraph's doc): >= the
    # localizer's `surface_window_keyframes` (60), the oldest keyframe whose estimate it reads back.
    window_keyframes: int = 100
    marginalise_every: int = 100  # with a window: keyframes are marginalised this many at a time (graph.posegraph)
    # With a window: a landmark no live keyframe sees is marginalised with the keyframes and re-enters when seen
    # again (graph.posegraph), so the live graph holds the doors in view, not every door mapped.
    marginalise_landmarks: bool = True


@dataclass(frozen=True)
class LocalizerParams:
    """The localizer's parameters, one part per component (see module doc)."""

    odometry: OdometryParams = field(default_factory=OdometryParams)
    landmarks: LandmarkParams = field(default_factory=LandmarkParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    anchor: AnchorParams = field(default_factory=AnchorParams)
    depth: DepthParams = field(default_factory=DepthParams)
    far: FarParams = field(default_factory=FarParams)
    judge: JudgeParams = field(default_factory=JudgeParams)
    fit: SurfaceFitParams = field(default_factory=SurfaceFitParams)
    status: StatusParams = field(default_factory=StatusParams)
    recovery: RecoveryParams = field(default_factory=RecoveryParams)


@dataclass(frozen=True)
class VerifyParams:
    """How a pose's matches are verified (graph.verify)."""

    gate_sigmas: float = 3.0  # g: a residual beyond g sigma of its noise model is not a match (normal, sides) ...
    position_gate_chi2: float = 14.16  # ... and a centroid beyond this chi-square (3 dof, the 99.7 % of g = 3)
    false_detection_rate: float = 0.2  # eps, the prior of a false detection (the outlier process)
    normal_floor_deg: float = 3.0  # the wall normal is never trusted better than this (CAD and detector frames)
    size_floor_m: float = 0.10  # nor a side length better than this (opening vs frame of a door)
    neighbours: int = 4  # CAD features within the position gate considered per observation


@dataclass(frozen=True)
class RobustParams:
    """The one-shot registration's parameters (graph.robust; `[localize]` sets some of them)."""

    inlier_threshold_m: float = 0.30  # a refined pose explains an observation within this distance
    size_tolerance_m: float = 0.35  # observed vs CAD rectangle side lengths
    coarse_base_m: float = 0.45  # coarse verification tolerance: base + slope x distance from the seed
    coarse_slope: float = 0.12
    max_seeds: int = 8  # observed rectangles used to generate hypotheses, at most
    min_seeds: int = 2  # seeds added per round (refinement runs after each round)
    early_stop_fraction: float = 0.5  # stop seeding once a refined pose explains this fraction
    refine_top: int = 6  # distinct coarse hypotheses refined (a symmetric rival scores like the best: it is kept)
    scan_top: int = 300  # coarse hypotheses scanned for distinct ones
    refine_iterations: int = 2
    gravity_tolerance_deg: float = 15.0
    ambiguity_tau_m: float = 0.30  # an observation farther than this from any CAD feature explains nothing
    rival_self_maps: int = 8  # the best pose's self-map images (graph.self_maps) refined and scored as rivals
    landing_alpha: float = 0.1  # the rival margin covers the chance landings of false detections but this often
    seed_rivals: int = 3  # per seed observation, its best distinct coarse hypotheses verified for its best pose
    noise_floor_m: float = 0.05  # lower bound of the 3-D residual RMS used as the noise scale
    distinct_m: float = 0.5  # poses that move the matched observations by more than this are different ...
    distinct_deg: float = 5.0  # ... and so are poses whose rotations differ by more than this
    pair_min_baseline_m: float = 2.0  # pair hypotheses (gravity known) need observations this far apart ...
    pair_max_baseline_m: float = 30.0  # ... and CAD pairs up to this far apart are considered
    pair_tolerance_m: float = 0.35  # horizontal distance / height difference agreement of a pair
    coarse_observations: int = 12  # observations nearest the seed used to rank its hypotheses
    polish_tau_m: float = 0.45  # tolerance of the ranking after the vectorised polishing step
    rival_candidates: int = 4  # best-supported distinct hypotheses refined when looking for a rival
    min_inlier_fraction: float = 0.35  # a pose explaining fewer of the observations is not trusted
    cross_type_weight: float = 0.5  # an observation on a feature of the other type (door/window confusion) counts half
    min_inliers: int = 3
    min_inliers_without_gravity: int = 4  # 6 DoF: three centroids fit some pose anywhere; ask for more support ...
    # ... unless every inlier is a rectangle, verified by its wall normal and sides (graph.verify): then min_inliers
    # Below this many inliers the answer is only candidates for other evidence (the walls) to choose among: then
    # they are every distinct hypothesis that explains as many observations as the best, or one fewer (down to
    # two), not the refined few (a building with many alike door pairs offers dozens, and the truth must be among
    # them, also where one observation is a false detection that a wrong pose happens to explain: the truth then
    # explains one fewer than the best, and the walls, offered no true pose, may take a wrong one that fits them;
    # docs/measurements.md, "Registration's candidates below four landmarks"). 0: the refined few.
    complete_below: int = 0
    # Issue 37: candidates ranked by the layout descriptor (graph.layout), and rivals found by it.
    prune_top: int = 64  # per seed rectangle (gravity known), the CAD candidates kept, best layout score first (0:
    # every one); 64 keeps the true one for nearly every seed rectangle (bench.bench_scale; docs/measurements.md,
    # "Issue 37: registration that scales")
    image_anchors: int = 3  # matched features of the best pose whose alike features propose its images
    image_anchor_gap_m: float = 3.0  # anchors: the matched features with most matched ones around, this far apart
    image_alike_fraction: float = 0.7  # alike: its layout explains this fraction of the anchor's relations
    image_landing_m: float = 0.45  # an image maps a matched feature onto one of its type this close ...
    image_min_fraction: float = 0.5  # ... and does so for this fraction of them (at least 2) ...
    image_check: int = 8  # ... of this many, spread over the footprint
    image_slack: float = 2.0  # images explaining fewer observations than the best less the rival margin (in
    # observations) and this many more cannot come within the margin: they are not judged
    verify: VerifyParams = VerifyParams()
    seed: int = 0
