"""The detector's own time per 640 x 480 frame (letterbox, onnxruntime, decode, NMS), new beside old, one run.

    python -m bench.bench_detector [--new out/run/detector.onnx] [--old /tmp/old/detector.onnx] [--frames 100]
        [--threads 2]

The frame is the real left image of ../shared/data/stereo/rtabmap_stereo_rect (a random one when absent). The old
model is whichever ONNX file `--old` names, with its sidecar beside it (default: the shipped one before issue 32,
taken from git when `--old` is not given and git has it). A benchmark: it prints figures, it asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from bench.common import row, time_ms

ROOT = Path(__file__).resolve().parents[1]
FRAME = Path(os.environ.get("MACROLOC_SHARED_DATA", ROOT.parent / "shared" / "data")) / "stereo" / \
    "rtabmap_stereo_rect" / "left" / "50.jpg"
TARGET_MS = 25.0
OLD_COMMIT = "0077fe3"  # the last commit with the facade-only detector (before issue 32)


def old_from_git(folder: Path) -> Path | None:
    """The pre-issue-32 detector.onnx and .json written into `folder`, or None where git cannot give them."""
    try:
        for suffix in (".onnx", ".json"):
            blob = subprocess.run(["git", "show", f"{OLD_COMMIT}:perception/models/detector{suffix}"], cwd=ROOT,
                                  capture_output=True, check=True).stdout
            (folder / f"detector{suffix}").write_bytes(blob)
    except (subprocess.CalledProcessError, FileNotFoundError):
        return None
    return folder / "detector.onnx"


def load_frame() -> np.ndarray:
    """The real 640 x 480 left frame, or a random one where the shared data is absent."""
    image = cv2.imread(str(FRAME)) if FRAME.exists() else None
    if image is not None and image.shape == (480, 640, 3):
        return image
    return np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--new", type=Path, default=None, help="ONNX model with its sidecar (default: the shipped one)")
    ap.add_argument("--old", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    from macroloc.perception.detector import DEFAULT_MODEL, Detector

    cv2.setNumThreads(args.threads)
    frame = load_frame()
    with tempfile.TemporaryDirectory() as tmp:
        old = args.old or old_from_git(Path(tmp))
        models = [("new", args.new or DEFAULT_MODEL)] + ([("old", old)] if old is not None else [])
        print(f"onnxruntime intra-op threads: {args.threads}; frame 640x480 "
              f"({'rtabmap_stereo_rect/left/50.jpg' if FRAME.exists() else 'random'}); {args.frames} frames")
        for name, path in models:
            detector = Detector(path, threads=args.threads)
            ms = time_ms(partial(detector.detect, frame), repeat=args.frames, warmup=5)
            mb = path.stat().st_size / 2**20
            w, h = detector.spec.input_wh
            print(row(f"{name} detector ({w}x{h} input, {mb:.1f} MB) mean", f"{ms.mean():.1f} ms", "<= 25 ms",
                      bool(ms.mean() <= TARGET_MS)))
            print(row(f"{name} detector p95", f"{np.percentile(ms, 95):.1f} ms", "(none)"))


if __name__ == "__main__":
    main()
