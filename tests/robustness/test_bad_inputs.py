"""Bad inputs across every stage: each gives one line on stderr naming the file, field or option
and the problem, exit code 2, no traceback, and no output file (nor temporary file) left behind.
docs/reliability.md counts them."""

import json
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from goi_cli.main import main
from stages.query.prompts import safe_name
from stages.render.rasterizer import Rasterizer
from stages.scene.formats.colmap import write_colmap
from stages.scene.gaussians import load_ply
from tests.helpers import front_camera, random_vertex, semantic_scene, write_ply


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A small scene taken through every stage once, so each case can break one input."""
    root = tmp_path_factory.mktemp("world")
    s = semantic_scene(root, n=3000, n_views=6, size=(48, 36), dim=16)
    w = root / "w"
    w.mkdir()
    sc = ["--scene", str(s["scene"])]
    assert main(["extract", *sc, "--from", str(s["features"]), "--out", str(w / "f.h5")]) == 0
    assert main(["init-codebook", "--features", str(w / "f.h5"), "--entries", "8",
                 "--out", str(w / "c.h5")]) == 0  # fmt: skip
    assert main(["fit-field", *sc, "--features", str(w / "f.h5"), "--codebook", str(w / "c.h5"),
                 "--out", str(w / "field.h5"), "--iterations", "20", "--cells-per-view", "64",
                 "--checkpoint-every", "0"]) == 0  # fmt: skip
    (w / "text.json").write_text(json.dumps({"box": s["objects"][1].tolist()}))
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    (w / "res").mkdir()
    for name in s["train"]:
        share = rast.render_features(s["cameras"][name], s["onehot"]).image
        cv2.imwrite(str(w / "res" / f"{name}.png"), (share.argmax(2) == 1).astype(np.uint8) * 255)
    q = ["query", *sc, "--field", str(w / "field.h5"), "--prompt", "box",
         "--text-embeddings", str(w / "text.json"), "--res-masks", str(w / "res"),
         "--out", str(w / "q")]  # fmt: skip
    assert main(q) == 0
    s["w"] = w
    s["query"] = q
    s["selection"] = w / "q" / safe_name("box") / "selection.h5"
    return s


@dataclass
class Case:
    name: str
    make: Callable  # (world, tmp) -> argv; may write broken files into tmp
    words: tuple[str, ...]


def _copy_scene(s, tmp: Path) -> Path:
    d = tmp / "scene"
    shutil.copytree(s["scene"], d)
    return d


def _ply_case(mutate):
    def make(s, tmp):
        d = _copy_scene(s, tmp)
        mutate(d / "point_cloud.ply")
        return ["export-ply", "--scene", str(d), "--selection", str(s["selection"]),
                "--out", str(tmp / "out.ply")]  # fmt: skip

    return make


def _truncate(p: Path):
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 1000])


def _set_field(name, value):
    def mutate(p: Path):
        v = load_ply(p).vertex.copy()
        v[name][7] = value
        write_ply(p, v)

    return mutate


def _drop_fields(*names):
    def mutate(p: Path):
        v = load_ply(p).vertex
        keep = [n for n in v.dtype.names if n not in names]
        write_ply(p, v[keep])

    return mutate


def _header_vertices(n):
    def mutate(p: Path):
        data = p.read_bytes()
        head, _, body = data.partition(b"end_header\n")
        import re

        head = re.sub(rb"element vertex \d+", b"element vertex %d" % n, head)
        p.write_bytes(head + b"end_header\n" + body)

    return mutate


def _field_args(s, tmp, features=None, codebook=None, extra=()):
    return ["fit-field", "--scene", str(s["scene"]),
            "--features", str(features or s["w"] / "f.h5"),
            "--codebook", str(codebook or s["w"] / "c.h5"), "--out", str(tmp / "out.h5"),
            "--iterations", "2", *extra]  # fmt: skip


def _features_dir(s, tmp, change):
    d = tmp / "feats"
    shutil.copytree(s["features"], d)
    change(d)
    return ["extract", "--scene", str(s["scene"]), "--from", str(d), "--out", str(tmp / "out.h5")]


def _npy(mutate):
    def change(d: Path):
        f = sorted(d.glob("*.npy"))[1]
        np.save(f, mutate(np.load(f)))

    return lambda s, tmp: _features_dir(s, tmp, change)


def _h5(mutate, schema_arg="--features"):
    def make(s, tmp):
        p = tmp / "bad.h5"
        shutil.copy(s["w"] / "f.h5", p)
        mutate(p)
        return ["init-codebook", schema_arg, str(p), "--out", str(tmp / "out.h5")]

    return make


def _set_attr(name, value):
    def mutate(p):
        with h5py.File(p, "r+") as f:
            f.attrs[name] = value

    return mutate


def _cams(write):
    def make(s, tmp):
        d = _copy_scene(s, tmp)
        (d / "cameras.json").unlink()
        write(d, s)
        return ["extract", "--scene", str(d), "--from", str(s["features"]),
                "--out", str(tmp / "out.h5")]  # fmt: skip

    return make


def _colmap_distorted(d, s):
    write_colmap(d / "sparse" / "0", list(s["cameras"].values()), binary=False, model="OPENCV")


def _transforms_no_intrinsics(d, s):
    (d / "transforms.json").write_text(json.dumps({"frames": [
        {"file_path": "v000", "transform_matrix": np.eye(4).tolist()}]}))  # fmt: skip


def _cameras_missing_field(d, s):
    (d / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "v000", "width": 48}]))


def _query(s, tmp, *replace, drop=()):
    argv = list(s["query"])
    argv[argv.index("--out") + 1] = str(tmp / "q")
    for opt, value in zip(replace[::2], replace[1::2], strict=True):
        argv[argv.index(opt) + 1] = value
    for opt in drop:
        i = argv.index(opt)
        del argv[i : i + 2]
    return argv


def _res(mutate):
    def make(s, tmp):
        d = tmp / "res"
        shutil.copytree(s["w"] / "res", d)
        mutate(d)
        return _query(s, tmp, "--res-masks", str(d))

    return make


def _bundle(change):
    def make(s, tmp):
        from tests.models.test_bundle import make_bundle

        root, _, _, manifest = make_bundle(tmp / "bundle")
        change(root, manifest)
        d = _copy_scene(s, tmp)
        (d / "images").mkdir()
        for c in s["cameras"].values():
            cv2.imwrite(str(d / "images" / f"{c.name}.png"), np.full((36, 48, 3), 90, np.uint8))
        return ["extract", "--scene", str(d), "--bundle", str(root), "--out", str(tmp / "out.h5")]

    return make


def _manifest(edit):
    def change(root, manifest):
        m = json.loads(json.dumps(manifest))
        edit(m)
        (root / "manifest.json").write_text(json.dumps(m))

    return _bundle(change)


def _onnx(model, args, inputs, outputs):
    def change(root, manifest):
        from tests.models.test_bundle import _export

        _export(model, args, root / "image_encoder.onnx", inputs, outputs, None)

    return _bundle(change)


def _images(mutate):
    def change(root, manifest):
        pass

    def make(s, tmp):
        argv = _bundle(change)(s, tmp)
        mutate(tmp / "scene" / "images")
        return argv

    return make


class _Rank2(__import__("torch").nn.Module):
    def forward(self, image):
        return image.sum(1)


def _selection_other_ply(s, tmp):
    d = _copy_scene(s, tmp)
    v = load_ply(d / "point_cloud.ply").vertex.copy()
    v["x"] += 0.001
    write_ply(d / "point_cloud.ply", v)
    return ["export-ply", "--scene", str(d), "--selection", str(s["selection"]),
            "--out", str(tmp / "out.ply")]  # fmt: skip


def _export(*extra):
    def make(s, tmp):
        return ["export-ply", "--scene", str(s["scene"]), "--selection", str(s["selection"]),
                "--out", str(tmp / "out.ply"), *extra]  # fmt: skip

    return make


def _codebook_other_dim(s, tmp):
    p = tmp / "c.h5"
    with h5py.File(s["w"] / "c.h5") as src, h5py.File(p, "w") as f:
        for k, v in src.attrs.items():
            f.attrs[k] = v
        f.attrs["dim"] = 5
        for k in src:
            data = src[k][()]
            f.create_dataset(k, data=data[:, :5] if data.ndim == 2 else data)
    return _field_args(s, tmp, codebook=p)


def _resume_other_scene(s, tmp):
    """A checkpoint left by an interrupted run on another scene, then --resume here."""
    other = semantic_scene(tmp / "other", n=2000, n_views=6, size=(48, 36), dim=16, seed=3)
    w = tmp
    sc = ["--scene", str(other["scene"])]
    assert main(["extract", *sc, "--from", str(other["features"]), "--out", str(w / "f2.h5")]) == 0
    import stages.semantics.fit_field as fm

    real, calls = fm.save_checkpoint, {"n": 0}

    def stop(*a, **k):
        calls["n"] += 1
        real(*a, **k)
        raise KeyboardInterrupt

    fm.save_checkpoint = stop
    try:
        main(["fit-field", *sc, "--features", str(w / "f2.h5"), "--codebook", str(s["w"] / "c.h5"),
              "--out", str(tmp / "out.h5"), "--iterations", "4", "--checkpoint-every", "2",
              "--cells-per-view", "16"])  # fmt: skip
    finally:
        fm.save_checkpoint = real
    assert (tmp / "out.h5.ckpt").exists() and calls["n"] == 1
    return _field_args(s, tmp, extra=("--resume", "--iterations", "4", "--checkpoint-every",
                                      "2", "--cells-per-view", "16"))  # fmt: skip


CASES = [
    Case("truncated PLY", _ply_case(_truncate), ("point_cloud.ply", "truncated")),
    Case("PLY with NaN", _ply_case(_set_field("x", np.nan)), ("point_cloud.ply", "NaN")),
    Case("PLY with inf", _ply_case(_set_field("scale_0", np.inf)), ("point_cloud.ply", "inf")),
    Case("PLY without f_dc", _ply_case(_drop_fields("f_dc_0", "f_dc_1", "f_dc_2")), ("f_dc_0",)),
    Case(
        "PLY without scales", _ply_case(_drop_fields("scale_0", "scale_1", "scale_2")), ("scale_0",)
    ),  # fmt: skip
    Case("PLY with zero Gaussians", _ply_case(_header_vertices(0)), ("point_cloud.ply",)),
    Case(
        "PLY declaring 10^12 vertices",
        _ply_case(_header_vertices(10**12)),
        ("point_cloud.ply", "vertices"),
    ),  # fmt: skip
    Case(
        "not a PLY", _ply_case(lambda p: p.write_bytes(b"\x00garbage" * 50)), ("point_cloud.ply",)
    ),  # fmt: skip
    Case("COLMAP with a distorted camera model", _cams(_colmap_distorted), ("OPENCV", "undistort")),
    Case(
        "transforms.json without intrinsics", _cams(_transforms_no_intrinsics), ("transforms.json",)
    ),  # fmt: skip
    Case("cameras.json missing fields", _cams(_cameras_missing_field), ("cameras.json",)),
    Case(
        "cameras referencing missing images",
        _images(lambda d: next(d.glob("v002.png")).unlink()),
        ("v002",),
    ),  # fmt: skip
    Case(
        "image of another size than its camera",
        _images(lambda d: cv2.imwrite(str(d / "v002.png"), np.zeros((20, 48, 3), np.uint8))),
        ("v002.png", "48x20", "48x36"),
    ),  # fmt: skip
    Case(
        "image of 100k x 100k pixels",
        _images(
            lambda d: (d / "v002.png").write_bytes(
                b"\x89PNG\r\n\x1a\n"
                + struct.pack(">I", 13)
                + b"IHDR"
                + struct.pack(">II", 100_000, 100_000)
                + b"\x08\x02\x00\x00\x00"
            )
        ),
        ("v002.png", "100000x100000", "megapixels"),
    ),  # fmt: skip
    Case("features of the wrong dimension", _npy(lambda a: a[:8]), ("dimension",)),
    Case(
        "features for other view names",
        lambda s, tmp: _features_dir(
            s, tmp, lambda d: [f.rename(d / f"x{f.name}") for f in d.glob("*.npy")]
        ),
        ("--from", "belong to this scene"),
    ),  # fmt: skip
    Case("features with NaN", _npy(lambda a: np.where(a == a.max(), np.nan, a)), ("NaN",)),
    Case("features of the wrong rank", _npy(lambda a: a[0]), ("shape",)),
    Case(
        "HDF5 artifact truncated",
        _h5(lambda p: p.write_bytes(p.read_bytes()[:2000])),
        ("bad.h5", "HDF5"),
    ),  # fmt: skip
    Case(
        "HDF5 artifact of another schema",
        lambda s, tmp: [
            "init-codebook",
            "--features",
            str(s["w"] / "c.h5"),
            "--out",
            str(tmp / "out.h5"),
        ],
        ("c.h5", "goi.codebook", "goi.features"),
    ),  # fmt: skip
    Case(
        "HDF5 artifact of a newer major version",
        _h5(_set_attr("schema_version", "9.0")),
        ("bad.h5", "9.0", "upgrade goi"),
    ),  # fmt: skip
    Case("not an HDF5 file", _h5(lambda p: p.write_text("hello")), ("bad.h5",)),
    Case(
        "codebook of another dimension than the features", _codebook_other_dim, ("dimension",)
    ),  # fmt: skip
    Case(
        "ONNX model with the wrong input rank",
        _onnx(_Rank2(), (__import__("torch").randn(1, 3, 8, 8),), ["image"], ["features"]),
        ("image_encoder.onnx", "rank"),
    ),  # fmt: skip
    Case(
        "ONNX model with another output name",
        _onnx(
            __import__("torch").nn.Conv2d(3, 12, 4, stride=4),
            (__import__("torch").randn(1, 3, 8, 8),),
            ["image"],
            ["feats"],
        ),
        ("image_encoder.onnx", "no output named 'features'"),
    ),  # fmt: skip
    Case(
        "manifest.json missing fields",
        _manifest(lambda m: m.pop("feature_dim")),
        ("manifest.json", "feature_dim"),
    ),  # fmt: skip
    Case(
        "manifest path outside the bundle",
        _manifest(lambda m: m["image_encoder"].update(file="../../etc/passwd")),
        ("outside the bundle",),
    ),  # fmt: skip
    Case(
        "RES mask directory without masks",
        _res(lambda d: [f.unlink() for f in d.glob("*")]),
        ("--res-masks", "no <view>.png"),
    ),  # fmt: skip
    Case("empty prompt", lambda s, tmp: _query(s, tmp, "--prompt", "  "), ("--prompt", "empty")),
    Case(
        "prompt of 10,000 characters",
        lambda s, tmp: _query(s, tmp, "--prompt", "a" * 10_000),
        ("--prompt", "10000 characters"),
    ),  # fmt: skip
    Case(
        "prompt missing from the embeddings file",
        lambda s, tmp: _query(s, tmp, "--prompt", "chair"),
        ("text.json", "'chair'"),
    ),
    Case(
        "no text source",
        lambda s, tmp: _query(s, tmp, drop=("--text-embeddings",)),
        ("--text-embeddings",),
    ),  # fmt: skip
    Case(
        "output directory missing",
        lambda s, tmp: (
            _field_args(s, tmp)[:-3] + [str(tmp / "no" / "out.h5")] + ["--iterations", "2"]
        ),
        ("does not exist",),
    ),  # fmt: skip
    Case(
        "output exists without --force",
        lambda s, tmp: [
            "init-codebook",
            "--features",
            str(s["w"] / "f.h5"),
            "--out",
            str(s["w"] / "c.h5"),
        ],
        ("already exists", "--force"),
    ),
    Case("selection made for another PLY", _selection_other_ply, ("--selection", "another PLY")),
    Case("two edits at once", _export("--invert", "--highlight", "red"), ("at most one",)),
    Case("not a colour", _export("--highlight", "blurple"), ("--highlight", "blurple")),
    Case("not a translation", _export("--translate", "1,2"), ("--translate",)),
    Case("unknown view", lambda s, tmp: _query(s, tmp) + ["--views", "v999"], ("--views", "v999")),
    Case("unknown loss", lambda s, tmp: _query(s, tmp) + ["--loss", "l2"], ("--loss",)),
    Case(
        "--resume with a checkpoint from another scene",
        _resume_other_scene,
        ("out.h5.ckpt", "other"),
    ),  # fmt: skip
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input(case, world, tmp_path, capsys):
    argv = case.make(world, tmp_path)
    capsys.readouterr()
    before = {p for p in tmp_path.rglob("*")}
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("goi: error: "), err
    assert "Traceback" not in err
    for w in case.words:
        assert w in err, (w, err)
    new = {p for p in tmp_path.rglob("*")} - before
    leftovers = [p for p in new if p.is_file()]
    assert not leftovers, leftovers


def test_big_endian_ply_is_accepted(tmp_path):
    import plyfile

    v = random_vertex(50)
    el = plyfile.PlyElement.describe(v.astype(v.dtype.newbyteorder(">")), "vertex")
    plyfile.PlyData([el], text=False, byte_order=">").write(str(tmp_path / "be.ply"))
    be = load_ply(tmp_path / "be.ply")
    np.testing.assert_array_equal(be.vertex["x"], v["x"])
    # and it renders exactly as the same Gaussians written little-endian
    le = load_ply(write_ply(tmp_path / "le.ply", v))
    cam = front_camera()
    a = Rasterizer.from_gaussians(be).render_rgb(cam).image
    b = Rasterizer.from_gaussians(le).render_rgb(cam).image
    assert a.any() and np.array_equal(a, b)


def test_res_mask_of_another_size_is_resized_with_a_warning(world, tmp_path, capsys):
    d = tmp_path / "res"
    shutil.copytree(world["w"] / "res", d)
    for f in d.glob("*.png"):
        m = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(f), cv2.resize(m, (96, 72), interpolation=cv2.INTER_NEAREST))
    assert main(_query(world, tmp_path, "--res-masks", str(d))) == 0
    assert "resized" in capsys.readouterr().err


def test_disk_full_leaves_nothing_half_written(world, tmp_path, capsys, monkeypatch):
    import errno
    import os

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    out = tmp_path / "c.h5"
    code = main(["init-codebook", "--features", str(world["w"] / "f.h5"), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "c.h5" in err and "No space left" in err
    assert list(tmp_path.iterdir()) == []


def test_unwritable_output_directory(world, tmp_path, capsys, monkeypatch):
    import os

    real = os.access
    monkeypatch.setattr(os, "access", lambda p, m: False if Path(p) == tmp_path else real(p, m))
    code = main(["init-codebook", "--features", str(world["w"] / "f.h5"),
                 "--out", str(tmp_path / "c.h5")])  # fmt: skip
    assert code == 2 and "not writable" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
