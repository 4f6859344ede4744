"""Pictures of a replay: the top-down view (the model's walls cut at the flight's height, doors and windows, true and
estimated trajectories, matched features; a saved map's keyframe views and the keyframes placed in them) and the
per-frame figures (position error with its horizontal and height
parts, tilt and yaw errors, status, sightings, iSAM2 update time), plus result.json, the trajectories for evo
(TUM: estimate_tum.txt, truth_tum.txt) and the resolved configuration (config.json)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from macroloc.graph.features import BuildingModel
from macroloc.service.offline.plots import WALL_COLOUR, wall_segments_xy
from macroloc.service.offline.replay import ReplayResult
from macroloc.service.saved_map import SavedMap

STATUS_LEVEL = {"exploring": 0, "ambiguous": 1, "localized": 2, "degraded": 3, "lost": 4}


def write_report(result: ReplayResult, model: BuildingModel, out_dir: Path, wall_mesh: Any = None,
                 stored: SavedMap | None = None, config: dict | None = None) -> list[Path]:
    """Write topdown.png, frames.png, result.json, the TUM trajectories (`write_tum`) and `config` (the resolved
    configuration, as config.json) into `out_dir`; returns their paths. `wall_mesh`: the model's
    walls (service.offline.plots.load_wall_mesh), drawn as a floor plan cut at the flight's height; `stored`: the
    map the flight re-localized into, whose keyframe views are drawn with the keyframes placed in them."""
    import matplotlib  # here, not at the top: the backend is chosen before pyplot is imported (see _topdown)

    matplotlib.use("Agg")
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [_topdown(result, model, out_dir / "topdown.png", wall_mesh, stored),
             _frames(result, out_dir / "frames.png")]
    doc = out_dir / "result.json"
    doc.write_text(json.dumps(result.to_json(), indent=2))
    paths += [doc, *write_tum(result, out_dir)]
    if config is not None:
        (out_dir / "config.json").write_text(json.dumps(config, indent=2))
        paths.append(out_dir / "config.json")
    return paths


def write_tum(result: ReplayResult, out_dir: Path) -> list[Path]:
    """estimate_tum.txt (the frames APE scores: `localized`, `degraded` or `lost` with a pose) and, where the flight
    has truth, truth_tum.txt (every frame with truth), as TUM lines `stamp_s tx ty tz qx qy qz qw` (CAD frame, s,
    m), so that `evo_ape tum truth_tum.txt estimate_tum.txt` (no alignment, translation) gives ape_rmse_m."""
    tr = result.trace
    est = [(s, T) for s, status, T in zip(tr.stamp_ns, tr.status, tr.T_est, strict=True)
           if T is not None and status in ("localized", "degraded", "lost")]
    truth = [(s, T) for s, T in zip(tr.stamp_ns, tr.T_true, strict=True) if np.isfinite(T).all()]
    paths = [_tum(out_dir / "estimate_tum.txt", est)]
    if truth:
        paths.append(_tum(out_dir / "truth_tum.txt", truth))
    return paths


def _tum(path: Path, poses: list[tuple[int, np.ndarray]]) -> Path:
    lines = []
    for stamp_ns, T in poses:
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # scipy: x, y, z, w (TUM's order)
        t = T[:3, 3]
        lines.append(f"{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} "
                     f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    path.write_text("\n".join(lines) + ("\n" if lines else ""))
    return path


def _topdown(result: ReplayResult, model: BuildingModel, path: Path, wall_mesh: Any = None,
             stored: SavedMap | None = None) -> Path:
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection


    tr = result.trace
    true_xyz = np.array([T[:3, 3] for T in tr.T_true])
    z = np.nanmedian(true_xyz[:, 2]) if np.isfinite(true_xyz).any() else 0.0
    feats = [f for f in model.features if abs(f.centroid_cad[2] - z) < 2.5] or model.features
    fig, ax = plt.subplots(figsize=(10, 8))
    walls = wall_segments_xy(wall_mesh, float(z))  # cut at the camera's height: through doors and windows
    if len(walls):
        ax.add_collection(LineCollection(list(walls), colors=WALL_COLOUR, linewidths=0.8, zorder=0, label="walls"))
    for kind, colour in (("door", "tab:red"), ("window", "tab:blue")):
        xy = np.array([f.centroid_cad[:2] for f in feats if f.type == kind]).reshape(-1, 2)
        ax.scatter(xy[:, 0], xy[:, 1], s=14, c=colour, marker="s" if kind == "window" else "o", label=kind)
    matched = {f.id: f for f in model.features}
    linked = np.array([matched[fid].centroid_cad[:2] for fid in result.localizer.links.values() if fid in matched])
    if len(linked):
        ax.scatter(linked[:, 0], linked[:, 1], s=90, facecolors="none", edgecolors="tab:green", label="matched")
    _stored_views(ax, stored)
    ax.plot(true_xyz[:, 0], true_xyz[:, 1], "k-", lw=1.2, label="truth")
    est = np.array([T[:3, 3] if T is not None else [np.nan] * 3 for T in tr.T_est])
    ax.plot(est[:, 0], est[:, 1], "-", color="tab:orange", lw=1.0, label="estimate (CAD frame)")
    T_cad_map = result.localizer.graph.T_cad_map()
    if result.localizer.placed and T_cad_map is not None:
        xy = np.array([(T_cad_map @ result.localizer.graph.T_map_body(i))[:2, 3] for i in result.localizer.placed])
        ax.scatter(xy[:, 0], xy[:, 1], s=70, marker="*", c="tab:purple", zorder=5, label="placed in the saved map")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, CAD)")
    ax.set_ylabel("y (m, CAD)")
    ax.legend(loc="best", fontsize=8)
    j = result.to_json()
    ax.set_title(f"localized after {j['time_to_localize_s']} s, APE RMSE {j['ape_rmse_m']} m")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _stored_views(ax: Any, stored: SavedMap | None) -> None:
    """The saved map's keyframe views in the CAD frame, each an arrow along its camera's heading."""
    if stored is None or stored.T_cad_map is None or not stored.placed_views():
        return
    T = np.array([stored.T_cad_map @ T_map_body for T_map_body, _ in stored.placed_views()])
    ax.quiver(T[:, 0, 3], T[:, 1, 3], T[:, 0, 0], T[:, 1, 0], color="tab:gray", alpha=0.6, width=0.002, scale=60,
              zorder=1, label="saved views")


def _frames(result: ReplayResult, path: Path) -> Path:
    import matplotlib.pyplot as plt

    tr = result.trace
    t = np.array(tr.t_s)
    err = np.array([_pose_error(E, T) for E, T in zip(tr.T_est, tr.T_true, strict=True)])  # (N, 5)
    fig, axes = plt.subplots(5, 1, figsize=(10, 11), sharex=True)
    axes[0].plot(t, err[:, 0], label="position")
    axes[0].plot(t, err[:, 1], lw=0.8, label="horizontal")
    axes[0].plot(t, err[:, 2], lw=0.8, label="height (estimate - truth)")
    axes[0].axhline(0.0, color="0.7", lw=0.5)
    axes[0].set_ylabel("error (m)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].plot(t, err[:, 3], lw=0.8, label="tilt")
    axes[1].plot(t, err[:, 4], lw=0.8, label="yaw")
    axes[1].set_ylabel("attitude error (deg)")
    axes[1].legend(loc="upper right", fontsize=8)
    axes[2].step(t, [STATUS_LEVEL.get(s, -1) for s in tr.status], where="post")
    axes[2].set_yticks(list(STATUS_LEVEL.values()), list(STATUS_LEVEL.keys()))
    axes[3].plot(t, tr.n_sightings, ".", ms=2)
    axes[3].set_ylabel("sightings")
    kf = np.array(tr.keyframe)
    axes[4].plot(t[kf], np.array(tr.update_ms)[kf], ".", ms=2)
    axes[4].set_ylabel("iSAM2 update (ms)")
    axes[4].set_xlabel("flight time (s)")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def _pose_error(T_est: np.ndarray | None, T_true: np.ndarray) -> np.ndarray:
    """(position, horizontal, height signed, tilt deg, |yaw| deg) of an estimate against the truth, CAD frame;
    NaN where there is no estimate."""
    if T_est is None:
        return np.full(5, np.nan)
    d = T_est[:3, 3] - T_true[:3, 3]
    up_est, up_true = T_est[:3, :3] @ [0.0, 0.0, 1.0], T_true[:3, :3] @ [0.0, 0.0, 1.0]
    tilt = np.degrees(np.arctan2(np.linalg.norm(np.cross(up_est, up_true)), up_est @ up_true))  # exact near 0 deg
    R = T_true[:3, :3].T @ T_est[:3, :3]
    yaw = abs(np.degrees(np.arctan2(R[1, 0], R[0, 0])))
    return np.array([np.linalg.norm(d), np.linalg.norm(d[:2]), d[2], tilt, yaw])
