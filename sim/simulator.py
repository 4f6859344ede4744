"""The simulator: a building, a storey, a seeded flight, and the frames a stereo camera on the drone sees.

`Simulator(building, params)` loads the model's macro-features and geometry, picks the storey, plans the flight,
dresses the scene (textures, colours, door styles, lights) and renders frame after frame:

    sim = Simulator(Path("office.ifc"), SimulationParams(seed=3))
    for frame in sim.frames():      # SimFrame: images, depth, instances, poses, features in view
        ...
    imu = sim.imu()                  # ImuSamples at params.imu_rate_hz

Frames: `T_cad_body` (body x forward, y left, z up), `T_body_cam` (left camera, optical frame).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from macroloc.common.geometry import forward_stereo_T_body_cam
from macroloc.graph.bim import load_building
from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.sim.flight import FlightParams, FreeSpace, Trajectory, doors_crossed, plan_flight
from macroloc.sim.groundtruth import FeatureInView, feature_half_depths, features_in_view
from macroloc.sim.imu import ImuNoise, ImuSamples, simulate_imu
from macroloc.sim.materials import dress_scene
from macroloc.sim.render import CameraModel, Lighting, StereoRenderer
from macroloc.sim.scene import load_scene
from macroloc.sim.textures import facade_crops, make_texture_layers

log = logging.getLogger(__name__)

DEFAULT_STOREY_HEIGHT_M = 3.0


@dataclass
class SimulationParams:
    seed: int = 0
    appearance_seed: int | None = None  # the building's look (textures, dressing, lights); None: `seed`. The same
    #                                     look with another `seed` is the same building flown along another path
    storey: str | None = None  # default: the storey with the most features
    camera: CameraModel = field(default_factory=CameraModel)
    camera_rate_hz: float = 30.0
    flight: FlightParams = field(default_factory=FlightParams)
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    facade_photos: Path | None = None  # real door/window photos to texture some openings (train split only)


@dataclass
class SimFrame:
    """One stereo frame. left_bgr/right_bgr: (H, W, 3) uint8; depth_m: (H, W) float32 (left, 0 = nothing);
    instance: (H, W) int32 (left; k = features[k - 1]); features: ground truth of the doors/windows in view."""

    index: int
    stamp_ns: int
    T_cad_body: np.ndarray
    left_bgr: np.ndarray
    right_bgr: np.ndarray
    depth_m: np.ndarray
    instance: np.ndarray
    features: list[FeatureInView]


def choose_storey(model: BuildingModel, name: str | None) -> str:
    """`name` when the model has it; default: the storey holding the most doors and windows."""
    counts = {k: len(v) for k, v in model.by_storey().items() if k is not None}
    if name is not None:
        if name not in model.storeys and name not in counts:
            raise UserInputError(f"storey {name!r} not in {Path(model.source).name} "
                                 f"(storeys: {', '.join(model.storeys) or 'none'})")
        return name
    if not counts:
        raise UserInputError(f"{Path(model.source).name}: no storey holds doors or windows")
    return max(counts, key=lambda k: counts[k])


def storey_levels(model: BuildingModel, storey: str) -> tuple[float, float | None]:
    """(floor elevation, next storey's elevation or None), metres."""
    elev = model.storey_elevations_m
    if storey not in elev:  # no placement known: the lowest feature's bottom
        feats = [f for f in model.features if f.storey == storey]
        return float(min(f.corners_cad[:, 2].min() for f in feats)), None
    z0 = elev[storey]
    above = sorted(z for z in elev.values() if z > z0 + 1.5)
    return z0, (above[0] if above else None)


class Simulator:
    """Renders a seeded flight through one storey of a building (see the module docstring)."""

    def __init__(self, building: Path, params: SimulationParams) -> None:
        self.params = params
        self.model = load_building(building)
        self.features: list[MacroFeature] = self.model.features
        self.scene = load_scene(building)
        self.storey = choose_storey(self.model, params.storey)
        self.floor_z_m, ceiling = storey_levels(self.model, self.storey)
        self.trajectory, self.free_space = plan_flight(self.scene, self.floor_z_m, params.flight, params.seed,
                                                       ceiling, self.features)
        self.ceiling_z_m = ceiling if ceiling is not None else self.floor_z_m + DEFAULT_STOREY_HEIGHT_M
        self.T_body_cam = forward_stereo_T_body_cam(params.camera.baseline_m)
        look = params.seed if params.appearance_seed is None else params.appearance_seed
        rng = np.random.default_rng([look, 0x5CE])
        self.lighting = make_lighting(self.free_space, self.ceiling_z_m, rng)
        self._exposure_phase = rng.uniform(0, 2 * np.pi, 2)
        self.open_doors = doors_crossed(self.trajectory, self.features)
        layers = make_texture_layers(look)
        doors_rgb, windows_rgb = (facade_crops(params.facade_photos, look) if params.facade_photos is not None
                                  else (layers[:0], layers[:0]))
        n0 = len(layers)
        photo_doors = tuple(range(n0, n0 + len(doors_rgb)))
        photo_windows = tuple(range(n0 + len(doors_rgb), n0 + len(doors_rgb) + len(windows_rgb)))
        vertices = dress_scene(self.scene, self.features, look, ground_z_m=self._ground_z(),
                               open_doors=self.open_doors,
                               floor_levels_m=tuple(self.model.storey_elevations_m.values()),
                               photo_door_layers=photo_doors, photo_window_layers=photo_windows,
                               storey_z_m=(self.floor_z_m, self.ceiling_z_m))
        self.renderer = StereoRenderer(vertices, np.concatenate([layers, doors_rgb, windows_rgb]), params.camera)
        self.renderer.z_range_m = (self.floor_z_m - 1.0, self.ceiling_z_m + 1.0)  # other storeys are hidden
        self.half_depths = feature_half_depths(self.scene, self.features)

    def _ground_z(self) -> float:
        lowest = min(self.model.storey_elevations_m.values(), default=float(self.scene.bounds_cad[0, 2]))
        return min(lowest, self.floor_z_m) - 0.2

    @property
    def frame_times_s(self) -> np.ndarray:
        dt = 1.0 / self.params.camera_rate_hz
        return np.arange(0.0, self.trajectory.duration_s + 1e-9, dt)

    def imu(self) -> ImuSamples:
        return simulate_imu(self.trajectory, self.params.imu_noise, self.params.seed)

    def render_at(self, index: int, t_s: float) -> SimFrame:
        T_cad_body = self.trajectory.T_cad_body(t_s)
        T_cad_cam = T_cad_body @ self.T_body_cam
        light = self.lighting
        light.exposure = float(self._base_exposure * (1 + 0.08 * np.sin(t_s / 3.0 + self._exposure_phase[0])
                                                      + 0.04 * np.sin(t_s * 1.3 + self._exposure_phase[1])))
        left, right = self.renderer.render_stereo(T_cad_cam, light, frame_seed=float(index))
        assert left.depth_m is not None and left.instance is not None
        feats = features_in_view(self.features, self.half_depths, T_cad_cam, self.params.camera, left.depth_m,
                                 left.instance)
        return SimFrame(index, int(round(t_s * 1e9)), T_cad_body, left.image_bgr, right, left.depth_m,
                        left.instance, feats)

    @property
    def _base_exposure(self) -> float:
        return float(self.lighting.extra_gain)

    def frames(self) -> Iterator[SimFrame]:
        for i, t in enumerate(self.frame_times_s):
            yield self.render_at(i, float(t))

    def close(self) -> None:
        self.renderer.release()


@dataclass
class FlightLighting(Lighting):
    extra_gain: float = 1.0


def make_lighting(space: FreeSpace, ceiling_z_m: float, rng: np.random.Generator) -> FlightLighting:
    """Ceiling lights on a ~4 m grid over the free space, a seeded colour temperature, ambient, gain, noise."""
    step = max(1, int(round(4.0 / space.cell_m)))
    ij = np.argwhere(space.safe)
    ij = ij[(ij[:, 0] % step == step // 2) & (ij[:, 1] % step == step // 2)]
    if len(ij) == 0:
        ij = np.argwhere(space.safe)[:1]
    xy = space.to_xy(ij)
    pos = np.column_stack([xy, np.full(len(xy), ceiling_z_m - 0.35)])
    warmth = rng.uniform(-1, 1)
    colour = np.array([1.0 + 0.12 * warmth, 1.0, 1.0 - 0.15 * warmth]) * rng.uniform(1.0, 1.8)
    colours = np.tile(colour, (len(pos), 1)) * rng.uniform(0.8, 1.2, (len(pos), 1))
    amb = float(rng.uniform(0.25, 0.45))
    return FlightLighting(positions_cad=pos, colours=colours, ambient=(amb, amb, amb * rng.uniform(0.95, 1.05)),
                          exposure=1.0, noise_sigma=float(rng.uniform(0.008, 0.025)),
                          sky_rgb=(rng.uniform(0.5, 0.8), rng.uniform(0.65, 0.85), rng.uniform(0.8, 0.95)),
                          extra_gain=float(rng.uniform(0.8, 1.25)))


def plan_only(building: Path, params: SimulationParams) -> tuple[Trajectory, str]:
    """The flight a Simulator would fly (no rendering): (trajectory, storey)."""
    model = load_building(building)
    storey = choose_storey(model, params.storey)
    z0, ceiling = storey_levels(model, storey)
    traj, _ = plan_flight(load_scene(building), z0, params.flight, params.seed, ceiling, model.features)
    return traj, storey
