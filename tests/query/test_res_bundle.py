"""goi query / fit-hyperplane with a bundle whose RES is a (tiny, random) Grounded-SAM
pipeline: the masks the fit used are written beside the outputs; bad bundles leave nothing."""

import json
import shutil

import h5py
import numpy as np
import pytest

from goi_cli.main import main
from stages.models.bundle import load_bundle
from stages.query.prompts import safe_name
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from stages.scene.images import read_mask

PROMPT = "the red box"

pytestmark = pytest.mark.slow  # the session's fitted field and tiny RES models, ~1 min


@pytest.fixture(scope="module")
def setup(fitted, res_bundles, tmp_path_factory):
    s, run = fitted
    root = tmp_path_factory.mktemp("resq")
    (root / "text.json").write_text(json.dumps({PROMPT: s["objects"][2].tolist()}))
    return s, run, root, res_bundles["grounded"]


def _argv(s, run, root, bundle, out, *extra):
    return ["query", "--scene", str(s["scene"]), "--field", str(run / "field.h5"),
            "--prompt", PROMPT, "--text-embeddings", str(root / "text.json"),
            "--bundle", str(bundle), "--out", str(out), *extra]  # fmt: skip


def _rgb(s, view):
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    rgb = rast.render_rgb(s["cameras"][view]).image
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def test_query_with_a_grounded_bundle_writes_the_masks_it_used(setup, capsys):
    s, run, root, bundle = setup
    out = root / "q"
    assert main(_argv(s, run, root, bundle, out, "--fit-views", "2")) == 0
    printed = capsys.readouterr().out
    res = out / safe_name(PROMPT) / "res"
    assert f"RES masks:  {res}" in printed
    with h5py.File(out / "hyperplanes.h5") as f:
        g = next(iter(f["prompts"].values()))
        views = json.loads(g.attrs["views"])
        assert g.attrs["mask_source"].startswith("bundle:")
    assert len(views) == 2
    assert sorted(p.stem for p in res.glob("*.png")) == sorted(views)
    b = load_bundle(bundle)
    for view in views:
        got = read_mask(res / f"{view}.png")
        assert got.any()
        np.testing.assert_array_equal(got, b.segment(_rgb(s, view), PROMPT))
    # a cached plane runs no model and leaves the masks of the fit that made it
    before = {p.name: p.read_bytes() for p in res.iterdir()}
    assert main(_argv(s, run, root, bundle, out, "--fit-views", "2")) == 0
    assert "RES masks" not in capsys.readouterr().out
    assert {p.name: p.read_bytes() for p in res.iterdir()} == before


def test_fit_hyperplane_with_a_grounded_bundle(setup, capsys):
    s, run, root, bundle = setup
    out = root / "fh" / "planes.h5"
    out.parent.mkdir()
    argv = ["fit-hyperplane", "--scene", str(s["scene"]), "--field", str(run / "field.h5"),
            "--prompt", PROMPT, "--text-embeddings", str(root / "text.json"),
            "--bundle", str(bundle), "--out", str(out), "--fit-on", s["train"][1]]  # fmt: skip
    assert main(argv) == 0
    res = out.parent / safe_name(PROMPT) / "res"
    assert f"fitted on: {res}" in capsys.readouterr().out
    assert [p.name for p in res.iterdir()] == [f"{s['train'][1]}.png"]


def test_a_grounded_bundle_missing_a_model_leaves_nothing(setup, tmp_path, capsys):
    s, run, root, bundle = setup
    bad = tmp_path / "bundle"
    shutil.copytree(bundle, bad)
    (bad / "sam_encoder.onnx").unlink()
    capsys.readouterr()
    assert main(_argv(s, run, root, bad, tmp_path / "out")) == 2
    err = capsys.readouterr().err
    assert err.startswith("goi: error:") and err.count("\n") == 1
    assert "sam_encoder.onnx is missing" in err and "grounded.sam_encoder" in err
    assert not (tmp_path / "out").exists()
    m = json.loads((bundle / "manifest.json").read_text())
    m["grounded"]["sam_encoder"]["output"] = "embeddings"  # a tensor the file lacks
    shutil.copyfile(bundle / "sam_encoder.onnx", bad / "sam_encoder.onnx")
    (bad / "manifest.json").write_text(json.dumps(m))
    assert main(_argv(s, run, root, bad, tmp_path / "out")) == 2
    err = capsys.readouterr().err
    assert "sam_encoder.onnx: no output named 'embeddings'" in err
    assert not (tmp_path / "out").exists()


def test_a_prompt_too_long_for_the_res_tokenizer_is_cut_with_a_warning(setup, capsys):
    s, run, root, bundle = setup
    long = " ".join([PROMPT] * 12)  # 36 words; the tiny detector's tokenizer takes 32 tokens
    (root / "long.json").write_text(json.dumps({long: s["objects"][2].tolist()}))
    argv = ["query", "--scene", str(s["scene"]), "--field", str(run / "field.h5"),
            "--prompt", long, "--text-embeddings", str(root / "long.json"),
            "--bundle", str(bundle), "--out", str(root / "long"), "--fit-views", "1"]  # fmt: skip
    capsys.readouterr()
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "longer than the model's 32 tokens" in err and "it was cut to them" in err
    assert len(list((root / "long" / safe_name(long) / "res").glob("*.png"))) == 1
