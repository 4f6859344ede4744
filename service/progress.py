"""Progress of the long batch commands (simulate, replay, adapt-detector, a building's first preprocessing) on
stderr, with rich: shown to a person at a terminal, never on stdout (so `--json` stays clean), and not at all after
`macroloc --quiet`. Library code stays silent: the commands wrap their loops (`track`) or steps (`step`)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator
from typing import TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

T = TypeVar("T")

_quiet = False


def set_quiet(quiet: bool) -> None:
    """`macroloc --quiet`: no progress at all."""
    global _quiet
    _quiet = quiet


def _console():  # noqa: ANN202 - rich.console.Console, or None where nothing is shown
    if _quiet:
        return None

    console = Console(stderr=True)
    return console if console.is_terminal else None


def track(items: Iterable[T], description: str, total: float | None = None) -> Iterator[T]:
    """`items`, advancing a progress bar (a counter where `total` is unknown) as each is taken."""
    console = _console()
    if console is None:
        yield from items
        return

    columns = [SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn()]
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(description, total=total)
        for item in items:
            yield item
            bar.advance(task)


@contextlib.contextmanager
def step(description: str) -> Iterator[None]:
    """A spinner with `description` while the block runs (one long step whose parts cannot be counted)."""
    console = _console()
    if console is None:
        yield
        return
    with console.status(description):
        yield


def is_quiet() -> bool:
    """`macroloc --quiet` was given."""
    return _quiet
