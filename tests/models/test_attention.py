"""The attention rewrites of `goi export-model` (stages/models/export/attention.py) on small
graphs written here: the fused graph equals the plain one in onnxruntime, what does not match
exactly is left alone, and a rewrite that fails leaves the export as it was."""

import warnings

import numpy as np
import pytest
import torch

from stages.core.errors import GoiError, GoiWarning
from stages.models.export.attention import _bsnd_to_mha, fuse_hiera_attention
from stages.models.export.common import export_checked
from stages.models.onnx_io import session

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

S, C, N, D = 20, 12, 2, 8  # tokens, width in, heads, width of the attention


def hiera_like(extra_reader: bool = False):
    """x [1, S, C] -> SAM 2 Hiera's attention as transformers' export writes it -> [1, S, D]."""
    rng = np.random.default_rng(0)
    inits = [
        numpy_helper.from_array(rng.normal(size=(C, 3 * D)).astype(np.float32), "w"),
        numpy_helper.from_array(np.array([1, S, 3, N, -1], np.int64), "shape5"),
        numpy_helper.from_array(np.array([1, 1, 1], np.int64), "ones"),
        numpy_helper.from_array(np.array([2], np.int64), "axis2"),
        numpy_helper.from_array(np.array([1, S, D], np.int64), "shape3"),
        numpy_helper.from_array(np.array((D // N) ** -0.5, np.float32), "scale"),
    ]
    nodes = [
        helper.make_node("MatMul", ["x", "w"], ["qkv"]),
        helper.make_node("Reshape", ["qkv", "shape5"], ["qkv5"]),
        helper.make_node("Split", ["qkv5", "ones"], ["q5", "k5", "v5"], axis=2),
        *(helper.make_node("Squeeze", [f"{c}5", "axis2"], [c]) for c in "qkv"),
        helper.make_node("Transpose", ["q"], ["qt"], perm=[0, 2, 1, 3]),
        helper.make_node("Transpose", ["k"], ["kt"], perm=[0, 2, 3, 1]),
        helper.make_node("Transpose", ["v"], ["vt"], perm=[0, 2, 1, 3]),
        helper.make_node("MatMul", ["qt", "kt"], ["scores"]),
        helper.make_node("Mul", ["scores", "scale"], ["scaled"]),
        helper.make_node("Softmax", ["scaled"], ["p"], axis=-1),
        helper.make_node("Cast", ["p"], ["p32"], to=TensorProto.FLOAT),
        helper.make_node("MatMul", ["p32", "vt"], ["o"]),
        helper.make_node("Transpose", ["o"], ["ob"], perm=[0, 2, 1, 3]),
        helper.make_node("Reshape", ["ob", "shape3"], ["y"]),
    ]
    outputs = [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, S, D])]
    if extra_reader:  # the attention weights asked for as well: nothing to fuse
        outputs.append(helper.make_tensor_value_info("p", TensorProto.FLOAT, None))
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, S, C])
    graph = helper.make_graph(nodes, "hiera", [x], outputs, inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def run(path, x):
    return session(path).inner.run(["y"], {"x": x})[0]


def test_hiera_attention_runs_fused_and_equal(tmp_path):
    plain, fused = tmp_path / "plain.onnx", tmp_path / "fused.onnx"
    onnx.save(hiera_like(), plain)
    onnx.save(hiera_like(), fused)
    assert fuse_hiera_attention(fused) == 1
    model = onnx.load(fused)
    onnx.checker.check_model(model)  # the com.microsoft domain is declared
    ops = [n.op_type for n in model.graph.node]
    assert ops.count("MultiHeadAttention") == 1
    assert not {"Softmax", "Cast", "Transpose", "Mul"} & set(ops)
    assert "scale" not in {t.name for t in model.graph.initializer}  # read by nothing now
    x = np.random.default_rng(1).normal(size=(1, S, C)).astype(np.float32)
    np.testing.assert_allclose(run(fused, x), run(plain, x), rtol=1e-5, atol=1e-5)


def test_attention_read_elsewhere_is_left_alone():
    model = hiera_like(extra_reader=True)
    before = model.SerializeToString()
    assert _bsnd_to_mha(model) == 0
    assert model.SerializeToString() == before


def test_a_fused_copy_that_fails_leaves_the_export_as_it_was(tmp_path):
    module = torch.nn.Linear(4, 3).eval()
    feeds = [{"x": np.ones((1, 4), np.float32)}]

    def broken(path):
        path.write_bytes(b"not an onnx file")
        return 2

    path = tmp_path / "m.onnx"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        _, checks = export_checked(module, feeds, path, ["y"], {}, 17, fuse=broken)
    assert checks["fused_attention"] == 0 and checks["max_abs_error"] < 1e-5
    said = [str(w.message) for w in seen if issubclass(w.category, GoiWarning)]
    assert len(said) == 1
    assert said[0].startswith("m.onnx: its attention stays as exported, the fused copy failed (")
    assert not (tmp_path / "m.fused.onnx").exists()
    np.testing.assert_allclose(
        session(path).inner.run(None, feeds[0])[0],
        module(torch.ones(1, 4)).detach().numpy(),
        rtol=1e-5,
    )


def test_without_the_onnx_package_the_export_says_what_to_install(tmp_path):
    module = torch.nn.Linear(4, 3).eval()
    feeds = [{"x": np.ones((1, 4), np.float32)}]

    def no_onnx(path):
        raise ModuleNotFoundError("No module named 'onnx'", name="onnx")

    with pytest.raises(GoiError, match=r"pip install 'goi\[export\]'"):
        export_checked(module, feeds, tmp_path / "m.onnx", ["y"], {}, 17, fuse=no_onnx)
    assert not (tmp_path / "m.fused.onnx").exists()
