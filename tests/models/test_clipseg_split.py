"""CLIPSeg split into its vision activations, text and conditional-decoder graphs (the default
export): equal to the whole model in torch, to the whole-graph bundle, and behind the RES split."""

import json

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.models.bundle import load_bundle

transformers = pytest.importorskip("transformers")


@pytest.fixture(scope="module")
def split_bundle(res_checkpoints, tmp_path_factory):
    out = tmp_path_factory.mktemp("cs") / "clipseg-split"
    assert main(["export-model", str(res_checkpoints["clipseg"]), "--out", str(out)]) == 0
    return out


def test_split_graphs_equal_the_whole_model(res_checkpoints):
    from stages.models.export.clipseg import res_module
    from stages.models.export.clipseg_split import modules

    model = transformers.CLIPSegForImageSegmentation.from_pretrained(
        str(res_checkpoints["clipseg"]), attn_implementation="eager", use_safetensors=True
    ).eval()
    image, text, decoder = modules(model)
    x = torch.randn(1, 3, 64, 64, generator=torch.Generator().manual_seed(3))
    for ids in ([98, 5, 6, 7, 99], [98, 10, 99]):
        t = torch.tensor([ids])
        with torch.no_grad():
            want = res_module(model)(x, t, torch.ones_like(t))
            got = decoder(image(x), text(t, torch.ones_like(t)))
        assert torch.abs(got - want).max() <= 1e-6


def test_split_bundle_equals_the_whole_bundle_and_its_ground(split_bundle, res_bundles):
    split, whole = load_bundle(split_bundle), load_bundle(res_bundles["clipseg"])
    m = json.loads((split_bundle / "manifest.json").read_text())
    assert "res" not in m and set(m["export_checks"]) == {
        "clipseg_image.onnx", "clipseg_text.onnx", "clipseg_decoder.onnx"
    }  # fmt: skip
    assert split.res_kind == "clipseg" and split.res_indexable
    spec = split.res_image_side_spec()
    assert spec == {"clipseg_activations": ((3, 1, 17, 32), "float16")}
    rng = np.random.default_rng(4)
    for shape in ((90, 120, 3), (64, 50, 3)):
        rgb = rng.integers(0, 256, shape, dtype=np.uint8)
        side = split.res_image_side(rgb)
        assert {k: (v.shape, v.dtype.name) for k, v in side.items()} == spec
        exact = {"clipseg_activations": split._clipseg.activations(rgb)}
        for text in ("the red sofa", "a lamp"):
            want = split.ground(rgb, text)
            assert 0 < want.mask.mean() < 1
            assert (want.mask != whole.ground(rgb, text).mask).mean() < 1e-3  # float error only
            prompt = split.res_prompt(text)
            got = split.res_from_image_side(exact, shape[:2], prompt)  # no rgb needed
            assert np.array_equal(got.mask, want.mask)
            half = split.res_from_image_side(side, shape[:2], prompt)
            assert (half.mask != want.mask).mean() < 2e-3
