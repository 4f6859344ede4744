"""The real labelled photo sources, one entry each, and their splits: what a leave-one-source-out evaluation and
a training that leaves sources out are built from (numpy/OpenCV only).

A *source* is one photographer's or one camera's set (`../shared/data/images/<folder>`, README there): doors
of one source look alike in ways doors of another do not (camera, lens, building, exporter), so a split of one
source measures memory of it, and only a source left out of training measures what a new camera will see.

Each source is split 80/10/10 by *source photo* (`trainset.split_by_source`: augmented copies of one photo never
sit in two parts), seeded; the facades keep their fixed split (`trainset.split_facades`: img_n with n % 5 == 0 is
the test part).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from macroloc.perception.trainset import (
    FACADE_CLASS_MAP,
    IMAGE_SUFFIXES,
    INDOOR_CLASS_MAP,
    Sample,
    facade_label_path,
    load_sample,
    split_by_source,
    split_facades,
)

CACHE_SIDE_PX = 480  # samples are held with their long side at most this (the network sees 320 x 240)


@dataclass(frozen=True)
class RealSource:
    """One labelled source: its folder under the images root, its label class map, and whether it is indoor."""

    name: str
    folder: str
    class_map: dict[int, int] = field(default_factory=lambda: dict(INDOOR_CLASS_MAP))
    indoor: bool = True


REAL_SOURCES: dict[str, RealSource] = {s.name: s for s in (
    RealSource("robot_door_detection", "indoor_doors/robot_door_detection"),
    RealSource("indoor_objects", "indoor_doors/indoor_objects"),
    RealSource("fisheye_robot", "indoor_doors/fisheye_robot"),
    RealSource("facades", "facades", dict(FACADE_CLASS_MAP), indoor=False),
)}
PARTS = ("train", "val", "test")


def source(name: str) -> RealSource:
    """The registered source of that name; ValueError naming the known ones otherwise."""
    if name not in REAL_SOURCES:
        raise ValueError(f"unknown photo source {name!r} (known: {', '.join(REAL_SOURCES)})")
    return REAL_SOURCES[name]


def folder_images(folder: Path) -> list[Path]:
    """Every image file of a source's folder (its images/, sorted); empty where it is absent."""
    images = folder / "images"
    if not images.is_dir():
        return []
    return sorted(p for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def source_images(images_root: Path, src: RealSource) -> list[Path]:
    """Every image file of one source under the images root (sorted); empty where the folder is absent."""
    return folder_images(images_root / src.folder)


def split_folder(folder: Path, src: RealSource, seed: int = 0) -> dict[str, list[Path]]:
    """{"train", "val", "test"} image paths of one source's folder: by source photo, or the facades' fixed split."""
    if not src.indoor:
        return split_facades(folder, seed) if (folder / "images").is_dir() else {p: [] for p in PARTS}
    return split_by_source(folder_images(folder), seed)


def split_source(images_root: Path, src: RealSource, seed: int = 0) -> dict[str, list[Path]]:
    """`split_folder` of one source under the images root."""
    return split_folder(images_root / src.folder, src, seed)


def load(paths: list[Path], src: RealSource) -> list[Sample]:
    """The images and their boxes in memory (long side <= `CACHE_SIDE_PX`)."""
    return [load_sample(p, facade_label_path(p), src.class_map, CACHE_SIDE_PX) for p in paths]


def load_split(images_root: Path, src: RealSource, seed: int = 0) -> dict[str, list[Sample]]:
    """One source's parts, loaded."""
    return {part: load(paths, src) for part, paths in split_source(images_root, src, seed).items()}


def load_all(images_root: Path, src: RealSource) -> list[Sample]:
    """All of one source: what a model trained without it is scored on."""
    return load(source_images(images_root, src), src)
