"""The terminal side of `stages.core.report.Report`: news on stderr, progress bars on a terminal.

Bars are drawn only when stderr is a terminal, so that logs and pipelines see only results,
news lines and errors.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

import click

T = TypeVar("T")


class TerminalReport:
    def log(self, message: str) -> None:
        click.echo(f"goi: {message}", err=True)

    def progress(
        self,
        items: Iterable[T],
        label: str,
        length: int | None = None,
        show: Callable[[T | None], str | None] | None = None,
    ) -> Iterator[T]:
        if not sys.stderr.isatty():
            yield from items
            return
        with click.progressbar(
            items,
            length=length,
            label=label,
            file=sys.stderr,
            item_show_func=show,
            show_pos=True,
            width=30,
        ) as bar:
            yield from bar


TERMINAL = TerminalReport()
