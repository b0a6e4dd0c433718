"""Artifact files: atomic writes, provenance and the checked opening of HDF5 artifacts.

Every artifact is written to a temporary file beside its destination, flushed to disk and then
renamed into place, so an interrupted run never leaves a half-written artifact under the real name.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shlex
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from stages import __version__
from stages.core.errors import GoiError
from stages.core.files import check_output_name, file_in_the_way, refuse_if_input, with_option
from stages.core.hdf5 import read_h5
from stages.core.staging import current_stage, fsync_dir

#: argv of the running command, recorded in every artifact (the CLI sets it; tests may not).
_COMMAND: list[str] = []


def set_command(argv: Sequence[str]) -> None:
    _COMMAND[:] = list(argv)


def command_line() -> str:
    return shlex.join(_COMMAND or ["goi", "(library call)"])


def sha256_file(path: str | os.PathLike[str], chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_files(paths: Sequence[str | os.PathLike[str]]) -> str:
    """One digest for a set of files (sorted by name), e.g. a directory of feature files."""
    h = hashlib.sha256()
    for p in sorted(str(p) for p in paths):
        h.update(Path(p).name.encode())
        h.update(sha256_file(p).encode())
    return h.hexdigest()


def provenance(inputs: dict[str, str]) -> dict[str, str]:
    """Root attributes every artifact carries. `inputs` maps a role (e.g. 'ply') to a SHA-256."""
    return {
        "goi_version": __version__,
        "command": command_line(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "inputs": json.dumps(inputs, sort_keys=True),
    }


def check_writable(path: Path, force: bool, option: str | None = None) -> None:
    """Refuse to clobber an existing output or one of the command's inputs, and fail early on
    an unwritable directory. `option` (e.g. '--cache') starts the message when given."""
    path = Path(path)
    check_output_name(path, option)
    if path.is_dir():
        raise GoiError(
            with_option(option, f"{path}: is a directory; give the path of a file to write")
        )
    refuse_if_input(path, option)
    if (path.exists() or path.is_symlink()) and not force:
        raise GoiError(with_option(option, f"{path}: already exists; pass --force to overwrite it"))
    parent = path.parent if str(path.parent) else Path(".")
    blocker = file_in_the_way(parent)
    if blocker is not None:
        raise GoiError(with_option(option, f"{path}: {blocker} is a file, not a directory"))
    if not parent.is_dir():
        raise GoiError(with_option(option, f"{path}: directory {parent} does not exist"))
    if not os.access(parent, os.W_OK):
        raise GoiError(with_option(option, f"{path}: directory {parent} is not writable"))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], force: bool = False) -> Iterator[Path]:
    """Yield a temporary path; on success it is fsynced and renamed to `path` (at the end of
    the current `staged_outputs()` block, if one is open), else removed."""
    dest = Path(path)
    check_writable(dest, force)
    try:
        # the temporary name is short: the destination's own name may be at the length limit
        fd, tmp_name = tempfile.mkstemp(prefix=".goi-", suffix=".tmp", dir=dest.parent)
    except OSError as e:
        raise GoiError(f"{dest}: could not write ({e.strerror or e})") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; use the user's umask
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        stage = current_stage()
        if stage is not None:  # renamed with the command's other outputs, at its end
            stage.add(tmp, dest)
            return
        os.replace(tmp, dest)
        fsync_dir(dest.parent)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise GoiError(f"{dest}: could not write ({e.strerror or e})") from e
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def write_h5(
    path: str | os.PathLike[str],
    schema: str,
    inputs: dict[str, str],
    force: bool = False,
) -> Iterator[h5py.File]:
    """Create an HDF5 artifact atomically, stamped with its schema, version and provenance."""
    with atomic_path(path, force) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        stamp(f, schema, inputs)
        yield f


def stamp(f: h5py.File, schema: str, inputs: dict[str, str]) -> None:
    """Write the root attributes every artifact carries: schema, version, provenance."""
    from schemas import current_version

    f.attrs["schema"] = schema
    f.attrs["schema_version"] = current_version(schema)
    for k, v in provenance(inputs).items():
        f.attrs[k] = v


def put(group: h5py.Group, name: str, data: Any, compress: bool = False) -> h5py.Dataset:
    """Create a dataset without timestamps, so equal inputs give byte-identical files."""
    arr = np.asarray(data)
    kwargs: dict[str, Any] = {"track_times": False}
    if compress and arr.ndim > 0 and arr.size > 1024:
        kwargs.update(compression="gzip", compression_opts=4, shuffle=True, chunks=True)
    return group.create_dataset(name, data=arr, **kwargs)


@contextlib.contextmanager
def open_h5(path: str | os.PathLike[str], schema: str) -> Iterator[h5py.File]:
    """Open an artifact for reading after validating it against `schema`. Damage that only
    shows while reading (h5py raises OSError, KeyError, ValueError...) becomes a GoiError."""
    from schemas import validate_file

    validate_file(path, expected=schema, raise_on_error=True)
    try:
        with read_h5(path) as f:
            yield f
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as e:
        raise GoiError(f"{path}: damaged HDF5 artifact ({str(e)[:200]})") from None


def write_json(path: str | os.PathLike[str], obj: Any, force: bool = False) -> None:
    with atomic_path(path, force) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, sort_keys=False) + "\n")


def write_png(path: str | os.PathLike[str], image: np.ndarray, force: bool = False) -> None:
    """An image ([H, W] grey or [H, W, 3] RGB, uint8) as a PNG, atomically."""
    import cv2

    img = image if image.ndim == 2 else np.ascontiguousarray(image[:, :, ::-1])
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise GoiError(f"{path}: could not encode PNG")
    with atomic_path(path, force) as tmp:
        tmp.write_bytes(buf.tobytes())


def input_digest(label: str, path: str | os.PathLike[str]) -> dict[str, str]:
    p = Path(path)
    if p.is_dir():
        return {label: sha256_files([q for q in p.rglob("*") if q.is_file()])}
    return {label: sha256_file(p)}
