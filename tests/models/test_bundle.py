import json
import warnings

import cv2
import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.models.bundle import load_bundle
from stages.scene.formats.inria import write_inria
from stages.semantics.features import load_features
from tests.helpers import front_camera, random_vertex, write_ply

DIM = 12
VOCAB = ["[UNK]", "red", "chair", "the", "green", "sofa"]
#: The test bundles' image normalisation.
NORMALISED = {"mean": [0.5, 0.5, 0.5], "std": [0.25, 0.25, 0.25], "channel_order": "RGB"}


class Dense(torch.nn.Module):
    """A tiny dense encoder of the contract's shape: [1, 3, H, W] -> [1, D, H/4, W/4]."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, DIM, 4, stride=4)

    def forward(self, image):
        return self.conv(image)


class Text(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.emb = torch.nn.Embedding(len(VOCAB), 8)
        self.proj = torch.nn.Linear(8, DIM)

    def forward(self, input_ids):
        return self.proj(self.emb(input_ids).mean(1))


def _export(model, args, path, inputs, outputs, axes):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            args,
            str(path),
            input_names=inputs,
            output_names=outputs,
            dynamic_axes=axes,
            dynamo=False,
        )


def make_bundle(root, image_output="features"):
    from tokenizers import Tokenizer, models, pre_tokenizers

    root.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    dense, text = Dense().eval(), Text().eval()
    _export(
        dense,
        (torch.randn(1, 3, 32, 32),),
        root / "image_encoder.onnx",
        ["image"],
        [image_output],
        {"image": {2: "h", 3: "w"}},
    )
    _export(
        text,
        (torch.zeros(1, 3, dtype=torch.int64),),
        root / "text_encoder.onnx",
        ["input_ids"],
        ["text_embeds"],
        {"input_ids": {1: "n"}},
    )
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(VOCAB)}, unk_token="[UNK]"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.save(str(root / "tokenizer.json"))
    manifest = {
        "schema": "goi.bundle",
        "schema_version": "1.0",
        "name": "tiny",
        "feature_dim": DIM,
        "image_encoder": {
            "file": "image_encoder.onnx",
            "input": "image",
            "output": "features",
            **NORMALISED,
        },
        "text_encoder": {
            "file": "text_encoder.onnx",
            "input_ids": "input_ids",
            "output": "text_embeds",
            "tokenizer": {"kind": "huggingface", "file": "tokenizer.json", "max_length": 16},
        },
    }
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root, dense, text, manifest


def test_encoders_match_their_torch_models(tmp_path):
    root, dense, text, _ = make_bundle(tmp_path / "b")
    b = load_bundle(root)
    rgb = np.random.default_rng(0).integers(0, 256, (40, 48, 3), dtype=np.uint8)
    got = b.encode_image(rgb)
    x = torch.from_numpy((rgb / 255.0 - 0.5) / 0.25).float().permute(2, 0, 1)[None]
    with torch.no_grad():
        want = dense(x)[0].numpy()
    assert got.shape == (DIM, 10, 12)
    np.testing.assert_allclose(got, want, atol=1e-4)
    emb = b.encode_text("the green sofa")
    with torch.no_grad():
        ref = text(torch.tensor([[3, 4, 5]]))[0].numpy()
    np.testing.assert_allclose(emb, ref / np.linalg.norm(ref), atol=1e-5)


def _refused(root, *words):
    with pytest.raises(GoiError) as e:
        b = load_bundle(root)
        b.encode_image(np.zeros((32, 32, 3), np.uint8))
    for w in words:
        assert w in str(e.value), str(e.value)


def test_model_io_mismatches_are_named(tmp_path):
    root, *_ = make_bundle(tmp_path / "b", image_output="feats")
    _refused(root, "image_encoder.onnx", "no output named 'features'", "feats")
    root, *_ = make_bundle(tmp_path / "c")
    _export(
        torch.nn.Linear(5, DIM),
        (torch.randn(3, 5),),
        root / "image_encoder.onnx",
        ["image"],
        ["features"],
        None,
    )
    _refused(root, "input 'image' has rank 2", "expected 4")


def test_manifest_problems_are_named(tmp_path):
    root, _, _, manifest = make_bundle(tmp_path / "b")
    bad = json.loads(json.dumps(manifest))
    del bad["image_encoder"]["std"]
    (root / "manifest.json").write_text(json.dumps(bad))
    _refused(root, "manifest.json", "'image_encoder.std' is missing")
    bad = json.loads(json.dumps(manifest))
    bad["image_encoder"]["file"] = "../../etc/passwd"
    (root / "manifest.json").write_text(json.dumps(bad))
    _refused(root, "outside the bundle")
    bad["schema_version"] = "7.0"
    (root / "manifest.json").write_text(json.dumps(bad))
    _refused(root, "version 7.0")


def test_a_directory_without_a_manifest_names_export_model(tmp_path):
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "config.json").write_text("{}")
    with pytest.raises(GoiError) as e:
        load_bundle(ckpt)
    assert str(e.value).startswith(f"--bundle: {ckpt} has no manifest.json: a Hugging Face ")
    assert "`goi export-model CHECKPOINT... --out BUNDLE`" in str(e.value)
    with pytest.raises(GoiError, match="not a model bundle; `goi export-model"):
        load_bundle(tmp_path)


def test_extract_with_a_bundle(tmp_path, capsys):
    root, *_ = make_bundle(tmp_path / "b")
    d = tmp_path / "scene"
    (d / "images").mkdir(parents=True)
    write_ply(d / "point_cloud.ply", random_vertex(40))
    cams = [front_camera(48, 40, f"v{i}") for i in range(2)]
    write_inria(d / "cameras.json", cams)
    for c in cams:
        cv2.imwrite(str(d / "images" / f"{c.name}.png"), np.full((40, 48, 3), 90, np.uint8))
    assert (
        main(["extract", "--scene", str(d), "--bundle", str(root), "--out", str(tmp_path / "f.h5")])
        == 0
    )
    fm = load_features(tmp_path / "f.h5")
    assert fm.dim == DIM and fm.maps["v1"].shape == (10, 12, DIM)
    cv2.imwrite(str(d / "images" / "v1.png"), np.zeros((20, 48, 3), np.uint8))
    assert (
        main(["extract", "--scene", str(d), "--bundle", str(root), "--out", str(tmp_path / "g.h5")])
        == 2
    )
    err = capsys.readouterr().err
    assert "v1.png: image is 48x20 but its camera says 48x40" in err
    assert not (tmp_path / "g.h5").exists()
    assert main(["extract", "--scene", str(d), "--out", str(tmp_path / "h.h5")]) == 2


class Res(torch.nn.Module):
    """A tiny referring-segmentation model: image + prompt -> scores [1, 1, H/2, W/2]."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 2, stride=2)
        self.emb = torch.nn.Embedding(len(VOCAB), 4)

    def forward(self, image, input_ids):
        return (self.conv(image) * self.emb(input_ids).mean(1)[:, :, None, None]).sum(1, True)


def test_res_model_gives_the_thresholded_mask(tmp_path):
    root, _, _, manifest = make_bundle(tmp_path / "b")
    torch.manual_seed(1)
    res = Res().eval()
    _export(
        res,
        (torch.randn(1, 3, 32, 32), torch.zeros(1, 2, dtype=torch.int64)),
        root / "res.onnx",
        ["image", "input_ids"],
        ["scores"],
        {"image": {2: "h", 3: "w"}, "input_ids": {1: "n"}},
    )
    manifest["res"] = {
        "file": "res.onnx",
        "image_input": "image",
        "input_ids": "input_ids",
        "output": "scores",
        **NORMALISED,
        "threshold": 0.0,
    }
    (root / "manifest.json").write_text(json.dumps(manifest))
    b = load_bundle(root)
    rgb = np.random.default_rng(3).integers(0, 256, (40, 48, 3), dtype=np.uint8)
    mask = b.segment(rgb, "red sofa")
    x = torch.from_numpy((rgb / 255.0 - 0.5) / 0.25).float().permute(2, 0, 1)[None]
    with torch.no_grad():
        score = res(x, torch.tensor([[1, 5]]))[0, 0].numpy()
    want = cv2.resize(score, (48, 40), interpolation=cv2.INTER_LINEAR) > 0
    assert mask.shape == (40, 48) and 0.05 < mask.mean() < 0.95
    assert (mask != want).mean() < 0.01  # float32 rounding at the threshold only
    del manifest["text_encoder"]
    (root / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(GoiError, match="'res' uses the text encoder"):
        load_bundle(root)
