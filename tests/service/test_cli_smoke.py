"""A smoke matrix of the command line: every command registers, has a --help that teaches, and fails cleanly."""

from __future__ import annotations

import pytest

from service.cli import COMMAND_MODULES, main

COMMANDS = [name.replace("_", "-") for name in COMMAND_MODULES]


def test_every_command_module_registers(capsys) -> None:
    assert main(["--help"]) == 0
    listing = capsys.readouterr().out
    for name in COMMANDS:
        assert name in listing, f"{name} missing from `macroloc --help`"


@pytest.mark.parametrize("name", COMMANDS)
def test_help_explains_the_command(name: str, capsys) -> None:
    assert main([name, "--help"]) == 0
    text = capsys.readouterr().out
    assert "Usage: " in text and len(text.split()) > 25  # a sentence or more beyond the usage line


@pytest.mark.parametrize("name", ["features", "localize", "eval", "inspect", "simulate", "detect", "replay"])
def test_a_missing_input_file_is_one_clean_line(name: str, tmp_path, capsys) -> None:
    missing = str(tmp_path / "does-not-exist.ifc")
    args = {"localize": [missing, "--observations", missing], "simulate": [missing, "--out", str(tmp_path / "f.mcap")],
            "replay": [str(tmp_path / "missing.mcap"), "--building", missing]}.get(name, [missing])
    rc = main([name, *args])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
