"""What place recognition keeps of a keyframe (perception.place makes it, graph.mapstore saves it)."""

from __future__ import annotations

import base64
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class KeyframeView:
    """What place recognition keeps of a keyframe: image features' 3D points (N, 3, body frame, metres) and
    their binary descriptors (N, 32 bytes: ORB), row for row."""

    points_body: np.ndarray
    descriptors: np.ndarray

    def to_bytes(self) -> tuple[bytes, bytes]:
        """(points as little-endian float32, descriptors as uint8), row for row."""
        return (np.ascontiguousarray(self.points_body, "<f4").tobytes(),
                np.ascontiguousarray(self.descriptors, np.uint8).tobytes())

    @classmethod
    def from_bytes(cls, points_body: bytes, descriptors: bytes) -> KeyframeView:
        """`to_bytes`' inverse; ValueError where the sizes do not make whole rows of equal number."""
        points = np.frombuffer(points_body, "<f4").reshape(-1, 3).astype(np.float64)
        rows = np.frombuffer(descriptors, np.uint8).reshape(-1, 32)
        if len(points) != len(rows):
            raise ValueError("a keyframe view's points and descriptors differ in number")
        return cls(points, rows)

    def to_json(self) -> dict:
        points, descriptors = self.to_bytes()
        return {"points_body": base64.b64encode(points).decode("ascii"),
                "descriptors": base64.b64encode(descriptors).decode("ascii")}

    @classmethod
    def from_json(cls, doc: dict) -> KeyframeView:
        return cls.from_bytes(base64.b64decode(doc["points_body"]), base64.b64decode(doc["descriptors"]))
