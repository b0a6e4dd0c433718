"""Hostile inputs to `goi eval --benchmark` (issue 36, class 6): the benchmark readers bound
what they allocate and never turn a label into a path, and an option the benchmark route
ignores is refused.

Each case writes a broken copy of one benchmark's release layout (stages/testing/
public_layouts.py) and goes through the real CLI: exit 2, one `goi: error:` line naming the
file, field or option, no traceback, and every byte of the case's directory and of the shared
scenes as it was (the assertions of test_hostile_inputs.py)."""

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from goi_cli.main import main
from stages.testing.public_layouts import synthetic_benchmark
from tests.robustness.test_hostile_inputs import _digest

#: one released scene per benchmark (an unknown name would add a warning line)
SCENE = {"lerf-ovs": "figurines", "lerf-mask": "figurines", "3d-ovs": "bed",
         "goi-m360": "room", "replica-goi": "room0"}  # fmt: skip
SIZE = {"3d-ovs": (160, 120)}


@pytest.fixture(scope="module")
def worlds(tmp_path_factory) -> dict[str, dict]:
    """One small scene per benchmark, shared and never written by a case."""
    root = tmp_path_factory.mktemp("benchmarks")
    return {
        b: synthetic_benchmark(root / b, b, scene=name, n=1500, size=SIZE.get(b, (64, 48)))
        for b, name in SCENE.items()
    }


@dataclass
class Case:
    name: str
    benchmark: str
    make: Callable[[Path, Path, dict], list[str]]  # (its bench copy, tmp, world) -> extra argv
    words: tuple[str, ...]


def _argv(s: dict, benchmark: str, bench: Path, tmp: Path, *extra: str) -> list[str]:
    return ["eval", "--benchmark", benchmark, str(bench), "--scene",
            f"{s['scene']}={s['trained']}", "--features", str(s["features"]), "--res-masks",
            str(s["res"]), "--text-embeddings", str(s["embeddings"]), "--out",
            str(tmp / "r.json"), "--iterations", "20", "--entries", "8", *extra]  # fmt: skip


def _huge_png(path: Path, width: int, height: int) -> None:
    """The PNG with its header declaring width x height (the pixels stay a few bytes)."""
    data = bytearray(path.read_bytes())
    assert data[12:16] == b"IHDR"
    data[16:20], data[20:24] = width.to_bytes(4, "big"), height.to_bytes(4, "big")
    path.write_bytes(bytes(data))


def _first(folder: Path, pattern: str) -> Path:
    return sorted(folder.glob(pattern))[0]


# --- frame sizes checked against the camera's before any array is made ---------------------


def _lerf_ovs_billion_rows(bench, tmp, s):
    label = _first(bench / "label" / s["scene"], "*.json")
    doc = json.loads(label.read_text())
    doc["info"].update(height=10**9, width=4 * 10**9 // 3)  # the camera's aspect ratio
    label.write_text(json.dumps(doc))
    return []


def _mask_header(pattern: str, width: int = 64000, height: int = 48000):
    def make(bench, tmp, s):
        _huge_png(_first(bench / s["scene"], pattern), width, height)
        return []

    return make


def _not_png(bench, tmp, s):
    seg = bench / s["scene"] / "segmentations"
    mask = _first(seg, "*/red box.png")
    ok, buf = cv2.imencode(".bmp", np.zeros((120, 160), np.uint8))
    mask.write_bytes(buf.tobytes())  # a BMP: its size cannot be read before decoding it
    return []


# --- class and query names are data, never path components ---------------------------------


def _class_is_a_path(bench, tmp, s):
    outside = tmp / "outside.png"  # what a class joined as a path would reach
    shutil.copy(_first(bench / s["scene"] / "segmentations", "*/wall.png"), outside)
    classes = bench / s["scene"] / "segmentations" / "classes.txt"
    rel = "../../../../outside"
    classes.write_text(classes.read_text() + rel + "\n")
    return []


def _query_longer_than_a_file_name(bench, tmp, s):
    label = _first(bench / "label" / s["scene"], "*.json")
    doc = json.loads(label.read_text())
    long = "a red box " * 30  # 300 bytes: a plain name, but no file name
    doc["objects"][0]["category"] = long
    label.write_text(json.dumps(doc))
    emb = json.loads(s["embeddings"].read_text())
    emb[long] = emb["red box"]
    (tmp / "emb.json").write_text(json.dumps(emb))
    return ["--text-embeddings", str(tmp / "emb.json")]


def _replica_class_is_a_path(bench, tmp, s):
    top = bench / s["scene"] / "test" / "top_list.json"
    doc = json.loads(top.read_text())
    key = next(iter(doc))
    doc[key][0]["class_name"] = "../../escaped"
    top.write_text(json.dumps(doc))
    emb = json.loads(s["embeddings"].read_text())
    emb["../../escaped"] = emb["red box"]
    (tmp / "emb.json").write_text(json.dumps(emb))
    (tmp / "escaped").mkdir()  # a RES folder the path would reach: never read
    shutil.copytree(s["res"] / "red box", tmp / "escaped", dirs_exist_ok=True)
    return ["--text-embeddings", str(tmp / "emb.json")]


# --- LERF-Mask's numbered folders -----------------------------------------------------------


def _lerf_mask_extra_folder(bench, tmp, s):
    masks = bench / s["scene"] / "test_mask"
    shutil.copytree(masks / "1", masks / "2")
    return []


def _lerf_mask_unknown_folder(bench, tmp, s):
    masks = bench / s["scene"] / "test_mask"
    (masks / "1").rename(masks / "frame_99999")
    return []


def _lerf_mask_twice(bench, tmp, s):
    d = bench / s["scene"] / "test_mask" / "0"
    shutil.copy(d / "red box.png", d / "red box.copy.png")  # the script's cat_id is 'red box'
    return []


# --- options the benchmark route ignores or cannot take -------------------------------------


def _res_index(bench, tmp, s):
    (tmp / "index.h5").write_bytes(b"not read")
    return ["--res-index", str(tmp / "index.h5")]


def _seeds(text: str):
    def make(bench, tmp, s):
        return ["--seeds", text]

    return make


CASES = [
    Case("lerf-ovs info of a billion rows", "lerf-ovs", _lerf_ovs_billion_rows,
         ("frame_00002.json", "'info.width' x 'info.height'", "more than 8 times")),
    Case("lerf-mask header of 64000x48000", "lerf-mask", _mask_header("test_mask/0/*.png"),
         ("test_mask/0/", "64000x48000", "more than 8 times its camera 'frame_00002'")),
    Case("goi-m360 header of 64000x48000", "goi-m360", _mask_header("*/masks/*.png"),
         ("masks/DSCF4661.JPG.png", "64000x48000", "more than 8 times")),
    Case("replica class-id map of 64000x48000", "replica-goi", _mask_header("test/sem/*.png"),
         ("test/sem/sem_1.png", "64000x48000", "more than 8 times")),
    Case("3d-ovs mask of another aspect", "3d-ovs",
         _mask_header("segmentations/01/wall.png", 1280, 120),
         ("segmentations/01/wall.png", "1280x120", "another aspect ratio")),
    Case("3d-ovs mask not PNG or JPEG", "3d-ovs", _not_png,
         ("red box.png", "not a PNG or JPEG")),
    Case("3d-ovs class that is a path", "3d-ovs", _class_is_a_path,
         ("classes.txt: line 6", "'../../../../outside' is not a file name")),
    Case("lerf-ovs category longer than a file name", "lerf-ovs",
         _query_longer_than_a_file_name, ("--res-masks: no <view>.png masks in", "a-red-box")),
    Case("replica class name that is a path", "replica-goi", _replica_class_is_a_path,
         ("--res-masks: no <view>.png masks in", "escaped-")),
    Case("lerf-mask a folder more than test cameras", "lerf-mask", _lerf_mask_extra_folder,
         ("test_mask: 3 numbered folders", "2 test cameras")),
    Case("lerf-mask a folder of no test camera", "lerf-mask", _lerf_mask_unknown_folder,
         ("test_mask/frame_99999", "neither a test-camera index")),
    Case("lerf-mask two masks of one prompt", "lerf-mask", _lerf_mask_twice,
         ("red box.copy.png", "a second mask of prompt 'red box'")),
    Case("--res-index with --benchmark", "lerf-mask", _res_index,
         ("--res-index: not used with --benchmark",)),
    Case("--seeds with one seed", "lerf-mask", _seeds("0"), ("--seeds: '0'", "2 or 3")),
    Case("--seeds not integers", "lerf-mask", _seeds("0,x"), ("--seeds: '0,x'", "integers")),
]  # fmt: skip


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hostile_benchmark_input(case, worlds, tmp_path, capsys):
    s = worlds[case.benchmark]
    bench = tmp_path / "bench"
    shutil.copytree(s["bench"], bench)
    argv = _argv(s, case.benchmark, bench, tmp_path, *case.make(bench, tmp_path, s))
    before, world = _digest(tmp_path), _digest(s["bench"].parent)
    _refused(argv, case.words, capsys)
    assert _digest(tmp_path) == before, "the output location or an input changed"
    assert _digest(s["bench"].parent) == world, "a shared scene changed"


def _refused(argv: list[str], words: tuple[str, ...], capsys) -> None:
    """Exit 2 with one `goi: error:` line holding every one of `words`, no traceback."""
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("goi: error: "), err
    assert "Traceback" not in err and "internal error" not in err
    assert all(w in lines[0] for w in words), (words, err)


def test_seeds_are_refused_outside_a_benchmark(worlds, tmp_path, capsys):
    s = worlds["lerf-mask"]
    before = _digest(s["bench"].parent)
    argv = ["eval", str(s["bench"]), "--features", str(s["features"]), "--res-masks",
            str(s["res"]), "--out", str(tmp_path / "r.json"), "--seeds", "0,1"]  # fmt: skip
    _refused(argv, ("--seeds: only with --benchmark",), capsys)
    assert not any(tmp_path.iterdir()) and _digest(s["bench"].parent) == before


def test_enough_cases():
    assert len(CASES) >= 6
