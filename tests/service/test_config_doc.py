"""docs/configuration.md is generated from the typed configuration (scripts/gen_config_doc.py): it must match
the code, and every key must say what it does."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_config_doc", ROOT / "scripts" / "gen_config_doc.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_reference_matches_the_code() -> None:
    gen = _generator()
    committed = (ROOT / "docs" / "configuration.md").read_text()
    assert committed == gen.render(), "docs/configuration.md is stale: run python scripts/gen_config_doc.py"


def test_every_key_has_a_description() -> None:
    gen = _generator()
    missing = [f"{section.name}.{key}" for section in gen.section_models()
               for key, k in section.keys.items() if not (k.field.description or "").strip()]
    assert not missing, f"config keys without a description: {missing}"


def test_every_key_is_in_the_reference() -> None:
    gen = _generator()
    text = gen.render()
    for section in gen.section_models():
        assert f"\n## {section.name}\n" in text
        for key in section.keys:
            assert f"| `{key}` |" in text


def test_a_misspelt_key_inside_a_section_is_refused(tmp_path) -> None:  # noqa: ANN001
    from macroloc.cli.main import main

    bad = tmp_path / "bad.toml"
    bad.write_text('[graph]\nstorey_hintt = "Level 1"\n')
    assert main(["dump-config", "--config", str(bad)]) == 2
