"""The composition root of `macroloc serve`: config -> model, saved map, front end, planner, service."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from macroloc.graph.errors import UserInputError
from macroloc.graph.geo import read_geo_reference
from macroloc.graph.wall_mesh import load_wall_mesh
from macroloc.service.assets import prepare_building
from macroloc.service.config import MacrolocConfig
from macroloc.service.foxglove_live import NullLiveView, start_live_view
from macroloc.service.front_end import make_front_end
from macroloc.service.inputs import limits_from_config
from macroloc.service.node import LocalizationService, ServiceParams
from macroloc.service.odometry_in import (
    PX4_ODOMETRY,
    ROS_ODOMETRY,
    TF_MESSAGE,
    SegmentRule,
    TfOdometry,
    VehicleOdometryInput,
    px4_odometry,
    ros_odometry,
)
from macroloc.service.px4 import Px4Keys, Px4Messages, Px4Output, ResetCounter
from macroloc.service.ros_out import (
    AllRosIntakes,
    NullRosInputs,
    RosFrames,
    RosInputs,
    RosIntakes,
    RosKeys,
    RosOutput,
    RosPriorInputs,
)
from macroloc.service.ros_sensors import CAMERA_INFO, COMPRESSED, IMAGE, IMU, RosSensorTopics
from macroloc.service.ros_transport import make_ros_transport as make
from macroloc.service.state import SavedMapFile
from macroloc.service.systemd import Notifier, notifier_from_environment
from macroloc.service.vehicle_out import NullVehicleOutput, VehicleOutput, VehicleOutputs
from macroloc.service.zenoh_io import describe_exposure, open_session, session_config

if TYPE_CHECKING:
    from macroloc.graph.features import BuildingModel
    from macroloc.service.foxglove_live import LiveView
    from macroloc.service.ros_transport import RosTransport

log = logging.getLogger(__name__)


def make_ros_transport(cfg: MacrolocConfig, session) -> RosTransport | None:  # noqa: ANN001
    """Where ROS 2 and PX4 topics travel on Zenoh ([ros] middleware: service.ros_transport), as one rmw_zenoh node
    named macroloc in the namespace /<[ros] namespace>/<vehicle>; None where neither [ros] nor [px4] is enabled."""
    if not (cfg.ros.enabled or cfg.px4.enabled or cfg.px4.take_odometry):
        return None
    node_namespace = "/" + "/".join(p for p in (cfg.ros.namespace.strip("/"), cfg.service.vehicle) if p)
    return make(cfg.ros.middleware, session, cfg.ros.domain_id, node_namespace)


def make_vehicle_io(cfg: MacrolocConfig, transport: RosTransport | None, T_enu_cad=None):  # noqa: ANN001, ANN201
    """The ROS 2 / PX4 outputs and the ROS inputs the config enables ([ros], [px4]) on the transport
    (`make_ros_transport`); null objects otherwise. `T_enu_cad`: the model's geo-reference (graph.geo), which makes
    PX4's pose frame true NED. The outputs close the transport after themselves."""
    outputs: list[VehicleOutput] = []
    inputs: list[RosIntakes] = []
    if transport is None:
        return NullVehicleOutput(), NullRosInputs()
    r, x = cfg.ros, cfg.px4
    rule = SegmentRule(cfg.inputs.odometry_max_speed_mps, float(np.deg2rad(cfg.inputs.odometry_max_rate_degps)))
    if r.enabled:
        keys, frames = RosKeys(cfg.service.vehicle, r.namespace), RosFrames(r.frame_map, r.frame_odom,
                                                                            r.frame_base_link)
        outputs.append(RosOutput(transport, keys, frames, r.odom_tf))
        inputs.append(RosInputs(keys, frames, transport))
        inputs.append(RosPriorInputs(keys, frames, transport, r.initialpose))
        log.info("ROS 2 topics (%s) /%s, /%s, ...", r.middleware, keys.topic("pose"), keys.tf)
        if r.odometry:
            inputs.append(VehicleOdometryInput(transport.subscription(keys.of(r.odometry), ROS_ODOMETRY),
                                               ros_odometry, rule))
        if r.odometry_tf:
            if r.odom_tf:
                raise UserInputError("[ros] odometry_tf takes odom -> base_link from /tf, where odom_tf publishes it: "
                                     "set one of them")
            inputs.append(VehicleOdometryInput(transport.subscription(keys.tf, TF_MESSAGE),
                                               TfOdometry(r.frame_odom, r.frame_base_link), rule))
    if x.enabled:
        reset = ResetCounter(x.reset_jump_m, float(np.deg2rad(x.reset_jump_deg)))
        outputs.append(Px4Output(transport, Px4Keys(x.namespace), Px4Messages(T_enu_cad, reset), x.offboard_rate_hz,
                                 x.reach_m))
        log.info("PX4 topics (%s) /%s", r.middleware, Px4Keys(x.namespace).visual_odometry)
    if x.take_odometry:
        inputs.append(VehicleOdometryInput(transport.subscription(Px4Keys(x.namespace).vehicle_odometry,
                                                                  PX4_ODOMETRY), px4_odometry, rule))
    return VehicleOutputs(outputs, then_close=[transport]), AllRosIntakes(inputs)


def ros_sensor_topics(cfg: MacrolocConfig, transport: RosTransport | None) -> RosSensorTopics:
    """The Zenoh keys of the ROS sensor topics [ros] names (under the namespace) on the transport, their
    subscriptions announced; none unless [ros] is enabled."""
    r = cfg.ros
    if not r.enabled or transport is None:
        return RosSensorTopics()
    keys = RosKeys(cfg.service.vehicle, r.namespace)

    def key(topic: str, typename: str) -> str:
        return transport.subscription(keys.of(topic), typename) if topic else ""

    image = COMPRESSED if r.compressed else IMAGE
    if not (r.left_image and r.right_image and r.left_info and r.right_info):  # a pair is taken whole or not at all
        return RosSensorTopics(imu=key(r.imu, IMU))
    return RosSensorTopics(key(r.left_image, image), key(r.right_image, image), key(r.left_info, CAMERA_INFO),
                           key(r.right_info, CAMERA_INFO), key(r.imu, IMU), r.compressed, r.rectified)


def make_live_view(cfg: MacrolocConfig, model: BuildingModel, building: Path) -> LiveView:
    """The operator's live view ([foxglove]: Foxglove's WebSocket server on host:port, service.foxglove_live); none
    where [foxglove] port is 0 (the default)."""
    f = cfg.foxglove
    if not f.port:
        return NullLiveView()
    return start_live_view(model, lambda: load_wall_mesh(building), f.host, f.port, f.image_rate_hz, f.queue_size,
                           f.pose_rate_hz)


def build_service(cfg: MacrolocConfig, session, store: SavedMapFile | None = None,  # noqa: ANN001
                  notifier: Notifier | None = None) -> LocalizationService:
    """Everything `serve` runs, on an open session (tests pass their own session and store)."""
    if cfg.service.building is None:
        raise UserInputError("no building model: set service.building in the config or pass --building")
    building = Path(cfg.service.building)
    prepared = prepare_building(building, cfg.graph, cfg.planning)
    model = prepared.model
    geo = read_geo_reference(building)
    log.info("geo-reference of %s: %s", building.name, geo.to_json() if geo else "none")
    store = store or SavedMapFile(cfg.service.state_dir, cfg.service.vehicle)
    snapshot = store.load(model.sha256)
    front_end = make_front_end(cfg, model, prepared.surfaces, snapshot)
    planner = prepared.planner
    log.info("%s: ready", building.name)
    s = cfg.service
    transport = make_ros_transport(cfg, session)
    params = ServiceParams(vehicle=s.vehicle, building=building.name, building_sha256=model.sha256,
                           cameras=list(s.cameras), ring_size=s.ring_size, queue_size=s.queue_size,
                           status_period_s=s.status_period_s, save_period_s=s.save_period_s,
                           replan_period_s=cfg.planning.replan_period_s, stall_after_s=s.stall_after_s,
                           drain_timeout_s=s.drain_timeout_s, lockstep=s.lockstep, geo=geo,
                           limits=limits_from_config(cfg.inputs, model), ros_sensors=ros_sensor_topics(cfg, transport),
                           T_body_cam=None if cfg.camera.T_body_cam is None else np.array(cfg.camera.T_body_cam, float))
    vehicle_out, ros_inputs = make_vehicle_io(cfg, transport, geo.T_enu_cad() if geo and geo.north_given else None)
    return LocalizationService(session, front_end, planner, store, params, vehicle_out, ros_inputs, notifier,
                               make_live_view(cfg, model, building))


def serve(cfg: MacrolocConfig, stop: threading.Event | None = None,
          on_ready: Callable[[LocalizationService], None] | None = None) -> None:
    """Run the service until SIGTERM/SIGINT (or `stop`); the map is saved on the way out."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda signum, frame: stop.set())
    run_dir = Path(cfg.service.state_dir).expanduser() / cfg.service.vehicle
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.resolved.json").write_text(cfg.model_dump_json(indent=2))  # beside the saved map
    with open_session(cfg.zenoh) as session:
        service = build_service(cfg, session, notifier=notifier_from_environment())
        log.info("zenoh %s session: %s", cfg.zenoh.mode, describe_exposure(session_config(cfg.zenoh)))
        if on_ready is not None:
            threading.Thread(target=lambda: service.ready.wait() and on_ready(service), daemon=True).start()
        service.run(stop)
