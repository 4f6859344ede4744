"""Every example the documentation marks as runnable runs, and does what the text says.

A fenced block is an example when an HTML comment (invisible on GitHub) stands on the line before it:

    <!-- example: file OBS.json -->      the block is written to OBS.json in the example's folder
    <!-- example: shell -->              each line runs in bash there (`macroloc` is this checkout's CLI)
    <!-- example: python -->            the block runs as a Python script there
    <!-- example: output json -->       the last run's stdout is JSON holding at least these keys and values
                                         (numbers within 0.01)
    <!-- example: output text -->       the last run's stdout, line by line (spaces collapsed)

The examples of one page run in order in one temporary folder, where `data/` is the repository's `data/`
(so the README's "from the repository root" paths hold).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MARKED = re.compile(r"<!-- example: (?P<kind>[a-z]+)(?: (?P<arg>\S+))? -->\n```[^\n]*\n(?P<body>.*?)\n```", re.S)
TOLERANCE = 0.01


@dataclass(frozen=True)
class Example:
    kind: str  # file | shell | python | output
    arg: str | None
    body: str
    line: int


def examples(page: Path) -> list[Example]:
    text = page.read_text()
    return [Example(m["kind"], m["arg"], m["body"], text.count("\n", 0, m.start()) + 1)
            for m in MARKED.finditer(text)]


def _contains(actual: object, expected: object, where: str) -> None:
    """`expected` is a subset of `actual`: dict keys, list items, numbers within TOLERANCE, the rest equal."""
    if isinstance(expected, dict):
        assert isinstance(actual, dict), f"{where}: expected an object, got {actual!r}"
        for key, value in expected.items():
            assert key in actual, f"{where}: no key {key!r} in {sorted(actual)}"
            _contains(actual[key], value, f"{where}.{key}")
    elif isinstance(expected, list):
        assert isinstance(actual, list) and len(actual) == len(expected), f"{where}: {actual!r} != {expected!r}"
        for k, (a, e) in enumerate(zip(actual, expected, strict=True)):
            _contains(a, e, f"{where}[{k}]")
    elif isinstance(expected, (int, float)) and not isinstance(expected, bool):
        assert isinstance(actual, (int, float)) and abs(actual - expected) <= TOLERANCE, \
            f"{where}: {actual!r} != {expected!r} (±{TOLERANCE})"
    else:
        assert actual == expected, f"{where}: {actual!r} != {expected!r}"


def _lines(text: str) -> list[str]:
    return [" ".join(line.split()) for line in text.strip().splitlines()]


def _folder(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """The examples' folder (data/ linked in) and an environment with this checkout's `macroloc` on PATH."""
    (tmp_path / "data").symlink_to(ROOT / "data")
    bin_dir = tmp_path / ".bin"
    bin_dir.mkdir()
    shim = bin_dir / "macroloc"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m macroloc.cli.main "$@"\n')
    shim.chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    return tmp_path, env


def _run(example: Example, page: Path, folder: Path, env: dict[str, str]) -> str:
    where = f"{page.name}:{example.line}"
    args = ["bash", "-e", "-c", example.body] if example.kind == "shell" else [sys.executable, "-c", example.body]
    done = subprocess.run(args, cwd=folder, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"{where}: exit {done.returncode}\n{done.stderr[-2000:]}"
    return done.stdout


PAGES_WITH_EXAMPLES = [p for p in PAGES if examples(p)]


@pytest.mark.parametrize("page", PAGES_WITH_EXAMPLES, ids=[p.name for p in PAGES_WITH_EXAMPLES])
def test_examples_run_and_do_what_the_text_says(page: Path, tmp_path: Path) -> None:
    folder, env = _folder(tmp_path)
    stdout: str | None = None
    for ex in examples(page):
        where = f"{page.name}:{ex.line}"
        if ex.kind == "file":
            assert ex.arg, f"{where}: `example: file` needs a file name"
            (folder / ex.arg).write_text(ex.body + "\n")
        elif ex.kind in ("shell", "python"):
            stdout = _run(ex, page, folder, env)
        elif ex.kind == "output":
            assert stdout is not None, f"{where}: an output with no example run before it"
            if ex.arg == "json":
                _contains(json.loads(stdout), json.loads(ex.body), where)
            else:
                assert _lines(stdout) == _lines(ex.body), f"{where}: printed\n{stdout}"
        else:
            pytest.fail(f"{where}: unknown example kind {ex.kind!r}")


def test_the_readme_keeps_its_runnable_examples() -> None:
    """The README's localize request, its command with the answer, and the Python example stay marked (an
    unmarked example would silently stop being tested)."""
    kinds = [(ex.kind, ex.arg) for ex in examples(ROOT / "README.md")]
    for needed in [("file", "OBS.json"), ("shell", None), ("output", "json"), ("python", None), ("output", "text")]:
        assert needed in kinds, f"README.md lost its {needed} example"


def test_no_page_points_users_at_files_they_do_not_have() -> None:
    """`../shared/...` and the project's internal DESIGN.md are not shipped: user-facing text must not send a
    user there (docs/measurements.md may cite the harness that measured its figures)."""
    for page in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]:
        text = page.read_text()
        if page.name != "measurements.md":
            assert "../shared" not in text, f"{page.name} points at ../shared"
        assert not re.search(r"(?<![/\w])DESIGN\.md", text), f"{page.name} points at DESIGN.md"


def test_no_help_text_points_users_at_files_they_do_not_have() -> None:
    """The commands' help (cli/main.py, cli/commands/*.py) names neither `../shared` nor DESIGN.md."""
    for source in [ROOT / "cli" / "main.py", *(ROOT / "cli" / "commands").glob("*.py")]:
        text = source.read_text()
        assert "../shared" not in text and "DESIGN.md" not in text, f"{source.name} points at an internal file"


def test_relative_links_lead_somewhere() -> None:
    """Every relative link of the README and docs/*.md names a file of the repository (and, with `#anchor`, a
    heading of that page)."""
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+:", target):
                continue  # https:, mailto:
            path, _, anchor = target.partition("#")
            linked = (page.parent / path).resolve() if path else page
            if not linked.exists():
                broken.append(f"{page.name}: {target}")
            elif anchor and linked.suffix == ".md":
                headings = {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
                            for h in re.findall(r"^#+ (.+)$", linked.read_text(), re.M)}
                if anchor not in headings:
                    broken.append(f"{page.name}: {target} (no such heading)")
    assert not broken, broken
