"""`macroloc dump-config [--config FILE]`: the resolved configuration (defaults < file < environment)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("dump-config")
    def dump_config(
        config: Path = typer.Option(None, "--config", "-c", help="Config file (JSON or TOML) to resolve."),
        toml_out: bool = typer.Option(False, "--toml", help="Print TOML-like sections instead of JSON."),
    ) -> None:
        """Print the resolved configuration as JSON (or TOML): every key with its value, a start for a config file.

        Environment variables override the file: MACROLOC_<SECTION>__<KEY>, e.g. MACROLOC_ZENOH__MODE=client.
        """
        import json
        import sys

        from macroloc.service.config import load_config

        doc = load_config(config).model_dump(mode="json")
        if not toml_out:
            sys.stdout.write(json.dumps(doc, indent=2) + "\n")
            return
        def table(name: str, values: dict) -> None:  # its keys, then its own tables ([graph], [graph.judge], ...)
            sys.stdout.write(f"[{name}]\n")
            for key, value in values.items():
                if value is not None and not isinstance(value, dict):
                    sys.stdout.write(f"{key} = {json.dumps(value)}\n")
            sys.stdout.write("\n")
            for key, value in values.items():
                if isinstance(value, dict):
                    table(f"{name}.{key}", value)

        for section, values in doc.items():
            table(section, values)
