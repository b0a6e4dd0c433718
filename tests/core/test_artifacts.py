import h5py
import numpy as np
import pytest

from schemas import known_schemas, validate_file
from stages.core.artifacts import atomic_path, open_h5
from stages.core.errors import GoiError
from stages.scene.formats.inria import write_inria
from tests.helpers import build_or_load, front_camera, random_vertex, write_ply


def _cache_file(tmp_path):
    from stages.scene.scene import load_scene

    write_ply(tmp_path / "point_cloud.ply", random_vertex(60))
    write_inria(tmp_path / "cameras.json", [front_camera(20, 16)])
    build_or_load(tmp_path / "c.h5", load_scene(tmp_path), [front_camera(20, 16)])
    return tmp_path / "c.h5"


def test_every_schema_definition_is_complete():
    assert "goi.blend_cache" in known_schemas()
    from schemas import definition

    for name in known_schemas():
        d = definition(name)
        assert d["schema"] == name
        major, minor = d["version"].split(".")
        assert major.isdigit() and minor.isdigit()
        for spec in d.get("datasets", {}).values():
            np.dtype(spec["dtype"]) if spec["dtype"] != "str" else None


def test_a_good_artifact_validates_and_records_provenance(tmp_path):
    p = _cache_file(tmp_path)
    schema, errors = validate_file(p)
    assert (schema, errors) == ("goi.blend_cache", [])
    with h5py.File(p) as f:
        assert f.attrs["schema_version"] == "1.0"
        assert len(f.attrs["ply_sha256"]) == 64
        assert "goi_version" in f.attrs and "command" in f.attrs and "created" in f.attrs


def _tamper(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda f: f.attrs.__setitem__("schema_version", "2.0"), ["version 2.0", "upgrade goi"]),
        (lambda f: f.attrs.__setitem__("schema_version", "0.3"), ["version 0.3", "re-create"]),
        (lambda f: f.attrs.__setitem__("schema", "goi.nonsense"), ["goi.nonsense"]),
        (lambda f: f.attrs.__delitem__("schema"), ["not a goi artifact"]),
        (lambda f: f.attrs.__delitem__("inputs"), ["'inputs' is missing"]),
        (lambda f: f.__delitem__("order"), ["'order' is missing"]),
        (lambda f: f["views/c0"].__delitem__("weights"), ["views/c0/weights' is missing"]),
        (
            lambda f: (f.__delitem__("order"), f.create_dataset("order", data=np.zeros(60))),
            ["dtype float64"],
        ),
        (
            lambda f: (
                f.__delitem__("order"),
                f.create_dataset("order", data=np.zeros(7, np.int32)),
            ),
            ["axis 0 has size 7"],
        ),
        (lambda f: f["views/c0"].attrs.__delitem__("width"), ["'width' is missing"]),
    ],
)
def test_bad_artifacts_are_refused_with_the_reason(tmp_path, change, words):
    p = _cache_file(tmp_path)
    _tamper(p, change)
    with pytest.raises(GoiError) as e:
        with open_h5(p, "goi.blend_cache"):
            pass
    msg = str(e.value)
    assert msg.startswith(str(p))
    for w in words:
        assert w in msg, msg


def test_wrong_kind_truncated_and_non_hdf5_files(tmp_path):
    p = _cache_file(tmp_path)
    with pytest.raises(GoiError, match="goi.blend_cache artifact, but a goi.field"):
        validate_file(p, expected="goi.field", raise_on_error=True)
    data = p.read_bytes()
    (tmp_path / "t.h5").write_bytes(data[: len(data) // 2])
    with pytest.raises(GoiError, match="t.h5"):
        with open_h5(tmp_path / "t.h5", "goi.blend_cache"):
            pass
    (tmp_path / "x.h5").write_text("not hdf5")
    assert validate_file(tmp_path / "x.h5")[1][0].startswith("not a readable HDF5 file")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    dest = tmp_path / "out.bin"
    with pytest.raises(RuntimeError), atomic_path(dest) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []
    with atomic_path(dest) as tmp:
        tmp.write_bytes(b"whole")
    assert dest.read_bytes() == b"whole"
    with pytest.raises(GoiError, match="already exists; pass --force"), atomic_path(dest):
        pass
    with atomic_path(dest, force=True) as tmp:
        tmp.write_bytes(b"again")
    assert dest.read_bytes() == b"again" and len(list(tmp_path.iterdir())) == 1


def test_unwritable_directory_is_named(tmp_path):
    with pytest.raises(GoiError, match="does not exist"), atomic_path(tmp_path / "no" / "x.h5"):
        pass


def test_same_inputs_give_byte_identical_artifacts_but_the_timestamp(tmp_path):
    (tmp_path / "1").mkdir()
    (tmp_path / "2").mkdir()
    a, b = _cache_file(tmp_path / "1"), _cache_file(tmp_path / "2")

    def normalised(p):
        with h5py.File(p) as f:
            stamp = f.attrs["created"].encode()
        return p.read_bytes().replace(stamp, b"T" * len(stamp))

    assert normalised(a) == normalised(b)
