"""The `macroloc` command line: a thin shell over library functions, with one error boundary.

Each command lives in `cli/commands/<name>.py` and exposes `register(app)`; heavy modules are
imported inside the command bodies so that `macroloc --help` stays fast.
"""

from __future__ import annotations

import importlib
import logging
import sys
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from typer._click.exceptions import ClickException as ClickExceptionType

from macroloc.graph.errors import UserInputError

COMMAND_MODULES = (
    "features",
    "prepare",
    "localize",
    "eval",
    "inspect",
    "simulate",
    "detect",
    "perceive",
    "adapt_detector",
    "replay",
    "serve",
    "demo",
    "dump_config",
)

app = typer.Typer(
    name="macroloc",
    help=(
        "Localize a drone indoors inside its building's own CAD/BIM model from the doors and windows it sees, "
        "then guide it to goals given in that model.\n\n"
        "Start with `macroloc demo`; `macroloc COMMAND --help` explains each command."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _register_all() -> None:
    """Each command into `app`, once per process: typer keeps every registration, so registering at each `main()`
    would make an in-process caller's n-th call build n copies of every command."""
    if app.registered_commands:
        return
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"macroloc.cli.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"macroloc.cli.commands.{name}":
                continue  # command not built yet
            raise
        module.register(app)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress at INFO level on stderr."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars on stderr (they show only at a "
                               "terminal, never on stdout)."),
) -> None:
    from macroloc.service.progress import set_quiet

    set_quiet(quiet)
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point. A user's mistake becomes one stderr line and exit 2; a bug keeps its traceback."""
    _register_all()
    try:
        app(args=argv, standalone_mode=False)
    except UserInputError as exc:
        print(f"macroloc: error: {exc}", file=sys.stderr)
        return 2
    except typer.Exit as exc:
        return int(exc.exit_code or 0)
    except typer.Abort:
        print("macroloc: aborted", file=sys.stderr)
        return 130
    except _usage_error() as exc:  # bad flags or arguments: click's message, on one line
        lines = exc.format_message().strip().splitlines()
        print(f"macroloc: error: {lines[0] if lines else exc}", file=sys.stderr)
        return 2
    return 0


def _usage_error() -> type[ClickExceptionType]:
    """The click exception base that this typer raises (vendored as typer._click since typer 0.20)."""
    try:
        from typer._click.exceptions import ClickException
    except ImportError:  # older typer on plain click
        from click.exceptions import ClickException  # type: ignore[no-redef,assignment]
    return ClickException


if __name__ == "__main__":
    sys.exit(main())
