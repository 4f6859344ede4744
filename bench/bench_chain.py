"""The whole per-frame chain at 640 x 480 on rendered frames with doors in view, before and after issue 37, in
the same run: visual odometry, depth points, detector, stereo, line refinement, reconstruction, stage by stage
in CPU ms (the process's, all threads) and wall ms, beside the 30 frames/s target.

    python -m bench.bench_chain [--frames 60] [--sgbm-scale 1.0] [--vo klt] [--schedule] [--json]

Frames: bench.chain_frames (Office_A seed 1, 60 consecutive frames, rendered once and cached). The detector runs
on every frame and is timed, but the boxes reconstructed are the true ones (the shipped detector finds few
openings in these renders; the issue's figures are for a door in view). The gyroscope's rotation between frames
is the true one. OLD: the chain as it was (its own band SGBM at 64 disparities, a full-frame SGBM at 128 for the
depth points every third frame and another at the odometry's keyframes; the pure-Python segment joiner; the
wall plane's RANSAC hypothesis by hypothesis and np.nanmedian; ORB 2000 matched every frame: bench.chain_old).
NEW: the chain as it is (the odometry's default: optical flow between keyframes, ORB only for new keyframes).
Old and new run frame by frame in turn, so both see the same load. Accuracy: each opening's corners, old against
new and both against the truth; the odometry's drift against the true path. A benchmark: it prints figures,
asserts nothing.

`--schedule`: both chains run as the service and the replay schedule them, not the whole chain on every frame:
the detector and what follows it on every third frame ([perception] detect_every), the odometry on every frame;
the old chain's depth points every third frame, the new chain's on the frames that become keyframes (the
session's keyframe rule on the odometry's poses: [perception.depth] at_keyframes), where the new chain's odometry
also re-keys ([perception.odometry] rekey_at_session_keyframes; its cost counted in "depth"). A stage's mean is
over all frames, skipped ones counting 0.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from macroloc.perception.odometry import StereoOdometry
    from macroloc.perception.pipeline import Perception
    from macroloc.service.frames import StereoDepth

ROOT = Path(__file__).resolve().parents[1]
BUDGET_MS = 1000.0 / 30.0
STAGES = ("vo", "depth", "detect", "lines", "stereo", "reconstruct")


@dataclass
class Chain:
    """One version of the per-frame chain: its components and the stages' CPU and wall ms per frame."""

    name: str
    odometry: StereoOdometry
    depth: StereoDepth
    perception: Perception
    join: Callable[..., list[np.ndarray]] | None  # the old joiner; also: the old reconstruction (bench.chain_old)
    cpu_ms: dict[str, list[float]] = field(default_factory=dict)
    wall_ms: dict[str, list[float]] = field(default_factory=dict)
    features: list[list[Any]] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)

    def lap(self, stage: str, fn: Callable[[], Any]) -> Any:
        c0, w0 = time.process_time(), time.perf_counter()
        out = fn()
        self.cpu_ms.setdefault(stage, []).append((time.process_time() - c0) * 1e3)
        self.wall_ms.setdefault(stage, []).append((time.perf_counter() - w0) * 1e3)
        return out


def make_chains(rig, sgbm_scale: float = 1.0, vo: str | None = None,  # type: ignore[no-untyped-def]
                at_keyframes: bool = False) -> tuple[Chain, Chain]:
    from bench.chain_old import OLD_ODOMETRY, join_segments_python
    from macroloc.perception.odometry import StereoOdometry, VisualOdometryParams
    from macroloc.perception.pipeline import Perception
    from macroloc.perception.stereo import FrameDisparity, SgbmMatcher, SgbmParams
    from macroloc.perception.threads import THREADS
    from macroloc.service.frames import StereoDepth

    old = Chain("old", StereoOdometry(rig, OLD_ODOMETRY), StereoDepth(), Perception.create(threads=2),
                join_segments_python)
    shared = FrameDisparity(SgbmMatcher(SgbmParams(num_disparities=128, scale=sgbm_scale)))  # one thread, as the
    #   service's front end: each frame's consumers in turn
    config = VisualOdometryParams() if vo is None else VisualOdometryParams(tracker=vo)
    new = Chain("new", StereoOdometry(rig, config, disparity=shared),
                StereoDepth(disparity=shared, at_keyframes=at_keyframes),
                Perception.create(threads=THREADS.onnxruntime, disparity=shared), None)
    return old, new


@dataclass
class Schedule:
    """`--schedule`: the detector every `detect_every`-th frame; depth points where the keyframe rule makes a
    keyframe of the odometry's pose (new chain) or every third frame (old chain)."""

    detect_every: int = 3
    frame_s: float = 1.0 / 30.0
    _T_kf: np.ndarray | None = None
    _since_kf_s: float = 0.0

    def keyframe(self, T_odom_cam: np.ndarray) -> bool:
        from macroloc.graph.keyframes import KeyframeRule

        due = KeyframeRule().is_keyframe(self._T_kf, T_odom_cam, self._since_kf_s, False, False)
        self._since_kf_s += self.frame_s
        if due:
            self._T_kf, self._since_kf_s = T_odom_cam, self.frame_s
        return due


def _keyframe_depth(chain: Chain, left: np.ndarray, right: np.ndarray, rig) -> np.ndarray:  # type: ignore[no-untyped-def]
    """A session keyframe's depth points, the odometry re-keyed on the same SGBM first where it is set to
    (replay_sources.VisualOdometry does the same)."""
    if chain.odometry.config.rekey_at_session_keyframes:
        chain.odometry.rekey()
    return chain.depth.measure(left, right, rig, np.eye(4))


def run_frame(chain: Chain, left: np.ndarray, right: np.ndarray, rig, boxes, R_prev_cur,  # type: ignore[no-untyped-def]
              schedule: Schedule | None = None, i: int = 0) -> None:
    from bench.chain_old import band_depth_m, old_reconstruction
    from macroloc.perception.detector import Detection
    from macroloc.perception.lines import refine_box
    from macroloc.perception.pipeline import ObservedFeature, StereoPair
    from macroloc.perception.stereo import to_gray

    p = chain.perception
    pair = StereoPair(left, right, rig)
    result = chain.lap("vo", lambda: chain.odometry.track(left, right, R_prev_cur))
    chain.poses.append(result.T_odom_cam)
    if schedule is not None and chain.depth.at_keyframes:
        due = schedule.keyframe(result.T_odom_cam)  # the rule on the camera's poses: the body's up to its lever arm
        chain.lap("depth", lambda: _keyframe_depth(chain, left, right, rig) if due else None)
    else:
        chain.lap("depth", lambda: chain.depth(left, right, rig, np.eye(4)))
    if schedule is not None and i % schedule.detect_every:
        for stage in STAGES[2:]:
            chain.lap(stage, lambda: None)
        chain.features.append([None] * len(boxes))
        return
    chain.lap("detect", lambda: p.detector.detect(left))
    dets = [Detection(t, 1.0, b) for t, b in boxes]
    kw: dict[str, Any] = {} if chain.join is None else {"join": chain.join}
    sides = chain.lap("lines", lambda: [refine_box(g, d.box_xyxy, p.lines, **kw)
                                        for g in [to_gray(left)] for d in dets])
    depth_m = chain.lap("stereo", lambda: band_depth_m(p, pair, dets) if chain.join is not None
                        else p._depth_m(pair, dets, sides))
    with old_reconstruction() if chain.join is not None else contextlib.nullcontext():
        out = chain.lap("reconstruct", lambda: [p._reconstruct(d, s, depth_m, pair)
                                                for d, s in zip(dets, sides, strict=True)])
    chain.features.append([f if isinstance(f, ObservedFeature) else None for f in out])


def drift(poses: list[np.ndarray], T_cad_cam: np.ndarray) -> tuple[float, float]:
    """(final position error, RMSE over the frames) of the odometry's path against the truth, metres."""
    T0 = T_cad_cam[0]
    err = [np.linalg.norm((np.linalg.inv(T0) @ T_cad_cam[i])[:3, 3] - P[:3, 3]) for i, P in enumerate(poses)]
    return float(err[-1]), float(np.sqrt(np.mean(np.square(err))))


def accuracy(old: Chain, new: Chain, truth: list[list[np.ndarray | None]]) -> dict[str, object]:
    both, only_old, only_new, diff = 0, 0, 0, []
    err: dict[str, list[float]] = {"old": [], "new": []}
    for fo, fn, tr in zip(old.features, new.features, truth, strict=True):
        for a, b, t in zip(fo, fn, tr, strict=True):
            both += a is not None and b is not None
            only_old += a is not None and b is None
            only_new += a is None and b is not None
            if a is not None and b is not None:
                diff.extend(np.linalg.norm(a.corners_cam - b.corners_cam, axis=1))
            for name, f in (("old", a), ("new", b)):
                if f is not None and t is not None:
                    err[name].extend(np.linalg.norm(f.corners_cam - t, axis=1))

    def q(v: list[float]) -> list[float] | None:
        return [round(float(np.median(v)), 4), round(float(np.percentile(v, 90)), 4), len(v)] if v else None
    return {"features_in_both": both, "only_old": only_old, "only_new": only_new,
            "corner_old_vs_new_m_median_p90_max": None if not diff else
            [round(float(np.median(diff)), 4), round(float(np.percentile(diff, 90)), 4), round(float(max(diff)), 4)],
            "corner_error_vs_truth_m_median_p90_n": {k: q(v) for k, v in err.items()}}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--sgbm-scale", type=float, default=1.0, help="the new chain's SGBM on the pair shrunk so")
    ap.add_argument("--boxes", type=int, default=0, help="keep the N largest openings a frame (0: all)")
    ap.add_argument("--vo", choices=("orb", "klt"), default=None,
                    help="the new chain's odometry tracker (default: VisualOdometryParams's)")
    ap.add_argument("--schedule", action="store_true",
                    help="the detector every third frame, the new chain's depth points at keyframes (see above)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    from bench.chain_frames import load, render
    from macroloc.perception.calib import StereoRig
    from macroloc.perception.threads import THREADS, set_threads

    set_threads()
    fr = load(render(ROOT / "data" / "buildings" / "office_a.ifc", 1, 60, 30.0))
    fx, fy, cx, cy, baseline_m, w, h = fr.rig
    rig = StereoRig(fx, fy, cx, cy, baseline_m, int(w), int(h))
    old, new = make_chains(rig, args.sgbm_scale, args.vo, at_keyframes=args.schedule)
    schedules = {old.name: Schedule(), new.name: Schedule()} if args.schedule else {}
    n = min(args.frames, len(fr.left))
    boxes, truth = fr.boxes, fr.corners_cam
    if args.boxes:  # the N largest openings of each frame (--boxes 1: the "one door in view")
        def area(box: tuple[str, tuple[float, float, float, float]]) -> float:
            x0, y0, x1, y1 = box[1]
            return (x1 - x0) * (y1 - y0)

        order = [[int(k) for k in np.argsort([-area(x) for x in b], kind="stable")[:args.boxes]] for b in boxes]
        boxes = [[b[k] for k in o] for b, o in zip(boxes, order, strict=True)]
        truth = [[t[k] for k in o] for t, o in zip(truth, order, strict=True)]
    for i in range(n):  # interleaved, frame by frame: both see the same load on the machine
        R = None if i == 0 else fr.T_cad_cam[i - 1][:3, :3].T @ fr.T_cad_cam[i][:3, :3]  # previous cam <- this
        for chain in (old, new):
            run_frame(chain, fr.left[i], fr.right[i], rig, boxes[i], R, schedules.get(chain.name), i)
    out: dict[str, Any] = {"frames": n, "openings": sum(len(b) for b in boxes[:n]),
                              "threads": THREADS.describe(), "budget_ms": round(BUDGET_MS, 1),
                          "sgbm_scale_new": args.sgbm_scale, "schedule": args.schedule}
    for c in (old, new):
        cpu = {k: round(float(np.mean(v)), 2) for k, v in c.cpu_ms.items()}
        wall = {k: round(float(np.mean(v)), 2) for k, v in c.wall_ms.items()}
        out[c.name] = {"cpu_ms": cpu, "wall_ms": wall, "cpu_total_ms": round(sum(cpu.values()), 1),
                       "wall_total_ms": round(sum(wall.values()), 1),
                       "fps_cpu": round(1000.0 / sum(cpu.values()), 1),
                       "fps_wall": round(1000.0 / sum(wall.values()), 1),
                       "vo_drift_final_rmse_m": [round(v, 4) for v in drift(c.poses, fr.T_cad_cam[:n])],
                       "sgbm_per_frame": round(getattr(c.depth.matcher, "computed", -1) / n, 2)}
    out["accuracy"] = accuracy(old, new, truth[:n])
    if args.json:
        print(json.dumps(out))
        return
    print(f"chain at 640x480, {n} rendered frames (Office_A seed 1), {out['openings']} openings in view; "
          f"threads: {out['threads']}; new SGBM scale {args.sgbm_scale}; "
          + ("as scheduled in the service (detector every 3rd frame; depth: old every 3rd, new at keyframes)"
             if args.schedule else "the whole chain on every frame"))
    print(f"{'stage':<12} {'old CPU':>8} {'new CPU':>8} {'old wall':>9} {'new wall':>9}  (ms a frame, mean)")
    o, w = out["old"], out["new"]
    for stage in STAGES:
        print(f"{stage:<12} {o['cpu_ms'][stage]:8.1f} {w['cpu_ms'][stage]:8.1f} {o['wall_ms'][stage]:9.1f} "
              f"{w['wall_ms'][stage]:9.1f}")
    print(f"{'total':<12} {o['cpu_total_ms']:8.1f} {w['cpu_total_ms']:8.1f} {o['wall_total_ms']:9.1f} "
          f"{w['wall_total_ms']:9.1f}")
    print(f"{'frames/s':<12} {o['fps_cpu']:8.1f} {w['fps_cpu']:8.1f} {o['fps_wall']:9.1f} {w['fps_wall']:9.1f}"
          f"   target >= 30 (budget {BUDGET_MS:.1f} ms)")
    print(f"odometry drift (final, RMSE m): old {o['vo_drift_final_rmse_m']}, new {w['vo_drift_final_rmse_m']}")
    print(f"SGBM runs a frame, new chain (one FrameDisparity): {w['sgbm_per_frame']}")
    print("accuracy:", json.dumps(out["accuracy"]))

if __name__ == "__main__":
    main()
