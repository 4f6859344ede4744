"""Visual odometry, ORB every frame (`VisualOdometryParams(tracker="orb")`) against optical flow between keyframes
(`tracker="klt"`), in the same run: CPU ms of `StereoOdometry.track` a frame and the path against the truth, on
whole rendered flights with the true gyroscope (issue 37, item 1).

    python -m bench.bench_odometry [--flights office_a-s5-60s jasmin-s3-60s ...] [--frames N] [--json]

Flights: bench.vo_frames (rendered once, cached under /tmp/macroloc-vo-frames; a flight still rendering is run as
far as it got). Both odometries see each frame in turn (which goes first alternates), so both run under the same
load; CPU is the process's (all threads) around `track`. The gyroscope's rotation between frames is the true one.
Accuracy, the path in the first camera's frame against the truth: the position error at the end (drift), its RMSE
over the frames, and the relative pose error over 1 s (30 frames: the translation error of the motion over each
second, median). Also: keyframes made, frames ORB ran on, frames not tracked. `office_a-s5-60s` is also reported on
its first 240 frames (the same run). A benchmark: it prints figures beside the 33.3 ms budget, asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
JASMIN = Path("/work/shared/data/bim/osbim__AC90R1-Jasmin-Sun-105-2x3.ifc")
OFFICE_A = ROOT / "data" / "buildings" / "office_a.ifc"
FLIGHTS = {  # name: (building, seed, duration s); seeds 5, 1, 3: development, 41 and 42: held out
    "office_a-s5-60s": (OFFICE_A, 5, 60.0),
    "office_a-s1-60s": (OFFICE_A, 1, 60.0),
    "jasmin-s3-60s": (JASMIN, 3, 60.0),
    "office_a-s41-30s": (OFFICE_A, 41, 30.0),
    "jasmin-s42-30s": (JASMIN, 42, 30.0),
}
BUDGET_MS = 1000.0 / 30.0
RPE_FRAMES = 30


def path_errors(poses: np.ndarray, T_cad_cam: np.ndarray) -> dict[str, float]:
    """Drift at the end, RMSE of the position error, median 1-s RPE (m), the path's length (m)."""
    truth = np.linalg.inv(T_cad_cam[0]) @ T_cad_cam  # in the first camera's frame, as the odometry's
    err = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    rpe = [np.linalg.norm((np.linalg.inv(np.linalg.inv(truth[i]) @ truth[i + RPE_FRAMES])
                           @ (np.linalg.inv(poses[i]) @ poses[i + RPE_FRAMES]))[:3, 3])
           for i in range(len(poses) - RPE_FRAMES)]
    return {"drift_m": float(err[-1]), "rmse_m": float(np.sqrt(np.mean(err ** 2))),
            "rpe1s_median_m": float(np.median(rpe)) if rpe else float("nan"),
            "path_m": float(np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)))}


class Counted:
    """A StereoOdometry whose ORB runs and keyframes are counted (the instance's methods wrapped)."""

    def __init__(self, odometry: Any) -> None:
        self.vo = odometry
        self.orb_frames = 0
        self.keyframes = 0
        features, keyframe = odometry._features, odometry._keyframe

        def counted_features(*a: Any) -> Any:
            self.orb_frames += 1
            return features(*a)

        def counted_keyframe(*a: Any) -> Any:
            self.keyframes += 1
            return keyframe(*a)
        odometry._features, odometry._keyframe = counted_features, counted_keyframe


def run_flight(name: str, frames: int | None, new: dict[str, Any] | None = None) -> dict[str, Any]:
    from bench.vo_frames import cached, load
    from macroloc.perception.calib import StereoRig
    from macroloc.perception.odometry import StereoOdometry, VisualOdometryParams

    building, seed, duration = FLIGHTS[name]
    fl = load(cached(building, seed, duration), frames)
    fx, fy, cx, cy, baseline_m, w, h = fl.rig
    rig = StereoRig(fx, fy, cx, cy, baseline_m, int(w), int(h))
    modes = {m: Counted(StereoOdometry(rig, VisualOdometryParams(tracker=m, **(new or {}) if m == "klt" else {})))
             for m in ("orb", "klt")}
    cpu: dict[str, list[float]] = {m: [] for m in modes}
    poses: dict[str, list[np.ndarray]] = {m: [] for m in modes}
    lost = dict.fromkeys(modes, 0)
    for i in range(len(fl.left)):
        left, right = np.ascontiguousarray(fl.left[i]), np.ascontiguousarray(fl.right[i])
        R = None if i == 0 else fl.T_cad_cam[i - 1][:3, :3].T @ fl.T_cad_cam[i][:3, :3]  # previous cam <- this
        for m in (("orb", "klt") if i % 2 == 0 else ("klt", "orb")):
            c0 = time.process_time()
            result = modes[m].vo.track(left, right, R)
            cpu[m].append((time.process_time() - c0) * 1e3)
            poses[m].append(result.T_odom_cam)
            lost[m] += not result.tracked
    out: dict[str, Any] = {"flight": name, "frames": len(fl.left)}
    for m, counted in modes.items():
        c = np.array(cpu[m][1:])  # the first frame: a keyframe from nothing
        P = np.array(poses[m])
        out[m] = {"cpu_ms_mean": float(c.mean()), "cpu_ms_p95": float(np.percentile(c, 95)),
                  "keyframes": counted.keyframes, "orb_frames": counted.orb_frames, "lost": lost[m],
                  **path_errors(P, fl.T_cad_cam)}
        if name == "office_a-s5-60s" and len(P) > 240:
            out[m]["first_240"] = {"cpu_ms_mean": float(np.mean(cpu[m][1:240])),
                                   "cpu_ms_p95": float(np.percentile(cpu[m][1:240], 95)),
                                   **path_errors(P[:240], fl.T_cad_cam[:240])}
    return out


def print_flight(r: dict[str, Any]) -> None:
    def row(label: str, o: dict[str, Any], k: dict[str, Any], extra: bool) -> None:
        print(f"{label:<24} {o['cpu_ms_mean']:6.1f} {k['cpu_ms_mean']:6.1f} {o['cpu_ms_p95']:6.1f} "
              f"{k['cpu_ms_p95']:6.1f}  {100 * o['drift_m']:7.2f} {100 * k['drift_m']:7.2f}  "
              f"{100 * o['rmse_m']:6.2f} {100 * k['rmse_m']:6.2f}  {1000 * o['rpe1s_median_m']:6.1f} "
              f"{1000 * k['rpe1s_median_m']:6.1f}  {k['path_m']:5.1f}"
              + (f"  {o['keyframes']}/{k['keyframes']} {o['orb_frames']}/{k['orb_frames']} "
                 f"{o['lost']}/{k['lost']}" if extra else ""))
    row(f"{r['flight']} ({r['frames']})", r["orb"], r["klt"], True)
    if "first_240" in r["orb"]:
        row("  first 240 frames", r["orb"]["first_240"], r["klt"]["first_240"], False)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", nargs="+", default=list(FLIGHTS), choices=list(FLIGHTS))
    ap.add_argument("--frames", type=int, default=None, help="at most this many frames of each flight")
    ap.add_argument("--new", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="VisualOdometryParams fields for the klt odometry (numbers or words), to try settings")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    from macroloc.perception.threads import set_threads

    set_threads()
    if not args.json:
        print(f"visual odometry, orb | klt, true gyro; CPU ms of track() a frame (budget for the whole chain "
              f"{BUDGET_MS:.1f})")
        print(f"{'flight (frames)':<24} {'CPU mean':>13} {'CPU p95':>13}  {'drift cm':>15}  {'RMSE cm':>13}  "
              f"{'RPE 1s mm':>13}  {'path m':>5}  keyframes, ORB frames, lost")
    results = []
    for name in args.flights:
        new = {k: json.loads(v) if v[:1].isdigit() or v[:1] == "-" else v
               for k, v in (a.split("=", 1) for a in args.new)}
        r = run_flight(name, args.frames, new)
        results.append(r)
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            print_flight(r)


if __name__ == "__main__":
    main()
