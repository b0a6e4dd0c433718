"""An output directory that a long-running program owns file by file (goi view's --out).

A program that writes into one directory again and again, at its users' request (goi view's
exports, saved cameras, the plane cache), must never replace a file it did not write, never
write outside the directory, and never leave a half-written or unrecorded file behind. So:

- Every write goes through `OwnedDir.write(writer)`: the writer writes with the usual artifact
  helpers (`stages.core.artifacts`), inside `staged_outputs()`, so its files land beside their
  destinations as temporary files and appear together at the end, or not at all (an exception,
  a Ctrl-C: nothing is left that blocks the next write).
- Before they appear, every destination is checked: below the directory, no symbolic link on
  the way (the directory itself is the user's choice; anything below it is goi's), and either
  new or a file this directory's manifest lists with its current SHA-256 (written by the
  program, unchanged since). A file in the way is refused with one line; nothing is written.
- The manifest (`<dir>/<manifest>`, JSON, schema goi.owned_dir) records each file's SHA-256.
  It is written before the files appear, listing both the old and the new digest of every file
  about to be replaced, and again after, with the new one alone: a crash between the two
  leaves every file recognised as the program's own.
- `max_bytes` bounds the bytes of the program's files in the directory: a write that would
  pass it is refused (from an estimate before any work when the writer gives one).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import stat
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

from stages.core.artifacts import sha256_file, write_json
from stages.core.errors import GoiError
from stages.core.files import check_output_name, make_dir, read_json
from stages.core.staging import staged_outputs

SCHEMA = "goi.owned_dir"
SCHEMA_VERSION = "1.0"

T = TypeVar("T")


def _mib(n: int) -> str:
    return f"{n / 2**20:,.1f} MiB"


class OwnedDir:
    """`root`, written by `who` (named in refusals) through `write`, listed in `manifest`."""

    def __init__(
        self,
        root: Path,
        who: str,
        manifest: str,
        option: str = "--out",
        max_bytes: int | None = None,
        max_bytes_option: str = "",
    ):
        self.root = Path(root)
        self.who = who
        self.manifest = self.root / manifest
        self.option = option
        self.max_bytes = max_bytes
        self.max_bytes_option = max_bytes_option
        self._lock = threading.Lock()
        check_output_name(self.root, option)
        if self.root.exists() and not self.root.is_dir():
            raise GoiError(f"{option}: {self.root} is a file; {who} writes a directory")
        if self.root.is_dir():
            self._read()  # a damaged manifest is refused before any work

    # -- paths ------------------------------------------------------------------------------

    def check(self, path: Path, owned: dict[str, list[str]] | None = None) -> str:
        """`path`'s name relative to the directory, when goi may write it: below the directory
        with no symbolic link on the way, and new or one of the program's own files."""
        path = Path(path)
        try:
            rel = path.relative_to(self.root)
        except ValueError:
            raise GoiError(f"{path}: outside {self.option} {self.root}; never written") from None
        if not rel.parts or ".." in rel.parts or rel == Path(self.manifest.name):
            raise GoiError(f"{path}: not a file {self.who} writes in {self.option}")
        self._no_link_below(rel.parts[:-1])
        kind = _kind(path)
        if kind is None:
            return str(rel)
        owned = self._read() if owned is None else owned
        if kind != "file" or sha256_file(path) not in owned.get(str(rel), []):
            what = "a symbolic link" if kind == "link" else "exists"
            raise GoiError(
                f"{path}: {what} and was not written by {self.who} (or was changed since); "
                f"{self.who} never replaces such a file: move it, or give another {self.option}"
            )
        return str(rel)

    def check_dir(self, path: Path) -> None:
        """`path` is a directory goi may write files in: below the directory, no symbolic
        link on the way or at it, nothing but directories there."""
        try:
            rel = Path(path).relative_to(self.root)
        except ValueError:
            raise GoiError(f"{path}: outside {self.option} {self.root}; never written") from None
        if ".." in rel.parts:
            raise GoiError(f"{path}: not a directory {self.who} writes in {self.option}")
        self._no_link_below(rel.parts)

    def _no_link_below(self, parts: tuple[str, ...]) -> None:
        d = self.root
        for part in parts:
            d = d / part
            kind = _kind(d)
            if kind == "link":
                raise GoiError(
                    f"{d}: a symbolic link inside {self.option}; {self.who} never writes "
                    "through one: remove it, or give another " + self.option
                )
            if kind not in (None, "dir"):
                raise GoiError(f"{d}: a file where {self.who} needs a directory; move it")

    def owns(self, path: Path) -> bool:
        """Whether `path` is one of the program's files, unchanged since it wrote it."""
        try:
            self.check(path)
        except GoiError:
            return False
        return _kind(path) == "file"

    # -- writing ----------------------------------------------------------------------------

    def write(
        self,
        writer: Callable[[], T],
        expect: Iterable[Path] = (),
        estimate: int = 0,
        dirs: Iterable[Path] = (),
    ) -> tuple[T, list[Path]]:
        """Run `writer` (it writes through `stages.core.artifacts`), its files checked,
        recorded and made to appear together (see the module doc); returns what it returned
        and the files written. `expect`: paths it will write (checked before it runs);
        `dirs`: directories it will write in; `estimate`: the bytes it will add, checked
        against `max_bytes` before it runs."""
        with self._lock:
            owned = self._read()
            for d in dirs:
                self.check_dir(d)
            for p in expect:
                self.check(p, owned)
            self._within_budget(owned, estimate, {})
            make_dir(self.root, self.option)
            with staged_outputs() as stage:
                result = writer()
                new: dict[str, str] = {}
                sizes: dict[str, int] = {}
                for dest, tmp in stage.pending.items():
                    rel = self.check(dest, owned)
                    new[rel] = sha256_file(tmp)
                    sizes[rel] = tmp.stat().st_size
                self._within_budget(owned, 0, sizes)
                # recorded before the files appear: old and new digests both recognised
                during = {k: list(v) for k, v in owned.items()}
                for k, v in new.items():
                    during[k] = [*during.get(k, []), v]
                self._save(during)
            owned.update({k: [v] for k, v in new.items()})
            self._save(owned)
        return result, [self.root / rel for rel in new]

    def _within_budget(self, owned: dict[str, list[str]], estimate: int, sizes: dict) -> None:
        if self.max_bytes is None:
            return
        held = {rel: _size(self.root / rel) for rel in owned}
        after = sum(v for k, v in held.items() if k not in sizes) + sum(sizes.values()) + estimate
        if after > self.max_bytes:
            raise GoiError(
                f"{self.max_bytes_option}: this would bring {self.who}'s files in {self.root} "
                f"to {_mib(after)}, past the limit of {_mib(self.max_bytes)}; remove some of "
                f"them (and their lines in {self.manifest.name}), or raise {self.max_bytes_option}"
            )

    # -- the manifest -----------------------------------------------------------------------

    def _read(self) -> dict[str, list[str]]:
        path = self.manifest
        kind = _kind(path)
        if kind is None:
            return {}
        if kind != "file":
            raise GoiError(f"{path}: not a regular file; {self.who} keeps its list of files there")
        raw = read_json(path)
        if isinstance(raw, dict) and "schema" in raw:
            from schemas import validate_json

            validate_json(raw, SCHEMA, str(path))
        files = raw.get("files") if isinstance(raw, dict) else None
        if not isinstance(files, dict):  # (a list from before the schema has no 'schema')
            raise GoiError(f"{path}: not {self.who}'s list of the files it wrote")
        out: dict[str, list[str]] = {}
        for k, v in files.items():
            digests = [v] if isinstance(v, str) else v
            if not (isinstance(digests, list) and all(isinstance(d, str) for d in digests)):
                raise GoiError(f"{path}: the entry of {k[:80]!r} is not a SHA-256 or a list")
            out[str(k)] = digests
        return out

    def _save(self, owned: dict[str, list[str]]) -> None:
        files = {k: v[0] if len(v) == 1 else v for k, v in sorted(owned.items())}
        doc = {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "written_by": self.who,
               "files": files}  # fmt: skip
        # in a context of its own: written at once, never staged with the files it lists
        contextvars.Context().run(write_json, self.manifest, doc, True)


def _kind(path: Path) -> str | None:
    """'file', 'dir', 'link', 'other', or None when nothing is there (never followed)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as e:
        raise GoiError(f"{path}: cannot examine it ({e.strerror or e})") from None
    if stat.S_ISLNK(mode):
        return "link"
    if stat.S_ISDIR(mode):
        return "dir"
    return "file" if stat.S_ISREG(mode) else "other"


def _size(path: Path) -> int:
    with contextlib.suppress(OSError):
        return os.lstat(path).st_size
    return 0
