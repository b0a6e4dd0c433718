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
#: a version byte (1), 3 reserved bytes and the collection's size; then objects, each a header
#: (index u16, reference count u16, 4 reserved, size) and its data padded to 8 bytes. Object 0
#: is the collection's free space, its size counting its own header. Sizes take the file's
#: "size of lengths" bytes (the superblock's; 8 from h5py), and both headers are padded to 8.
Buffer = bytes | mmap.mmap  # the file's bytes, mapped or read
_SIGNATURE = b"GCOL"
_HDF5 = b"\x89HDF\r\n\x1a\n"
#: libhdf5 never makes a collection smaller than this (H5HG_MINSIZE), and refuses one that
#: claims less with an error; the signature found in a smaller one is no collection to walk.
_MIN_COLLECTION = 4096


def _align8(n: int) -> int:
    return (n + 7) & ~7


def _size_of_lengths(buf: Buffer) -> int:
    """The superblock's size of lengths (at byte 0, 512, 1024, ...; 8 when none is found):
    superblock versions 0 and 1 hold it at byte 14, versions 2 and 3 at byte 10."""
    at = 0
    while at + 16 <= len(buf):
        if buf[at : at + 8] == _HDF5:
            size = buf[at + 14] if buf[at + 8] in (0, 1) else buf[at + 10]
            return size if size in (2, 4, 8, 16) else 8
        at = 512 if at == 0 else at * 2
    return 8


def _walk_collection(buf: Buffer, at: int, length: int) -> str | None:
    """The problem that would stop libhdf5's walk of the collection at `at`, or None."""
    head = _align8(8 + length)  # the collection's header and each object's
    if at + head > len(buf) or buf[at + 4] != 1 or buf[at + 5 : at + 8] != b"\0\0\0":
        return None  # not a collection header: libhdf5 refuses one like it with an error
    size = int.from_bytes(buf[at + 8 : at + 8 + length], "little")
    if size < _MIN_COLLECTION:
        return None
    end = at + size
    if end > len(buf):
        return f"global heap collection at byte {at} runs past the end of the file"
    p = at + head
    while p < end:
        if p + head > end:
            break  # a tail too small for a header is free space, as libhdf5 reads it
        idx = int.from_bytes(buf[p : p + 2], "little")
        obj = int.from_bytes(buf[p + 8 : p + 8 + length], "little")
        need = head + _align8(obj) if idx > 0 else obj
        if need < head or p + need > end:
            return f"global heap collection at byte {at} has a damaged object at byte {p}"
        p += need
    return None


def _scan(buf: Buffer) -> str | None:
    length = _size_of_lengths(buf)
    at = buf.find(_SIGNATURE)
    while at >= 0:
        problem = _walk_collection(buf, at, length)
        if problem:
            return problem
        at = buf.find(_SIGNATURE, at + 1)
    return None


@lru_cache(maxsize=256)
def _heap_problem(path: str, key: tuple[int, ...]) -> str | None:
    del key  # size, mtime, ctime, inode, device: a file changed in any way is walked again
    with open(path, "rb") as fh:
        if os.fstat(fh.fileno()).st_size == 0:
            return None
        try:
            buf = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # a file system that cannot map files: read it whole
            return _scan(fh.read())
        with buf:
            return _scan(buf)


def heap_problem(path: str | os.PathLike[str]) -> str | None:
    """Why libhdf5 would hang reading `path` (a damaged global heap), or None."""
    p = os.fspath(path)
    st = os.stat(p)
    key = (st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev)
    return _heap_problem(os.path.realpath(p), key)


class DamagedHDF5(OSError):
    """An OSError, as h5py raises for the damage libhdf5 reports itself, so that every reader
    handles both alike (a partial file is started again, an artifact refused by name)."""


@contextlib.contextmanager
def read_h5(path: str | os.PathLike[str]) -> Iterator[h5py.File]:
    """`h5py.File(path, "r")`, refused first (DamagedHDF5) when it would hang libhdf5."""
    problem = heap_problem(path)
    if problem:
        raise DamagedHDF5(problem)
    with h5py.File(path, "r") as f:
        yield f
