"""Input files and directories as a user hands them to goi: checked before they are read.

Every reader of a user's file goes through `regular_file` (or `read_text`/`read_json`), so a
FIFO, a device, a directory, a missing path or an oversized file is a clean error naming the
path, never a hang, an endless read or a traceback. Output paths are checked here too: never
an input, never a file where a directory is needed, never a name the file system refuses.

Inputs are protected twice. A command's preflight calls `refuse_inputs` with every output it
will write and every input it reads, before any work. The inputs it names are also recorded
for the running command (`guarded_inputs`, opened by the CLI around each command), and every
artifact write and output removal checks that record (`refuse_if_input`), so an output path
that a preflight missed still cannot replace or delete an input: the command fails instead,
and its staged outputs are dropped.
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from stages.core.errors import GoiError
from stages.core.staging import current_stage, fsync_dir

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


def with_option(option: str | None, message: str) -> str:
    """`message`, prefixed with the option that named the path when there is one."""
    return f"{option}: {message}" if option else message


def check_output_name(path: Path, option: str | None = None) -> None:
    """The file system will take this name: no component longer than its limit (usually 255
    bytes). Checked before anything else touches the path: stat() itself fails on such names."""
    limit = 255
    for part in path.parts:
        if len(os.fsencode(part)) > limit:
            raise GoiError(
                with_option(
                    option,
                    f"{path}: the file name is longer than the file system allows ({limit} bytes)",
                )
            )
    parent = path.parent if str(path.parent) else Path(".")
    if parent.is_dir() and len(os.fsencode(path.name)) > _name_max(parent):
        raise GoiError(
            with_option(
                option,
                f"{path}: the file name is longer than the file system allows "
                f"({_name_max(parent)} bytes)",
            )
        )


def check_out_dir(out: Path, force: bool, who: str, ours: Callable[[], bool], risk: str) -> None:
    """--out is a directory that `who` writes: new, empty, or its own (`ours()`, asked once it
    is known to be a directory or absent); a directory of other files is refused without
    --force, before anything is written. `risk`: what would befall those files."""
    check_output_name(out, "--out")
    if out.exists() and not out.is_dir():
        raise GoiError(f"--out: {out} is a file; {who} writes a directory")
    mine = ours()
    if force or not out.is_dir() or mine:
        return
    theirs = sorted(p.name for p in out.iterdir())
    if theirs:
        raise GoiError(
            f"--out: {out} holds files {who} did not make (e.g. {theirs[0][:60]}); {risk}: "
            "choose a new directory, or pass --force"
        )


def check_output_file(path: Path, option: str, force: bool = True) -> None:
    """Preflight of a file a command will write later, in a directory it may still have to
    create: a name the file system takes, no directory, FIFO or device at the path, no file in
    the way of its directories, and (without `force`) nothing there yet."""
    path = Path(path)
    check_output_name(path, option)
    if path.is_dir():
        raise GoiError(f"{option}: {path} is a directory; goi writes a file there")
    if path.exists() and not path.is_file():
        raise GoiError(f"{option}: {path} is not a regular file (a FIFO or a device?)")
    if (path.exists() or path.is_symlink()) and not force:
        raise GoiError(f"{option}: {path} already exists; pass --force to overwrite it")
    blocker = file_in_the_way(path.parent)
    if blocker is not None:
        raise GoiError(f"{option}: {path}: {blocker} is a file, not a directory")


def file_in_the_way(directory: Path) -> Path | None:
    """The first of `directory` and its parents that exists but is not a directory."""
    return next((d for d in [directory, *directory.parents] if d.exists() and not d.is_dir()), None)


def make_dir(path: str | os.PathLike[str], option: str) -> Path:
    """Create an output directory (and its parents); a file in the way is a clean error."""
    p = Path(path)
    check_output_name(p, option)
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


#: A directory given as an input is protected file by file, up to this many files.
MAX_PROTECTED_FILES = 200_000


class _Guard:
    """The inputs of the running command: their (device, inode) and their resolved paths."""

    def __init__(self) -> None:
        self.ids: set[tuple[int, int]] = set()
        self.paths: set[Path] = set()

    def add(self, path: Path) -> None:
        if path.is_dir():
            files = (q for q in path.rglob("*") if q.is_file())
            for i, q in enumerate(files):
                if i >= MAX_PROTECTED_FILES:
                    break
                self._add_file(q)
        else:
            self._add_file(path)

    def _add_file(self, path: Path) -> None:
        with contextlib.suppress(OSError, ValueError):
            st = path.stat()
            self.ids.add((st.st_dev, st.st_ino))
            self.paths.add(path.resolve())

    def holds(self, path: Path) -> bool:
        try:
            st = path.stat()
        except (OSError, ValueError):
            return False  # nothing there (or nothing reachable): no input to lose
        if (st.st_dev, st.st_ino) in self.ids:
            return True
        with contextlib.suppress(OSError, ValueError):
            return path.resolve() in self.paths
        return False


_GUARD: ContextVar[_Guard | None] = ContextVar("goi_input_guard", default=None)


@contextlib.contextmanager
def guarded_inputs() -> Iterator[None]:
    """Record the inputs the enclosed command names (through `refuse_inputs`/`protect`), so
    that no artifact it writes and no file it removes can be one of them."""
    token = _GUARD.set(_Guard())
    try:
        yield
    finally:
        _GUARD.reset(token)


def protect(inputs: Iterable[str | os.PathLike[str] | None]) -> None:
    """Add inputs of the running command to its record (a directory: every file in it)."""
    guard = _GUARD.get()
    if guard is None:
        return
    for i in inputs:
        if i is not None:
            guard.add(Path(i))


def refuse_if_input(path: str | os.PathLike[str], option: str | None = None) -> None:
    """The last line of defence of every write and removal: never one of the command's
    inputs (as recorded by `protect`), whatever --force says."""
    guard = _GUARD.get()
    if guard is not None and guard.holds(Path(path)):
        raise GoiError(
            with_option(
                option,
                f"{path} is one of this command's inputs; goi never writes over "
                "an input: choose another path",
            )
        )


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    with contextlib.suppress(OSError, ValueError):
        return a.resolve() == b.resolve()
    return False


def _inside(path: Path, directory: Path) -> bool:
    with contextlib.suppress(OSError, ValueError):
        return path.resolve().is_relative_to(directory.resolve())
    return False


Outputs = Mapping[str, "str | os.PathLike[str] | Iterable[str | os.PathLike[str]] | None"]


def refuse_inputs(outputs: Outputs, inputs: Iterable[str | os.PathLike[str] | None]) -> None:
    """An output path may never be one of the command's inputs (writing it would destroy the
    input, e.g. `fit-field --cache FEATURES.h5`). `outputs` maps an option to the file, or the
    files, written under it; an input may be a directory, whose files are all protected. The
    inputs are also recorded for the running command (`protect`)."""
    ins = [Path(i) for i in inputs if i is not None]
    protect(ins)
    for option, value in outputs.items():
        if value is None:
            continue
        files = [value] if isinstance(value, str | os.PathLike) else list(value)
        for out in map(Path, files):
            check_output_name(out, option)  # before stat(), which fails on such names
            for i in ins:
                if _same(out, i) or (i.is_dir() and out.exists() and _inside(out, i)):
                    raise GoiError(
                        f"{option}: {out} is one of this command's inputs; choose another path"
                    )


# --- partial files and output locks --------------------------------------------------------
#
# A long command (extract, the blend cache) keeps its unfinished work in `<out>.partial`, which
# the next run resumes. Such a file is only ever goi's own: a regular file (not a link, a FIFO,
# a device, nor a second name of another file) of this user, opened only while the run holds
# the output's lock, so two runs never write, resume or remove one partial file together.


def partial_exists(path: Path, option: str) -> bool:
    """Whether `path` holds a partial file to resume (checked: goi's kind of file), False when
    nothing is there; anything else at the path is refused, never written through or removed."""
    path = Path(path)
    check_output_name(path, option)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return False
    except OSError as e:
        raise GoiError(f"{option}: cannot examine {path} ({e.strerror or e})") from None
    what = "where goi keeps an unfinished run"
    if stat.S_ISLNK(st.st_mode):
        raise GoiError(
            f"{option}: {path} ({what}) is a symbolic link; goi never writes through one: remove it"
        )
    if not stat.S_ISREG(st.st_mode):
        raise GoiError(
            f"{option}: {path} ({what}) is not a regular file (a FIFO, a device or a "
            "directory?); move it away"
        )
    if st.st_nlink > 1:
        raise GoiError(
            f"{option}: {path} ({what}) is a hard link, a second name of another file that "
            "goi would write over; remove it"
        )
    if st.st_uid != os.getuid():
        raise GoiError(
            f"{option}: {path} ({what}) belongs to another user (uid {st.st_uid}); remove it "
            "or choose another path"
        )
    refuse_if_input(path, option)
    return True


def create_partial(path: Path, option: str) -> None:
    """Create `path` as a new, empty partial file of this run (never through a link, never
    over a file that appeared meanwhile)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o666)
    except FileExistsError:
        path.unlink()  # an old partial of other inputs, checked by partial_exists
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o666)
    except OSError as e:
        raise GoiError(f"{option}: cannot create {path} ({e.strerror or e})") from None
    os.close(fd)


def finish_partial(path: Path, dest: Path) -> None:
    """A finished partial file made durable (fsync) and renamed to its destination (the rename
    persisted too)."""
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(path, dest)
    fsync_dir(dest.parent)


class OutputBusy(GoiError):
    """`output_lock` found the output being written by another goi run (a caller may wait)."""


@contextlib.contextmanager
def output_lock(path: str | os.PathLike[str], option: str) -> Iterator[None]:
    """Hold `<path>.lock` while a command writes `path` (and its partial file): a second run
    with the same output meets a clean refusal naming the first run's process id, before it
    touches anything. The lock is the kernel's (flock): a run that dies releases it, and the
    next run takes the file over."""
    import fcntl

    path = Path(path)
    lock = path.with_name(path.name + ".lock")
    check_output_name(lock, option)
    parent = lock.parent if str(lock.parent) else Path(".")
    if not parent.is_dir():
        raise GoiError(f"{option}: {path}: directory {parent} does not exist")
    refuse_if_input(lock, option)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
        except OSError as e:
            raise GoiError(f"{option}: cannot create the lock {lock} ({e.strerror or e})") from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink > 1:
            os.close(fd)
            raise GoiError(f"{option}: {lock} is not goi's lock file (a link, a FIFO?); remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            other = os.read(fd, 64).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise OutputBusy(
                f"{option}: {path} is being written by another goi run (pid {other}); wait "
                "for it to end, or choose another path"
            ) from None
        try:  # the holder removes the file as it lets go: then lock the new one instead
            same = os.stat(lock, follow_symlinks=False).st_ino == st.st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # before the lock is released: a waiter then sees a new file
        os.close(fd)
