"""The layering (docs/architecture.md): common/ imports nothing of the project; graph/ and perception/ are pure
libraries that share only common/; proto/ is the wire (protobuf messages, recordings, ROS 2 CDR types, Zenoh keys)
below both the service and the simulated vehicle; sim/ (the simulator and its vehicle) and service/ (the runtime,
its ROS 2 / PX4 adapters and service.offline: replay, bags, reports) never import each other; cli/ (the commands
and the demo, which runs the service against the simulated vehicle) is the composition root above them all. Of the
simulator, only the vehicle (agent) speaks Zenoh. Within service/, the running service never imports
service.offline."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("common", "graph", "perception", "proto", "service", "sim", "cli")
NEVER = {  # package -> what it must never import, anywhere (project packages by their short name)
    "common": ("graph", "perception", "proto", "service", "sim", "cli", "zenoh", "typer"),
    "graph": ("perception", "proto", "service", "sim", "cli", "zenoh", "typer"),
    "perception": ("graph", "proto", "service", "sim", "cli", "zenoh", "typer"),
    "proto": ("service", "sim", "cli", "typer"),
    "sim": ("service", "cli", "typer"),
    "service": ("sim", "cli"),
}
SIM_ON_ZENOH = ("agent",)  # the simulated vehicle on the wire; the rest of sim/ never touches Zenoh


def _imports(path: Path, top_level_only: bool = False) -> list[str]:
    """The modules `path` imports (`from m import x` gives m), anywhere or, with `top_level_only`, those imported
    when the module is: at module level and in class bodies, not inside functions nor under `if TYPE_CHECKING:`."""
    found: list[str] = []

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, ast.Import):
                found.extend(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                found.append(node.module or "")
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if not top_level_only:
                    visit(node.body)
            elif isinstance(node, ast.If) and top_level_only and _is_type_checking(node.test):
                visit(node.orelse)
            else:
                for field in ("body", "orelse", "finalbody", "handlers"):
                    visit([n for n in getattr(node, field, []) if isinstance(n, (ast.stmt, ast.excepthandler))])

    visit(ast.parse(path.read_text()).body)
    return found


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


@pytest.mark.parametrize("package", sorted(NEVER))
def test_each_package_imports_only_what_its_layer_may(package: str) -> None:
    offenders = []
    for path in sorted((ROOT / package).rglob("*.py")):
        if "_pb2" in path.stem:
            continue  # protoc's generated code
        offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path) if _package(n) in NEVER[package]]
        if package == "sim" and path.stem not in SIM_ON_ZENOH:
            offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path) if _package(n) == "zenoh"]
    assert not offenders, offenders


def test_the_running_service_never_imports_offline() -> None:
    offenders = []
    for path in sorted((ROOT / "service").glob("*.py")):
        offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path)
                      if n.startswith("macroloc.service.offline")]
    assert not offenders, offenders


def test_the_rooms_exist() -> None:
    """A guard on the tests above: the folders they read are where they look."""
    assert (ROOT / "service" / "offline" / "replay.py").is_file()
    assert (ROOT / "service" / "front_end.py").is_file() and (ROOT / "service" / "localizer_loop.py").is_file()
    assert (ROOT / "proto" / "recording.py").is_file()
    assert (ROOT / "cli" / "main.py").is_file()
    assert (ROOT / "sim" / "agent.py").is_file()
    assert len(list((ROOT / "service").glob("*.py"))) > 20


def _package(module: str) -> str:
    """`macroloc.service.x` -> `service`; a third-party `zenoh.x` -> `zenoh`."""
    parts = module.split(".")
    return parts[1] if parts[0] == "macroloc" and len(parts) > 1 else parts[0]


@pytest.mark.parametrize("folder", ["common", "graph", "perception", "proto", "service", "sim", "cli", "tests",
                                    "bench", "scripts"])
def test_the_project_is_imported_under_its_namespace_only(folder: str) -> None:
    """Installed, the packages are `macroloc.graph`, `macroloc.service`, ...: a bare `import service` would take
    PyPI's `service` (or nothing) instead of ours."""
    bare = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        if "_pb2" in path.stem:
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
