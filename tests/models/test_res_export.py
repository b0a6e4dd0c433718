"""goi export-model on randomly initialised small Grounding DINO, SAM and CLIPSeg checkpoints:
each ONNX graph equals the torch model loaded from the same checkpoint (<= 1e-4)."""

import json

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.models import res_processing as rp
from stages.models.bundle import load_bundle
from stages.models.onnx_io import session
from tests.conftest import GROUNDED

transformers = pytest.importorskip("transformers")
H, W = GROUNDED["canvas"]


def _load(cls, path):
    m = cls.from_pretrained(str(path), attn_implementation="eager", use_safetensors=True).eval()
    m.requires_grad_(False)
    return m


def _diff(got, want):
    g, w = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert g.shape == w.shape
    same_inf = np.isinf(g) & np.isinf(w) & (np.sign(g) == np.sign(w))
    return float(np.where(same_inf, 0, np.abs(g - w)).max())


def test_text_masks_equal_transformers():
    from transformers.models.grounding_dino import modeling_grounding_dino as mg

    from stages.models.export.grounding_dino import text_masks

    special = torch.tensor(mg.SPECIAL_TOKENS)
    vocab = torch.tensor([101, 102, 1012, 1029, 5, 6, 7, 8])
    for seed in range(60):
        g = torch.Generator().manual_seed(seed)
        n = int(torch.randint(1, 30, (1,), generator=g))
        ids = vocab[torch.randint(0, 8, (3, n), generator=g)]
        a0, p0 = mg.generate_masks_with_special_tokens_and_transfer_map(ids, special)
        a1, p1 = text_masks(ids, special)
        assert torch.equal(a0, a1) and torch.equal(p0, p1)


@pytest.mark.parametrize(
    "ids,valid",
    [
        ([101, 200, 202, 205, 1012, 102], None),
        ([101, 200, 202, 205, 1012, 201, 203, 206, 1012, 102], (80, 100)),  # padded canvas
        ([101, 207, 102], (96, 64)),  # another prompt length: L is dynamic
    ],
)
def test_detector_equals_torch(res_checkpoints, res_bundles, ids, valid):
    from stages.models.export.grounding_dino import detector_module

    model = _load(transformers.GroundingDinoForObjectDetection, res_checkpoints["detector"])
    sess = session(res_bundles["grounded"] / "detector.onnx")
    g = torch.Generator().manual_seed(len(ids))
    mask = torch.zeros(1, H, W, dtype=torch.int64)
    vh, vw = valid or (H, W)
    mask[:, :vh, :vw] = 1
    pixels = torch.randn(1, 3, H, W, generator=g) * mask[:, None]
    t = torch.tensor([ids])
    args = (pixels, mask, t, torch.ones_like(t), torch.zeros_like(t))
    with torch.no_grad():
        want = [x.numpy() for x in detector_module(model)(*args)]
    names = ["pixel_values", "pixel_mask", "input_ids", "attention_mask", "token_type_ids"]
    got = sess.run(None, {k: v.numpy() for k, v in zip(names, args, strict=True)})
    assert got[0].shape == (1, 30, len(ids)) and got[1].shape == (1, 30, 4)
    assert max(_diff(a, b) for a, b in zip(got, want, strict=True)) <= 1e-4


def test_detector_canvas_is_fixed(res_bundles):
    """The trace bakes the feature-map sizes in: the canvas is a static input, the prompt not."""
    shapes = {
        i.name: i.shape for i in session(res_bundles["grounded"] / "detector.onnx").get_inputs()
    }
    assert shapes["pixel_values"] == [1, 3, H, W] and shapes["pixel_mask"] == [1, H, W]
    assert isinstance(shapes["input_ids"][1], str)
    manifest = json.loads((res_bundles["grounded"] / "manifest.json").read_text())
    assert manifest["grounded"]["detector"]["size"] == [W, H]
    assert manifest["schema_version"] == "1.4"
    assert set(manifest["export_checks"]) == {
        "detector.onnx",
        "sam_encoder.onnx",
        "sam_decoder.onnx",
    }


def _sam_matches(model, enc, dec, size):
    from stages.models.export.sam import modules

    encoder, decoder = modules(model)
    x = torch.randn(1, 3, size, size, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        emb = encoder(x)
    assert _diff(enc.run(None, {"pixel_values": x.numpy()})[0], emb.numpy()) <= 1e-4
    for n in (1, 2, 3):
        boxes = rp.sam_boxes(np.asarray([[5, 8, 60, 50], [30, 2, 120, 90], [0, 0, 128, 96]][:n]),
                             (96, 128), size)  # fmt: skip
        with torch.no_grad():
            want = [t.numpy() for t in decoder(emb, torch.from_numpy(boxes))]
        got = dec.run(None, {"image_embeddings": emb.numpy(), "input_boxes": boxes})
        assert got[0].shape == (1, n, 1, size // 4, size // 4) and got[1].shape == (1, n, 1)
        assert max(_diff(a, b) for a, b in zip(got, want, strict=True)) <= 1e-4


def test_sam_encoder_and_decoder_equal_torch(res_checkpoints, res_bundles):
    model = _load(transformers.SamModel, res_checkpoints["sam"])
    root = res_bundles["grounded"]
    _sam_matches(model, session(root / "sam_encoder.onnx"), session(root / "sam_decoder.onnx"), 128)


def test_sam_at_a_smaller_input(res_checkpoints, tmp_path):
    """--sam-size resamples the position embeddings; the graphs equal the resampled model."""
    from stages.models.export.sam import export_sam, resize_input

    ck = res_checkpoints
    sam = _load(transformers.SamModel, ck["sam"])
    enc_spec, _, _ = export_sam(sam, ck["sam"], tmp_path, 64, 17)
    assert enc_spec["size"] == [64, 64]
    model = _load(transformers.SamModel, ck["sam"])
    resize_input(model, 64)
    enc, dec = session(tmp_path / "sam_encoder.onnx"), session(tmp_path / "sam_decoder.onnx")
    _sam_matches(model, enc, dec, 64)
    argv = ["export-model", str(ck["detector"]), str(ck["sam"]), "--out", str(tmp_path / "c"),
            "--sam-size", "72"]  # fmt: skip
    assert main(argv) == 2  # not a multiple of the patch size: refused before any export
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("ids", [[98, 5, 6, 7, 99], [98, 10, 99], list(range(2, 14)) + [99]])
def test_clipseg_equals_torch(res_checkpoints, res_bundles, ids):
    from stages.models.export.clipseg import res_module

    model = _load(transformers.CLIPSegForImageSegmentation, res_checkpoints["clipseg"])
    sess = session(res_bundles["clipseg"] / "res.onnx")
    x = torch.randn(1, 3, 64, 64, generator=torch.Generator().manual_seed(len(ids)))
    t = torch.tensor([ids])
    with torch.no_grad():
        want = res_module(model)(x, t, torch.ones_like(t)).numpy()
    got = sess.run(None, {"pixel_values": x.numpy(), "input_ids": t.numpy(),
                          "attention_mask": np.ones_like(t.numpy())})  # fmt: skip
    assert got[0].shape == (1, 1, 64, 64)
    assert _diff(got[0], want) <= 1e-4


def test_clipseg_bundle_equals_the_processor_and_torch(res_checkpoints, res_bundles):
    """numpy pre + ONNX + numpy post == ViTImageProcessor + torch + interpolate + threshold."""
    pytest.importorskip("PIL")
    model = _load(transformers.CLIPSegForImageSegmentation, res_checkpoints["clipseg"])
    bundle = load_bundle(res_bundles["clipseg"])
    spec = bundle.manifest["res"]
    assert "feature_dim" not in bundle.manifest and spec["size"] == [64, 64]
    rgb = np.random.default_rng(2).integers(0, 256, (90, 120, 3), dtype=np.uint8)
    proc = transformers.ViTImageProcessorPil(
        size={"height": 64, "width": 64}, resample=2, image_mean=spec["mean"], image_std=spec["std"]
    )
    x = proc(images=rgb, return_tensors="pt")["pixel_values"]
    ids, _ = bundle._res[1].encode("the red sofa")
    with torch.no_grad():
        probs = model(pixel_values=x, input_ids=torch.from_numpy(ids)).logits.reshape(64, 64)
    up = torch.nn.functional.interpolate(probs.sigmoid()[None, None], (90, 120), mode="bilinear")
    want = (up[0, 0] > spec["threshold"]).numpy()
    got = bundle.segment(rgb, "the red sofa")
    assert 0 < want.mean() < 1
    assert (got != want).mean() < 1e-3  # pixels within float error of the threshold only
