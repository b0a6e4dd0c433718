"""An owned output directory (stages.core.owned): files appear together or not at all, are
recorded with their digest, are never written through a symbolic link or over a file the
program did not write, and stay within a byte budget; a crash between the record and the
files leaves both recognised."""

import json
import os

import numpy as np
import pytest

from stages.core import staging
from stages.core.artifacts import write_json, write_png
from stages.core.errors import GoiError
from stages.core.files import make_dir
from stages.core.owned import OwnedDir


def _dir(tmp_path, **kw) -> OwnedDir:  # noqa: ANN003
    return OwnedDir(tmp_path / "out", "goi view", "goi-view.json", **kw)


def _listed(d: OwnedDir) -> dict:
    return json.loads(d.manifest.read_text())["files"]


def test_files_are_recorded_and_replaced_only_when_their_own(tmp_path):
    d = _dir(tmp_path)
    f = d.root / "p" / "a.json"

    def write(value: int) -> None:
        make_dir(f.parent, "--out")
        write_json(f, {"v": value}, force=True)

    _, files = d.write(lambda: write(1), expect=[f])
    assert files == [f] and set(_listed(d)) == {"p/a.json"}
    doc = json.loads(d.manifest.read_text())
    assert doc["schema"] == "goi.owned_dir" and doc["written_by"] == "goi view"
    d.write(lambda: write(2), expect=[f])  # its own, unchanged: replaced
    assert json.loads(f.read_text()) == {"v": 2}
    f.write_text('{"v": "mine"}')  # changed since
    with pytest.raises(GoiError, match="changed since"):
        d.write(lambda: write(3), expect=[f])
    with pytest.raises(GoiError, match="changed since"):
        d.write(lambda: write(3))  # found when the writer wrote it: nothing replaced
    assert f.read_text() == '{"v": "mine"}'
    assert not list(f.parent.glob(".goi-*"))  # no temporary file left behind


def test_nothing_is_written_through_a_symbolic_link(tmp_path):
    d = _dir(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    d.root.mkdir()
    (d.root / "p").symlink_to(elsewhere)
    f = d.root / "p" / "a.json"
    with pytest.raises(GoiError, match="symbolic link"):
        d.write(lambda: write_json(f, {}, force=True), expect=[f])
    with pytest.raises(GoiError, match="symbolic link"):
        d.write(lambda: write_json(f, {}, force=True))  # not announced: still refused
    with pytest.raises(GoiError, match="symbolic link"):
        d.write(lambda: None, dirs=[d.root / "p"])
    (d.root / "x.json").symlink_to(elsewhere / "x.json")
    with pytest.raises(GoiError, match="a symbolic link and was not written"):
        d.write(lambda: write_json(d.root / "x.json", {}, force=True))
    assert list(elsewhere.iterdir()) == []
    with pytest.raises(GoiError, match="outside"):
        d.write(lambda: write_json(tmp_path / "y.json", {}, force=True))
    assert not (tmp_path / "y.json").exists()


def test_an_interrupted_write_leaves_nothing_that_blocks_the_next(tmp_path):
    d = _dir(tmp_path)
    masks = d.root / "p" / "masks"
    img = np.zeros((4, 4), np.uint8)

    def write(fail_at: int | None) -> None:
        make_dir(masks, "--out")
        for i in range(5):
            if i == fail_at:
                raise KeyboardInterrupt  # Ctrl-C half-way
            write_png(masks / f"v{i}.png", img, force=True)

    with pytest.raises(KeyboardInterrupt):
        d.write(lambda: write(2))
    assert not masks.exists() or list(masks.iterdir()) == []
    _, files = d.write(lambda: write(None))
    assert len(files) == 5 and len(_listed(d)) == 5


def test_a_crash_between_the_record_and_the_files_leaves_both_recognised(tmp_path, monkeypatch):
    d = _dir(tmp_path)
    f, g = d.root / "a.json", d.root / "b.json"

    def write(v: int) -> None:
        write_json(f, {"v": v}, force=True)
        write_json(g, {"v": v}, force=True)

    d.write(lambda: write(1))
    real = staging.Stage.commit

    def dies_half_way(self):  # noqa: ANN001, ANN202
        dest, tmp = next(iter(self.pending.items()))
        os.replace(tmp, dest)  # the first file renamed, then the process dies
        self.pending.pop(dest)
        raise SystemExit("killed")

    monkeypatch.setattr(staging.Stage, "commit", dies_half_way)
    with pytest.raises(SystemExit):
        d.write(lambda: write(2))
    monkeypatch.setattr(staging.Stage, "commit", real)
    assert json.loads(f.read_text()) == {"v": 2} and json.loads(g.read_text()) == {"v": 1}
    d.write(lambda: write(3))  # both are still goi's own: replaced
    assert json.loads(f.read_text()) == json.loads(g.read_text()) == {"v": 3}
    assert all(isinstance(v, str) for v in _listed(d).values())  # one digest each again


def test_a_write_past_the_budget_is_refused(tmp_path):
    d = _dir(tmp_path, max_bytes=1000, max_bytes_option="--max-out-mib")
    with pytest.raises(GoiError, match="--max-out-mib: .* past the limit"):
        d.write(lambda: None, estimate=2000)  # refused before any work
    d.write(lambda: write_json(d.root / "a.json", {"x": "y" * 400}, force=True))
    with pytest.raises(GoiError, match="past the limit"):
        d.write(lambda: write_json(d.root / "b.json", {"x": "y" * 700}, force=True))
    assert not (d.root / "b.json").exists()
    # replacing a file counts its new size, not both
    d.write(lambda: write_json(d.root / "a.json", {"x": "z" * 800}, force=True))


def test_a_damaged_record_is_refused_at_once(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "goi-view.json").write_text('{"files": [1, 2]}')
    with pytest.raises(GoiError, match="not goi view's list"):
        _dir(tmp_path)
    (out / "goi-view.json").write_text(
        '{"schema": "goi.owned_dir", "schema_version": "2.0", "files": {}}'
    )
    with pytest.raises(GoiError, match="version"):
        _dir(tmp_path)
    # goi view's list from before the schema is read
    (out / "goi-view.json").write_text('{"written_by": "goi view", "files": {}}')
    _dir(tmp_path)
