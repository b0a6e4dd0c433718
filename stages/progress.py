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
    """Yield `items` while drawing a bar (a label line only, when stderr is not a terminal)."""
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
