"""The size of an encoded PNG or JPEG image read from its header, without decoding a pixel.

A compressed image can declare any size: 20000 x 20000 zero pixels compress to a few hundred KB of PNG, and
decoding it (400 MB) and handing it to OpenCV's stereo matcher crashed the process. Whoever decodes bytes
that came from the wire or a file reads the size here first and refuses what is larger than it may be
(`check_encoded`). Only the header is parsed: the PNG's IHDR chunk (which the format requires first) or the
JPEG's first start-of-frame marker (segments before it are skipped by their lengths; an embedded EXIF thumbnail
lies inside its APP1 segment and is skipped with it).
"""

from __future__ import annotations

import struct

DEFAULT_MAX_PIXELS = 4096 * 4096  # the default cap (service.config: inputs.max_image_pixels)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers carry the size; C4 (DHT), C8 (JPG) and CC (DAC) share the range but do not
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD8)}  # TEM, RST0-7: markers without a length


class ImageHeaderError(ValueError):
    """The bytes are not an image this module can size, or the size is not allowed."""


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) in pixels from the IHDR chunk, or None when `data` is not a PNG with one."""
    if len(data) < 24 or data[:8] != PNG_SIGNATURE:
        return None
    length, kind = struct.unpack(">I4s", data[8:16])
    if kind != b"IHDR" or length != 13:
        return None
    width, height = struct.unpack(">II", data[16:24])
    return int(width), int(height)


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) in pixels from the first start-of-frame marker, or None when there is none before the
    scan data (not a JPEG, truncated, or a size left to a later DNL marker: height 0)."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte before a marker
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image or start of scan before any frame header
            return None
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if length < 2:
            return None
        if marker in _JPEG_SOF:
            if i + 9 > len(data) or length < 7:
                return None
            height, width = struct.unpack(">HH", data[i + 5:i + 9])  # after length (2) and precision (1)
            return (int(width), int(height)) if height > 0 else None
        i += 2 + length
    return None


def encoded_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of PNG or JPEG bytes (told apart by their signature), or None."""
    return png_size(data) if data[:8] == PNG_SIGNATURE else jpeg_size(data)


def check_encoded(data: bytes, max_pixels: int, expected_wh: tuple[int, int] | None = None) -> tuple[int, int]:
    """The (width, height) of PNG/JPEG bytes when decoding them is allowed: a readable header, both sides
    positive, at most `max_pixels` pixels, and equal to `expected_wh` where given (the size the message
    declared). Raises ImageHeaderError with the reason otherwise."""
    size = encoded_size(data)
    if size is None:
        raise ImageHeaderError("not a PNG or JPEG with a readable header")
    width, height = size
    if width <= 0 or height <= 0:
        raise ImageHeaderError(f"header says {width}x{height} pixels")
    if width * height > max_pixels:
        raise ImageHeaderError(f"header says {width}x{height} pixels, more than the cap of {max_pixels}")
    if expected_wh is not None and (width, height) != tuple(expected_wh):
        raise ImageHeaderError(f"header says {width}x{height} pixels, the message {expected_wh[0]}x{expected_wh[1]}")
    return width, height
