"""Issue 33's figures: a simulated flight as ROS 2 bags replays to the native recording's figures.

    python -m bench.bench_ros_bag [--flight FLIGHT.mcap | --seed 4 --duration 6] [--building office_a.ifc]
                                  [--detector data/buildings/office_a_detector/detector.onnx] [--out /tmp/rosbag-bench]

The flight (rendered with `macroloc simulate` unless given) is written as bags with service.offline.ros_bag_write:
`.db3` with sensor_msgs/Image, one `.mcap` with CompressedImage (non-default topic names in both), and a `.db3` whose
images are distorted with known coefficients (CameraInfo D) for the reader to rectify. Printed: the bag reading
throughput beside the native reader's (frames/s, images decoded), the rectified images' median absolute difference
from the originals (grey levels), and each replay's frames, time to localize and APE (`--observations perception`).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shutil
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DISTORTION = np.array([-0.28, 0.09, 0.0008, -0.0005, -0.012])  # k1, k2, p1, p2, k3
TOPICS = dict(left="/drone/stereo/left/image", right="/drone/stereo/right/image", left_info="/drone/stereo/left/info",
              right_info="/drone/stereo/right/info", imu="/drone/imu", truth="/mocap/body_in_cad")


def _read_fps(frames) -> tuple[int, float]:  # noqa: ANN001 - an iterator of FlightFrame
    from macroloc.proto.recording import decode_image

    start, n = time.perf_counter(), 0
    for f in frames:
        decode_image(f.stereo.left), decode_image(f.stereo.right)
        n += 1
    return n, n / (time.perf_counter() - start)


def _replay(path: Path, building: Path, config: Path | None, topics: dict[str, str] | None) -> dict:
    import json

    from macroloc.cli.main import main

    argv = ["replay", str(path), "--building", str(building), "--observations", "perception", "--json"]
    argv += ["--config", str(config)] if config else []
    for name, topic in (topics or {}).items():
        argv += ["--topic", f"{name}={topic}"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    return json.loads(out.getvalue())


def main() -> None:
    from macroloc.proto.recording import decode_image, read_flight
    from macroloc.service.offline.ros_bag import read_ros_bag
    from macroloc.service.offline.ros_bag_write import BagTopics, write_ros_bag

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flight", type=Path)
    parser.add_argument("--building", type=Path, default=ROOT / "data/buildings/office_a.ifc")
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--duration", type=float, default=6.0)
    parser.add_argument("--detector", type=Path, default=ROOT / "data/buildings/office_a_detector/detector.onnx")
    parser.add_argument("--out", type=Path, default=Path("/tmp/rosbag-bench"))
    args = parser.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    flight = args.flight
    if flight is None:
        from macroloc.cli.main import main as cli

        flight = args.out / "flight.mcap"
        with contextlib.redirect_stdout(io.StringIO()):
            assert cli(["simulate", str(args.building), "--out", str(flight), "--seed", str(args.seed),
                        "--duration", str(args.duration), "--json"]) == 0
    config = None
    if args.detector:
        config = args.out / "detector.toml"
        config.write_text(f'[perception]\ndetector_model = "{args.detector}"\n')
    topics = BagTopics(**TOPICS)
    bags = {"db3 Image": write_ros_bag(flight, args.out / "db3", "sqlite3", topics),
            "mcap CompressedImage": next(write_ros_bag(flight, args.out / "mcap", "mcap", topics,
                                                       compressed=True).glob("*.mcap")),
            "db3 distorted": write_ros_bag(flight, args.out / "distorted", "sqlite3", topics, distortion=DISTORTION)}
    n, fps = _read_fps(read_flight(flight))
    print(f"read native MCAP: {n} frames, {fps:.1f} frames/s")
    for name, bag in bags.items():
        n, fps = _read_fps(read_ros_bag(bag, TOPICS))
        print(f"read bag {name}: {n} frames, {fps:.1f} frames/s")
    diffs = [np.median(np.abs(decode_image(b.stereo.left)[60:-60, 80:-80].astype(int)
                              - decode_image(a.stereo.left)[60:-60, 80:-80].astype(int)))
             for a, b in zip(read_flight(flight), read_ros_bag(bags["db3 distorted"], TOPICS), strict=True)]
    print(f"rectified vs original left images (inner 3/4): median |diff| {np.median(diffs):.2f} grey levels "
          f"(per-frame medians {min(diffs):.1f}-{max(diffs):.1f})")
    print(f"{'recording':<22} {'frames':>6} {'localize s':>10} {'APE rmse m':>10} {'keyframes':>9} {'wall s':>7}")
    for name, path, tp in [("native", flight, None), *[(k, v, TOPICS) for k, v in bags.items()]]:
        start = time.perf_counter()
        doc = _replay(path, args.building, config, tp)
        print(f"{name:<22} {doc['frames']:>6} {doc['time_to_localize_s']!s:>10} {doc['ape_rmse_m']!s:>10} "
              f"{doc['keyframes']:>9} {time.perf_counter() - start:>7.1f}")


if __name__ == "__main__":
    main()
