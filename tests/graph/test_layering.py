"""The layering (docs/architecture.md): common/ imports nothing of the project; graph/ and perception/ are pure
libraries that share only common/; sim/ may use graph/; none of them imports service/, zenoh or the CLI, except
sim's vehicle side (agent, demo, demo_route, truth_flight), which speaks the service's wire. The rooms of service/:
its runtime modules (what `macroloc serve` runs) never import service.offline (replay, reports, plots, bags) and
import sim/ only inside functions; service.offline may import the runtime modules."""

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
# sim's vehicle side: the simulated vehicle on the wire (agent), ground-truth flights written as recordings
# (truth_flight) and the closed-loop demo that runs the service against the vehicle (demo, and its route on the
# service's planner: demo_route)
SIM_VEHICLE_SIDE = ("agent", "demo", "demo_route", "truth_flight")
# what the vehicle side may import of the service at module level: the wire (messages, recordings, Zenoh keys)
# and the configuration; any other service module only inside a function (the demo builds the service)
SERVICE_WIRE = ("macroloc.service.wire", "macroloc.service.recording", "macroloc.service.zenoh_io",
                "macroloc.service.config")


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
        if package == "sim" and path.stem in SIM_VEHICLE_SIDE:
            continue  # test_sims_vehicle_side_imports_only_the_services_wire_at_module_level
        offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path) if _package(n) in NEVER[package]]
        if package == "sim":  # the simulator core stays free of the service through the vehicle side, too
            offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path)
                          if n.split(".")[:2] == ["macroloc", "sim"] and n.split(".")[-1] in SIM_VEHICLE_SIDE]
    assert not offenders, offenders


def test_sims_vehicle_side_imports_only_the_services_wire_at_module_level() -> None:
    """agent, demo, demo_route and truth_flight: service's wire and config when imported; the rest of the service (the
    demo's planner and in-process service) only inside functions; never the CLI, nor service.offline."""
    offenders = []
    for stem in SIM_VEHICLE_SIDE:
        path = ROOT / "sim" / f"{stem}.py"
        assert path.is_file(), path
        offenders += [f"sim/{stem}.py: {n}" for n in _imports(path, top_level_only=True)
                      if _package(n) == "service" and not n.startswith(SERVICE_WIRE)]
        offenders += [f"sim/{stem}.py: {n}" for n in _imports(path)
                      if _package(n) == "typer" or n.startswith(("macroloc.service.offline", "macroloc.service.cli",
                                                                 "macroloc.service.commands"))]
    assert not offenders, offenders


def _service_runtime_modules() -> list[Path]:
    """service/'s own modules (what `macroloc serve` is built of, and the CLI's entry): not its sub-rooms
    (service.offline, service.commands) nor the generated wire code."""
    return sorted((ROOT / "service").glob("*.py"))


def test_the_running_service_never_imports_offline_and_sim_only_inside_functions() -> None:
    offenders = []
    for path in _service_runtime_modules():
        offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path)
                      if n.startswith("macroloc.service.offline")]
        offenders += [f"{path.relative_to(ROOT)} (module level): {n}" for n in _imports(path, top_level_only=True)
                      if _package(n) == "sim"]
    assert not offenders, offenders


def test_the_cli_commands_import_offline_and_sim_only_inside_their_command() -> None:
    """Every command module is imported at start (`macroloc serve` too): what replay or the demo needs is imported
    when that command runs."""
    offenders = []
    for path in sorted((ROOT / "service" / "commands").glob("*.py")):
        offenders += [f"{path.relative_to(ROOT)}: {n}" for n in _imports(path, top_level_only=True)
                      if _package(n) == "sim" or n.startswith("macroloc.service.offline")]
    assert not offenders, offenders


def test_the_rooms_exist() -> None:
    """A guard on the tests above: the folders they read are where they look."""
    assert (ROOT / "service" / "offline" / "replay.py").is_file()
    assert (ROOT / "service" / "session.py").is_file()
    assert len(_service_runtime_modules()) > 20


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
