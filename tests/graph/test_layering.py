"""The layering (docs/architecture.md): common/ imports nothing of the project; graph/ and perception/ are pure
libraries that share only common/; sim/ may use graph/; none of them imports service/, zenoh or the CLI."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("common", "graph", "perception", "service", "sim")
NEVER = {  # package -> what it must never import (project packages by their short name)
    "common": ("graph", "perception", "service", "sim", "zenoh", "typer"),
    "graph": ("perception", "service", "sim", "zenoh", "typer"),
    "perception": ("graph", "service", "sim", "zenoh", "typer"),
    "sim": ("service", "zenoh", "typer"),
}


@pytest.mark.parametrize("package", sorted(NEVER))
def test_each_package_imports_only_what_its_layer_may(package: str) -> None:
    offenders = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            offenders += [f"{path.relative_to(ROOT)}: {n}" for n in names if _package(n) in NEVER[package]]
    assert not offenders, offenders


def _package(module: str) -> str:
    """`macroloc.service.x` -> `service`; a third-party `zenoh.x` -> `zenoh`."""
    parts = module.split(".")
    return parts[1] if parts[0] == "macroloc" and len(parts) > 1 else parts[0]


@pytest.mark.parametrize("folder", ["common", "graph", "perception", "service", "sim", "tests", "bench", "scripts"])
def test_the_project_is_imported_under_its_namespace_only(folder: str) -> None:
    """Installed, the packages are `macroloc.graph`, `macroloc.service`, ...: a bare `import service` would take
    PyPI's `service` (or nothing) instead of ours."""
    bare = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        if "wire" in path.parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
            bare += [f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in PROJECT_PACKAGES]
    assert not bare, bare


def _graph_imports(path: Path) -> set[str]:
    """The graph modules `path` imports, by name (`registration`), at module level and inside functions alike:
    `from macroloc.graph import x` names module x where graph/x.py exists."""
    modules = {p.stem for p in (ROOT / "graph").glob("*.py")}
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[:2] == ["macroloc", "graph"] and len(parts) > 2 and parts[2] in modules:
                found.add(parts[2])
    return found - {path.stem}


def test_graph_has_no_import_cycle() -> None:
    """Each graph module depends on the ones below it only: no two import each other, however indirectly."""
    imports = {p.stem: _graph_imports(p) for p in sorted((ROOT / "graph").glob("*.py"))}
    state: dict[str, str] = {}  # module -> 'open' while on the path being walked, 'done' once cleared

    def cycle_from(module: str, path: list[str]) -> list[str] | None:
        state[module] = "open"
        for dep in sorted(imports.get(module, ())):
            if state.get(dep) == "open":
                return [*path[path.index(dep):], dep] if dep in path else [module, dep]
            if dep not in state and (found := cycle_from(dep, [*path, dep])):
                return found
        state[module] = "done"
        return None

    for module in imports:
        if module not in state:
            cycle = cycle_from(module, [module])
            assert cycle is None, " -> ".join(cycle)
