"""Input files and directories as a user hands them to goi: checked before they are read.

Every reader of a user's file goes through `regular_file` (or `read_text`/`read_json`), so a
FIFO, a device, a directory, a missing path or an oversized file is a clean error naming the
path, never a hang, an endless read or a traceback. Output paths are checked here too: never
an input, never a file where a directory is needed, never a name the file system refuses.
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from stages.core.errors import GoiError
from stages.core.staging import current_stage

#: JSON and text inputs (cameras, prompts, embeddings, manifests) larger than this are refused.
MAX_TEXT_BYTES = 512 << 20


def regular_file(path: str | os.PathLike[str], what: str = "file") -> Path:
    """`path` when it is an existing regular file (symlinks followed)."""
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise GoiError(f"{p}: no such file (a {what} is needed here)") from None
    except OSError as e:
        raise GoiError(f"{p}: cannot read the {what} ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise GoiError(f"{p}: is a directory, but a {what} is needed here")
    if not stat.S_ISREG(st.st_mode):
        raise GoiError(f"{p}: not a regular file (a FIFO or a device?); a {what} is needed here")
    return p


def existing_dir(path: str | os.PathLike[str], what: str = "directory") -> Path:
    p = Path(path)
    if not p.is_dir():
        state = "not a directory" if p.exists() else "no such directory"
        raise GoiError(f"{p}: {state} ({what})")
    return p


def read_bytes(path: str | os.PathLike[str], what: str, limit: int = MAX_TEXT_BYTES) -> bytes:
    p = regular_file(path, what)
    size = p.stat().st_size
    if size > limit:
        raise GoiError(f"{p}: {size} bytes; goi reads a {what} of at most {limit} bytes")
    try:
        return p.read_bytes()
    except OSError as e:
        raise GoiError(f"{p}: cannot read the {what} ({e.strerror or e})") from None


def read_text(path: str | os.PathLike[str], what: str, limit: int = MAX_TEXT_BYTES) -> str:
    data = read_bytes(path, what, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise GoiError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def read_json(path: str | os.PathLike[str], missing: str = "missing") -> Any:
    """A JSON document; a missing, unreadable or malformed file is a GoiError naming it."""
    p = Path(path)
    if not p.exists() and not p.is_symlink():
        raise GoiError(f"{p}: {missing}")
    try:
        return json.loads(
            read_text(p, "JSON file"), parse_constant=_no_constant, object_pairs_hook=_unique
        )
    except (json.JSONDecodeError, RecursionError, ValueError) as e:
        raise GoiError(f"{p}: not valid JSON ({str(e)[:200]})") from None


def _unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    # json keeps the last of two equal keys; an ambiguous document is refused instead.
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"key {k[:60]!r} appears twice in one object")
        out[k] = v
    return out


def _no_constant(name: str) -> Any:
    # json accepts NaN and Infinity, which are not JSON: refuse them at the source.
    raise ValueError(f"{name} is not a JSON number")


def _name_max(directory: Path) -> int:
    try:
        return os.pathconf(directory, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def check_output_name(path: Path) -> None:
    """The file system will take this name: no component longer than its limit (usually 255
    bytes). Checked before anything else touches the path: stat() itself fails on such names."""
    limit = 255
    for part in path.parts:
        if len(os.fsencode(part)) > limit:
            raise GoiError(f"{path}: the file name is longer than the file system allows ({limit})")
    parent = path.parent if str(path.parent) else Path(".")
    if parent.is_dir() and len(os.fsencode(path.name)) > _name_max(parent):
        raise GoiError(
            f"{path}: the file name is longer than the file system allows ({_name_max(parent)})"
        )


def file_in_the_way(directory: Path) -> Path | None:
    """The first of `directory` and its parents that exists but is not a directory."""
    return next((d for d in [directory, *directory.parents] if d.exists() and not d.is_dir()), None)


def make_dir(path: str | os.PathLike[str], option: str) -> Path:
    """Create an output directory (and its parents); a file in the way is a clean error."""
    p = Path(path)
    check_output_name(p)
    blocker = file_in_the_way(p)
    if blocker is not None:
        raise GoiError(f"{option}: {p}: {blocker} is a file, not a directory")
    new = [d for d in [p, *p.parents] if not d.exists()][::-1]  # outermost first
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise GoiError(f"{option}: cannot create {p} ({e.strerror or e})") from None
    stage = current_stage()
    if stage is not None:
        stage.created_dirs.extend(new)
    return p


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def refuse_inputs(outputs: Mapping[str, Path | None], inputs: Iterable[Path | None]) -> None:
    """An output path may never be one of the command's inputs (writing it would destroy the
    input, e.g. `fit-field --cache FEATURES.h5`)."""
    ins = [Path(i) for i in inputs if i is not None]
    for option, out in outputs.items():
        if out is None:
            continue
        for i in ins:
            if _same(Path(out), i):
                raise GoiError(
                    f"{option}: {out} is one of this command's inputs; choose another path"
                )
