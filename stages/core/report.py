"""How stages tell the user what they are doing: one callback, supplied by the caller.

A stage never prints. It takes a `Report` and calls `report.log(...)` for a line of news and
`report.progress(...)` around any loop that takes more than a few seconds. The CLI passes one
that writes to stderr and draws bars on a terminal (goi_cli/report.py); library callers and
tests get `SILENT` by default.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Protocol, TypeVar

T = TypeVar("T")


class Report(Protocol):
    def log(self, message: str) -> None:
        """One line of news (e.g. 'resuming from X', 'fitted on v001: IoU 0.6 -> 0.9')."""

    def progress(
        self,
        items: Iterable[T],
        label: str,
        length: int | None = None,
        show: Callable[[T | None], str | None] | None = None,
    ) -> Iterator[T]:
        """Yield `items`, showing how far the loop has got. `show` names the current item."""
        ...


class Silent:
    """Reports nothing: the default for library calls and tests."""

    def log(self, message: str) -> None:
        pass

    def progress(
        self,
        items: Iterable[T],
        label: str,
        length: int | None = None,
        show: Callable[[T | None], str | None] | None = None,
    ) -> Iterator[T]:
        yield from items


SILENT: Report = Silent()


def size_text(nbytes: float) -> str:
    """A size as a person reads it: GiB, MiB or KiB with three significant digits (a small
    fit's sizes are not all 0.00 GiB)."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{int(nbytes)} bytes"
