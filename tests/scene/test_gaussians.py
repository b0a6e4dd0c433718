import numpy as np
import plyfile
import pytest

from stages.core.errors import GoiError, GoiWarning
from stages.scene.gaussians import SH_C0, load_ply, save_ply
from tests.helpers import random_vertex, write_ply


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("normals", [True, False])
def test_every_sh_degree_loads_with_inria_activations(tmp_path, degree, normals):
    v = random_vertex(50, degree=degree, normals=normals, extra=("sem_0",), seed=degree)
    g = load_ply(write_ply(tmp_path / "s.ply", v))
    k = (degree + 1) ** 2
    assert g.sh_degree == degree and g.sh.shape == (50, k, 3)
    assert g.extra_fields == ["sem_0"]
    np.testing.assert_allclose(g.opacities, 1 / (1 + np.exp(-v["opacity"])), rtol=1e-6)
    np.testing.assert_allclose(g.scales[:, 1], np.exp(v["scale_1"]), rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(g.quats, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(g.colors_dc()[:, 2], np.clip(0.5 + SH_C0 * v["f_dc_2"], 0, 1))
    if degree:
        # f_rest is channel-major: coefficient 1 of green is f_rest_{k-1}.
        np.testing.assert_array_equal(g.sh[:, 1, 1], v[f"f_rest_{k - 1}"])
        np.testing.assert_array_equal(g.sh[:, k - 1, 2], v[f"f_rest_{3 * (k - 1) - 1}"])


def test_big_endian_and_ascii_are_accepted(tmp_path):
    v = random_vertex(20, degree=1)
    ref = load_ply(write_ply(tmp_path / "le.ply", v))
    for name, kw in [("be.ply", {"byte_order": ">"}), ("a.ply", {"text": True})]:
        el = plyfile.PlyElement.describe(v.astype(v.dtype.newbyteorder(">")), "vertex")
        plyfile.PlyData([el], **kw).write(str(tmp_path / name))
        g = load_ply(tmp_path / name)
        np.testing.assert_allclose(g.means, ref.means, rtol=1e-6)
        np.testing.assert_allclose(g.sh, ref.sh, rtol=1e-6)


def test_save_keeps_every_field(tmp_path):
    v = random_vertex(30, degree=2, extra=("sem_0", "sem_1"))
    g = load_ply(write_ply(tmp_path / "a.ply", v))
    save_ply(tmp_path / "b.ply", g.vertex)
    back = plyfile.PlyData.read(str(tmp_path / "b.ply"))["vertex"].data
    assert back.dtype.names == v.dtype.names
    for name in v.dtype.names:
        np.testing.assert_array_equal(back[name], v[name])


def _expect(path, *words):
    with pytest.raises(GoiError) as e:
        load_ply(path)
    msg = str(e.value)
    assert str(path) in msg
    for w in words:
        assert w in msg, msg


def test_truncated_ply_is_refused_before_reading(tmp_path):
    p = write_ply(tmp_path / "t.ply", random_vertex(100))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 100])
    _expect(p, "truncated", "100 vertices")


def test_absurd_vertex_count_is_refused(tmp_path):
    p = write_ply(tmp_path / "t.ply", random_vertex(3))
    p.write_bytes(p.read_bytes().replace(b"element vertex 3", b"element vertex 1000000000000"))
    _expect(p, "1000000000000")


@pytest.mark.parametrize("field", ["x", "opacity", "scale_2", "f_dc_1"])
def test_nan_and_inf_are_refused_naming_the_field(tmp_path, field):
    v = random_vertex(10)
    v[field][3] = np.nan if field != "x" else np.inf
    _expect(write_ply(tmp_path / "n.ply", v), field, "NaN/inf", "vertex 3")


@pytest.mark.parametrize("field", ["f_dc_0", "scale_1", "rot_3"])
def test_missing_fields_are_named(tmp_path, field):
    v = random_vertex(10)
    keep = [n for n in v.dtype.names if n != field]
    _expect(write_ply(tmp_path / "m.ply", v[keep]), field, "missing")


def test_zero_gaussians_and_bad_rest_counts(tmp_path):
    _expect(write_ply(tmp_path / "z.ply", random_vertex(0)), "zero Gaussians")
    v = random_vertex(5, degree=1)
    keep = [n for n in v.dtype.names if n != "f_rest_8"]
    _expect(write_ply(tmp_path / "r.ply", v[keep]), "f_rest")


def test_not_a_ply(tmp_path):
    p = tmp_path / "x.ply"
    p.write_text("hello")
    _expect(p, "not a PLY")


def test_zero_quaternion_is_skipped_with_a_warning(tmp_path):
    v = random_vertex(10)
    for c in range(4):
        v[f"rot_{c}"][2] = 0
    with pytest.warns(GoiWarning, match="1 Gaussians have a zero quaternion"):
        g = load_ply(write_ply(tmp_path / "q.ply", v))
    assert not g.valid[2] and g.valid.sum() == 9
