"""How a component's parameter is declared, once: a field of its frozen dataclass with its default, its bounds and
the one line that says what it does (`param`). The service's config (service/config.py) takes these dataclasses
as its tables, and pydantic reads the bounds and the description from the field's metadata, so that a key of a
config file, its check, its line in docs/configuration.md and `macroloc dump-config` all come from the field.

    @dataclass(frozen=True)
    class JudgeParams(Parameters):
        surface_margin: float = param(0.3, "every other candidate pose scores this much less", ge=0)

Imports nothing (pydantic included): the libraries stay free of the service's config.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import field
from typing import Any, ClassVar, TypeVar

T = TypeVar("T")


class Parameters:
    """The base of a component's parameter dataclass: as a config table, a key that is not one of its fields is
    refused with its name (pydantic's `extra="forbid"`, read from `__pydantic_config__`), never ignored."""

    __pydantic_config__: ClassVar[dict[str, Any]] = {"extra": "forbid"}


def param(default: T, description: str, *, gt: float | None = None, ge: float | None = None,
          lt: float | None = None, le: float | None = None, multiple_of: int | None = None) -> T:
    """A dataclass field (`dataclasses.field`) with its default, its description and its bounds (gt: >, ge: >=,
    lt: <, le: <=, multiple_of), which the config checks when a file or the environment sets it. The default is
    an immutable value (a number, a string, a tuple)."""
    bounds = {"gt": gt, "ge": ge, "lt": lt, "le": le, "multiple_of": multiple_of}
    metadata = {"description": description, **{k: v for k, v in bounds.items() if v is not None}}
    return field(default=default, metadata=metadata)  # type: ignore[no-any-return]  # a Field, read by @dataclass


def table(factory: Callable[[], T], description: str) -> T:
    """A dataclass field that is another component's parameters (`factory()` its default): a table of its own
    in the config (`[localize.verify]`), described by `description`."""
    return field(default_factory=factory, metadata={"description": description})  # type: ignore[no-any-return]
