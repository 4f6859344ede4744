"""perception.image_header: PNG/JPEG sizes read from the header agree with what OpenCV decodes; bombs are sized
without being decoded."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from macroloc.perception.image_header import ImageHeaderError, check_encoded, encoded_size, jpeg_size, png_size
from tests.perception.helpers import png_bomb


def _encode(ext: str, image: np.ndarray, *params: int) -> bytes:
    ok, buf = cv2.imencode(ext, image, list(params))
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("shape", [(48, 64), (480, 640, 3), (1, 1), (7, 3001)])
def test_sizes_from_headers_equal_the_decoded_sizes(shape: tuple[int, ...]) -> None:
    image = (np.random.default_rng(0).random(shape) * 255).astype(np.uint8)
    progressive = _encode(".jpg", image, cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
    for data in (_encode(".png", image), _encode(".jpg", image), progressive):
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert encoded_size(data) == (decoded.shape[1], decoded.shape[0])


def test_a_16_bit_png_and_a_jpeg_with_a_large_app_segment_are_sized() -> None:
    assert png_size(_encode(".png", np.zeros((30, 40), np.uint16))) == (40, 30)
    jpeg = _encode(".jpg", np.zeros((30, 40), np.uint8))
    app1 = b"\xff\xe1" + (2 + 5000).to_bytes(2, "big") + b"\xff\xc0" * 2500  # SOF-like bytes inside a segment
    assert jpeg_size(jpeg[:2] + app1 + jpeg[2:]) == (40, 30)


def test_garbage_and_truncated_headers_are_not_sized() -> None:
    jpeg = _encode(".jpg", np.zeros((30, 40), np.uint8))
    png = _encode(".png", np.zeros((30, 40), np.uint8))
    for data in (b"", b"\x89PNG", png[:20], jpeg[:10], b"\xff\xd8\xff\xda\x00\x02", b"GIF89a" + bytes(20),
                 b"\xff\xd8" + b"\x00" * 30):
        assert encoded_size(data) is None
        with pytest.raises(ImageHeaderError):
            check_encoded(data, 10**9)


def test_the_bomb_is_sized_in_microseconds_and_refused() -> None:
    bomb = png_bomb(20000, 20000)
    assert len(bomb) < 500_000  # ~390 KB on the wire ...
    start = time.perf_counter()
    assert png_size(bomb) == (20000, 20000)  # ... 400 MB decoded
    print(f"header read in {(time.perf_counter() - start) * 1e6:.1f} us for {len(bomb)} bytes")
    with pytest.raises(ImageHeaderError, match="cap"):
        check_encoded(bomb, 4096 * 4096)
    with pytest.raises(ImageHeaderError, match="the message 640x480"):
        check_encoded(bomb, 10**9, (640, 480))
    assert check_encoded(png_bomb(64, 48, 8), 4096, (64, 48)) == (64, 48)


def test_the_crafted_png_decodes_as_it_declares() -> None:
    """The bomb helper builds a real PNG: a small one decodes to zeros of its declared size."""
    image = cv2.imdecode(np.frombuffer(png_bomb(300, 200), np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (200, 300) and image.dtype == np.uint8 and not image.any()
