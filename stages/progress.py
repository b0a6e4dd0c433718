"""Progress bars on stderr for anything that takes more than a few seconds."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

import click

T = TypeVar("T")


def progress(
    items: Iterable[T],
    label: str,
    length: int | None = None,
    show: Callable[[T | None], str | None] | None = None,
) -> Iterator[T]:
    """Yield `items` while drawing a bar on a terminal; silent otherwise, so that logs and
    pipelines see only results and errors."""
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
