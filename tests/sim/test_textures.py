"""Textures: seeded procedural layers, and photo crops only from the train split of the facade photos."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from macroloc.sim.textures import TEXTURE_SIZE_PX, facade_crops, make_texture_layers


def test_procedural_layers_are_seeded_and_textured() -> None:
    a, b, c = make_texture_layers(1, 64), make_texture_layers(1, 64), make_texture_layers(2, 64)
    assert a.dtype == np.uint8 and a.shape[1:] == (64, 64, 3)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert all(layer.std() > 4 for layer in a)  # every surface carries texture for stereo and odometry


def _photo(folder: Path, n: int, colour: tuple[int, int, int]) -> None:
    import cv2

    img = np.zeros((200, 200, 3), np.uint8)
    img[:] = colour
    cv2.imwrite(str(folder / "images" / f"img_{n}.jpg"), img)
    # one door (class 5) and one window (class 0) box
    (folder / "labels" / f"img_{n}.txt").write_text("5 0.5 0.5 0.5 0.8\n0 0.5 0.5 0.5 0.5\n")


def test_photo_crops_never_use_the_held_out_split(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    (tmp_path / "labels").mkdir()
    _photo(tmp_path, 10, (0, 0, 255))  # n % 5 == 0: the detector's test split, red
    _photo(tmp_path, 15, (0, 0, 255))
    _photo(tmp_path, 11, (255, 0, 0))  # train split, blue (BGR)
    _photo(tmp_path, 12, (255, 0, 0))
    doors, windows = facade_crops(tmp_path, seed=0, n_doors=4, n_windows=4)
    crops = np.concatenate([doors, windows])
    assert len(crops) >= 1 and crops.shape[1:] == (TEXTURE_SIZE_PX, TEXTURE_SIZE_PX, 3)
    assert (crops[..., 2] > 200).all() and (crops[..., 0] < 50).all()  # RGB: blue photos only, never red


def test_the_simulator_core_does_not_import_service() -> None:
    root = Path(__file__).resolve().parents[2] / "sim"
    for path in root.glob("*.py"):
        if path.stem in ("agent", "demo", "truth_flight"):
            continue  # sim's vehicle side speaks the service's wire: tests/graph/test_layering.py holds its rule
        text = path.read_text()
        assert "from service" not in text and "import service" not in text and "zenoh" not in text, path.name
