"""The Grounded-SAM RES of a bundle equals a torch reference of the same steps built from the
transformers processors; bad checkpoints and bad bundles are refused, naming what is wrong."""

import json
import shutil
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.core.errors import GoiError, GoiWarning
from stages.models import res_processing as rp
from stages.models.bundle import load_bundle
from tests.conftest import GROUNDED

transformers = pytest.importorskip("transformers")
pytest.importorskip("PIL")


def _reference(ck, rgb, prompt, sam_size=128):
    """Grounded-SAM in torch: the processors' pre- and post-processing, the top boxes, SAM on
    them, the union of the masks. -> mask logits [B, H, W], boxes, scores."""
    from tokenizers import Tokenizer
    from transformers.models.grounding_dino.processing_grounding_dino import (
        GroundingDinoProcessor,
    )

    h, w = GROUNDED["canvas"]
    det = transformers.GroundingDinoForObjectDetection.from_pretrained(
        str(ck["detector"]), attn_implementation="eager"
    ).eval()
    proc = transformers.GroundingDinoImageProcessorPil(
        size={"max_height": h, "max_width": w}, pad_size={"height": h, "width": w}
    )
    x = proc(images=rgb, return_tensors="pt")
    ids = torch.tensor([Tokenizer.from_file(str(ck["detector"] / "tokenizer.json")).encode(
        rp.detector_caption(prompt)).ids])  # fmt: skip
    with torch.no_grad():
        out = det(pixel_values=x["pixel_values"], pixel_mask=x["pixel_mask"], input_ids=ids)

    class Proc:
        batch_decode = staticmethod(lambda label_ids: [list(map(int, t)) for t in label_ids])

    found = GroundingDinoProcessor.post_process_grounded_object_detection(
        Proc(),
        SimpleNamespace(logits=out.logits, pred_boxes=out.pred_boxes, input_ids=ids),
        threshold=GROUNDED["box_threshold"],
        target_sizes=[rgb.shape[:2]],
    )[0]
    order = torch.argsort(found["scores"], descending=True, stable=True)[: GROUNDED["max_boxes"]]
    boxes, scores = found["boxes"][order], found["scores"][order]
    if len(boxes) == 0:
        return np.full((0, *rgb.shape[:2]), -1.0), boxes.numpy(), scores.numpy()
    sam = transformers.SamModel.from_pretrained(str(ck["sam"]), attn_implementation="eager")
    sproc = transformers.SamProcessor(
        image_processor=transformers.SamImageProcessorPil(
            size={"longest_edge": sam_size}, pad_size={"height": sam_size, "width": sam_size}
        )
    )
    s = sproc(images=rgb, input_boxes=[boxes.tolist()], return_tensors="pt")
    with torch.no_grad():
        o = sam.eval()(
            pixel_values=s["pixel_values"], input_boxes=s["input_boxes"], multimask_output=False
        )
    logits = sproc.image_processor.post_process_masks(
        [o.pred_masks[0]], s["original_sizes"], s["reshaped_input_sizes"], binarize=False
    )[0][:, 0]
    return logits.numpy(), boxes.numpy(), scores.numpy()


@pytest.mark.parametrize("shape,prompt", [((96, 128), "a red chair"), ((130, 90), "The Sofa.")])
def test_grounded_pipeline_equals_the_torch_reference(res_checkpoints, res_bundles, shape, prompt):
    rgb = np.random.default_rng(shape[0]).integers(0, 256, (*shape, 3), dtype=np.uint8)
    logits, boxes, scores = _reference(res_checkpoints, rgb, prompt)
    got = load_bundle(res_bundles["grounded"]).ground(rgb, prompt)
    assert len(scores) == GROUNDED["max_boxes"]  # more boxes pass: the cap is exercised
    assert np.abs(got.scores - scores).max() <= 1e-5
    assert np.abs(got.boxes - boxes).max() <= 1e-3  # pixels
    want = (logits > GROUNDED["mask_threshold"]).any(0)
    assert 0 < want.mean() < 1
    differ = got.mask != want  # only where a mask logit is within float error of the threshold
    assert np.all(np.abs(logits[:, differ] - GROUNDED["mask_threshold"]).min(0) < 1e-4)


def _copy(src, tmp):
    dest = tmp / "bundle"
    shutil.copytree(src, dest)
    return dest


def _edit(root, edit):
    m = json.loads((root / "manifest.json").read_text())
    edit(m)
    (root / "manifest.json").write_text(json.dumps(m))


def test_no_box_gives_an_empty_mask(res_bundles, tmp_path):
    root = _copy(res_bundles["grounded"], tmp_path)
    _edit(root, lambda m: m["grounded"].update(box_threshold=0.99999))
    rgb = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    got = load_bundle(root).ground(rgb, "a red chair")
    assert len(got.boxes) == 0 and got.mask.shape == (96, 128) and not got.mask.any()


def test_a_prompt_longer_than_the_tokenizer_is_cut_with_a_warning(res_bundles):
    bundle = load_bundle(res_bundles["grounded"])
    rgb = np.random.default_rng(1).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    with pytest.warns(GoiWarning, match="longer than the model's 32 tokens"):
        mask = bundle.segment(rgb, " ".join(["the red chair on the green sofa"] * 8))
    assert mask.shape == (96, 128)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bundle.segment(rgb, "the red chair")


def _refused(root, *words):
    with pytest.raises(GoiError) as e:
        b = load_bundle(root)
        b.segment(np.zeros((96, 128, 3), np.uint8), "a red chair")
    for w in words:
        assert w in str(e.value), str(e.value)


def test_bad_grounded_bundles_are_refused_naming_the_file(res_bundles, tmp_path):
    root = _copy(res_bundles["grounded"], tmp_path)
    (root / "sam_decoder.onnx").rename(tmp_path / "away.onnx")
    _refused(root, "manifest.json", "grounded.sam_decoder", "sam_decoder.onnx is missing")
    (tmp_path / "away.onnx").rename(root / "sam_decoder.onnx")
    _edit(root, lambda m: m["grounded"]["sam_decoder"].update(boxes="boxes_in"))
    _refused(root, "sam_decoder.onnx", "no input named 'boxes_in'", "input_boxes")
    _edit(root, lambda m: m["grounded"]["sam_decoder"].update(boxes="input_boxes"))
    _edit(root, lambda m: m["grounded"]["detector"].update(logits="scores"))
    _refused(root, "detector.onnx", "no output named 'scores'")
    _edit(root, lambda m: m["grounded"]["detector"].update(logits="logits", size=[100, 96]))
    _refused(root, "detector.onnx", "'pixel_values' has size 128 on axis 3, expected 100")
    _edit(root, lambda m: m["grounded"].pop("max_boxes"))
    _refused(root, "manifest.json", "'grounded.max_boxes' is missing")
    _edit(root, lambda m: m.update(grounded={**m["grounded"], "max_boxes": 2}, res={}))
    _refused(root, "manifest.json", "field 'res.file' is missing")


def test_bad_checkpoints_are_refused_before_any_export(res_checkpoints, tmp_path, capsys):
    """Exit 2, one line naming the checkpoint, and no bundle nor temporary directory left."""
    ck = res_checkpoints
    wrong = tmp_path / "wrong"
    shutil.copytree(ck["clipseg"], wrong)  # CLIPSeg's weights under SAM's config
    shutil.copyfile(ck["sam"] / "config.json", wrong / "config.json")
    pickled = tmp_path / "pickled"  # a .bin is never unpickled
    pickled.mkdir()
    shutil.copyfile(ck["sam"] / "config.json", pickled / "config.json")
    (pickled / "pytorch_model.bin").write_bytes(b"not read")
    owl = tmp_path / "owl"
    owl.mkdir()
    (owl / "config.json").write_text('{"model_type": "owlv2"}')
    cases = [
        ([ck["detector"], pickled], ("pickled", "no model.safetensors", "pytorch_model.bin")),
        ([owl, ck["sam"]], ("owl", "no model.safetensors")),
        ([ck["detector"]], ("grounding-dino", "needs a SAM checkpoint")),
        ([ck["detector"], ck["sam"], ck["clipseg"]], ("one RES",)),
        ([ck["clipseg"], ck["clipseg"]], ("both clipseg checkpoints",)),
        ([ck["detector"], wrong], ("wrong", "SAM model reads are missing", "another architecture")),
    ]
    for sources, words in cases:
        capsys.readouterr()
        assert main(["export-model", *map(str, sources), "--out", str(tmp_path / "b")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("goi: error:"), err
        for word in words:
            assert word in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["owl", "pickled", "wrong"]


def test_a_sam_checkpoint_alone_is_a_sam_bundle(res_checkpoints, tmp_path):
    """A SAM with no detector is no RES: it exports as a SAM alone, for clicks and boxes."""
    out = tmp_path / "b"
    assert main(["export-model", str(res_checkpoints["sam"]), "--out", str(out)]) == 0
    b = load_bundle(out)
    assert b.has_sam and not b.has_res and b.index_kind == "sam"


def test_a_checkpoint_without_tokenizer_json_gets_one_built(tmp_path):
    """Older checkpoints ship only the slow tokenizer's files: transformers converts them."""
    from tokenizers import Tokenizer

    from stages.models.export.common import tokenizer_json

    (tmp_path / "vocab.txt").write_text("[PAD]\n[UNK]\n[CLS]\n[SEP]\n[MASK]\na\nred\nchair\n.\n")
    (tmp_path / "tokenizer_config.json").write_text('{"tokenizer_class": "BertTokenizer"}')
    (tmp_path / "config.json").write_text('{"model_type": "grounding-dino"}')
    enc = Tokenizer.from_str(tokenizer_json(tmp_path)).encode("A red chair.")
    assert enc.tokens == ["[CLS]", "a", "red", "chair", ".", "[SEP]"]
    (tmp_path / "vocab.txt").unlink()
    with pytest.raises(GoiError, match="tokenizer.json: missing, and the checkpoint has no"):
        tokenizer_json(tmp_path)


def test_sams_boxes_are_one_decoder_batch_equal_to_one_box_a_run(res_bundles):
    """The K boxes of a view go through SAM's decoder as one prompt batch: each box's logits
    are those of its own run (no box sees another)."""
    g = load_bundle(res_bundles["grounded"])._grounded
    rgb = np.random.default_rng(3).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    emb = g.sam.embed(rgb)
    boxes = np.asarray([[4, 6, 60, 80], [30, 10, 120, 90], [0, 0, 128, 96]], np.float32)
    batch = g.sam.boxes_logits(emb, boxes, (96, 128))
    one = np.stack([g.sam.box_logits(emb, b, (96, 128)) for b in boxes])
    assert batch.shape == (3, 96, 128)
    assert np.abs(batch - one).max() <= 1e-4 * max(1.0, float(np.abs(one).max()))
