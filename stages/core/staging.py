"""Staged outputs: the files a command writes appear together at its end, or not at all.

Inside `staged_outputs()`, every artifact written through `stages.core.artifacts` lands in a
temporary file beside its destination, and every output directory created through
`stages.core.files.make_dir` is remembered. When the block ends normally all temporary files
are renamed into place; when it raises (a bad input found late, a full disk, Ctrl-C) they are
removed, and so are the directories it created, so the output location is left as it was.
Outside such a block each artifact is renamed into place as soon as it is complete.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path


class Stage:
    def __init__(self) -> None:
        self.pending: dict[Path, Path] = {}  # destination -> its finished temporary file
        self.created_dirs: list[Path] = []

    def add(self, tmp: Path, dest: Path) -> None:
        old = self.pending.pop(dest, None)
        if old is not None:  # written twice: the later version wins
            old.unlink(missing_ok=True)
        self.pending[dest] = tmp

    def commit(self) -> None:
        parents = set()
        for dest, tmp in self.pending.items():
            os.replace(tmp, dest)
            parents.add(dest.parent)
        self.pending.clear()
        for parent in parents:
            fsync_dir(parent)

    def abort(self) -> None:
        for tmp in self.pending.values():
            tmp.unlink(missing_ok=True)
        self.pending.clear()
        for d in reversed(self.created_dirs):
            with contextlib.suppress(OSError):
                d.rmdir()  # only if empty: never a file that was there before


_CURRENT: ContextVar[Stage | None] = ContextVar("goi_stage", default=None)


def current_stage() -> Stage | None:
    return _CURRENT.get()


@contextlib.contextmanager
def staged_outputs() -> Iterator[Stage]:
    stage = Stage()
    token = _CURRENT.set(stage)
    try:
        yield stage
        stage.commit()
    except BaseException:
        stage.abort()
        raise
    finally:
        _CURRENT.reset(token)


@contextlib.contextmanager
def kept_on_interrupt(partial: Path, created: bool) -> Iterator[None]:
    """For a resumable `<out>.partial`: on a failure nothing of this run is worth keeping, so a
    partial file it created goes; an interruption (Ctrl-C, a crash) keeps it, so that the next
    run resumes it."""
    try:
        yield
    except Exception:  # a bad input (or a bug); KeyboardInterrupt is no Exception: kept
        if created:
            partial.unlink(missing_ok=True)
        raise


def fsync_dir(directory: Path) -> None:
    """Persist the renames into `directory` (its entry list); not possible everywhere."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
