"""A simulated flight written as a recording (`macroloc simulate`): the rendered stereo frames, the IMU and the
ground truth as the service would receive them (contract: proto/recording.py), plus a contact sheet PNG and,
optionally, detector training data."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from macroloc.service.config import MacrolocConfig
    from macroloc.sim.simulator import SimFrame, Simulator

log = logging.getLogger(__name__)

CONTACT_SHEET_TILES = 16


def simulation_params(cfg: MacrolocConfig, seed: int, storey: str | None,  # noqa: ANN201 - SimulationParams
                      appearance_seed: int | None = None):
    from macroloc.sim.flight import FlightParams
    from macroloc.sim.render import CameraModel
    from macroloc.sim.simulator import SimulationParams

    c = cfg.camera
    camera = CameraModel(width=c.width, height=c.height, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, baseline_m=c.baseline_m)
    flight = replace(FlightParams(), duration_s=cfg.sim.duration_s, speed_mps=cfg.sim.speed_mps,
                     min_height_m=cfg.sim.min_height_m, max_height_m=cfg.sim.max_height_m,
                     rate_hz=cfg.sim.imu_rate_hz)
    photos = cfg.sim.facade_photos
    if photos is not None and not (photos / "images").is_dir():
        from macroloc.graph.errors import UserInputError

        raise UserInputError(f"sim.facade_photos: {photos} has no images/ folder")
    return SimulationParams(seed=seed, appearance_seed=appearance_seed, storey=storey, camera=camera,
                            camera_rate_hz=c.rate_hz, flight=flight,
                            facade_photos=photos)


def simulate_to_mcap(building: Path, out: Path, cfg: MacrolocConfig, seed: int = 0, storey: str | None = None,
                     contact_sheet: Path | None = None, yolo_dir: Path | None = None,
                     yolo_every: int = 10, appearance_seed: int | None = None) -> dict[str, Any]:
    """Simulate and record one flight; returns {"frames", "duration_s", "render_fps", "channels", "storey", ...}.

    contact_sheet: a PNG of sampled frames with their ground truth drawn; yolo_dir: also export every
    `yolo_every`-th left image with YOLO labels there.
    """
    import cv2

    from macroloc.proto.recording import FlightMetadata, FlightWriter
    from macroloc.service.progress import track
    from macroloc.sim.contact_sheet import annotate
    from macroloc.sim.contact_sheet import contact_sheet as make_sheet
    from macroloc.sim.simulator import Simulator

    t_start = time.perf_counter()
    sim = Simulator(building, simulation_params(cfg, seed, storey, appearance_seed))
    exporter = None
    if yolo_dir is not None:
        from macroloc.sim.export import YoloExporter

        exporter = YoloExporter(yolo_dir, f"{building.stem}_s{seed}_{_slug(sim.storey)}", every_n=yolo_every)
    imu = sim.imu()
    times = sim.frame_times_s
    sample_at = set(np.linspace(0, len(times) - 1, min(CONTACT_SHEET_TILES, len(times))).round().astype(int).tolist())
    tiles = []
    meta = FlightMetadata(building=building.name, building_sha256=sim.model.sha256, seed=seed, storey=sim.storey,
                          duration_s=float(times[-1]) if len(times) else 0.0,
                          extra={"camera_rate_hz": str(cfg.camera.rate_hz), "imu_rate_hz": str(cfg.sim.imu_rate_hz),
                                 "generator": "macroloc simulate",
                                 **({"appearance_seed": str(appearance_seed)} if appearance_seed is not None else {})})
    render_s = 0.0
    k_imu = 0
    imu_ns = np.round(imu.stamps_s * 1e9).astype(np.int64)
    try:
        with FlightWriter(out, meta) as writer:
            from macroloc.service.offline.foxglove_out import SimulationChannels
            from macroloc.service.offline.plots import load_wall_mesh

            foxglove = SimulationChannels(writer.write, sim.model, load_wall_mesh(building))
            for i, t in enumerate(track(times, f"simulate {building.name}", total=len(times))):
                t0 = time.perf_counter()
                frame = sim.render_at(i, float(t))
                render_s += time.perf_counter() - t0
                while k_imu < len(imu_ns) and imu_ns[k_imu] <= frame.stamp_ns:
                    writer.write_imu(imu_message(imu, k_imu, int(imu_ns[k_imu])))
                    k_imu += 1
                stereo, truth, instances = frame_messages(frame, sim, cfg)
                writer.write_stereo(stereo)
                writer.write_ground_truth(truth, instances)
                foxglove.frame(stereo, frame.T_cad_body, sim.T_body_cam)
                if exporter is not None:
                    exporter.add(i, frame.left_bgr, frame.features)
                if i in sample_at:
                    tiles.append(annotate(frame.left_bgr, frame.features, f"{frame.stamp_ns / 1e9:.1f} s"))
            while k_imu < len(imu_ns):
                writer.write_imu(imu_message(imu, k_imu, int(imu_ns[k_imu])))
                k_imu += 1
            channels = dict(writer.counts)
    finally:
        sim.close()
    if contact_sheet is not None:
        contact_sheet.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(contact_sheet), make_sheet(tiles))
    return {"frames": len(times), "duration_s": round(meta.duration_s, 6),
            "render_fps": round(len(times) / render_s, 2) if render_s > 0 else None,
            "channels": channels, "storey": sim.storey, "out": str(out),
            "contact_sheet": str(contact_sheet) if contact_sheet is not None else None,
            "yolo": dict(exporter.counts, dir=str(yolo_dir)) if exporter is not None else None,
            "wall_s": round(time.perf_counter() - t_start, 2)}


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in text)


def imu_message(imu, k: int, stamp_ns: int):  # noqa: ANN001, ANN201 - (ImuSamples, index) -> pb.Imu
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import vector3

    return pb.Imu(header=pb.Header(stamp_ns=stamp_ns, frame_id="body", seq=k),
                  accel_mps2=vector3(imu.accel_mps2[k]), gyro_radps=vector3(imu.gyro_radps[k]))


def frame_messages(frame: SimFrame, sim: Simulator, cfg: MacrolocConfig):  # noqa: ANN201 - protobuf messages
    """(StereoFrame, GroundTruth, instance mask Image) of one simulated frame (contract: proto/recording.py)."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb
    from macroloc.proto.recording import add_features_in_view, depth_image_mm, encode_image, pose_from_matrix

    cam = sim.params.camera
    T_body_cam = pose_from_matrix(sim.T_body_cam)
    info = pb.CameraInfo(width=cam.width, height=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                         baseline_m=cam.baseline_m, T_body_cam=T_body_cam)
    enc = cfg.sim.image_encoding
    stereo = pb.StereoFrame(header=pb.Header(stamp_ns=frame.stamp_ns, frame_id="cam_left", seq=frame.index),
                            camera_id="front", left=encode_image(frame.left_bgr, enc),
                            right=encode_image(frame.right_bgr, enc), info=info)
    truth = pb.GroundTruth(header=pb.Header(stamp_ns=frame.stamp_ns, frame_id="cam_left", seq=frame.index),
                           T_cad_body=pose_from_matrix(frame.T_cad_body), T_body_cam=T_body_cam)
    add_features_in_view(truth, frame.features[:255])
    lut = np.zeros(len(sim.features) + 1, np.uint8)
    for j, f in enumerate(frame.features[:255]):
        lut[f.index + 1] = j + 1
    if cfg.sim.depth:
        truth.depth.CopyFrom(depth_image_mm(frame.depth_m))
    instances = encode_image(lut[frame.instance], "png")
    return stereo, truth, instances
