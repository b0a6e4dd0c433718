"""How stages tell the user what they are doing: one callback, supplied by the caller.

A stage never prints. It takes a `Report` and calls `report.log(...)` for a line of news and
`report.progress(...)` around any loop that takes more than a few seconds. `Lines` is the one
implementation: the CLI's writes to stderr and draws bars on a terminal (goi_cli/report.py);
library callers and tests get `SILENT` (reports nothing) by default.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager
from typing import Any, Protocol, TypeVar

from stages.core.interrupts import check

T = TypeVar("T")
#: What a progress line or bar says of the current item (None: nothing).
Show = Callable[[T | None], str | None]


class Report(Protocol):
    def log(self, message: str) -> None:
        """One line of news (e.g. 'resuming from X', 'fitted on v001: IoU 0.6 -> 0.9')."""

    def progress(
        self, items: Iterable[T], label: str, length: int | None = None, show: Show[T] | None = None
    ) -> Iterator[T]:
        """Yield `items`, showing how far the loop has got. `show` names the current item."""
        ...


#: A progress bar around a loop: bar(items, label, length, show) gives a context manager that
#: yields the items, or None where no bar can be drawn.
Bar = Callable[..., AbstractContextManager[Iterable[Any]] | None]


class Lines:
    """The one `Report` goi has: each line of news goes to `write` (None: nowhere), and a loop's
    progress to a bar where `bar` draws one (the CLI's, when stderr is a terminal); else a loop
    of known length that runs past `quiet_s` seconds gets a line at every `every` of it, so that
    a log shows a long fit moving. `Lines()` reports nothing (SILENT)."""

    def __init__(
        self,
        write: Callable[[str], None] | None = None,
        bar: Bar | None = None,
        every: float = 0.05,
        quiet_s: float = 5.0,
    ):
        self.write = write
        self.bar = bar
        self.every = every
        self.quiet_s = quiet_s

    def log(self, message: str) -> None:
        if self.write is not None:
            self.write(message)

    def progress(
        self, items: Iterable[T], label: str, length: int | None = None, show: Show[T] | None = None
    ) -> Iterator[T]:
        drawn = self.bar(items, label, length, show) if self.bar is not None else None
        if drawn is not None:
            with drawn as bar:
                yield from _stoppable(bar)
            return
        items = _stoppable(items)
        if self.write is None or not length:
            yield from items
            return
        t0 = time.monotonic()
        step = max(1, math.ceil(length * self.every))
        for done, item in enumerate(items, 1):
            yield item
            elapsed = time.monotonic() - t0
            if (done % step == 0 or done == length) and elapsed >= self.quiet_s:
                shown = show(item) if show is not None else None
                self.write(
                    f"{label}: {done}/{length} ({100 * done // length}%), {elapsed:.0f} s"
                    + (f", {shown}" if shown else "")
                )


def _stoppable(items: Iterable[T]) -> Iterator[T]:
    """The items, each after `interrupts.check`: a Ctrl-C swallowed on its way (in a weakref
    callback) stops the loop at its next item."""
    for item in items:
        check()
        yield item


SILENT: Report = Lines()


def size_text(nbytes: float) -> str:
    """A size as a person reads it: GiB, MiB or KiB with three significant digits (a small
    fit's sizes are not all 0.00 GiB)."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{int(nbytes)} bytes"
