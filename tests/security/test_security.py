"""Untrusted inputs: prompts as paths, HTML, ONNX custom operators, absurd sizes.
(Pickled feature files: tests/test_extract.py::test_a_pickled_object_is_refused_and_never_runs.)"""

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.query.pipeline import QueryResult

EVIL = ["../../escape", "/etc/passwd", "..", "a/../../b", "x" * 900, "<script>alert(1)</script>"]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from tests.robustness.test_bad_inputs import world as make

    return make.__wrapped__(tmp_path_factory)


def test_prompts_never_write_outside_the_output_directory(world, tmp_path):
    emb = {t: world["objects"][1].tolist() for t in EVIL}
    (tmp_path / "t.json").write_text(json.dumps(emb))
    out = tmp_path / "deep" / "out"
    before = {p for p in Path("/tmp").glob("*")} | {p for p in tmp_path.rglob("*")}
    for text in EVIL:
        argv = ["query", "--scene", str(world["scene"]), "--field", str(world["w"] / "field.h5"),
                "--prompt", text, "--mode", "threshold", "--text-embeddings",
                str(tmp_path / "t.json"), "--out", str(out)]  # fmt: skip
        assert main(argv) == 0
    after = {p for p in Path("/tmp").glob("*")} | {p for p in tmp_path.rglob("*")}
    for p in after - before:
        inside = p.resolve().is_relative_to(out.resolve())
        assert inside or out.resolve().is_relative_to(p.resolve()), p  # out or its parents
    assert len(list(out.iterdir())) == len(EVIL)  # one directory per prompt, no collision
    from stages.query.selection import load_selection

    texts = {load_selection(d / "selection.h5").prompt for d in out.iterdir()}
    assert texts == set(EVIL)  # the original text is kept in the artifact


def test_html_pages_escape_user_strings(tmp_path):
    from stages.evaluation.demo import DemoAnswer, _index
    from stages.evaluation.room import Prompt

    d = tmp_path / "q" / "p"
    (d / "masks").mkdir(parents=True)
    bad = "<script>alert('x')</script>"
    r = QueryResult(bad, d, False, [], d / "selection.h5", d / "a&b<c>.ply", 3, {})
    _index(tmp_path / "index.html", [DemoAnswer(Prompt("p", bad, [], [], ""), r, 0.5)], [])
    page = (tmp_path / "index.html").read_text()
    assert "<script>" not in page and "&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt;" in page
    assert "a&amp;b&lt;c&gt;.ply" in page


def test_eval_page_escapes_prompts_and_views(tmp_path):
    from stages.evaluation.report import eval_page
    from stages.evaluation.room import Prompt

    bad = '"><img src=x onerror=alert(1)>'
    report = {
        "room": bad, "threshold": 0.5, "goi_version": "0", "timings_s": {bad: 1.0},
        "variants": {"full": {"miou": 0.5, "mpa": 0.5, "mp": 0.5, "prompts": {
            "p1": {"iou": 0.5, "views": {}}}}},
    }  # fmt: skip
    res = {"p1": (bad, {bad: (np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), bool))})}
    eval_page(
        tmp_path / "r.html", report, [Prompt("p1", bad, [1], [], "")],
        {"full": {"p1": [{}, {}]}}, {}, None, res,
    )  # fmt: skip
    page = (tmp_path / "r.html").read_text()
    assert "<img src=x" not in page and "&lt;img src=x onerror=alert(1)&gt;" in page
    assert "<b>RES</b>" in page  # the RES row's source and view name are escaped too
    assert all(p.parent == tmp_path / "r_files" for p in tmp_path.rglob("*.png"))


def test_onnx_custom_operators_are_never_loaded(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    from tests.models.test_bundle import make_bundle

    root, _, _, _ = make_bundle(tmp_path / "b")
    node = helper.make_node("Evil", ["image"], ["features"], domain="com.evil")
    graph = helper.make_graph(
        [node], "g",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])],
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, 12, "h", "w"])],
    )  # fmt: skip
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("com.evil", 1)]
    )
    onnx.save(model, str(root / "image_encoder.onnx"))
    from stages.models.bundle import load_bundle

    with pytest.raises(GoiError, match="not a loadable ONNX model"):
        load_bundle(root).encode_image(np.zeros((32, 32, 3), np.uint8))


def test_hdf5_declaring_an_absurd_dataset_is_refused_before_reading(world, tmp_path):
    from stages.semantics.codebook import load_codebook

    p = tmp_path / "c.h5"
    with h5py.File(world["w"] / "c.h5") as src, h5py.File(p, "w") as f:
        for k, v in src.attrs.items():
            f.attrs[k] = v
        for k in src:
            if k == "entries":
                f.create_dataset(k, shape=(10**6, 10**6), dtype="float32", chunks=(1, 1024))
            else:
                f.create_dataset(k, data=src[k][()])
    assert p.stat().st_size < 1_000_000
    with pytest.raises(GoiError, match="more than goi reads"):
        load_codebook(p)
