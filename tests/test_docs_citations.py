"""Every citation of docs/measurements.md in the code names one of its headings.

The code states its rules and cites the figures behind them by title: `(docs/measurements.md, "Title")` (also
`docs/measurements.md: "Title"`), in a docstring, a comment or a config field's description, the title free to
run over lines. A citation resolves when a heading (`#`, `##` or `###`) of docs/measurements.md starts with the
quoted title and the title ends there at a word's end: a heading's dates and issue numbers may be left off, but a
misspelt or truncated title fails.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MEASUREMENTS = ROOT / "docs" / "measurements.md"
SCANNED = ("graph", "perception", "proto", "service", "common", "sim", "cli", "bench")

CITATION = re.compile(r'docs/measurements\.md[,:]\s*"(?P<title>[^"]+)"')
SEAM = re.compile(r'(?<!")"[ \t]*\n[ \t]*"(?!")')  # adjacent string literals: "... " \n "..."
COMMENT_RUN = re.compile(r"\n[ \t]*#[ \t]*")  # a comment going on over the next line


def headings(text: str) -> list[str]:
    """The text of every `#`, `##` and `###` heading outside fenced blocks."""
    found, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"#{1,3} (.+)$", line)):
            found.append(m.group(1).strip())
    return found


def citations(source: str) -> list[str]:
    """The titles cited in a Python file's text, whitespace collapsed."""
    text = SEAM.sub("", source).replace('\\"', '"')
    text = COMMENT_RUN.sub(" ", text)
    return [" ".join(m.group("title").split()) for m in CITATION.finditer(text)]


def resolves(title: str, heads: list[str]) -> bool:
    return any(h.startswith(title) and (len(h) == len(title) or not h[len(title)].isalnum()) for h in heads)


def _cited() -> list[tuple[str, str]]:
    out = []
    for folder in SCANNED:
        for path in sorted((ROOT / folder).rglob("*.py")):
            out += [(str(path.relative_to(ROOT)), t) for t in citations(path.read_text(encoding="utf-8"))]
    return out


CITED = _cited()


def test_the_scan_finds_the_citations() -> None:
    assert len(CITED) >= 30, CITED  # a scan that finds none would pass everything


def test_the_rule_rejects_a_misspelt_or_cut_title() -> None:
    heads = ["A pose the odometry carried alone: not held, then found again (issues 38, 32)", "Change by change"]
    assert resolves("A pose the odometry carried alone: not held", heads)
    assert resolves("Change by change", heads)
    assert not resolves("A pose the odometry carried alone is not held", heads)
    assert not resolves("Change by chang", heads)
    assert not resolves("Change by changes", heads)


def test_the_scan_reads_titles_over_lines_and_literals() -> None:
    source = ('x = 1  # (docs/measurements.md, "The border\n    # margin")\n'
              'd = ("a (docs/measurements.md, \\"One keyframe rule for "\n     "replay and service\\")")\n')
    assert citations(source) == ["The border margin", "One keyframe rule for replay and service"]


@pytest.mark.parametrize(("where", "title"), CITED)
def test_a_citation_names_a_heading(where: str, title: str) -> None:
    heads = headings(MEASUREMENTS.read_text(encoding="utf-8"))
    assert resolves(title, heads), f'{where} cites docs/measurements.md, "{title}": no heading starts so'
