"""Every `file.py:function` that docs/architecture.md's data-flow diagram names exists: the file, and in it the
function, the class, or the class's method."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "architecture.md"
BOX = re.compile(r"\b((?:[a-z_]+/)+[a-z_0-9]+\.py):([A-Za-z_][A-Za-z_0-9]*(?:\.[A-Za-z_][A-Za-z_0-9]*)?)")


def _diagram() -> str:
    text = ARCHITECTURE.read_text()
    start = text.index("## Data flow")
    block = text.index("```mermaid", start)
    return text[block:text.index("```", block + 3)]


def _defined(path: Path) -> set[str]:
    """`name` of each module-level function and class, `Class.method` of each method."""
    names: set[str] = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(node.name)
        elif isinstance(node, ast.ClassDef):
            names.add(node.name)
            names |= {f"{node.name}.{m.name}" for m in node.body
                      if isinstance(m, (ast.FunctionDef, ast.AsyncFunctionDef))}
    return names


def test_every_box_of_the_frames_path_is_a_function_that_exists() -> None:
    boxes = BOX.findall(_diagram())
    assert len(boxes) > 25, "the diagram names its boxes file.py:function"
    missing = [f"{path}:{name}" for path, name in boxes
               if not (ROOT / path).is_file() or name not in _defined(ROOT / path)]
    assert not missing, missing
