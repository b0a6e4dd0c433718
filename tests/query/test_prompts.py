"""Prompts, the names made from them, and text embeddings."""

import json

import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.query.prompts import (
    check_prompt,
    read_prompt_table,
    read_text_embeddings,
    safe_name,
    text_embedding,
    view_file_name,
)


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


def test_a_table_read_once_answers_as_its_file(tmp_path):
    """goi view reads --text-embeddings once; its answers and refusals are the CLI's."""
    f = tmp_path / "t.json"
    f.write_text(json.dumps({"sofa": [3.0, 4.0]}))
    table = read_text_embeddings(f)
    for src in (f, table):
        v, where = text_embedding("sofa", 2, embeddings=src)
        np.testing.assert_allclose(v, [0.6, 0.8], atol=1e-7)
        assert where == "file:t.json"
        with pytest.raises(GoiError, match=f"^{f}: no embedding for prompt 'chair'"):
            text_embedding("chair", 2, embeddings=src)
        with pytest.raises(GoiError, match="has 2 dimensions but the field's codebook has 3"):
            text_embedding("sofa", 3, embeddings=src)
    f.write_text(json.dumps({"sofa": [1.0, 0.0]}))  # read once: the table keeps what it read
    np.testing.assert_allclose(text_embedding("sofa", 2, embeddings=table)[0], [0.6, 0.8])


def test_a_prompts_file_is_checked(tmp_path):
    bad = [
        ({"id": "p1", "text": "x"}, "JSON list"),
        ([{"id": "../x", "text": "a"}], "not a plain name"),
        ([{"id": "p1", "text": ""}], "empty"),
        ([{"id": 3, "text": "a"}], "string 'id'"),
    ]
    for raw, message in bad:
        (tmp_path / "p.json").write_text(json.dumps(raw))
        with pytest.raises(GoiError, match=message):
            read_prompt_table(tmp_path / "p.json")
    (tmp_path / "p.json").write_text(
        json.dumps([{"id": "p1", "text": " a "}, {"id": "p2", "text": "a"}])
    )
    assert read_prompt_table(tmp_path / "p.json") == {"a": "p1"}
