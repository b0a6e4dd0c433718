"""The global heap walk that keeps libhdf5 from hanging on a damaged file (stages.core.hdf5)."""

from __future__ import annotations

import subprocess
import sys

import h5py
import pytest

from stages.core.hdf5 import DamagedHDF5, _scan, heap_problem, read_h5


def _strings_file(path, length_size: int = 8):  # noqa: ANN001, ANN202
    """A file whose string attributes live in a global heap; sizes of `length_size` bytes."""
    fcpl = h5py.h5p.create(h5py.h5p.FILE_CREATE)
    fcpl.set_sizes(8, length_size)
    with h5py.File(h5py.h5f.create(str(path).encode(), h5py.h5f.ACC_TRUNC, fcpl=fcpl)) as f:
        f.attrs["a"] = "hello world!"
        f.attrs["b"] = "xyz"
    return bytearray(path.read_bytes())


def _objects(data: bytearray, length_size: int):  # noqa: ANN202
    """(offset, index) of each object of the first collection."""
    at = data.find(b"GCOL")
    end = at + int.from_bytes(data[at + 8 : at + 8 + length_size], "little")
    p, out = at + 16, []
    while p + 16 <= end:
        idx = int.from_bytes(data[p : p + 2], "little")
        size = int.from_bytes(data[p + 8 : p + 8 + length_size], "little")
        out.append((p, idx))
        p += size if idx == 0 else 16 + (size + 7) // 8 * 8
    return out


@pytest.mark.parametrize("length_size", [8, 4])
def test_a_free_space_object_of_zero_bytes_is_refused(tmp_path, length_size):
    data = _strings_file(tmp_path / "f.h5", length_size)
    assert heap_problem(tmp_path / "f.h5") is None
    (free,) = [p for p, idx in _objects(data, length_size) if idx == 0]
    data[free + 8 : free + 8 + length_size] = bytes(length_size)
    bad = tmp_path / "bad.h5"
    bad.write_bytes(bytes(data))
    assert "damaged object" in (heap_problem(bad) or "")
    assert "damaged object" in (_scan(bytes(data)) or "")  # read whole, where maps fail
    with pytest.raises(DamagedHDF5), read_h5(bad):
        pass
    # what the walk spares a reader: libhdf5 2.0 never returns on this file (a later one
    # that refuses it with an error is as good)
    probe = f"import h5py; h5py.File({str(bad)!r}).attrs['a']"
    try:
        done = subprocess.run([sys.executable, "-c", probe], timeout=5, capture_output=True)
        assert done.returncode != 0
    except subprocess.TimeoutExpired:
        pass


def test_padding_after_four_byte_sizes_is_not_read_as_size(tmp_path):
    """With 4-byte lengths each size is followed by 4 padding bytes, which libhdf5 does not
    promise to clear: a walk that read 8 bytes there would refuse a good file."""
    data = _strings_file(tmp_path / "f.h5", 4)
    for p, _ in _objects(data, 4):
        data[p + 12 : p + 16] = b"\xff" * 4
    good = tmp_path / "good.h5"
    good.write_bytes(bytes(data))
    assert heap_problem(good) is None
    with read_h5(good) as f:
        assert f.attrs["a"] == "hello world!"


def test_a_file_rewritten_in_place_is_walked_again(tmp_path):
    p = tmp_path / "f.h5"
    data = _strings_file(p)
    assert heap_problem(p) is None
    (free,) = [q for q, idx in _objects(data, 8) if idx == 0]
    data[free + 8 : free + 16] = bytes(8)
    with open(p, "r+b") as fh:  # same path, inode and size
        fh.write(bytes(data))
    assert heap_problem(p) is not None
