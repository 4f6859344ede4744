"""A smoke matrix of the command line: every command registers, has a --help that teaches, and fails cleanly."""

from __future__ import annotations

import pytest

from macroloc.cli.main import COMMAND_MODULES, main

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


def test_no_help_text_holds_what_rich_would_take_for_markup(capsys) -> None:
    """`--help` goes through rich: a "[word]" in a help string is read as a style tag and vanishes from it."""
    import re

    import typer

    from macroloc.cli.main import app

    assert main(["--help"]) == 0  # registers every command

    markup = re.compile(r"(?<!\\)\[/?[A-Za-z_#@][^\]\[]*\]")  # rich's tag syntax; "\\[" escapes it
    group = typer.main.get_command(app)
    texts = []
    for name, command in group.commands.items():  # type: ignore[attr-defined]
        texts += [(name, command.help or "")] + [(f"{name} {p.name}", getattr(p, "help", "") or "")
                                                for p in command.params]
    swallowed = [(where, text) for where, text in texts if markup.search(text)]
    assert len(texts) > 40 and not swallowed


def test_replay_names_a_missing_detector_from_the_config_in_one_line(tmp_path, capsys) -> None:
    flight = tmp_path / "f.mcap"
    flight.write_bytes(b"\x89MCAP0\r\n")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[perception]\ndetector_model = "{tmp_path / "nope.onnx"}"\n')
    rc = main(["replay", str(flight), "--building", str(tmp_path / "b.ifc"), "--observations", "perception",
               "--config", str(cfg)])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "detector model" in err and "nope.onnx" in err


def test_calling_main_again_registers_no_command_twice(capsys) -> None:
    """An in-process caller (the eval driver, the tests) calls main() many times: each call must find the commands
    registered once, not once more per call (the n-th call built n copies of every command)."""
    from macroloc.cli.main import app

    for _ in range(3):
        assert main(["dump-config"]) == 0
    names = [c.name or c.callback.__name__ for c in app.registered_commands if c.callback is not None]
    assert len(names) == len(set(names)) >= len(COMMAND_MODULES)
