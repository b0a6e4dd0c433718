"""Hostile inputs, second sweep (docs/reliability.md): each case breaks one thing and must give
exit 2, one `goi: error:` line naming the file, field or option, no traceback, and leave every
file it was given, and the whole place it writes to, exactly as it was. For the cases that used
to fail late, 'unchanged' is the proof that the error came before the expensive step: no blend
cache, no mask, no hyperplane was written."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from goi_cli.main import main
from stages.query.prompts import safe_name
from stages.scene.gaussians import load_ply
from tests.helpers import write_ply


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from tests.robustness.test_bad_inputs import world as make

    s = make.__wrapped__(tmp_path_factory)
    w = s["w"]
    # a plane for render-mask and select, and a tiny benchmark room for eval
    assert main(["fit-hyperplane", "--scene", str(s["scene"]), "--field", str(w / "field.h5"),
                 "--prompt", "box", "--text-embeddings", str(w / "text.json"),
                 "--res-masks", str(w / "res"), "--out", str(w / "planes.h5")]) == 0  # fmt: skip
    room = w / "room"
    shutil.copytree(s["scene"], room)
    test = s["test"]
    prompt = {"id": "p1", "text": "box", "targets": [1], "test_views": test, "kind": "category"}
    (room / "prompts.json").write_text(json.dumps([prompt]))
    shutil.copy(w / "text.json", room / "text_embeddings.json")
    for v in test:
        (room / "eval" / "masks" / "p1").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(room / "eval" / "masks" / "p1" / f"{v}.png"), np.zeros((36, 48), np.uint8))
    shutil.copytree(w / "res", w / "room_res" / "p1")
    s["room"] = room
    return s


@dataclass
class Case:
    name: str
    make: Callable  # (world, tmp) -> argv; may write broken inputs into tmp
    words: tuple[str, ...]
    subprocess: bool = False  # run in a child with a timeout (a hang must fail, not block)


def _digest(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink() or not (p.is_file() or p.is_dir()):
            out[str(p)] = "special"
        elif p.is_file():
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[str(p)] = "dir"
    return out


# --- building blocks ----------------------------------------------------------------------


def _scene(s, tmp: Path) -> Path:
    d = tmp / "scene"
    shutil.copytree(s["scene"], d)
    return d


def _extract(d: Path, s, tmp: Path) -> list[str]:
    return ["extract", "--scene", str(d), "--from", str(s["features"]), "--out", str(tmp / "o.h5")]


def _scene_case(edit: Callable[[Path], None]):
    def make(s, tmp):
        d = _scene(s, tmp)
        edit(d)
        return _extract(d, s, tmp)

    return make


def _cameras_json(edit: Callable[[list], None]):
    def change(d: Path):
        cams = json.loads((d / "cameras.json").read_text())
        edit(cams)
        (d / "cameras.json").write_text(json.dumps(cams))

    return _scene_case(change)


def _transforms(edit: Callable[[dict], None]):
    def change(d: Path):
        from stages.scene.formats import load_cameras
        from stages.scene.formats.nerf import write_transforms

        cams = load_cameras(d / "cameras.json")
        (d / "cameras.json").unlink()
        write_transforms(d / "transforms.json", cams)
        data = json.loads((d / "transforms.json").read_text())
        edit(data)
        (d / "transforms.json").write_text(json.dumps(data))

    return _scene_case(change)


def _skew(cams):
    r = np.asarray(cams[1]["rotation"])
    shear = np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # det 1, not orthonormal
    cams[1]["rotation"] = (r @ shear).tolist()


def _colmap_latin1(d: Path):
    from stages.scene.formats import load_cameras
    from stages.scene.formats.colmap import write_colmap

    cams = load_cameras(d / "cameras.json")
    (d / "cameras.json").unlink()
    write_colmap(d / "sparse" / "0", cams, binary=False)
    images = d / "sparse" / "0" / "images.txt"
    images.write_bytes(images.read_bytes().replace(b"# Image list", b"# Bild\xe4r"))


def _ply_case(edit: Callable[[Path], None]):
    """A command that reads the scene's PLY (extract does not need it)."""

    def make(s, tmp):
        d = _scene(s, tmp)
        edit(d)
        return ["export-ply", "--scene", str(d), "--selection", str(s["selection"]),
                "--out", str(tmp / "o.ply")]  # fmt: skip

    return make


def _ply_text(header: str, body: bytes = b""):
    def edit(d: Path):
        (d / "point_cloud.ply").write_bytes(header.encode() + body)

    return _ply_case(edit)


def _zero_quaternions(d: Path):
    v = load_ply(d / "point_cloud.ply").vertex.copy()
    for c in range(4):
        v[f"rot_{c}"] = 0
    write_ply(d / "point_cloud.ply", v)


def _h5_copy(s, tmp: Path, name: str, edit: Callable[[h5py.File], None], src=None) -> Path:
    p = tmp / name
    shutil.copy(src or s["w"] / name, p)
    with h5py.File(p, "r+") as f:
        edit(f)
    return p


def _replace(name: str, fn: Callable[[np.ndarray], np.ndarray]):
    def edit(f: h5py.File):
        data = fn(f[name][()])
        del f[name]
        f.create_dataset(name, data=data)

    return edit


def _after(setup: Callable[[Path], object], make: Callable) -> Callable:
    """A case that first puts something in its directory, then runs `make`."""

    def run(s, tmp):
        setup(tmp)
        return make(s, tmp)

    return run


def _bigger_decoder(f: h5py.File) -> None:
    """Three decoder rows more than the codebook has entries (weight and bias agree)."""
    _replace("decoder_weight", lambda a: np.concatenate([a, a[:3]]))(f)
    _replace("decoder_bias", lambda a: np.concatenate([a, a[:3]]))(f)


def _wide_camera(s, tmp):
    d = _scene(s, tmp)
    text = (d / "cameras.json").read_text()
    (d / "cameras.json").write_text(text.replace('"width": 48', '"width": 1e400', 1))
    return _extract(d, s, tmp)


def _eval_room_missing(s, tmp):
    argv = _eval_room(s, tmp)
    next((tmp / "room" / "eval" / "masks" / "p1").glob("*.png")).unlink()
    return argv


def _select(s, tmp, field=None, planes=None, extra=()):
    return ["select", "--scene", str(s["scene"]), "--field", str(field or s["w"] / "field.h5"),
            "--prompt", "box", "--hyperplanes", str(planes or s["w"] / "planes.h5"),
            "--out", str(tmp / "sel.h5"), *extra]  # fmt: skip


def _render(s, tmp, field=None, planes=None, extra=()):
    return ["render-mask", "--scene", str(s["scene"]), "--field",
            str(field or s["w"] / "field.h5"), "--prompt", "box", "--hyperplanes",
            str(planes or s["w"] / "planes.h5"), "--out", str(tmp / "masks"), *extra]  # fmt: skip


def _field(s, tmp, *extra, features=None, codebook=None, out=None):
    return ["fit-field", "--scene", str(s["scene"]), "--features",
            str(features or s["w"] / "f.h5"), "--codebook", str(codebook or s["w"] / "c.h5"),
            "--out", str(out or tmp / "field.h5"), "--iterations", "2", *extra]  # fmt: skip


def _query(s, tmp, *extra, text=None, out=None):
    return ["query", "--scene", str(s["scene"]), "--field", str(s["w"] / "field.h5"),
            "--prompt", "box", "--text-embeddings", str(text or s["w"] / "text.json"),
            "--res-masks", str(s["w"] / "res"), "--out", str(out or tmp / "q"), *extra]  # fmt: skip


def _text(content: str):
    def make(s, tmp):
        (tmp / "t.json").write_text(content)
        return _query(s, tmp, text=tmp / "t.json")

    return make


def _npy_dir(write: Callable[[Path], None]):
    def make(s, tmp):
        d = tmp / "feats"
        shutil.copytree(s["features"], d)
        write(sorted(d.glob("*.npy"))[1])
        return ["extract", "--scene", str(s["scene"]), "--from", str(d), "--out",
                str(tmp / "o.h5")]  # fmt: skip

    return make


def _fifo_cameras(s, tmp):
    d = _scene(s, tmp)
    os.mkfifo(tmp / "cams.json")
    return ["extract", "--scene", str(d), "--cameras", str(tmp / "cams.json"), "--from",
            str(s["features"]), "--out", str(tmp / "o.h5")]  # fmt: skip


def _one_mask_exists(s, tmp):
    (tmp / "masks").mkdir()
    view = s["test"][1]
    (tmp / "masks" / f"{view}.overlay.png").write_bytes(b"mine")
    return _render(s, tmp)


def _features_without_views(s, tmp):
    p = _h5_copy(s, tmp, "f.h5", lambda f: [f["views"].pop(v) for v in list(f["views"])])
    return ["init-codebook", "--features", str(p), "--out", str(tmp / "c.h5")]


def _codebook_of(entries: int):
    def make(s, tmp):
        p = _h5_copy(s, tmp, "c.h5", lambda f: None)
        with h5py.File(p, "r+") as f:
            for name in ("entries", "counts"):
                data = f[name][()][:entries]
                del f[name]
                f.create_dataset(name, data=data)
            f.attrs["n_entries"] = entries
        return _field(s, tmp, codebook=p)

    return make


def _eval_room(s, tmp, features=None, text=None):
    room = tmp / "room"
    shutil.copytree(s["room"], room)
    if text is not None:
        (room / "text_embeddings.json").write_text(json.dumps(text))
    return ["eval", str(room), "--features", str(features or s["features"]),
            "--res-masks", str(s["w"] / "room_res"), "--out", str(tmp / "r.json"),
            "--iterations", "2"]  # fmt: skip


def _cache_with_a_bad_id(s, tmp):
    def edit(f):
        view = next(iter(f["views"]))
        ids = f["views"][view]["indices"][()]
        ids[0] = 10**6
        del f["views"][view]["indices"]
        f["views"][view].create_dataset("indices", data=ids)

    cache = _h5_copy(s, tmp, "blend_cache.h5", edit)
    return _field(s, tmp, "--cache", str(cache))


# --- third sweep: outputs that are (or hold) inputs, and the rest of the external run ----------


def _box_dir(out: Path) -> Path:
    return out / safe_name("box")


def _export(s, tmp, out, *extra, selection=None):
    return ["export-ply", "--scene", str(s["scene"]), "--selection",
            str(selection or s["selection"]), "--out", str(out), *extra]  # fmt: skip


def _copy(src: Path, dst: Path) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    (shutil.copytree if src.is_dir() else shutil.copy)(src, dst)
    return dst


def _ckpt_is_codebook(s, tmp):
    cb = _copy(s["w"] / "c.h5", tmp / "field.h5.ckpt")  # <out>.ckpt is the codebook given
    return _field(s, tmp, "--checkpoint-every", "1", codebook=cb, out=tmp / "field.h5")


def _query_field_inside_out(s, tmp):
    field = _copy(s["w"] / "field.h5", _box_dir(tmp / "q") / "selection.h5")
    return _query(s, tmp)[:4] + [str(field)] + _query(s, tmp)[5:]


def _query_res_inside_out(s, tmp):
    res = _copy(s["w"] / "res", _box_dir(tmp / "q") / "masks")
    argv = _query(s, tmp, "--views", s["train"][0])
    return [str(res) if a == str(s["w"] / "res") else a for a in argv]


def _query_ply_inside_out(s, tmp):
    ply = _copy(s["scene"] / "point_cloud.ply", _box_dir(tmp / "q") / f"{safe_name('box')}.ply")
    return ["query", "--ply", str(ply), "--cameras", str(s["scene"] / "cameras.json"),
            *_query(s, tmp)[3:]]  # fmt: skip


def _in_query_out(make_thing: Callable[[Path], object]):
    def make(s, tmp):
        make_thing(_box_dir(tmp / "q"))
        return _query(s, tmp)

    return make


def _partial(kind: str):
    def make(s, tmp):
        partial = tmp / "o.h5.partial"
        os.mkfifo(partial) if kind == "fifo" else partial.mkdir()
        return _extract(s["scene"], s, tmp)

    return make


def _eval_with(edit: Callable[[Path], object], *extra: str, features=None):
    def make(s, tmp):
        argv = _eval_room(s, tmp, features=features(s, tmp) if features else None)
        edit(tmp / "room")
        return argv + [a.replace("{tmp}", str(tmp)) for a in extra]

    return make


def _prompts(edit: Callable[[list], object]):
    def change(room: Path):
        prompts = json.loads((room / "prompts.json").read_text())
        edit(prompts)
        (room / "prompts.json").write_text(json.dumps(prompts))

    return change


def _work_holds_user_files(s, tmp):
    _copy(s["w"] / "f.h5", tmp / "work" / "features.h5")
    _copy(s["w"] / "c.h5", tmp / "work" / "codebook.h5")
    return _eval_room(s, tmp) + ["--work", str(tmp / "work")]


def _work_is_the_room(s, tmp):
    argv = _eval_room(s, tmp)
    _copy(s["w"] / "f.h5", tmp / "room" / "features.h5")
    return argv + ["--work", str(tmp / "room")]


def _huge_camera(s, tmp):
    cams = json.loads((s["scene"] / "cameras.json").read_text())[:1]
    cams[0].update(width=16384, height=16384, img_name="novel")
    (tmp / "novel.json").write_text(json.dumps(cams))
    return _render(s, tmp, extra=("--camera-file", str(tmp / "novel.json")))


def _planes_of_dim(d: int):
    def edit(f: h5py.File):
        g = f["prompts"][safe_name("box")]
        for name in ("W", "text_embedding"):
            data = g[name][()][:d]
            del g[name]
            g.create_dataset(name, data=data)

    return edit


def _zero_codebook(f: h5py.File) -> None:
    _replace("entries", lambda a: np.zeros_like(a))(f)


def _transparent(d: Path):
    v = load_ply(d / "point_cloud.ply").vertex.copy()
    v["opacity"] = -1e30
    write_ply(d / "point_cloud.ply", v)


def _scene_field(edit: Callable[[Path], None]):
    def make(s, tmp):
        d = _scene(s, tmp)
        edit(d)
        return ["fit-field", "--scene", str(d), "--features", str(s["w"] / "f.h5"),
                "--codebook", str(s["w"] / "c.h5"), "--out", str(tmp / "field.h5"),
                "--iterations", "2"]  # fmt: skip

    return make


def _res_copy(edit: Callable[[Path, dict], None]):
    def make(s, tmp):
        res = _copy(s["w"] / "res", tmp / "res")
        edit(res, s)
        argv = _query(s, tmp)
        return [str(res) if a == str(s["w"] / "res") else a for a in argv]

    return make


def _only_test_view_masks(res: Path, s) -> None:
    for f in list(res.glob("*.png")):
        f.unlink()
    for v in s["test"]:
        cv2.imwrite(str(res / f"{v}.png"), np.full((36, 48), 255, np.uint8))


def _fit_on_missing(s, tmp):
    argv = _res_copy(lambda r, s: (r / f"{s['train'][0]}.png").unlink())(s, tmp)
    return argv + ["--fit-on", s["train"][0]]


def _corrupt_res_mask(res: Path, s) -> None:
    (res / f"{s['train'][0]}.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)


def _prompt(text: str, embed: bool = True):
    def make(s, tmp):
        emb = json.loads((s["w"] / "text.json").read_text())
        if embed:
            emb[text] = emb["box"]
        (tmp / "t.json").write_text(json.dumps(emb))
        argv = _query(s, tmp, text=tmp / "t.json")
        argv[argv.index("--prompt") + 1] = text
        return argv

    return make


LONG = "x" * 300

CASES = [
    # data loss: an output that is an input, or that exists
    Case("--cache is the features file (even with --force)",
         lambda s, t: _field(s, t, "--cache", str(s["w"] / "f.h5"), "--force"),
         ("--cache", "f.h5", "inputs")),
    Case("--out is the codebook (even with --force)",
         lambda s, t: _field(s, t, "--force", out=s["w"] / "c.h5"), ("--out", "c.h5", "inputs")),
    Case("init-codebook --out is its features (even with --force)",
         lambda s, t: ["init-codebook", "--features", str(s["w"] / "f.h5"), "--out",
                       str(s["w"] / "f.h5"), "--force"], ("--out", "f.h5", "inputs")),
    Case("export-ply --out is the scene's PLY (even with --force)",
         lambda s, t: ["export-ply", "--scene", str(s["scene"]), "--selection", str(s["selection"]),
                       "--out", str(s["scene"] / "point_cloud.ply"), "--force"],
         ("--out", "point_cloud.ply", "inputs")),
    Case("select --out is the field (even with --force)",
         lambda s, t: _select(s, t, extra=("--force",))[:-3] + ["--out", str(s["w"] / "field.h5"),
                                                                 "--force"],
         ("--out", "field.h5", "inputs")),
    Case("--cache holds another file, no --force",
         _after(lambda t: (t / "mine.h5").write_bytes(b"precious"),
                lambda s, t: _field(s, t, "--cache", str(t / "mine.h5"))),
         ("--cache", "mine.h5", "--force")),
    Case("--cache is a directory",
         _after(lambda t: (t / "d").mkdir(), lambda s, t: _field(s, t, "--cache", str(t / "d"))),
         ("--cache", "directory")),
    Case("--out under a regular file",
         _after(lambda t: (t / "afile").write_text("x"),
                lambda s, t: _query(s, t, out=t / "afile" / "q")),
         ("--out", "afile", "is a file")),
    Case("render-mask where one output already exists", _one_mask_exists,
         ("overlay.png", "already exists", "--force")),
    Case("an output name too long for the file system",
         lambda s, t: ["init-codebook", "--features", str(s["w"] / "f.h5"), "--out",
                       str(t / f"{LONG}.h5")], ("longer than the file system allows",)),
    # HDF5 artifacts whose values or cross-references are broken
    Case("HDF5 signature with a garbage body (inspect)",
         _after(lambda t: (t / "g.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x07" * 3000),
                lambda s, t: ["inspect", str(t / "g.h5")]), ("g.h5",)),
    Case("a field whose decoder has more rows than the codebook has entries",
         lambda s, t: _select(s, t, field=_h5_copy(s, t, "field.h5", _bigger_decoder)),
         ("field.h5", "decoder", "codebook entries")),
    Case("a field with NaN features",
         lambda s, t: _select(s, t, field=_h5_copy(s, t, "field.h5", _replace(
             "features", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 5, np.nan, a)))),
         ("field.h5", "features", "NaN")),
    Case("a field with an infinite codebook entry",
         lambda s, t: _select(s, t, field=_h5_copy(s, t, "field.h5", _replace(
             "codebook", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 3, np.inf, a)))),
         ("field.h5", "codebook", "inf")),
    Case("a field that is inspected (decoder too big)",
         lambda s, t: ["inspect", str(_h5_copy(s, t, "field.h5", _bigger_decoder))],
         ("field.h5", "problem")),
    Case("hyperplanes fitted on another field",
         lambda s, t: _render(s, t, field=_h5_copy(s, t, "field.h5", _replace(
             "features", lambda a: a * 1.5))), ("planes.h5", "another field")),
    Case("hyperplanes with NaN scores",
         lambda s, t: _render(s, t, planes=_h5_copy(s, t, "planes.h5", lambda f: _replace(
             f"prompts/{safe_name('box')}/entry_scores", lambda a: a * np.nan)(f))),
         ("planes.h5", "entry_scores", "NaN")),
    Case("a features file with no views", _features_without_views, ("f.h5", "no views")),
    Case("a codebook with 0 entries", _codebook_of(0), ("c.h5",)),
    Case("a codebook with 1 entry", _codebook_of(1), ("c.h5", "at least 2 entries")),
    Case("a selection with values other than 0/1",
         lambda s, t: ["export-ply", "--scene", str(s["scene"]), "--selection",
                       str(_h5_copy(s, t, "sel.h5", _replace("selected", lambda a: a * 3),
                                    src=s["selection"])),
                       "--out", str(t / "o.ply")], ("sel.h5", "selected")),
    Case("a blend cache with a Gaussian id out of range", _cache_with_a_bad_id,
         ("blend_cache.h5", "outside")),
    Case("--resume with a garbage checkpoint",
         _after(lambda t: (t / "field.h5.ckpt").write_bytes(b"\x89HDF\r\n\x1a\n" + b"junk" * 99),
                lambda s, t: _field(s, t, "--resume")), ("field.h5.ckpt",)),
    # PLY headers that declare more than the file holds
    Case("a face element declaring 10^15 faces",
         _ply_text("ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
                   "element face 1000000000000000\nproperty list uchar int vertex_indices\n"
                   "end_header\n", b"\x00" * 64), ("point_cloud.ply", "face")),
    Case("an ASCII PLY declaring 200M vertices in a tiny file",
         _ply_text("ply\nformat ascii 1.0\nelement vertex 200000000\nproperty float x\n"
                   "end_header\n", b"1\n2\n"), ("point_cloud.ply", "200000000 vertices")),
    Case("a PLY whose quaternions are all zero", _ply_case(_zero_quaternions),
         ("point_cloud.ply", "zero quaternion")),
    # cameras
    Case("a camera width of 1e400", _wide_camera, ("cameras.json", "width")),
    Case("a camera width of 0", _cameras_json(lambda c: c[0].update(width=0)),
         ("cameras.json", "width")),
    Case("a camera height of 2.5", _cameras_json(lambda c: c[0].update(height=2.5)),
         ("cameras.json", "height")),
    Case("camera_angle_x of 0", _transforms(lambda d: d.update(camera_angle_x=0)),
         ("transforms.json", "camera_angle_x")),
    Case("a skewed rotation with determinant 1", _cameras_json(_skew),
         ("cameras.json", "not a rotation")),
    Case("a non-UTF-8 COLMAP text file", _scene_case(_colmap_latin1),
         ("images.txt", "UTF-8")),
    Case("split.json is a list", _scene_case(lambda d: (d / "split.json").write_text("[1, 2]")),
         ("split.json", "object")),
    Case("split.json names are not strings",
         _scene_case(lambda d: (d / "split.json").write_text('{"train": [1, {"a": 2}]}')),
         ("split.json", "'train'")),
    Case("a FIFO as --cameras", _fifo_cameras, ("cams.json", "regular file"), subprocess=True),
    # options
    Case("--seed -1", lambda s, t: _field(s, t, "--seed", "-1"), ("--seed",)),
    Case("--views ','", lambda s, t: _query(s, t, "--views", ","), ("--views",)),
    Case("--max-side 0",
         lambda s, t: _extract(s["scene"], s, t) + ["--max-side", "0"], ("--max-side",)),
    Case("--lr-features nan", lambda s, t: _field(s, t, "--lr-features", "nan"),
         ("--lr-features", "finite")),
    Case("--target-iou 2", lambda s, t: _query(s, t, "--target-iou", "2"), ("--target-iou",)),
    Case("--iterations -5", lambda s, t: _field(s, t, "--iterations", "-5"), ("--iterations",)),
    Case("--w-joint -1", lambda s, t: _field(s, t, "--w-joint", "-1"), ("--w-joint",)),
    Case("--fit-views 0", lambda s, t: _query(s, t, "--fit-views", "0"), ("--fit-views",)),
    Case("query --export highlight with a bad --color",
         lambda s, t: _query(s, t, "--export", "highlight", "--color", "notacolour"),
         ("--color", "notacolour")),
    Case("--translate 1e39,0,0",
         lambda s, t: ["export-ply", "--scene", str(s["scene"]), "--selection", str(s["selection"]),
                       "--out", str(t / "o.ply"), "--translate", "1e39,0,0"],
         ("--translate", "beyond")),
    # prompts and their embeddings
    Case("a prompt with a lone surrogate",
         lambda s, t: _query(s, t)[:6] + ["box\udcff"] + _query(s, t)[7:],
         ("--prompt", "Unicode")),
    Case("--text-embeddings is a device file",
         lambda s, t: _query(s, t, text=Path("/dev/zero")), ("/dev/zero", "regular file")),
    Case("text embeddings with NaN", _text('{"box": [NaN, 1.0]}'), ("t.json", "NaN")),
    Case("text embeddings with a key twice", _text('{"box": [1.0], "box": [2.0]}'),
         ("t.json", "twice")),
    Case("text embeddings of another dimension than the field",
         _text(json.dumps({"box": [1.0, 0.5, 0.25]})), ("t.json", "3 dimensions")),
    # feature files
    Case("a 0-byte .npy", _npy_dir(lambda f: f.write_bytes(b"")), (".npy",)),
    Case("an object-dtype .npy",
         _npy_dir(lambda f: np.save(f, np.array([{"a": 1}], dtype=object), allow_pickle=True)),
         (".npy", "not a plain numeric")),
    Case("a feature map with a zero-sized axis",
         _npy_dir(lambda f: np.save(f, np.zeros((16, 0, 12), np.float16))), (".npy", "non-zero")),
    # a benchmark room whose parts disagree, refused before any field is fitted
    Case("eval: features of another dimension than the text embeddings",
         lambda s, t: _eval_room(s, t, text={"box": [1.0, 0.5, 0.25]}),
         ("features", "16 dimensions", "text embeddings")),
    Case("eval: a ground-truth mask missing", _eval_room_missing, ("ground-truth mask",)),
    # third sweep: an output path that is, or holds, one of the inputs
    Case("fit-field: <out>.ckpt is the --codebook", _ckpt_is_codebook,
         ("field.h5.ckpt", "inputs")),
    Case("export-ply --out is --selection (even with --force)",
         lambda s, t: _export(s, t, _copy(s["selection"], t / "sel.h5"), "--force",
                              selection=t / "sel.h5"), ("--out", "sel.h5", "inputs")),
    Case("export-ply --semantics --field F --out F (even with --force)",
         lambda s, t: _export(s, t, _copy(s["w"] / "field.h5", t / "f.h5"), "--semantics",
                              "--field", str(t / "f.h5"), "--force"), ("--out", "f.h5", "inputs")),
    Case("query --out D where --field is D/<prompt>/selection.h5", _query_field_inside_out,
         ("--out", "selection.h5", "inputs")),
    Case("query --out D where --res-masks is D/<prompt>/masks", _query_res_inside_out,
         ("--out", "masks", "inputs")),
    Case("query --out D where --ply is D/<prompt>/<prompt>.ply", _query_ply_inside_out,
         ("--out", ".ply", "inputs")),
    Case("query: out/<prompt>/selection.h5 is a directory (before fitting)",
         _in_query_out(lambda d: (d / "selection.h5").mkdir(parents=True)),
         ("--out", "selection.h5", "directory")),
    Case("query: out/<prompt>/masks is a file (before fitting)",
         _in_query_out(lambda d: (d.mkdir(parents=True), (d / "masks").write_text("x"))),
         ("--out", "masks", "is a file")),
    Case("eval --html is the room's text_embeddings.json (even with --force)",
         _eval_with(lambda r: None, "--html", "{tmp}/room/text_embeddings.json", "--force"),
         ("--html", "text_embeddings.json", "inputs")),
    Case("eval --out and --html the same file",
         _eval_with(lambda r: None, "--html", "{tmp}/r.json"), ("--html", "--out")),
    Case("eval --work holding the user's own features.h5 and codebook.h5", _work_holds_user_files,
         ("--work", "features.h5", "did not write")),
    Case("eval --work is the room (holding a features.h5)", _work_is_the_room,
         ("--work", "features.h5")),
    Case("extract: <out>.partial is a FIFO", _partial("fifo"), ("o.h5.partial", "regular file")),
    Case("extract: <out>.partial is a directory", _partial("dir"),
         ("o.h5.partial", "regular file")),
    # third sweep: internal errors
    Case("render-mask --camera-file with a 16384x16384 camera", _huge_camera,
         ("novel.json", "megapixels")),
    Case("prompts.json targets 1e400",
         _eval_with(lambda r: (r / "prompts.json").write_text(
             (r / "prompts.json").read_text().replace('"targets": [1]', '"targets": [1e400]'))),
         ("prompts.json", "targets")),
    Case("hyperplanes whose W has another dimension than the field",
         lambda s, t: _select(s, t, planes=_h5_copy(s, t, "planes.h5", _planes_of_dim(5)),
                              extra=("--mode", "threshold")), ("planes.h5", "dimensions")),
    Case("extract --out of 255 bytes (its .partial is longer)",
         lambda s, t: _extract(s["scene"], s, t)[:-1] + [str(t / ("n" * 252 + ".h5"))],
         ("--out", ".partial", "longer than the file system allows")),
    Case("render-mask --out directory name of 300 bytes",
         lambda s, t: _render(s, t)[:-1] + [str(t / LONG)],
         ("--out", "longer than the file system allows")),
    Case("a list property for x in the PLY",
         _ply_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty list uchar float x\n"
                   "property float y\nend_header\n", b"1 0.5 1\n2 0.5 0.25 1\n"),
         ("point_cloud.ply", "'x'", "list")),
    # third sweep: values silently accepted, or refused late
    Case("a codebook whose entries are all zero",
         lambda s, t: _field(s, t, codebook=_h5_copy(s, t, "c.h5", _zero_codebook)),
         ("c.h5", "entries", "all zeros")),
    Case("a field with an all-zero codebook entry (inspect)",
         lambda s, t: ["inspect", str(_h5_copy(s, t, "field.h5", _replace(
             "codebook", lambda a: np.where(np.arange(len(a))[:, None] == 0, 0, a))))],
         ("field.h5", "problem")),
    Case("fit-field on a PLY whose Gaussians are all transparent", _scene_field(_transparent),
         ("point_cloud.ply", "transparent")),
    Case("export-ply --highlight 1e300,1e300,1e300",
         lambda s, t: _export(s, t, t / "o.ply", "--highlight", "1e300,1e300,1e300"),
         ("--highlight", "0..255")),
    Case("prompts.json test_views a string",
         _eval_with(_prompts(lambda p: p[0].update(test_views="v001"))),
         ("prompts.json", "test_views")),
    Case("prompts.json with a prompt id twice",
         _eval_with(_prompts(lambda p: p.append(dict(p[0])))), ("prompts.json", "'p1'", "twice")),
    Case("prompts.json test_views naming an unknown view",
         _eval_with(_prompts(lambda p: p[0]["test_views"].append("v999"))),
         ("prompts.json", "v999")),
    Case("prompts.json id '../../escape'",
         _eval_with(_prompts(lambda p: p[0].update(id="../../escape"))),
         ("prompts.json", "'id'", "plain name")),
    Case("prompts.json text with control characters",
         _eval_with(_prompts(lambda p: p[0].update(text="bo\x1bx"))),
         ("prompts.json", "control characters")),
    Case("prompts.json a prompt without text", _eval_with(_prompts(lambda p: p[0].pop("text"))),
         ("prompts.json", "'text'")),
    Case("an eval ground-truth mask of another size (before fitting)",
         _eval_with(lambda r: [cv2.imwrite(str(f), np.zeros((10, 10), np.uint8))
                               for f in sorted((r / "eval" / "masks" / "p1").glob("*.png"))[:1]]),
         ("eval", "10x10", "48x36")),
    Case("an eval ground-truth mask that is not an image (before fitting)",
         _eval_with(lambda r: [f.write_bytes(b"junk")
                               for f in sorted((r / "eval" / "masks" / "p1").glob("*.png"))[:1]]),
         ("eval", "cannot read mask image")),
    Case("a room without split.json (no test views)",
         _eval_with(lambda r: (r / "split.json").unlink()), ("room", "no test views")),
    Case("eval --features is a regular file",
         lambda s, t: [a if a != str(s["features"]) else str(s["w"] / "text.json")
                       for a in _eval_room(s, t)], ("--features", "not a directory")),
    Case("eval --entries more than the feature cells (before writing anything)",
         _eval_with(lambda r: None, "--entries", "100000"), ("--entries", "100000")),
    Case("eval --work name of 300 bytes", _eval_with(lambda r: None, "--work", "{tmp}/" + LONG),
         ("--work", "longer than the file system allows")),
    Case("fit-field --out of 255 bytes with checkpoints (<out>.ckpt is longer)",
         lambda s, t: _field(s, t, "--checkpoint-every", "1", out=t / ("n" * 252 + ".h5")),
         ("--out", ".ckpt", "longer than the file system allows")),
    Case("fit-field --cache in a missing directory",
         lambda s, t: _field(s, t, "--cache", str(t / "no" / "bc.h5")),
         ("--cache", "does not exist")),
    Case("init-codebook --samples 3 --entries 8",
         lambda s, t: ["init-codebook", "--features", str(s["w"] / "f.h5"), "--entries", "8",
                       "--samples", "3", "--out", str(t / "c.h5")], ("--entries", "--samples")),
    Case("a PLY header with non-ASCII bytes in a property name",
         _ply_case(lambda d: (d / "point_cloud.ply").write_bytes((d / "point_cloud.ply")
                   .read_bytes().replace(b"float opacity", b"float opac\xc3\xa9ity", 1))),
         ("point_cloud.ply", "not ASCII", "opac")),
    Case("split.json is a FIFO (never silently skipped)",
         _scene_case(lambda d: ((d / "split.json").unlink(), os.mkfifo(d / "split.json"))),
         ("split.json", "regular file")),
    Case("a camera img_name with NUL", _cameras_json(lambda c: c[1].update(img_name="v\x00001")),
         ("cameras.json", "img_name")),
    Case("a camera img_name '../../etc/passwd' (split.json then names a view without camera)",
         _cameras_json(lambda c: c[1].update(img_name="../../etc/passwd")),
         ("split.json", "without a camera in cameras.json")),
    Case("a camera position of 2 numbers", _cameras_json(lambda c: c[1].update(position=[0, 0])),
         ("cameras.json", "'position'")),
    Case("a prompt with DEL and C1 control characters (in the embeddings)",
         _prompt("bo\x7fx\x85"), ("--prompt", "control characters")),
    Case("a prompt of only a zero-width space", _prompt("\u200b"), ("--prompt", "visible")),
    Case("--prompt-id '../..'", lambda s, t: _query(s, t, "--prompt-id", "../.."),
         ("--prompt-id", "plain name")),
    Case("RES masks only for the test views", _res_copy(_only_test_view_masks),
         ("--res-masks", "training view")),
    Case("--fit-on a view whose RES mask is missing", _fit_on_missing, ("--fit-on", "RES mask")),
    Case("a damaged RES mask gives one line (OpenCV's own log silenced)",
         _res_copy(_corrupt_res_mask), ("cannot read mask image",), subprocess=True),
]  # fmt: skip


def _run(case: Case, argv: list[str], capsys) -> tuple[int, str]:
    if not case.subprocess:
        capsys.readouterr()
        code = main(argv)
        return code, capsys.readouterr().err
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-m", "goi_cli", *argv], capture_output=True,
                          text=True, timeout=60, cwd=root)  # fmt: skip
    return done.returncode, done.stderr


def assert_refused(code: int, err: str, words: tuple[str, ...]) -> None:
    """Exit 2 and one `goi: error:` line holding every one of `words`, no traceback."""
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("goi: error: "), err
    assert "Traceback" not in err and "internal error" not in err
    for w in words:
        assert w in err, (w, err)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hostile_input(case, world, tmp_path, capsys):
    argv = case.make(world, tmp_path)
    before, world_before = _digest(tmp_path), _digest(world["w"])
    code, err = _run(case, argv, capsys)
    assert_refused(code, err, case.words)
    assert _digest(tmp_path) == before, "the output location or an input changed"
    assert _digest(world["w"]) == world_before, "an input of the shared world changed"


def test_enough_cases():
    assert len(CASES) >= 100


def test_float16_overflow_is_stored_finite(world, tmp_path):
    """Feature values beyond float16's range are scaled per cell, not stored as inf."""
    from stages.semantics.features import load_features

    d = tmp_path / "feats"
    shutil.copytree(world["features"], d)
    f = sorted(d.glob("*.npy"))[0]
    a = np.load(f).astype(np.float32)
    a[:, 0, 0] *= 1e6  # one cell far beyond 65504
    np.save(f, a)
    out = tmp_path / "f.h5"
    assert main(["extract", "--scene", str(world["scene"]), "--from", str(d), "--out",
                 str(out)]) == 0  # fmt: skip
    with h5py.File(out) as h:
        assert np.isfinite(h["views"][f.stem]["features"][()].astype(np.float32)).all()
    cell = load_features(out).maps[f.stem][0, 0]
    want = a[:, 0, 0] / np.linalg.norm(a[:, 0, 0])
    assert float(cell @ want) > 0.999
