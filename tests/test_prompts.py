"""Prompts, names made from them, text embeddings, RES mask files and the decode kernel."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.cameras import Camera
from stages.errors import GoiError
from stages.hyperplane import HyperplaneOptions, ResFiles, choose_views
from stages.prompts import check_prompt, safe_name, text_embedding, view_file_name
from stages.semantic_render import _decode_kernel, decode_reference


@pytest.mark.parametrize(
    "text", ["../../x", "/etc/passwd", "a\\b", "x" * 5000, "ünïcödé ✓", "CON", ".hidden", "a/./b"]
)
def test_names_stay_inside_the_directory(text, tmp_path):
    name = safe_name(text)
    assert "/" not in name and "\\" not in name and not name.startswith(".")
    assert len(name) <= 49
    p = (tmp_path / name).resolve()
    assert p.parent == tmp_path.resolve()


def test_names_do_not_collide():
    texts = ["a b", "a-b", "A B", "a  b", "a_b"]
    assert len({safe_name(t) for t in texts}) == len(texts)
    assert view_file_name("v000") == "v000" and view_file_name("IMG_1.JPG") == "IMG_1.JPG"
    assert view_file_name("../v000") != "../v000" and "/" not in view_file_name("a/b")


@pytest.mark.parametrize(
    ("text", "words"),
    [("", "empty"), ("   ", "empty"), ("x" * 10_000, "10000 characters"), ("a\x00b", "control")],
)
def test_bad_prompts_are_refused(text, words):
    with pytest.raises(GoiError, match=words):
        check_prompt(text)


def test_text_embeddings_file(tmp_path):
    f = tmp_path / "t.json"
    f.write_text(json.dumps({"sofa": [3.0, 4.0], "tv": [1.0, 0.0]}))
    v, src = text_embedding("sofa", 2, embeddings=f)
    np.testing.assert_allclose(v, [0.6, 0.8], atol=1e-7)
    with pytest.raises(GoiError, match="no embedding for prompt 'chair'"):
        text_embedding("chair", 2, embeddings=f)
    with pytest.raises(GoiError, match="has 2 dimensions but the field's codebook has 3"):
        text_embedding("sofa", 3, embeddings=f)
    f.write_text(json.dumps({"sofa": [1.0, "x"]}))
    with pytest.raises(GoiError, match="not a list of finite numbers"):
        text_embedding("sofa", 2, embeddings=f)
    f.write_text("{not json")
    with pytest.raises(GoiError, match="not valid JSON"):
        text_embedding("sofa", 2, embeddings=f)


def _cam(name, w=40, h=30):
    return Camera(name, w, h, 30.0, 30.0, w / 2, h / 2, np.eye(3), np.zeros(3), None)


def test_res_masks_resized_with_a_warning_and_empty_ones_skipped(tmp_path, recwarn):
    d: Path = tmp_path / "res" / "p1"
    d.mkdir(parents=True)
    small = np.zeros((15, 20), np.uint8)
    small[5:10, 5:10] = 255
    cv2.imwrite(str(d / "a.png"), small)
    cv2.imwrite(str(d / "b.png"), np.zeros((30, 40), np.uint8))
    src = ResFiles(tmp_path / "res", "p1", "x")
    chosen = choose_views(src, [_cam("a"), _cam("b")], HyperplaneOptions(out=None))
    assert [c.name for c, _ in chosen] == ["a"] and chosen[0][1].shape == (30, 40)
    assert chosen[0][1].sum() == 100
    assert any("resized" in str(w.message) for w in recwarn)
    with pytest.raises(GoiError, match="RES mask of view 'b' is empty"):
        choose_views(src, [_cam("a"), _cam("b")], HyperplaneOptions(out=None, fit_on="b"))
    cv2.imwrite(str(d / "a.png"), np.zeros((30, 40), np.uint8))
    with pytest.raises(GoiError, match="every RES mask of this prompt is empty"):
        choose_views(src, [_cam("a"), _cam("b")], HyperplaneOptions(out=None))
    with pytest.raises(GoiError, match="no <view>.png masks"):
        ResFiles(tmp_path / "res", "p2", "x")


def test_decode_kernel_equals_the_reference():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(5000, 10)).astype(np.float32)
    w = rng.normal(size=(300, 10)).astype(np.float32)
    b = rng.normal(size=300).astype(np.float32)
    out = np.empty(5000, np.int32)
    _decode_kernel(f, np.ascontiguousarray(w.T), b, out)
    ref = decode_reference(f, w, b)
    logits = f.astype(np.float64) @ w.T.astype(np.float64) + b
    differ = out != ref
    # float32 vs float64 can only disagree on near-ties
    rows = np.nonzero(differ)[0]
    assert differ.mean() < 1e-3
    np.testing.assert_allclose(logits[rows, out[rows]], logits[rows, ref[rows]], atol=1e-4)
