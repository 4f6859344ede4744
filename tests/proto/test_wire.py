"""The committed Python of the wire contract is exactly what protoc makes of proto/ today."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _gen_module():
    spec = importlib.util.spec_from_file_location("gen_proto", ROOT / "scripts" / "gen_proto.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("gen_proto", module)
    spec.loader.exec_module(module)
    return module


def test_generated_python_matches_schemas(tmp_path: Path) -> None:
    fresh = _gen_module().generate(tmp_path)
    assert fresh, "protoc produced nothing"
    for path in fresh:
        committed = ROOT / "proto" / path.relative_to(tmp_path)
        assert committed.exists(), f"{committed} is missing: run `make proto`"
        assert committed.read_bytes() == path.read_bytes(), f"{committed} is stale: run `make proto`"


def test_field_numbers_are_stable() -> None:
    """Subscribers in other languages rely on these numbers: add fields, never renumber."""
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb

    def numbers(msg) -> dict[str, int]:
        return {f.name: f.number for f in msg.DESCRIPTOR.fields}

    assert numbers(pb.StereoFrame) == {"header": 1, "camera_id": 2, "left": 3, "right": 4, "info": 5, "depth": 6}
    assert numbers(pb.PoseEstimate) == {"header": 1, "T_cad_body": 2, "covariance": 3, "status": 4, "storey": 5,
                                        "T_cad_map": 6, "inliers": 7, "T_enu_body": 8, "wgs84": 9}
    assert numbers(pb.Goal)["position_cad"] == 2 and numbers(pb.Goal)["space_name"] == 4
    assert numbers(pb.Waypoints)["points_cad"] == 2 and numbers(pb.Waypoints)["yaw_rad"] == 6
    assert numbers(pb.Odometry) == {"header": 1, "T_map_body": 2, "covariance": 3}
    assert pb.DESCRIPTOR.package == "macroloc.v1"


def test_round_trip_of_every_message() -> None:
    from macroloc.proto.macroloc.v1 import macroloc_pb2 as pb

    for name, desc in pb.DESCRIPTOR.message_types_by_name.items():
        cls = getattr(pb, name)
        msg = cls()
        if "header" in desc.fields_by_name:
            msg.header.stamp_ns = 123
        assert cls.FromString(msg.SerializeToString()) == msg


def test_the_declared_protobuf_runtime_is_one_the_generated_code_accepts() -> None:
    """The generated modules refuse a protobuf runtime older than the protoc that made them
    (`ValidateProtobufRuntimeVersion`) or of another major: pyproject.toml must not allow one."""
    import re
    import tomllib

    from packaging.requirements import Requirement
    from packaging.version import Version

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    declared = next(Requirement(d) for d in deps if Requirement(d).name == "protobuf").specifier
    for module in (ROOT / "proto").rglob("*_pb2.py"):
        found = re.search(r"ValidateProtobufRuntimeVersion\(\s*\S+,\s*(\d+),\s*(\d+),\s*(\d+),", module.read_text())
        assert found, f"{module}: no runtime version check found"
        needed = Version(".".join(found.groups()))
        older = Version(f"{needed.major}.{needed.minor}.{needed.micro - 1}") if needed.micro else \
            Version(f"{needed.major}.{needed.minor - 1}.99") if needed.minor else Version(f"{needed.major - 1}.99")
        assert declared.contains(needed), f"pyproject.toml's protobuf{declared} refuses {needed}, {module.name}'s"
        assert not declared.contains(older), f"pyproject.toml's protobuf{declared} allows {older} < {needed}"
        assert not declared.contains(f"{needed.major + 1}.0.0"), f"protobuf{declared} allows another major"
