"""Regenerate proto/ from proto/ with grpcio-tools' protoc (committed; a test checks it is current)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCHEMAS = sorted((ROOT / "proto").rglob("*.proto"))


def generate(out_dir: Path) -> list[Path]:
    from grpc_tools import protoc

    out_dir.mkdir(parents=True, exist_ok=True)
    args = ["protoc", f"-I{ROOT / 'proto'}", f"--python_out={out_dir}", f"--pyi_out={out_dir}"]
    rc = protoc.main(args + [str(p) for p in SCHEMAS])
    if rc != 0:
        raise RuntimeError(f"protoc failed with status {rc}")
    return sorted(p for p in out_dir.rglob("*_pb2.py*"))


if __name__ == "__main__":
    files = generate(ROOT / "proto")
    print("\n".join(str(f.relative_to(ROOT)) for f in files))
    sys.exit(0)
