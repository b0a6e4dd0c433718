"""The input guard: what a command names as its inputs can never be written or removed by it,
even through a path its preflight did not list."""

import os

import pytest

from stages.core.artifacts import write_json
from stages.core.errors import GoiError
from stages.core.files import guarded_inputs, refuse_if_input, refuse_inputs
from stages.core.staging import staged_outputs


def test_a_recorded_input_is_never_written_even_with_force(tmp_path):
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    mine = inputs / "mine.json"
    mine.write_text("precious")
    os.link(mine, tmp_path / "alias.json")  # another name of the same file
    with guarded_inputs():
        refuse_inputs({"--out": tmp_path / "new.json"}, [inputs])  # a directory: each file
        for path in (mine, tmp_path / "alias.json"):
            with pytest.raises(GoiError, match="inputs"):
                write_json(path, {}, force=True)
        with pytest.raises(GoiError, match="--out: .*inputs"):
            refuse_if_input(tmp_path / "alias.json", "--out")
        write_json(tmp_path / "new.json", {})  # any other path is written as usual
    assert mine.read_text() == "precious"
    write_json(mine, {}, force=True)  # outside the command the record is gone
    assert mine.read_text() != "precious"


def test_a_refused_write_drops_the_staged_outputs(tmp_path):
    mine = tmp_path / "mine.json"
    mine.write_text("precious")
    with guarded_inputs():
        refuse_inputs({}, [mine])
        with pytest.raises(GoiError), staged_outputs():
            write_json(tmp_path / "a.json", {})
            write_json(mine, {}, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.json"]


def test_an_output_inside_an_input_directory_is_refused_only_when_it_exists(tmp_path):
    res = tmp_path / "res"
    res.mkdir()
    (res / "v000.png").write_bytes(b"mask")
    refuse_inputs({"--out": [res / "v001.png"]}, [res])  # a new file there is no input
    with pytest.raises(GoiError, match="--out: .*v000.png is one of this command's inputs"):
        refuse_inputs({"--out": [res / "v001.png", res / "v000.png"]}, [res])
    with pytest.raises(GoiError, match="--out: .*longer than the file system allows"):
        refuse_inputs({"--out": tmp_path / ("x" * 300)}, [res])
