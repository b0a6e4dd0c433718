"""Open HDF5 files that a user hands goi without letting a damaged one hang it.

libhdf5 (2.0, as h5py 3.16 ships it) walks a global heap collection -- where variable-length
strings live, e.g. every string attribute h5py writes -- with a loop that only advances by the
size each object's header declares. A damaged header that declares 0 leaves the loop where it
is, forever, holding the GIL: `f.attrs["schema"]` never returns and no timeout in Python can stop
it. So before h5py reads a file, every collection in it is walked here the same way with bounds
checked, and a file whose walk would not advance or would leave its collection is refused as
damaged. Other damage libhdf5 reports itself, as an exception.
"""

from __future__ import annotations

import contextlib
import mmap
import os
from collections.abc import Iterator
from functools import lru_cache

import h5py

#: Layout of a global heap collection (HDF5 file format spec, "Global Heap"): the signature,
#: a version byte (1), 3 reserved bytes and the collection's size; then objects, each a 16-byte
#: header (index u16, reference count u16, 4 reserved, size u64) and its data padded to 8 bytes.
#: Object 0 is the collection's free space, its size counting its own header.
_SIGNATURE = b"GCOL"
_HEAD = 16
_OBJ_HEAD = 16
#: libhdf5 never makes a collection smaller than this (H5HG_MINSIZE); the signature found in a
#: smaller one is a chance match inside other data, not a collection.
_MIN_COLLECTION = 4096


def _align8(n: int) -> int:
    return (n + 7) & ~7


def _walk_collection(buf: mmap.mmap, at: int) -> str | None:
    """The problem that would stop libhdf5's walk of the collection at `at`, or None."""
    if buf[at + 4] != 1 or buf[at + 5 : at + 8] != b"\0\0\0":
        return None  # not a collection header: libhdf5 refuses one like it with an error
    size = int.from_bytes(buf[at + 8 : at + 16], "little")
    if size < _MIN_COLLECTION:
        return None
    end = at + size
    if end > len(buf):
        return f"global heap collection at byte {at} runs past the end of the file"
    p = at + _HEAD
    while p < end:
        if p + _OBJ_HEAD > end:
            break  # a tail too small for a header is free space, as libhdf5 reads it
        idx = int.from_bytes(buf[p : p + 2], "little")
        obj = int.from_bytes(buf[p + 8 : p + 16], "little")
        need = _OBJ_HEAD + _align8(obj) if idx > 0 else obj
        if need < _OBJ_HEAD or p + need > end:
            return f"global heap collection at byte {at} has a damaged object at byte {p}"
        p += need
    return None


@lru_cache(maxsize=256)
def _heap_problem(path: str, size: int, mtime_ns: int, inode: int) -> str | None:
    del size, mtime_ns, inode  # the cache key: a file rewritten in place is walked again
    with open(path, "rb") as fh:
        if os.fstat(fh.fileno()).st_size == 0:
            return None
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            at = buf.find(_SIGNATURE)
            while at >= 0:
                if at + _HEAD <= len(buf):
                    problem = _walk_collection(buf, at)
                    if problem:
                        return problem
                at = buf.find(_SIGNATURE, at + 1)
    return None


def heap_problem(path: str | os.PathLike[str]) -> str | None:
    """Why libhdf5 would hang reading `path` (a damaged global heap), or None."""
    p = os.fspath(path)
    st = os.stat(p)
    return _heap_problem(os.path.realpath(p), st.st_size, st.st_mtime_ns, st.st_ino)


class DamagedHDF5(OSError):
    """An OSError, as h5py raises for the damage libhdf5 reports itself, so that every reader
    handles both alike (a partial file is started again, an artifact refused by name)."""


def check_readable(path: str | os.PathLike[str]) -> None:
    """Raise DamagedHDF5 when reading `path` would hang libhdf5."""
    problem = heap_problem(path)
    if problem:
        raise DamagedHDF5(problem)


@contextlib.contextmanager
def read_h5(path: str | os.PathLike[str]) -> Iterator[h5py.File]:
    """`h5py.File(path, "r")`, refused first (DamagedHDF5) when it would hang libhdf5."""
    check_readable(path)
    with h5py.File(path, "r") as f:
        yield f
