"""The CLI's `stages.core.report.Lines`: news on stderr, a progress bar on a terminal.

Bars are drawn only when stderr is a terminal; elsewhere (a log, a pipeline, a CI job) a long
loop says how far it has got in a line every few percent, on stderr too, so that stdout holds
only results.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager
from typing import Any

import click

from stages.core.report import Lines


def _news(message: str) -> None:
    click.echo(f"goi: {message}", err=True)


def _bar(
    items: Iterable[Any],
    label: str,
    length: int | None,
    show: Callable[[Any], str | None] | None,
) -> AbstractContextManager[Iterable[Any]] | None:
    if not sys.stderr.isatty():
        return None
    return click.progressbar(
        items,
        length=length,
        label=label,
        file=sys.stderr,
        item_show_func=show,
        show_pos=True,
        width=30,
    )


TERMINAL = Lines(write=_news, bar=_bar)
