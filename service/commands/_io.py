"""Small helpers shared by the commands: reading user files with clean errors, printing JSON."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

from graph.errors import UserInputError


def existing_file(path: Path, what: str) -> Path:
    if not path.exists():
        raise UserInputError(f"{what} not found: {path}")
    if not path.is_file():
        raise UserInputError(f"{what} is not a file: {path}")
    return path


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
