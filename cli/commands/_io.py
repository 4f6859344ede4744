"""Small helpers shared by the commands: reading user files with clean errors, printing JSON."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

from macroloc.graph.errors import UserInputError


def existing_file(path: Path, what: str) -> Path:
    if not path.exists():
        raise UserInputError(f"{what} not found: {path}")
    if not path.is_file():
        raise UserInputError(f"{what} is not a file: {path}")
    return path


def read_image(path: Path, what: str, flags: int, max_pixels: int | None = None) -> Any:
    """An image file as numpy (cv2.imdecode `flags`), its size read from the header first: a file that
    declares more than `max_pixels` (default: the config's inputs.max_image_pixels) pixels, or whose header
    cannot be read, is refused (UserInputError) before anything is decoded. PNG and JPEG headers are parsed
    here (perception.image_header); other formats are sized by Pillow, which reads only the header."""
    import cv2
    import numpy as np

    from macroloc.perception.image_header import ImageHeaderError, check_encoded, encoded_size

    if max_pixels is None:
        from macroloc.service.config import load_config

        max_pixels = load_config().inputs.max_image_pixels
    data = existing_file(path, what).read_bytes()
    try:
        if encoded_size(data) is None:
            _check_with_pillow(path, max_pixels)
        else:
            check_encoded(data, max_pixels)
    except ImageHeaderError as exc:
        raise UserInputError(f"{what} {path} refused before decoding: {exc}") from None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise UserInputError(f"cannot read {what} (not a supported image file): {path}")
    return image


def _check_with_pillow(path: Path, max_pixels: int) -> None:
    from PIL import Image, UnidentifiedImageError

    from macroloc.perception.image_header import ImageHeaderError

    try:
        with Image.open(path) as image:  # lazy: the header only
            width, height = image.size
    except Image.DecompressionBombError as exc:
        raise ImageHeaderError(str(exc)) from None
    except (UnidentifiedImageError, OSError, ValueError):
        raise ImageHeaderError("not an image file whose header can be read") from None
    if width * height > max_pixels:
        raise ImageHeaderError(f"header says {width}x{height} pixels, more than the cap of {max_pixels}")


MAX_JSON_BYTES = 64 * 2**20  # a request or a config, not a data set: bigger files are refused before reading


def read_json(path: Path, what: str) -> Any:
    """A user's JSON file; one-line UserInputError for a missing, oversized, malformed, too deeply nested file or
    an integer of more digits than Python converts (4300)."""
    existing_file(path, what)
    size = path.stat().st_size
    if size > MAX_JSON_BYTES:
        raise UserInputError(f"{what} {path} is {size / 2**20:.0f} MiB, more than the {MAX_JSON_BYTES >> 20} MiB "
                             f"accepted")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UserInputError(f"{what} {path} is not valid JSON: {exc.msg} at line {exc.lineno}") from None
    except UnicodeDecodeError:
        raise UserInputError(f"{what} {path} is not a text file") from None
    except RecursionError:
        raise UserInputError(f"{what} {path} nests arrays or objects too deeply") from None
    except ValueError as exc:  # an integer beyond sys.get_int_max_str_digits()
        raise UserInputError(f"{what} {path}: {str(exc).split(';')[0]}") from None


def _finite(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def print_json(doc: Any) -> None:
    """Print a JSON document on stdout (NaN/inf become null: strict JSON)."""
    sys.stdout.write(json.dumps(_finite(doc)) + "\n")
    sys.stdout.flush()
